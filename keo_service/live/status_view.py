"""The service's status as a person reads it, and what changed between two of them.

`status_table`: `keo status` (the service's health, uptime, rates, delay with its standard
error, clock domains, counters and newest messages, then each adapter's state, rate, counters
and newest reject messages). `StatusEvents` and `StatusRates`: the differences between
successive snapshots, as events for a text log and as rates per second (Rerun's view draws
them). Both read the status document (`ServiceStatus` as plain values, with `adapters`), the
same one `keo status --json` prints; fields missing from it are left out, never guessed.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from typing import Any

from keo_service.live.messages import ADAPTER_TROUBLE

NEWEST = 5  # reject and service messages shown per source (the JSON has all it carries)
WIDTH = 96
MAX_LOG_MESSAGES_PER_STATUS = 3  # reject messages copied to the text log per status row
EVENT_GAP_S = 1.0  # a flapping health or flag: at most one text log entry this often
# counters that count work done, not trouble: shown as stream rates, not as rejects
THROUGHPUT = frozenset(
    {"encoder_samples", "tracker_samples", "estimates", "published", "received", "channels"}
)
THROUGHPUT_WORDS = ("samples", "frames", "published", "received", "sent", "bytes", "packets")
EVENT_WORDS = ("connect", "clock", "epoch")  # counters whose increase goes to the text log


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(float(value)) else None


def _duration(seconds: Any) -> str:
    s = _number(seconds)
    if s is None:
        return "?"
    if s < 120:
        return f"{s:.1f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"


def _hz(value: Any) -> str:
    v = _number(value)
    return "?" if v is None else f"{v:.1f} Hz"


def _wrap(label: str, items: list[str], indent: int = 2) -> list[str]:
    """`label  a · b · c`, wrapped under the first item at WIDTH."""
    head = " " * indent + f"{label:<16}"
    if not items:
        return [head + "-"]
    lines, line = [], head
    for item in items:
        sep = "" if line == head else " · "
        if line != head and len(line) + len(sep) + len(item) > WIDTH:
            lines.append(line)
            line, sep = " " * len(head), ""
        line += sep + item
    lines.append(line)
    return lines


def _counters(counters: Any) -> list[str]:
    """Non-zero counters as `name value`, sorted by name; the zeros summed up in one item."""
    if not isinstance(counters, dict):
        return []
    items = [f"{k} {v}" for k, v in sorted(counters.items()) if v]
    zeros = sum(1 for v in counters.values() if not v)
    if zeros:
        items.append(f"({zeros} more at 0)")
    return items


def _stream_time(t: float) -> str:
    """A stream time on the host clock (seconds since the epoch) as the time of day in UTC, one
    a user can match with the log; a device's or a simulation's own time as it is."""
    if t < 1e9:
        return f"{t:.1f} s"
    return time.strftime("%H:%M:%S UTC", time.gmtime(t))


def _field(state: Any, name: str) -> Any:
    """A field of a `DelayState`, as the struct or as the status document's plain values."""
    return state.get(name) if isinstance(state, Mapping) else getattr(state, name, None)


def delay_tracking_text(state: Any) -> str:
    """The delay in use's source and the tracker's last decision, one line: the words of
    `keo status`, the status document's `delay_tracking` (and so the Rerun view's event log).
    The one place a `DelayState` (or its plain values) becomes text; the decision's reason
    carries no delay of a fit, so the line shows one delay, the one in use."""
    source = str(_field(state, "source") or "?")
    t = _number(_field(state, "source_t"))
    if source == "confirmed":
        where = "configured, confirmed by the fit" + ("" if t is None else f" at {_stream_time(t)}")
    elif source == "fit":
        where = "fit" + ("" if t is None else f" at {_stream_time(t)}")
    else:
        where = source
    if _field(state, "settled") is False:
        where += ", unsettled"
    verdict, reason = _field(state, "verdict"), _field(state, "reason")
    decision = str(verdict or "") + (f": {reason}" if reason else "")
    return f"{where}; {decision}" if decision else where


REFINEMENTS_SAID_S = 30.0  # the log says the delay's refinements at most this often (stream s)


def _ms(value: float) -> str:
    return f"{value * 1e3:.3f} ms"


class DelayLog:
    """Which of the online delay tracker's decisions the service's log says, and in what
    words. A user reading the log must be able to follow the delay in use: every decision is
    logged with the fits' values (`text`, the tracker's own line), at INFO when its kind
    changes or the delay in use moved beyond its standard error since last said, else at
    DEBUG; and the delay in use's quiet changes get their own INFO line, with the value in
    use, rendered through `delay_tracking_text`: the configured delay confirmed by a fit
    (once per confirmation), and the refinements within its standard error (at most one line
    per `every_s` of stream time, counting those between; a refinement alone changes no
    kind, so a run of them toggled nothing and was never said)."""

    def __init__(self, delay_s: float | None, every_s: float = REFINEMENTS_SAID_S) -> None:
        self.every_s = every_s
        self._kind = ""  # the kind of decision last said (a refinement is no kind of its own)
        self._value = delay_s  # the delay in use last said (s)
        self._source = ""  # the source last seen
        self._refinements = 0  # the tracker's refinements counted when last said
        self._refined_said_t = -math.inf  # the stream time of the last refinement line

    def lines(
        self,
        kind: str,
        text: str,
        delay_s: float | None,
        se_s: float | None,
        state: Any,
        refinements: int,
    ) -> list[tuple[int, str]]:
        """The (level, words) to log after a decision: `kind` and `text` the tracker's
        (`state`, `last_result`), `delay_s` and `se_s` the delay in use now, `state` the
        `DelayState`, `refinements` the tracker's count of them so far."""
        out: list[tuple[int, str]] = []
        before, now = self._value, delay_s
        if now is None or before is None:
            moved = now is not before
        else:
            moved = abs(now - before) > (se_s or 0.0)
        source = str(_field(state, "source") or "")
        confirmed = source == "confirmed" and self._source != "confirmed"
        self._source = source
        refined = refinements - self._refinements
        t = _number(_field(state, "decided_t"))
        due = t is None or not 0.0 <= t - self._refined_said_t < self.every_s  # or went back
        said = kind if kind != "refined" else self._kind
        if (said != self._kind or moved) and not (kind == "refined" and refined > 0):
            out.append((logging.INFO, f"delay tracking: {text}"))
        else:
            out.append((logging.DEBUG, f"delay tracking: {text}"))
        self._kind = said
        in_use = "delay in use ?" if now is None else f"delay in use {_ms(now)}"
        if se_s is not None:
            in_use += f" ± {_ms(se_s)}"
        if confirmed:
            out.append((logging.INFO, f"{in_use}: {delay_tracking_text(state)}"))
        if refined > 0 and (due or moved):
            count = "1 refinement" if refined == 1 else f"{refined} refinements"
            was = "" if before is None else f", was {_ms(before)}"
            out.append((logging.INFO, f"{in_use} ({count}{was}): {delay_tracking_text(state)}"))
            self._refinements = refinements
            self._refined_said_t = -math.inf if t is None else t
        if out[0][0] == logging.INFO or len(out) > 1:
            self._value = now
        return out

    def forget(self, delay_s: float | None) -> None:
        """A delay set anew (a reload): said from it on."""
        self._value = delay_s


def _unknown(doc: dict[str, Any]) -> bool:
    """Nothing configured and nothing found yet (an older service says it only in words)."""
    state = doc.get("delay_state")
    if isinstance(state, Mapping):
        return state.get("source") == "unknown"
    return str(doc.get("delay_tracking") or "").startswith("unknown")


def _delay(doc: dict[str, Any]) -> str:
    delay = _number(doc.get("delay_s"))
    if delay is None:
        return "?"
    se = _number(doc.get("delay_se_s"))
    text = f"{delay * 1e3:.2f} ms"
    if se is not None:
        text += f" ± {se * 1e3:.2f} ms"
    elif _unknown(doc):
        text = f"not known yet ({text} in use)"
    else:
        text += " (configured, no standard error yet)"
    drift = _number(doc.get("drift"))
    if drift:
        text += f", drift {drift * 1e6:+.1f} ppm"
    return text


def _estimate(last: Any) -> list[str]:
    if not isinstance(last, dict):
        return _wrap("last estimate", ["none yet"])
    channels = last.get("channels") or []
    values = last.get("estimate") or []
    items = []
    for name, value in zip(channels, values, strict=False):
        v = _number(value)
        unit = "mm" if str(name).startswith("p") else "mrad"
        items.append(f"{name} {v * 1e3:+.3f} {unit}" if v is not None else f"{name} ?")
    flags = last.get("flags") or []
    if flags:
        items.append("flags " + ",".join(map(str, flags)))
    return _wrap("last estimate", items)


def _messages(label: str, messages: Any, indent: int = 2) -> list[str]:
    if not isinstance(messages, list) or not messages:
        return []
    newest = [str(m) for m in messages[-NEWEST:]]
    more = len(messages) - len(newest)
    head = f"{label} (newest {len(newest)} of {len(messages)})" if more else label
    return [" " * indent + head + ":"] + [" " * (indent + 2) + "- " + m for m in newest]


def service_lines(doc: dict[str, Any]) -> list[str]:
    """The service's part of the table."""
    lines = [
        f"keo status: cell {doc.get('cell', '?')}: {doc.get('health', '?')}, "
        f"up {_duration(doc.get('uptime_s'))}"
    ]
    rates = doc.get("rates_hz")
    if isinstance(rates, dict):
        lines += _wrap("rates", [f"{k} {_hz(v)}" for k, v in rates.items()])
    # one delay, shown once: the delay in use, its uncertainty, its source and the tracker's
    # last decision (the source leads the tracker's line)
    tracking = doc.get("delay_tracking")
    lines += _wrap("delay", [_delay(doc) + (f"; {tracking}" if tracking else "")])
    domains = doc.get("clock_domains")
    if isinstance(domains, dict):
        lines += _wrap("clock domains", [f"{k} {v}" for k, v in sorted(domains.items())])
    if "alignment" in doc:
        lines += _wrap("alignment", [str(doc["alignment"])])
    lines += _estimate(doc.get("last_estimate"))
    lines += _wrap("counters", _counters(doc.get("counters")))
    lines += _messages("messages", doc.get("messages"))
    return lines


def _adapter_counters(status: dict[str, Any]) -> list[str]:
    """The adapter's own counters, then its codec's (decoder or parser) and clock's."""
    items = _counters(status.get("counters"))
    for part in ("decoder", "parser"):
        codec = status.get(part)
        if isinstance(codec, dict) and any(codec.values()):
            items += [f"{part}.{k} {v}" for k, v in sorted(codec.items()) if v]
    clock = status.get("clock")
    if isinstance(clock, dict) and isinstance(clock.get("counters"), dict):
        items += [f"clock.{k} {v}" for k, v in sorted(clock["counters"].items()) if v]
    return items


def adapter_lines(adapters: Any) -> list[str]:
    """Each adapter: a row of state, protocol, endpoint, rate and data age, then its counters
    and newest reject messages."""
    if not isinstance(adapters, dict) or not adapters:
        return ["adapters: none answered"]
    rows = [("adapter", "state", "protocol", "endpoint", "rate", "last data")]
    for name, status in sorted(adapters.items()):
        s = status if isinstance(status, dict) else {}
        age = _number(s.get("last_data_age_s"))
        rows.append(
            (
                str(name),
                str(s.get("state", "?")),
                str(s.get("protocol", "?")),
                str(s.get("endpoint", "?")),
                _hz(s.get("rate_hz")),
                "never" if age is None else f"{age:.2f} s ago",
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["adapters:"]
    lines += [
        "  " + "  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows
    ]
    for name, status in sorted(adapters.items()):
        s = status if isinstance(status, dict) else {}
        lines.append(f"  {name}:")
        lines += _wrap("counters", _adapter_counters(s), indent=4)
        for key, label in (("problem", "problem"), ("last_error", "last error")):
            if s.get(key):
                lines += _wrap(label, [str(s[key])], indent=4)
        if s.get("silent_events"):
            lines += _wrap("silent", [f"{s['silent_events']} times"], indent=4)
        lines += _messages("rejects", s.get("messages"), indent=4)
        clock = s.get("clock")
        if isinstance(clock, dict):
            lines += _messages("clock", clock.get("messages"), indent=4)
    return lines


def status_table(doc: dict[str, Any]) -> str:
    """The whole status document as text (ends with a newline)."""
    return "\n".join([*service_lines(doc), "", *adapter_lines(doc.get("adapters"))]) + "\n"


# ---- what changed between two snapshots (the text log and the rates of Rerun's view) ----


def _group(name: str) -> str | None:
    """Where a service counter is drawn: 'held', 'rejects', or None (throughput)."""
    if name in THROUGHPUT or name == "rejected":
        return None
    if name.startswith("held_"):
        return "held"
    return "rejects"


class StatusRates:
    """Rates per second from the service's running counters: differences between status
    snapshots over their host times. A reason gets its series once its counter is above zero
    and keeps it (zero while the counter stands still); `total` is always there, so a quiet plot
    shows a zero line. A counter that went back (a restarted service) counts as no step."""

    def __init__(self) -> None:
        self._prev: dict[str, int] = {}
        self._prev_s: float | None = None
        self.seen: dict[str, set[str]] = {"rejects": set(), "held": set()}

    def update(
        self, counters: Mapping[str, int], now_s: float
    ) -> dict[str, dict[str, float]] | None:
        """{'rejects': {reason: per_s, 'total': per_s}, 'held': {...}}, or None for the first
        snapshot (and one at the same host time as the previous)."""
        prev, prev_s = self._prev, self._prev_s
        self._prev = dict(counters)
        self._prev_s = now_s
        for name, value in counters.items():
            group = _group(name)
            if group is not None and value > 0:
                self.seen[group].add(name)
        if prev_s is None or now_s <= prev_s:
            return None
        dt = now_s - prev_s
        out: dict[str, dict[str, float]] = {"rejects": {}, "held": {}}
        for group, names in self.seen.items():
            for name in names:
                step = counters.get(name, 0) - prev.get(name, 0)
                reason = name.removeprefix("held_") if group == "held" else name
                out[group][reason] = max(step, 0) / dt
            out[group]["total"] = sum(out[group].values())
        return out


def adapter_counters(adapters: Mapping[str, Any]) -> dict[str, int]:
    """The adapters' own trouble counters, named '<adapter>.<counter>' (throughput left out)."""
    out: dict[str, int] = {}
    for name, doc in adapters.items():
        counters = doc.get("counters") if isinstance(doc, Mapping) else None
        if not isinstance(counters, Mapping):
            continue
        for key, value in counters.items():
            if isinstance(value, int) and not any(w in key for w in THROUGHPUT_WORDS):
                out[f"{name}.{key}"] = value
    return out


class StatusEvents:
    """What in a status snapshot is an event for the text log: a change of health, of an
    adapter's state or clock epoch, of a stream's clock domain, of what delay tracking
    says; a counter of (re)connections or clock resets going up; new reject messages."""

    def __init__(self) -> None:
        self._prev: dict[str, Any] | None = None
        self._health: Any = None  # as last written to the log
        self._health_at = -math.inf
        self._flips = 0  # health changes since then, not written

    def _health_event(self, health: Any, previous: Any, t: float) -> list[tuple[str, str]]:
        """A health that flaps is written at most every EVENT_GAP_S, with how often it
        changed meanwhile; the health it settles on is always written."""
        if health != previous:
            self._flips += 1
        if health == self._health or t - self._health_at < EVENT_GAP_S:
            return []
        text = f"health {self._health} -> {health}"
        if self._flips > 1:
            text += f" ({self._flips} changes since the last entry)"
        self._health, self._health_at, self._flips = health, t, 0
        return [("INFO" if health == "ok" else "WARN", text)]

    def update(self, status: Mapping[str, Any], t: float = 0.0) -> list[tuple[str, str]]:
        """(level, text) pairs, oldest first; `t`: the snapshot's time (s)."""
        prev, now = self._prev, _snapshot(status)
        self._prev = now
        out: list[tuple[str, str]] = []
        if prev is None:
            self._health, self._health_at = now["health"], t
            out.append(("INFO", f"health {now['health']}"))
            for name, state in now["adapters"].items():
                out += _adapter_event(name, state, {})
            return out
        out += self._health_event(now["health"], prev["health"], t)
        for name, state in now["adapters"].items():
            out += _adapter_changes(name, state, prev["adapters"].get(name, {}))
        for stream, domain in now["clock_domains"].items():
            old = prev["clock_domains"].get(stream)
            if old is not None and old != domain:
                out.append(("WARN", f"{stream} clock domain {old} -> {domain}"))
        out += _counter_events(now["counters"], prev["counters"])
        if now["delay_tracking"] and now["delay_tracking"] != prev["delay_tracking"]:
            out.append(("INFO", f"delay tracking: {now['delay_tracking']}"))
        old_messages = set(prev["messages"])
        fresh = [m for m in now["messages"] if m not in old_messages]
        for message in fresh[-MAX_LOG_MESSAGES_PER_STATUS:]:
            out.append(("WARN", message))
        return out


def _snapshot(status: Mapping[str, Any]) -> dict[str, Any]:
    """The parts of a status document whose change is an event."""
    counters = dict(status.get("counters") or {})
    adapters = status.get("adapters") or {}
    counters.update(adapter_counters(adapters))
    return {
        "health": status.get("health"),
        "clock_domains": dict(status.get("clock_domains") or {}),
        "adapters": {
            name: _adapter_state(doc) for name, doc in adapters.items() if isinstance(doc, Mapping)
        },
        "delay_tracking": status.get("delay_tracking"),
        "counters": counters,
        "messages": list(status.get("messages") or []),
    }


def _counter_events(now: Mapping[str, int], before: Mapping[str, int]) -> list[tuple[str, str]]:
    """A counter of (re)connections or clock resets that went up."""
    out = []
    for name, value in now.items():
        if any(w in name for w in EVENT_WORDS):
            step = value - before.get(name, 0)
            if step > 0:
                out.append(("WARN", f"{name} +{step} (now {value})"))
    return out


def _adapter_event(
    name: str, state: Mapping[str, Any], before: Mapping[str, Any]
) -> list[tuple[str, str]]:
    """An adapter's own state change (silent, back, reconnected, wrong protocol), as it put
    it on its status key: once per `event_seq`."""
    event = state.get("event")
    if not event or state.get("event_seq") == before.get("event_seq"):
        return []
    words = state.get("level")
    if words in ("warning", "error"):  # the adapter's own judgement of its event
        level = "WARN" if words == "warning" else "ERROR"
    else:
        level = "WARN" if state.get("state") in ADAPTER_TROUBLE else "INFO"
    return [(level, f"{name}: {event}")]


def _adapter_changes(
    name: str, state: Mapping[str, Any], before: Mapping[str, Any]
) -> list[tuple[str, str]]:
    """What changed in one adapter's state between two snapshots: its own event, else
    (an adapter that publishes none) the state as compared here; its clock."""
    out = _adapter_event(name, state, before)
    for key, value in state.items():
        if key in ("event", "event_seq", "level") or (key == "state" and "event" in state):
            continue  # said by the adapter's event, in its own words
        if before.get(key) != value and key in before:
            level = "WARN" if key != "state" or value not in ("connected", "ok") else "INFO"
            out.append((level, f"{name}: {key} {before.get(key)} -> {value}"))
    return out


def _adapter_state(doc: Mapping[str, Any]) -> dict[str, Any]:
    """The parts of an adapter's status whose change is an event (`event`, `event_seq`:
    the adapter's own words for a change of state, when it published one)."""
    out: dict[str, Any] = {}
    for key in ("state", "connected", "event", "event_seq", "level"):
        if key in doc:
            out[key] = doc[key]
    clock = doc.get("clock")
    if isinstance(clock, Mapping):
        for key in ("domain", "epoch"):  # the epoch counts the clock's fresh starts
            if key in clock:
                out[f"clock {key}"] = clock[key]
    return out
