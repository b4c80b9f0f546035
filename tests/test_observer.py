"""The observer: exact ZOH steps, settling, noise gain, the best gain; checked against formulas."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.optimize import minimize_scalar

from keo_service.core import observer as ob
from keo_service.core.observer import KinematicErrorObserver, all_finite


def settling_from_samples(t: np.ndarray, remaining: np.ndarray, fraction: float = 0.02) -> float:
    """Time the remaining fraction crosses `fraction`, interpolated in log space between samples."""
    k = int(np.flatnonzero(remaining <= fraction)[0])
    r0, r1 = remaining[k - 1], remaining[k]
    return float(t[k - 1] + (t[k] - t[k - 1]) * math.log(r0 / fraction) / math.log(r0 / r1))


def step_response(gains, dts, euler=False):
    obs = KinematicErrorObserver(gains)
    target = np.ones(len(gains))
    t, out = [0.0], [obs.estimate.copy()]
    for dt in dts:
        if euler:
            obs.reset(obs.estimate + np.asarray(gains) * dt * (target - obs.estimate))
        else:
            assert obs.update(target, dt)
        t.append(t[-1] + dt)
        out.append(obs.estimate.copy())
    return np.array(t), 1.0 - np.array(out)


@pytest.mark.parametrize("jitter", [0.0, 0.15])
def test_step_settles_at_ln50_over_L(jitter):
    rng = np.random.default_rng(7)
    gains = [1.0, 5.0, 10.0]
    dts = 0.025 * (1 + rng.uniform(-jitter, jitter, 400))
    t, remaining = step_response(gains, dts)
    for i, L in enumerate(gains):
        assert settling_from_samples(t, remaining[:, i]) == pytest.approx(
            math.log(50) / L, rel=0.01
        )


def test_forward_euler_departs_where_the_paper_disagreed():
    """L = 10 at T = 0.025 s: Euler takes a = LT = 0.25 per step instead of 1 - e^-0.25 = 0.221."""
    dts = np.full(100, 0.025)
    t, exact = step_response([10.0], dts)
    _, euler = step_response([10.0], dts, euler=True)
    theory = math.log(50) / 10
    assert settling_from_samples(t, exact[:, 0]) == pytest.approx(theory, rel=1e-6)
    euler_settle = settling_from_samples(t, euler[:, 0])
    assert (theory - euler_settle) / theory > 0.10  # Euler settles >10 % early
    # at L = 1 the two agree within 2 %: the discretization matters only when L T is large
    t1, e1 = step_response([1.0], np.full(400, 0.025), euler=True)
    assert settling_from_samples(t1, e1[:, 0]) == pytest.approx(math.log(50), rel=0.02)


def test_noise_gain_matches_formula_for_paper_sweep():
    rng = np.random.default_rng(11)
    gains = np.arange(1.0, 21.0)
    obs = KinematicErrorObserver(gains)
    T, n = 0.025, 200_000
    sigma = 0.3
    noise = rng.normal(0, sigma, (n, gains.size))
    out = np.empty_like(noise)
    for k in range(n):
        obs.update(noise[k], T)
        out[k] = obs.estimate
    measured = out[1000:].std(axis=0) / sigma
    predicted = np.array([ob.noise_gain(L, T) for L in gains])
    assert np.all(np.abs(measured / predicted - 1) < 0.03), measured / predicted


def test_bad_steps_are_rejected_and_state_kept():
    obs = KinematicErrorObserver([2.0, 2.0, 2.0], initial=[1.0, 2.0, 3.0])
    before = obs.estimate
    assert not obs.update(np.array([0.0, 0.0, 0.0]), 0.0)
    assert not obs.update(np.array([0.0, 0.0, 0.0]), -0.01)
    assert not obs.update(np.array([0.0, math.nan, 0.0]), 0.01)
    assert not obs.update(np.array([0.0, 0.0, 0.0]), math.inf)
    assert not obs.update(np.array([0.0, 0.0]), 0.01)
    assert obs.rejected == 5
    assert np.array_equal(obs.estimate, before)
    obs.reset()
    assert np.array_equal(obs.estimate, np.zeros(3))
    with pytest.raises(ValueError):
        KinematicErrorObserver([1.0, 0.0])


@pytest.mark.parametrize("extra", [0, 3])  # a position-only and a 6-DoF probe's step
def test_a_step_that_would_leave_the_finite_numbers_is_refused(extra):
    pad = [0.5] * extra
    obs = KinematicErrorObserver([2.0] * (3 + extra), initial=[1.0, -1e308, 3.0, *pad])
    assert not obs.update([0.0, 1e308, 0.0, *pad], 1.0)  # finite in, m - e overflows
    assert not obs.update([0.0, "1", 0.0, *pad], 0.01)
    assert not obs.update([0.0, 0.0, 0.0, *pad], math.nan)
    assert not obs.update([0.0, 0.0, 0.0, *pad, 0.0], 0.01)  # one value too many
    assert not obs.update([*pad, math.inf, 0.0, 0.0], 0.01)
    assert obs.rejected == 5
    assert obs.values == [1.0, -1e308, 3.0, *pad]
    # a finite state whose sum overflows is still a finite state
    obs.reset([0.0] * (3 + extra))
    assert obs.update([1e308] * (3 + extra), 1e3)
    assert obs.values == [1e308] * (3 + extra)


@pytest.mark.parametrize("gains", [[0.7] * 6, [3.0, 3.0, 3.0, 0.5, 0.5, 0.5], [1, 2, 3, 4, 5, 6]])
def test_one_step_is_the_exact_zero_order_hold_per_channel(gains):
    """e_k = e_{k-1} + (1 - exp(-L dt)) (m - e_{k-1}) per channel, written out here."""
    start = [0.1, -0.2, 0.3, -0.4, 0.5, -0.6]
    measured = [1.0, 2.0, -3.0, 0.25, -0.5, 4.0]
    obs = KinematicErrorObserver(gains, initial=start)
    assert obs.update(measured, 0.013)
    want = [
        s + (1 - math.exp(-g * 0.013)) * (m - s)
        for s, g, m in zip(start, gains, measured, strict=True)
    ]
    assert np.allclose(obs.values, want, rtol=1e-14, atol=1e-15)
    obs.set_gain([9.0] * 6)
    assert obs.update(measured, 0.5)
    want = [w + (1 - math.exp(-9.0 * 0.5)) * (m - w) for w, m in zip(want, measured, strict=True)]
    assert np.allclose(obs.estimate, want, rtol=1e-14, atol=1e-15)


def test_channels_come_from_the_gains():
    assert KinematicErrorObserver([1.0] * 3).channels == 3
    assert KinematicErrorObserver([1.0] * 6).channels == 6


def test_kalman_alpha_minimises_the_analytic_mse():
    T, r, d = 0.01, 20e-6, 5e-6
    a_best = ob.kalman_alpha(r, d, T)
    numeric = minimize_scalar(
        lambda a: ob.steady_state_mse(a, r, d, T),
        bounds=(1e-6, 1 - 1e-9),
        method="bounded",
        options={"xatol": 1e-12},
    )
    assert a_best == pytest.approx(numeric.x, rel=1e-4)


def test_best_gain_is_best_in_simulation():
    rng = np.random.default_rng(5)
    rate, noise, drift = 100.0, 20e-6, 5e-6
    T = 1.0 / rate
    best = ob.best_gain(noise, drift, rate)
    gains = np.array([best, best / 2, best * 2])
    channels = 8  # independent copies per gain for a tighter estimate of the MSE
    obs = KinematicErrorObserver(np.repeat(gains, channels))
    n = 60_000
    truth = np.cumsum(rng.normal(0, drift * math.sqrt(T), (n, gains.size * channels)), axis=0)
    meas = truth + rng.normal(0, noise, truth.shape)
    sq = np.zeros(gains.size * channels)
    obs.reset(meas[0])
    burn = 2000
    for k in range(1, n):
        obs.update(meas[k], T)
        if k >= burn:
            err = obs.estimate - truth[k]
            sq += err * err
    mse = (sq / (n - burn)).reshape(gains.size, channels).mean(axis=1)
    predicted_min = ob.steady_state_mse(ob.kalman_alpha(noise, drift, T), noise, drift, T)
    assert mse[0] == pytest.approx(predicted_min, rel=0.05)
    assert mse[0] < mse[1]
    assert mse[0] < mse[2]


def test_gain_command_prints_a_table(tmp_path):
    import json

    from tests.conftest import keo

    result = keo("gain", "--gain", "1", "5", "10", "--rate", "40", "--json")
    assert result.returncode == 0, result.stderr
    rows = json.loads(result.stdout)["gains"]
    assert [r["gain"] for r in rows] == [1, 5, 10]
    for r in rows:
        assert r["settling_time_s"] == pytest.approx(math.log(50) / r["gain"])
        a = 1 - math.exp(-r["gain"] / 40)
        assert r["noise_gain"] == pytest.approx(math.sqrt(a / (2 - a)))
    text = keo("gain", "--noise", "2e-5", "--drift", "5e-6", "--rate", "100").stdout
    assert "best" in text


@given(
    st.lists(
        st.floats(allow_nan=True, allow_infinity=True, width=64) | st.sampled_from([1e308, -1e308]),
        min_size=1,
        max_size=8,
    )
)
def test_all_finite_agrees_with_numpy_including_overflowing_sums(values):
    arr = np.array(values)
    assert all_finite(arr) == bool(np.isfinite(arr).all())


def test_settling_of_a_gain_so_large_that_one_sample_is_taken_whole() -> None:
    # exp(-30000 * 0.01) underflows to 0 in the step fraction: the observer takes the first
    # sample whole, so it has settled after one period (before: a math domain error in keo gain)
    assert ob.step_alpha(30000.0, 0.01) == 1.0
    assert ob.discrete_settling_time(30000.0, 0.01) == 0.01
    assert ob.discrete_settling_time(1e6, 1e-3) == 1e-3
