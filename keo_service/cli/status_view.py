"""`keo status` as a person reads it: the service's health, uptime, rates, delay with its
standard error, clock domains, counters and newest messages, then each adapter's state, rate,
counters and newest reject messages. Made from the status document (`ServiceStatus` as plain
values, with `adapters`), the same one `keo status --json` prints; fields missing from it
are left out, never guessed."""

from __future__ import annotations

import math
from typing import Any

NEWEST = 5  # reject and service messages shown per source (the JSON has all it carries)
WIDTH = 96


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


def _delay(doc: dict[str, Any]) -> str:
    delay = _number(doc.get("delay_s"))
    if delay is None:
        return "?"
    se = _number(doc.get("delay_se_s"))
    text = f"{delay * 1e3:.2f} ms"
    text += f" ± {se * 1e3:.2f} ms" if se is not None else " (configured, no standard error yet)"
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
