"""Carrying a mapped stream's stamps onto its clock mapping's newest line. No I/O.

A stamp in the "device" clock domain is the device's time `d` mapped by a line, `stamp = d +
offset + drift * (d - ref)` (core.clock.ClockMapper), and the line moves while the stream
runs: every quarter second its offset follows the median transport floor and its drift
converges. The device's clock does not move with it: its stamps are as regular as its
oscillator. So stamps mapped while the line moved disagree with each other by the line's
moves, and a delay between two mapped streams fitted from a stretch of them holds only until
either line moves on: a delay refitted every few seconds lags each move by its stretch, while
one fitted under one line per stream and carried along as the lines move (what `Anchor`
does) follows a move at once (docs/timing-delay.md, "Stamps on one line", has the figures).

An anchor is one sample on its line: (stamp, device stamp, the line's drift). Under it every
device stamp of the stream maps to `stamp + (d - device) * (1 + drift)`: the whole stretch on
one line. Two anchors of the same mapping say how far its stamps moved from the older line to
the newer one, at any instant (the lines' drifts may differ: a value that describes an
instant is carried by the move there).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Anchor", "moved"]


@dataclass(frozen=True)
class Anchor:
    stamp: float  # the sample's mapped stamp (s, the host's clock)
    device: float  # its device stamp (s, the device's clock)
    drift: float  # the drift of the line it was mapped with (s/s)

    def at(self, device: np.ndarray) -> np.ndarray:
        """The stamps of these device times under this anchor's line."""
        out: np.ndarray = self.stamp + (device - self.device) * (1.0 + self.drift)
        return out

    def moved_since(self, older: Anchor, at: float | None = None) -> float:
        """How far the stream's stamps moved from `older`'s line to this one's (s; positive:
        later) at stream time `at` (default: this anchor's). Where matters when the two
        lines' drifts differ: a value that describes an instant moves as the lines differ
        there."""
        d = self.device if at is None else self.device + (at - self.stamp) / (1.0 + self.drift)
        # stamp differences first: the stamps themselves are ~1e9 s, their lines agree to us
        return (self.stamp - older.stamp) + (
            (d - self.device) * (1.0 + self.drift) - (d - older.device) * (1.0 + older.drift)
        )


def moved(newer: Anchor | None, older: Anchor | None, at: float | None = None) -> float:
    """`newer.moved_since(older, at)`, 0 when either is missing (a stream whose stamps are not
    mapped by a line: a shared clock, receipt times; or not seen yet)."""
    if newer is None or older is None:
        return 0.0
    return newer.moved_since(older, at)
