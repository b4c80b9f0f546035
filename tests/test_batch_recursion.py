"""The batch observer's recursion, bit for bit: `keo estimate` writes the same file whatever
the layout its arrays take on the way (docs/performance.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from keo_service.core.batch import first_order_recursion


def _block_arithmetic(x0: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """x_k = b_k x_{k-1} + c_k in blocks of max(16, isqrt(n)) rows, written out one block and
    one row at a time: from zero inside each block (with the running product of b), the state
    carried from block end to block end, then each row's carry times its product added."""
    n, channels = c.shape
    b = np.broadcast_to(b, (n, channels))
    size = max(16, math.isqrt(n))
    out = np.empty((n, channels))
    state = x0.astype(float)
    for start in range(0, n, size):
        rows = range(start, min(start + size, n))
        local = np.empty((len(rows), channels))
        product = np.empty((len(rows), channels))
        for i, k in enumerate(rows):
            local[i] = c[k] if i == 0 else c[k] + b[k] * local[i - 1]
            product[i] = b[k] if i == 0 else b[k] * product[i - 1]
        out[start : start + len(rows)] = local + product * state
        state = product[-1] * state + local[-1]
    return out


@pytest.mark.parametrize("n", [1, 15, 16, 17, 300, 1025])
@pytest.mark.parametrize("shared", [False, True])
def test_recursion_is_the_block_arithmetic_bit_for_bit(n, shared):
    rng = np.random.default_rng(n)
    channels = 3
    b = np.exp(-rng.uniform(0, 3, (n, 1 if shared else channels)))
    c = rng.normal(size=(n, channels))
    x0 = rng.normal(size=channels)
    want = _block_arithmetic(x0, b, c)
    got = first_order_recursion(x0, b, c)
    assert got.tobytes() == want.tobytes()


def test_recursion_writes_into_rows_of_a_column_major_table():
    rng = np.random.default_rng(2)
    n, channels = 1000, 6
    b = np.exp(-rng.uniform(0, 1, (n, 1)))
    c = rng.normal(size=(n, channels))
    x0 = np.zeros(channels)
    table = np.full((n + 20, channels), -1.0, order="F")
    returned = first_order_recursion(x0, b, c, out=table[10 : 10 + n])
    assert np.shares_memory(returned, table)
    assert table[10 : 10 + n].tobytes() == _block_arithmetic(x0, b, c).tobytes()
    assert (table[:10] == -1.0).all()  # nothing written outside those rows
    assert (table[10 + n :] == -1.0).all()
