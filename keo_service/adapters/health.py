"""What a user needs to see of an adapter, in its log and in its status: its state, its rate,
its rejects as rate-limited warnings with the reason, a connected device gone silent, and a
device that does not speak the configured protocol.

Pure bookkeeping over the adapter's own status (counters and the codec's newest reject
messages); the adapter calls `tick` from a small periodic task, so nothing here touches the
network or the codecs.
"""

from __future__ import annotations

import collections
import logging
import math
from typing import Any

from keo_service.io.protocols import Section, protocol_for

WARN_EVERY_S = 5.0  # at most one reject warning per adapter this often
RATE_WINDOW_S = 5.0
MISMATCH_REJECTS = 3  # rejects with nothing valid on a connection: not this protocol


def rejects_of(status: dict[str, Any]) -> tuple[int, list[str]]:
    """Total rejects of the adapter's codec(s) and their newest messages."""
    total = 0
    for part in ("decoder", "parser"):
        counters = status.get(part)
        if isinstance(counters, dict):
            total += int(counters.get("rejected", 0))
    messages = status.get("messages")
    return total, [str(m) for m in messages] if isinstance(messages, list) else []


class AdapterHealth:
    """State, rate, silence and reject warnings of one adapter.

    `section`: the config section of its device ("robot", "tracker"), so messages can name
    the keys to fix; `protocol`: the configured protocol; `silent_after_s`: how long a
    connected device may send nothing before it is reported silent.
    """

    def __init__(
        self,
        name: str,
        section: str,
        protocol: str,
        endpoint: str,
        silent_after_s: float,
        log: logging.Logger,
    ) -> None:
        self.name, self.section, self.protocol = name, section, protocol
        self.endpoint = endpoint
        self.silent_after_s = silent_after_s
        self.log = log
        self.state = "starting"
        self.silent_events = 0
        self.mismatch: str = ""
        self._last_published = 0
        self._last_rejected = 0
        self._last_data_at: float | None = None
        self._connections = 0
        self._connected_at: float | None = None
        self._published_at_connect = 0
        self._rejects_at_connect = 0
        self._warned_rejects = 0
        self._last_warn = -math.inf
        self._silent = False
        self.rate_hz = 0.0
        self._rates: collections.deque[tuple[float, int]] = collections.deque()
        # the newest interval's rejects summarised for the service's log, until taken
        self._reject_summary = ""

    @property
    def expected(self) -> str:
        """What the device should be, in words (the protocol table's)."""
        section: Section = "tracker" if self.section == "tracker" else "robot"
        try:
            return protocol_for(section, self.protocol).words
        except KeyError:
            return self.protocol

    def tick(self, status: dict[str, Any], now: float) -> None:
        """Look at the adapter's status at monotonic time `now`; log what changed."""
        counters = status.get("counters", {})
        published = int(counters.get("published", 0))
        rejected, messages = rejects_of(status)
        connections = counters.get("connections")
        if connections is None:  # no TCP connection of its own (ROS 2, UDP): data is contact
            connected = published > 0 or rejected > 0
            connections = int(connected)
        else:
            connected = int(connections) > int(counters.get("disconnects", 0))
        if int(connections) != self._connections:  # a new connection: judge it afresh, from
            # the counts before it (a codec made anew per connection starts from zero)
            self._connections = int(connections)
            self._connected_at = now
            self._published_at_connect = min(self._last_published, published)
            self._rejects_at_connect = min(self._last_rejected, rejected)
            self._last_data_at = None
            self._rates.clear()  # the rate of this connection
            self.mismatch = ""
            self._silent = False
        self._last_rejected = rejected
        if published != self._last_published:
            self._last_published = published
            self._last_data_at = now
        self._rates.append((now, published))
        while self._rates and now - self._rates[0][0] > RATE_WINDOW_S:
            self._rates.popleft()
        (t_a, n_a), (t_b, n_b) = self._rates[0], self._rates[-1]
        self.rate_hz = (n_b - n_a) / (t_b - t_a) if t_b > t_a else 0.0
        self._warn_rejects(rejected, messages, now)
        if not connected:
            self.state = "connecting" if self._connections == 0 else "disconnected"
            return
        self._judge_protocol(published, rejected, messages, now)
        self._judge_silence(now)
        if self.mismatch:
            self.state = "wrong_protocol"
        elif self._silent:
            self.state = "silent"
        else:
            self.state = "receiving" if self._last_data_at is not None else "connected"

    def _warn_rejects(self, rejected: int, messages: list[str], now: float) -> None:
        """At most once per WARN_EVERY_S: the rejects since the last warning, in the adapter's
        log with the newest messages, and summarised for the service's log with the first
        (each message says where in the input it was)."""
        new = rejected - self._warned_rejects
        if new <= 0 or now - self._last_warn < WARN_EVERY_S:
            return
        newest = "; ".join(messages[-min(new, 3) :]) or "no message"
        interval = "" if self._last_warn == -math.inf else f" in the last {WARN_EVERY_S:g} s"
        self.log.warning("%s: %d input(s) rejected%s: %s", self.name, new, interval, newest)
        if not messages:
            first = "no message kept"
        elif new <= len(messages):
            first = f"the first: {messages[-new]}"
        else:  # more than the codec keeps: the oldest it still has
            first = f"the earliest kept: {messages[0]}"
        self._reject_summary = (
            f"{new} input(s) rejected{interval} from {self.endpoint}; {first}"
            + (f"; the newest: {messages[-1]}" if new > 1 and messages else "")
        )
        self._warned_rejects, self._last_warn = rejected, now

    def take_reject_summary(self) -> str:
        """The newest interval's rejects in one line, once ("" when there were none)."""
        summary, self._reject_summary = self._reject_summary, ""
        return summary

    def _judge_protocol(
        self, published: int, rejected: int, messages: list[str], now: float
    ) -> None:
        """Rejects and nothing valid since the connection began: several, or any for as long
        as silence takes (a codec that counts one reject per stretch of bad bytes)."""
        if self.mismatch or published > self._published_at_connect:
            return
        bad = rejected - self._rejects_at_connect
        since = now - self._connected_at if self._connected_at is not None else 0.0
        if bad >= MISMATCH_REJECTS or (bad > 0 and since >= self.silent_after_s):
            self.mismatch = (
                f"the device at {self.endpoint} does not speak {self.protocol}: {bad} inputs "
                f"rejected and none valid since it connected (newest: "
                f"{messages[-1] if messages else '?'}); expected {self.expected}: check "
                f"{self.section}.port and {self.section}.protocol"
            )
            self.log.error("%s: %s", self.name, self.mismatch)

    def _judge_silence(self, now: float) -> None:
        since = self._last_data_at if self._last_data_at is not None else self._connected_at
        if since is None:
            return
        quiet = now - since
        if quiet >= self.silent_after_s and not self._silent:
            self._silent = True
            self.silent_events += 1
            if self.mismatch:
                pass  # said already, and better
            elif self._last_data_at is None:
                self.log.warning(
                    "%s: connected to %s but nothing arrived in %.1f s (%s.silent_after_s): "
                    "is it %s? check %s.port",
                    self.name,
                    self.endpoint,
                    quiet,
                    self.section,
                    self.expected,
                    self.section,
                )
            else:
                self.log.warning(
                    "%s: the device at %s went silent: nothing for %.1f s (%s.silent_after_s "
                    "= %g) while still connected",
                    self.name,
                    self.endpoint,
                    quiet,
                    self.section,
                    self.silent_after_s,
                )
        elif quiet < self.silent_after_s and self._silent:
            self._silent = False
            self.log.info("%s: data again from %s", self.name, self.endpoint)

    def summary(self, now: float) -> dict[str, Any]:
        """The fields `keo status` shows for this adapter (safe from another thread: plain
        values only)."""
        age = None if self._last_data_at is None else round(now - self._last_data_at, 3)
        return {
            "state": self.state,
            "endpoint": self.endpoint,
            "protocol": self.protocol,
            "rate_hz": round(self.rate_hz, 2),
            "last_data_age_s": age,
            "silent_events": self.silent_events,
            "problem": self.mismatch,
        }
