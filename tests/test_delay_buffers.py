"""The delay tracker's sample buffers (issue 48): rows of floats in arrays, a stretch a slice
of them. They must give exactly the stretches the buffers before them gave (a deque of one
tuple per sample, a stretch a walk over it), checked here against that bookkeeping written
out anew: the same sample sequence (flags, a restart, repeated and out-of-order stamps,
non-finite values, poses without a quaternion, mapped and unmapped stamps, lines moving,
buffers overflowing) through both, every stretch's arrays equal exactly."""

from __future__ import annotations

import collections
import math

import numpy as np
import pytest

from keo_service.fit.stamp_lines import Anchor, moved


class _DequeBuffers:
    """The bookkeeping before: a bounded deque of (stamp, array, ..., device stamp or None)
    per stream, a stretch the rows found by walking it, its stamps mapped row by row."""

    def __init__(self, maxlen: int) -> None:
        self.enc: collections.deque = collections.deque(maxlen=maxlen)
        self.trk: collections.deque = collections.deque(maxlen=maxlen)

    def add_encoder(self, t, q, device) -> None:
        if (
            math.isfinite(t)
            and all(map(math.isfinite, q))
            and (not self.enc or t > self.enc[-1][0])
        ):
            self.enc.append((t, np.asarray(q, dtype=float), device))

    def add_tracker(self, t, p, quat, device) -> None:
        finite = all(map(math.isfinite, p)) and (quat is None or all(map(math.isfinite, quat)))
        if math.isfinite(t) and finite and (not self.trk or t > self.trk[-1][0]):
            q = None if quat is None else np.asarray(quat, dtype=float)
            self.trk.append((t, np.asarray(p, dtype=float), q, device))

    def due(self, span: float) -> bool:
        return bool(self.trk) and self.trk[-1][0] - self.trk[0][0] >= span

    def take(self, span: float, enc_line, trk_line):
        first = self.trk[0][0]
        trk = [s for s in self.trk if s[0] <= first + span]
        end = trk[-1][0]
        enc = [s for s in self.enc if first - 1.0 <= s[0] <= end + 1.0]
        while self.trk and self.trk[0][0] <= end:
            self.trk.popleft()
        while self.enc and self.enc[0][0] < end - 1.0:
            self.enc.popleft()

        def on_line(anchor, rows):
            t = np.array([r[0] for r in rows], dtype=float)
            if anchor is not None and t.size:
                device = np.array([math.nan if r[-1] is None else r[-1] for r in rows])
                ok = ~np.isnan(device)
                t[ok] = anchor.at(device[ok])
            return t

        quats = [s[2] for s in trk]
        return (
            on_line(enc_line, enc),
            np.array([s[1] for s in enc]) if enc else np.empty((0, 0)),
            on_line(trk_line, trk),
            np.array([s[1] for s in trk]),
            None if any(q is None for q in quats) else np.array(quats),
        )


def _samples(seed: int, seconds: float, grid: bool):
    """A 1 kHz tracker and a 250 Hz encoder with what a wire brings: device stamps (mapped
    on lines whose drift changes), samples without one, flags, stamps repeated or going
    back, non-finite values, poses without a quaternion, and a restart (a new epoch). On a
    `grid` of binary fractions, stamps fall exactly on a stretch's bounds."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(int(seconds * 1000)):
        t = 100.0 + (k / 1024 if grid else k * 1e-3 + rng.uniform(0, 2e-4))
        if k % 4 == 0:
            q = [float(x) for x in rng.normal(size=6)]
            out.append(("enc", t - (11 / 1024 if grid else 0.0107), q, k // 4))
        p = [float(x) for x in rng.normal(size=3)]
        quat = None if rng.uniform() < 0.002 else [float(x) for x in rng.normal(size=4)]
        out.append(("trk", t, p, quat, k))
    rng.shuffle(out[500:520])  # a burst out of order: stamps going back are not taken
    return out, rng


@pytest.mark.parametrize(
    ("seed", "maxlen", "grid"),
    [(1, 40_000, False), (2, 700, False), (3, 2600, False), (4, 40_000, True), (5, 2600, True)],
)
def test_stretches_equal_those_of_the_deques_before(demo_cell, seed, maxlen, grid):
    from keo_service.fit.delay_online import OnlineDelayTracker, stretch_arrays

    tracker = OnlineDelayTracker(demo_cell, None, 0.01, 0.001, max_samples=maxlen, settle_s=0.5)
    ref = _DequeBuffers(maxlen)
    samples, rng = _samples(seed, 24.0, grid)
    epoch, stretches, restart_at, restarts = 1, 0, 12_000, 0
    for n, s in enumerate(samples):
        if n == restart_at:
            epoch = 2
        mapped = n % 3 != 0 and n < 30_000
        device = s[1] * 0.999 + 5.0 if mapped else None
        drift = 1e-6 * (1 + (n // 1000) % 4) if mapped and n % 7 == 0 else None
        flagged = rng.uniform() < 0.01
        t = s[1]
        if rng.uniform() < 0.001:
            t = math.nan if rng.uniform() < 0.5 else t  # a stamp not finite
        if s[0] == "enc":
            q = list(s[2])
            if rng.uniform() < 0.001:
                q[2] = math.inf
            tracker.add_encoder(t, q, epoch, s[3] + 1, flagged, device, drift)
        else:
            tracker.add_tracker(t, s[2], s[3], epoch, s[4] + 1, flagged, device, drift)
        if tracker.counters["restarts"] != restarts:  # a time base anew: buffers cleared
            restarts = tracker.counters["restarts"]
            ref = _DequeBuffers(maxlen)
        # the reference takes what the tracker took (the same checks of flags and start)
        start = tracker._start
        device_kept = None if device is None or not math.isfinite(device) else device
        stream = "encoder" if s[0] == "enc" else "tracker"
        kept = device_kept if stream in tracker._newest_rows else None
        if not flagged and not (t < start):
            if s[0] == "enc":
                ref.add_encoder(t, q, kept)
            else:
                ref.add_tracker(t, s[2], s[3], kept)
        span = tracker._span()
        assert tracker.due() == ref.due(span)
        if n % 101 == 0:  # the newest lines as anchors, and the delay carried on them
            lines = tracker._newest
            assert set(lines) == set(tracker._newest_rows)
        if n % 101 == 0:
            assert (len(tracker._enc), len(tracker._trk)) == (len(ref.enc), len(ref.trk))
        # every due stretch, and now and then one taken early (from buffers that overflowed)
        if tracker.due() or (n % 9973 == 0 and ref.trk):
            enc_line = tracker._newest.get("encoder")
            trk_line = tracker._newest.get("tracker")
            want = ref.take(span, enc_line, trk_line)
            got = stretch_arrays(tracker.take())
            for g, w in zip(got, want, strict=True):
                if w is None:
                    assert g is None
                else:
                    assert g is not None
                    assert g.shape == w.shape
                    assert g.dtype == w.dtype
                    assert np.array_equal(g, w)
            stretches += 1
    assert stretches >= (2 if maxlen < 2500 else 7)  # 700 rows never make a due stretch
    assert restarts >= 1  # each stream's new epoch (one or two restarts)


def test_the_delay_carried_per_sample_is_the_anchors(demo_cell):
    """`delay_now` (per sample, on the lines' plain floats) equals the delay in use moved by
    `stamp_lines.moved` on the lines as anchors, with lines moved since the frame."""
    from keo_service.fit.delay_online import OnlineDelayTracker

    tracker = OnlineDelayTracker(demo_cell, None, 0.0, None)
    tracker.add_encoder(10.0, [0.0] * 6, 1, 1, False, 3.0, 2e-6)
    tracker.add_tracker(10.001, [0.0] * 3, None, 1, 1, False, 7.0, -1e-6)
    tracker._frame = {"encoder": Anchor(9.9, 2.9, 1e-6), "tracker": Anchor(9.8, 6.8, -3e-6)}
    tracker.applied, tracker._applied_t, tracker.source_kind = 0.0123, 9.95, "fit"
    for k in range(50):
        tracker.add_encoder(
            10.01 + k * 4e-3, [0.1] * 6, 1, k + 2, False, 3.01 + k * 4e-3, 2e-6 + k * 1e-9
        )
        tracker.add_tracker(
            10.011 + k * 1e-3, [0.1] * 3, None, 1, k + 2, False, 7.01 + k * 1e-3, -1e-6
        )
        newest, frame = tracker._newest, tracker._frame
        want = tracker.applied + (
            moved(newest["tracker"], frame["tracker"], 9.95)
            - moved(newest["encoder"], frame["encoder"], 9.95)
        )
        assert tracker.delay_now() == want
    assert tracker.delay_now() != tracker.applied  # the lines did move


def test_the_pool_is_bounded_and_emptied_once_settled(demo_cell):
    """While the delay is not settled, each stretch carries the pool of the rows since it was
    last unknown, for the pooled fit: its tracker rows thinned to at most `pool_rows`, its
    span at most `pool_s` plus a stretch, the encoder's rows without repeats (stretches
    overlap there); once settled, no pool. Fed 50 s of one joint at constant speed (never
    settled: the motion cannot separate a delay) from a MotoROS encoder and a 100 Hz tracker."""
    from keo_service.fit.delay_online import OnlineDelayTracker
    from keo_service.sim.delay_study import StreamCase, case_streams

    streams = case_streams(demo_cell, StreamCase("motoros", "line100", "one_joint", seconds=50.0))
    unknown = OnlineDelayTracker(demo_cell, pool_s=20.0, pool_rows=500)
    pools = _pools(unknown, streams, fit=True)
    assert not unknown.settled
    assert pools[0] is None
    assert all(p is not None for p in pools[1:]), pools
    assert len(pools) >= 6
    for pool in pools[1:]:
        assert pool.trk.shape[0] <= 500
        assert pool.trk[-1, 0] - pool.trk[0, 0] <= 20.0 + unknown.max_span_s
        assert np.all(np.diff(pool.enc[:, 0]) > 0)  # no encoder row twice
    assert pools[-1].trk[0, 0] > streams.trk_t[0] + 20.0  # the oldest rows left the pool
    # settled (a configured delay): no pool
    known = OnlineDelayTracker(demo_cell, prior_s=0.030, prior_se_s=0.0005)
    assert all(p is None for p in _pools(known, streams, fit=False))


def stretches_taken(tracker, streams):
    """Feed the streams' samples in time order (each encoder sample before the tracker
    samples it precedes) and yield each stretch the tracker takes, as it becomes due."""
    k = 0
    for i, t in enumerate(streams.trk_t):
        while k < streams.enc_t.size and streams.enc_t[k] <= t:
            tracker.add_encoder(float(streams.enc_t[k]), streams.enc_q[k])
            k += 1
        tracker.add_tracker(float(t), streams.trk_p[i], streams.trk_quat[i])
        if tracker.due():
            yield tracker.take()


def _pools(tracker, streams, fit: bool) -> list:
    """The pool of every stretch the tracker takes from the streams (each fitted and folded
    in when `fit`)."""
    from keo_service.fit.delay_online import pool_arrays, stretch_arrays

    pools = []
    for stretch in stretches_taken(tracker, streams):
        pools.append(stretch.pool)
        if fit:
            found = tracker.measure(stretch_arrays(stretch), 0.0, pool=pool_arrays(stretch))
            tracker.combine(found)
    return pools


def _feed(tracker, streams, t_from: float, t_to: float, encoder: bool, epoch: int = 0) -> list:
    """Feed the streams' samples in [t_from, t_to) (the encoder's only when `encoder`, with
    this `epoch`), each stretch fitted with its pool and folded in, as the service does:
    the measurements."""
    from keo_service.fit.delay_online import pool_arrays, stretch_arrays

    found_all = []
    enc = streams.enc_t
    k = int(np.searchsorted(enc, t_from))
    for i in np.flatnonzero((streams.trk_t >= t_from) & (streams.trk_t < t_to)).tolist():
        t = float(streams.trk_t[i])
        while encoder and k < enc.size and enc[k] <= t:
            tracker.add_encoder(float(enc[k]), streams.enc_q[k], epoch=epoch, seq=k)
            k += 1
        tracker.add_tracker(t, streams.trk_p[i], streams.trk_quat[i])
        if tracker.due():
            stretch = tracker.take()
            found = tracker.measure(stretch_arrays(stretch), 0.0, pool=pool_arrays(stretch))
            tracker.combine(found)
            found_all.append(found)
    return found_all


def test_a_stream_without_encoder_rows_gives_no_pool_and_no_error(demo_cell):
    """The encoder silent (its adapter late or down) while the tracker's poses come, the
    delay unknown: every stretch is refused for lack of data, none raises (a pool of
    tracker rows alone has no encoder rows to join), nothing is taken, and the refusal
    carries the stretch's end time."""
    from keo_service.fit.delay_online import DelayRefused, OnlineDelayTracker
    from keo_service.sim.delay_study import StreamCase, case_streams

    streams = case_streams(demo_cell, StreamCase("motoros", "line100", "all_slow", seconds=12.0))
    tracker = OnlineDelayTracker(demo_cell)
    found = _feed(tracker, streams, 0.0, 12.0, encoder=False)
    assert len(found) >= 3
    assert all(isinstance(f, DelayRefused) and f.counter == "fits_without_data" for f in found)
    assert all(math.isfinite(f.t) and f.t <= streams.trk_t[-1] for f in found)
    assert tracker.counters["fits_without_data"] == len(found)
    assert tracker.applied is None
    assert not tracker.settled


def test_an_encoder_restart_then_a_stall_gives_no_error(demo_cell):
    """Both streams for 10 s (the delay unknown, a pool growing), then the encoder's time
    base starts anew (a new epoch) and it falls silent while the tracker goes on 30 s: no stretch
    after that raises, each is refused for lack of data, and no pooled fit from before the
    restart is taken after it."""
    from keo_service.fit.delay_online import DelayRefused, OnlineDelayTracker
    from keo_service.sim.delay_study import StreamCase, case_streams

    streams = case_streams(demo_cell, StreamCase("motoros", "line100", "all_slow", seconds=40.0))
    tracker = OnlineDelayTracker(demo_cell)
    _feed(tracker, streams, 0.0, 10.0, encoder=True)
    k = int(np.searchsorted(streams.enc_t, 10.0))
    tracker.add_encoder(float(streams.enc_t[k]), streams.enc_q[k], epoch=1, seq=0)  # restart
    assert tracker.counters["restarts"] == 1
    applied = tracker.applied
    found = _feed(tracker, streams, 10.0, 40.0, encoder=False)
    assert len(found) >= 2
    assert all(isinstance(f, DelayRefused) and f.counter == "fits_without_data" for f in found)
    assert tracker.applied == applied  # nothing new taken without encoder rows
    assert tracker.pooled is None


def test_the_pool_is_thinned_as_if_joined_first():
    """The pool's tracker rows are thinned part by part (no join of every row on the event
    loop): the same rows as joining them all and keeping every k-th, k the least that keeps
    at most the limit, whatever the parts' sizes."""
    from keo_service.fit.delay_online import thinned

    rng = np.random.default_rng(48)
    for _ in range(200):
        sizes = rng.integers(0, 400, size=int(rng.integers(1, 12)))
        sizes[0] = max(sizes[0], 1)
        start = np.cumsum(np.concatenate([[0], sizes[:-1]]))
        parts = [
            np.column_stack([np.arange(a, a + n), -np.arange(a, a + n)])
            for a, n in zip(start, sizes, strict=True)
        ]
        most = int(rng.integers(1, 600))
        joined = np.concatenate(parts)
        k = math.ceil(joined.shape[0] / most)
        want = joined[::k]
        got = thinned(parts, most)
        assert want.shape[0] <= most
        assert np.array_equal(got, want)
