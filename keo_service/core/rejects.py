"""Bad input is counted, not fatal: one counter per reason, a total, and the latest messages.

Shared by the estimator and the device codecs, so that every reject reaches status the same
way: `counters[reason]`, `counters["rejected"]` and a bounded list of what, where and what
was expected. A codec sets `at` to where it is in its input (a line and byte offset of the
connection, a datagram's number) before it looks at the next part, so that each message says
where the bad input was: a user with a capture of the stream can find it.
"""

from __future__ import annotations

from collections import Counter, deque

__all__ = ["RejectLog"]


class RejectLog:
    """Counters and the last `keep` messages; bounded whatever the input."""

    def __init__(self, keep: int = 16) -> None:
        self.counters: Counter[str] = Counter()
        self.messages: deque[str] = deque(maxlen=keep)
        self.at = ""  # where the input being looked at is, in words ("" when unknown)

    def reject(self, reason: str, message: str) -> None:
        """Count the reject under `reason` and keep the message, with where it was."""
        self.counters[reason] += 1
        self.counters["rejected"] += 1
        self.messages.append(f"{message} ({self.at})" if self.at else message)

    def note(self, counter: str, message: str) -> None:
        """Something worth counting and telling that is not a reject."""
        self.counters[counter] += 1
        self.messages.append(message)
