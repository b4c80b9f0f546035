"""Bad input is counted, not fatal: one counter per reason, a total, and the latest messages.

Shared by the estimator and the device codecs, so that every reject reaches status the same
way: `counters[reason]`, `counters["rejected"]` and a bounded list of what, where and what
was expected.
"""

from __future__ import annotations

from collections import Counter, deque

__all__ = ["RejectLog"]


class RejectLog:
    """Counters and the last `keep` messages; bounded whatever the input."""

    def __init__(self, keep: int = 16) -> None:
        self.counters: Counter[str] = Counter()
        self.messages: deque[str] = deque(maxlen=keep)

    def reject(self, reason: str, message: str) -> None:
        self.counters[reason] += 1
        self.counters["rejected"] += 1
        self.messages.append(message)

    def note(self, counter: str, message: str) -> None:
        """Something worth counting and telling that is not a reject."""
        self.counters[counter] += 1
        self.messages.append(message)
