"""Bounded exponential backoff, the one retry policy of adapters and clients.

Hand-written (stdlib): the delay must reset after every good connection and the attempt
count shows in an adapter's status, which a generic retry decorator hides. The caller sleeps
(`asyncio.sleep` in async code), so a retry never blocks an event loop.
"""

from __future__ import annotations

import random
from dataclasses import dataclass

__all__ = ["Backoff"]


@dataclass
class Backoff:
    """Exponential delay between reconnects, bounded by `maximum`, with +-20 % jitter."""

    initial: float = 0.1
    maximum: float = 5.0
    factor: float = 2.0
    _current: float = 0.0

    def next_delay(self) -> float:
        self._current = (
            self.initial if self._current == 0 else min(self._current * self.factor, self.maximum)
        )
        return self._current * random.uniform(0.8, 1.2)

    def reset(self) -> None:
        self._current = 0.0
