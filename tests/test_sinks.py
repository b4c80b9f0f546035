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
