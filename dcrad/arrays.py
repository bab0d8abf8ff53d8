"""Sums over the short axis of (m, 3) arrays, fast.

numpy 2.4's ``a.sum(axis=0)`` and ``a.sum(axis=1)`` on an (m, 3) float64 array
run a strided reduction: 8-16 ms for m = 262144 on the bench machine, against
0.2-1 ms for the same sums taken column by column (bench/RESULTS.md, issue 12).
The solver sums per batch arrays of exactly this shape (ray power, power per
patch hit), so these two helpers stand in for them on the hot path.
"""

from __future__ import annotations

import numpy as np

__all__ = ["colsum", "rowsum"]


def colsum(a: np.ndarray) -> np.ndarray:
    """(c,) sum over the rows of an (m, c) array (``a.sum(axis=0)``), one column at a time."""
    a = np.asarray(a)
    out = np.empty(a.shape[1], np.result_type(a.dtype, np.float64))
    for c in range(a.shape[1]):
        out[c] = a[:, c].sum()
    return out


def rowsum(a: np.ndarray) -> np.ndarray:
    """(m,) sum over the columns of an (m, c) array (``a.sum(axis=1)``), by column adds."""
    a = np.asarray(a)
    if a.shape[1] == 0:
        return np.zeros(a.shape[0], a.dtype)
    out = a[:, 0].copy()
    for c in range(1, a.shape[1]):
        out += a[:, c]
    return out
