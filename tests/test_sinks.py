"""The service's outputs behind one protocol (keo_service.live.sinks): a sink that fails is
counted and logged with its cause, the others still get the same estimate, and the failure is
raised so that the service's supervision stops the service (exit non-zero)."""

from __future__ import annotations

import logging

import pytest

from keo_service.core.estimator import Estimate
from keo_service.live.messages import EstimateMessage
from keo_service.live.sinks import SinkFailedError, Sinks


class _Recorder:
    period_s = None

    def __init__(self, name: str, fail: bool = False) -> None:
        self.name = name
        self.fail = fail
        self.got: list[float] = []
        self.closed = False

    def on_input(self, sample: object) -> None:
        pass

    def on_estimate(self, estimate: Estimate, message: EstimateMessage) -> None:
        self.got.append(estimate.stamp)
        if self.fail:
            raise ValueError("disk on fire")

    def on_tick(self) -> None:
        pass

    def counters(self) -> dict[str, int]:
        return {f"{self.name}_seen": len(self.got)}

    def close(self) -> None:
        self.closed = True
        if self.fail:
            raise OSError("cannot close")


def _estimate(t: float) -> tuple[Estimate, EstimateMessage]:
    e = Estimate(t, [0.0] * 6, [0.0] * 6, (), t, ("px", "py", "pz", "rx", "ry", "rz"))
    msg = EstimateMessage(
        stamp=t, host_ns=0, channels=[], measured=None, estimate=[], flags=[], delay_s=0.0, seq=1
    )
    return e, msg


def test_a_failing_sink_is_counted_logged_and_raised_and_the_others_are_served(caplog):
    first, bad, last = _Recorder("bus"), _Recorder("ros2", fail=True), _Recorder("viz")
    sinks = Sinks([first, bad, last])
    with caplog.at_level(logging.ERROR, logger="keo.service"):
        for t in (1.0, 2.0):
            with pytest.raises(SinkFailedError, match="the ros2 output failed") as info:
                sinks.on_estimate(*_estimate(t))
            assert isinstance(info.value.__cause__, ValueError)
    assert first.got == [1.0, 2.0]
    assert last.got == [1.0, 2.0]  # the sink after the failing one still got both
    counters = sinks.counters()
    assert counters["sink_failed_ros2"] == 2
    assert counters["viz_seen"] == 2
    assert "sink_failed_bus" not in counters
    text = caplog.text
    assert "the ros2 output failed on an estimate (2 so far): ValueError: disk on fire" in text
    assert "Traceback" in text  # with its cause
    sinks.close()  # one that fails to close is logged; the others still close
    assert first.closed
    assert last.closed
    assert "closing the ros2 output failed: OSError: cannot close" in caplog.text


def test_samples_go_only_to_the_sinks_that_take_them():
    """A sink that keeps `_Base`'s no-op `on_input` is not called per sample; one with its
    own is, and a duck-typed sink (no `_Base`) always is."""
    from keo_service.live.sinks import _Base

    class Quiet(_Base):
        name = "quiet"

        def on_input(self, sample: object) -> None:  # must never run
            raise AssertionError("called")

    class NoInput(_Base):
        name = "no_input"

    class Takes(_Base):
        name = "takes"

        def __init__(self) -> None:
            self.got: list[object] = []

        def on_input(self, sample: object) -> None:
            self.got.append(sample)

    assert not Sinks([NoInput()]).takes_input
    takes, duck = Takes(), _Recorder("duck")
    sinks = Sinks([NoInput(), takes, duck])
    assert sinks.takes_input
    sinks.on_input("s1")
    assert takes.got == ["s1"]
    with pytest.raises(SinkFailedError, match="the quiet output failed on a sample"):
        Sinks([Quiet()]).on_input("s2")  # its own on_input: called (and here it fails)


def test_a_sink_failing_on_a_sample_is_counted_and_the_ones_after_it_still_get_it(caplog):
    class Fails(_Recorder):
        def on_input(self, sample: object) -> None:
            raise ValueError("bad sample")

    class Keeps(_Recorder):
        def on_input(self, sample: object) -> None:
            self.got.append(float(str(sample)))

    first, bad, last = Keeps("a"), Fails("b"), Keeps("c")
    sinks = Sinks([first, bad, last])
    with caplog.at_level(logging.ERROR, logger="keo.service"):
        with pytest.raises(SinkFailedError, match="the b output failed on a sample"):
            sinks.on_input("1.0")
        with pytest.raises(SinkFailedError):
            sinks.on_input("2.0")
    assert first.got == [1.0, 2.0]
    assert last.got == [1.0, 2.0]
    assert sinks.counters()["sink_failed_b"] == 2
    assert "sink_failed_a" not in sinks.counters()
