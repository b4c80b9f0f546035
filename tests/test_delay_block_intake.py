"""The delay tracker's block intake (`OnlineDelayTracker.add_samples`, what the service hands it
every 0.1-0.25 s) against its per-sample intake (`add_tracker` / `add_encoder`, what the
service called for every sample before): the same samples give the same buffers, counters,
clock lines, restarts and decisions, whatever the blocks' sizes."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from keo_service.fit.delay_online import OnlineDelayTracker, stretch_arrays
from keo_service.live.messages import JointSample, TrackerSample


def _stream(seed: int) -> list[JointSample | TrackerSample]:
    """Both streams interleaved as they arrive, with what the intake must judge: gaps,
    flagged stamps, non-finite values, wrong lengths, stamps going back, device stamps on a
    line whose drift changes, a single reflector's poses, and the encoder's and the
    tracker's time bases starting anew (an epoch change; a seq going back with no epoch)."""
    rng = random.Random(seed)
    out: list[JointSample | TrackerSample] = []
    t, enc_seq, trk_seq, enc_epoch, trk_epoch = 100.0, 0, 0, 1, 0
    drift = 3e-6
    for i in range(3000):
        t += 0.001
        if i == 1200:
            enc_epoch = 2  # the encoder adapter restarted
        if i == 2100:
            trk_seq = 0  # the tracker adapter restarted (its seq starts again, no epoch)
        if i % 500 == 0:
            drift += 1e-6  # the tracker's clock line moved
        if i % 4 == 0:
            enc_seq += 1
            q = [0.1 * math.sin(t + k) for k in range(6)]
            if rng.random() < 0.02:
                q[rng.randrange(6)] = math.nan
            if rng.random() < 0.01:
                q = q[:5]  # a wrong length
            stamp = t - 0.002 if rng.random() < 0.01 else t  # now and then one going back
            out.append(
                JointSample(
                    stamp=stamp,
                    host_ns=0,
                    seq=enc_seq,
                    joints=q,
                    clock="receipt",
                    clock_epoch=enc_epoch,
                    flags=["stamp_old"] if rng.random() < 0.02 else [],
                )
            )
        trk_seq += 1
        gap = rng.random() < 0.03
        p = None if gap else [1.0 + 0.1 * math.sin(t), 0.5 * math.cos(t), 0.2]
        if p is not None and rng.random() < 0.02:
            p[1] = math.inf
        quat = None if gap or rng.random() < 0.05 else [1.0, 0.0, 0.0, 0.0]
        device = 50.0 + t if rng.random() > 0.02 else None
        out.append(
            TrackerSample(
                stamp=t,
                host_ns=0,
                seq=trk_seq,
                status="beam_broken" if gap else "ok",
                position=p,
                quaternion=quat,
                device_stamp=device,
                clock="device",
                clock_epoch=trk_epoch,
                flags=["clock_relearning"] if rng.random() < 0.02 else [],
                clock_drift=drift if rng.random() > 0.05 else None,
            )
        )
    return out


def _per_sample(tracker: OnlineDelayTracker, samples: list[JointSample | TrackerSample]) -> None:
    """What the service did for each sample before (`_handle`)."""
    for m in samples:
        if isinstance(m, TrackerSample):
            if m.position is not None:
                tracker.add_tracker(
                    m.stamp, m.position, m.quaternion, m.clock_epoch, m.seq, bool(m.flags),
                    m.device_stamp, m.clock_drift,
                )  # fmt: skip
        else:
            tracker.add_encoder(
                m.stamp, m.joints, m.clock_epoch, m.seq, bool(m.flags), m.device_stamp,
                m.clock_drift,
            )  # fmt: skip


def _state(tracker: OnlineDelayTracker) -> dict[str, object]:
    return {
        "enc": tracker._enc.between(-np.inf, np.inf),
        "trk": tracker._trk.between(-np.inf, np.inf),
        "enc_last": tracker._enc.last,
        "trk_last": tracker._trk.last,
        "counters": dict(tracker.counters),
        "lines": dict(tracker._newest_rows),
        "sources": dict(tracker._sources),
        "start": tracker._start,
        "young_until": tracker._young_until,
        "applied": tracker.applied,
        "delay_now": tracker.delay_now(),
        "decision": tracker.decision,
    }


def _same(a: dict[str, object], b: dict[str, object]) -> None:
    assert a.keys() == b.keys()
    for key, x in a.items():
        y = b[key]
        if isinstance(x, np.ndarray):
            assert isinstance(y, np.ndarray)
            assert x.shape == y.shape, key
            assert np.array_equal(x, y, equal_nan=True), key
        else:
            nan = isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y)
            assert x == y or nan, key


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("max_samples", [20000, 700])
def test_a_block_at_a_time_takes_what_sample_by_sample_took(demo_cell, seed, max_samples):
    """Blocks of random sizes (1 to 400 samples) against sample by sample: equal state after
    every block, the restarts among them (two, injected) counted in both, and the buffers'
    bound (700 rows: the oldest dropped) kept alike."""
    samples = _stream(seed)
    one = OnlineDelayTracker(demo_cell, None, 0.028, 0.0005, max_samples=max_samples)
    block = OnlineDelayTracker(demo_cell, None, 0.028, 0.0005, max_samples=max_samples)
    rng = random.Random(seed)
    i, most = 0, 0
    while i < len(samples):
        size = rng.choice([1, 2, 3, 50, 125, 400])
        chunk = samples[i : i + size]
        i += size
        _per_sample(one, chunk)
        block.add_samples(chunk, TrackerSample)
        _same(_state(one), _state(block))
        most = max(most, len(block._trk))
    assert one.counters["restarts"] == 2
    assert one.counters["tracker_left_out"] > 0
    assert one.counters["encoder_left_out"] > 0
    assert one.counters["encoder_wrong_length"] > 0
    # 700: full, the oldest dropped; else more than that held before the first restart
    assert most == 700 if max_samples == 700 else most > 700


def test_a_stretch_and_its_fit_are_the_same_either_way(demo_cell, demo_config):
    """The bench's scenario (1 kHz / 250 Hz, the tracker on a device clock): after 6 s taken a
    block at a time or sample by sample, the stretch the service would fit is the same
    array, and folding the same fit in gives the same decision and delay."""
    from keo_service.bench.demo import loopback_config
    from keo_service.bench.live_path import wire_samples
    from keo_service.live.messages import decode

    config = loopback_config(demo_config)
    msgs = [decode(p) for _s, _k, p in wire_samples(config, 6.0)]
    one = OnlineDelayTracker(demo_cell, None, 0.028, 0.0005)
    block = OnlineDelayTracker(demo_cell, None, 0.028, 0.0005)
    _per_sample(one, msgs)  # type: ignore[arg-type]
    for k in range(0, len(msgs), 125):
        block.add_samples(msgs[k : k + 125], TrackerSample)
    assert one.due()
    assert block.due()
    a, b = stretch_arrays(one.take()), stretch_arrays(block.take())
    for x, y in zip(a, b, strict=True):
        assert (x is None and y is None) or np.array_equal(x, y)
    found = one.measure(a, 0.028, one.guess(0.028))
    assert one.combine(found) == block.combine(found)
    assert one.decision == block.decision
    assert one.delay_now() == block.delay_now()
