"""The batch path's merged order of the two streams and its bracket, against a plain merge
and bisect: sorted streams (counted from one search), ties, and unsorted or non-finite
stamps (the general path)."""

from __future__ import annotations

import bisect
import math
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from keo_service.core.batch import _bracket, _merged_order


def _plain_merge(enc: list[float], trk: list[float]) -> tuple[list[int], list[int]]:
    """Positions in the merge the offline runner makes: an encoder sample goes first while
    its stamp is not after the next tracker sample's."""
    enc_pos, trk_pos = [], []
    i = j = 0
    while i < len(enc) or j < len(trk):
        if j == len(trk) or (i < len(enc) and not enc[i] > trk[j]):
            enc_pos.append(i + j)
            i += 1
        else:
            trk_pos.append(i + j)
            j += 1
    return enc_pos, trk_pos


def _streams(rng: np.random.Generator, kind: str) -> tuple[np.ndarray, np.ndarray]:
    m, n = (int(v) for v in rng.integers(0, 30, 2))
    step = float(rng.choice([0.5, 1.0, 0.001]))  # coarse grids make ties
    enc = np.sort(np.round(rng.uniform(0.0, 10.0, m) / step) * step)
    trk = np.sort(np.round(rng.uniform(-1.0, 11.0, n) / step) * step)
    if kind == "unsorted" and n > 1:
        trk = rng.permutation(trk)
    if kind == "nan" and n:
        trk[rng.integers(n)] = math.nan
    if kind == "inf" and m:
        enc[-1] = math.inf
    return enc, trk


@pytest.mark.parametrize("kind", ["sorted", "unsorted", "nan", "inf"])
def test_merged_order_is_the_plain_merge(kind: str) -> None:
    rng = np.random.default_rng(48)
    for _ in range(400):
        enc, trk = _streams(rng, kind)
        enc_pos, trk_pos = _merged_order(enc, trk)
        want_enc, want_trk = _plain_merge(enc.tolist(), trk.tolist())
        assert enc_pos.tolist() == want_enc
        assert trk_pos.tolist() == want_trk


def test_ties_put_the_encoder_first() -> None:
    enc_pos, trk_pos = _merged_order(np.array([1.0, 2.0, 2.0]), np.array([0.0, 2.0, 2.0, 3.0]))
    assert enc_pos.tolist() == [1, 2, 3]
    assert trk_pos.tolist() == [0, 4, 5, 6]


@pytest.mark.parametrize("offset", [0.0, 0.25, -0.5])
def test_bracket_first_cover_is_bisect_left(offset: float) -> None:
    """The first encoder sample at or after each tracker sample's encoder time."""
    rng = np.random.default_rng(11)
    for _ in range(300):
        E = np.unique(np.round(rng.uniform(0.0, 10.0, int(rng.integers(1, 30))) * 4) / 4)
        T = np.unique(np.round(rng.uniform(-1.0, 11.0, int(rng.integers(1, 40))) * 4) / 4)
        delay = SimpleNamespace(encoder_times=lambda t, o=offset: t - o)
        streams: Any = SimpleNamespace(E=E, T=T)
        where = _bracket(SimpleNamespace(delay=delay), streams)  # type: ignore[arg-type]
        want = [bisect.bisect_left(E.tolist(), x) for x in (T - offset).tolist()]
        assert where.first_cover.tolist() == want
