"""Sums over the short axis of (m, 3) arrays, and row gathers/scatters, fast.

numpy 2.4's ``a.sum(axis=0)`` and ``a.sum(axis=1)`` on an (m, 3) float64 array
run a strided reduction: 8-16 ms for m = 262144 on the bench machine, against
0.2-1 ms for the same sums taken column by column (bench/RESULTS.md).
The solver sums per batch arrays of exactly this shape (ray power, power per
patch hit), so these two helpers stand in for them on the hot path.  Likewise
``take_rows`` / ``put_rows`` stand in for ``a[rows]`` and ``a[rows] = v`` on the
rows a batch hit (3-4x faster; figures in their docstrings).
"""

from __future__ import annotations

import numpy as np

__all__ = ["colsum", "put_rows", "rowsum", "take_rows", "ray_runs"]


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


def take_rows(a: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``a[rows]`` for an (n,) or (n, c) array: ``np.take`` along axis 0.

    numpy 2.4's fancy indexing ``a[rows]`` of an (n, 3) float64 array is 3-4x slower
    than ``np.take(a, rows, axis=0)`` at 80k rows of a 201k-row table (0.78 vs 0.20 ms).
    """
    return np.take(a, rows, axis=0)


def put_rows(a: np.ndarray, rows: np.ndarray, values: np.ndarray) -> None:
    """``a[rows] = values`` for a C-contiguous (n, c) array: one scatter of c-wide rows.

    Each row is viewed as one c * itemsize byte item, so the scatter moves whole rows
    (``np.put`` on the row view: 0.23 ms for 80k rows of a 201k x 3 table against 0.78
    for ``a[rows] = values``; 1.4 vs 4.7 ms at 1.27M).  Other layouts fall back to
    fancy assignment.  Rows should be distinct (a repeated row keeps one of its values).
    """
    if a.ndim == 2 and a.flags.c_contiguous and len(rows):
        row = np.dtype((np.void, a.dtype.itemsize * a.shape[1]))
        v = np.ascontiguousarray(values, a.dtype).reshape(len(rows), a.shape[1])
        np.put(a.view(row).reshape(-1), rows, v.view(row).reshape(-1))
    else:
        a[rows] = values


def ray_runs(counts: np.ndarray, limit: int):
    """Yield (lo, hi, owner, index): consecutive runs of entries whose ``counts`` (rays each) sum to
    at most ``limit`` (one entry at least), so that a batch of rays stays within memory whatever the
    counts; per ray of the run, its entry (``owner``, 0 .. hi - lo - 1) and its number among that
    entry's rays (``index``).  Runs without rays are skipped."""
    ends = np.cumsum(counts)
    lo = 0
    while lo < len(counts):
        hi = max(int(np.searchsorted(ends, (ends[lo - 1] if lo else 0) + limit, side="right")), lo + 1)
        c = counts[lo:hi]
        m = int(c.sum())
        if m:
            yield lo, hi, np.repeat(np.arange(hi - lo), c), np.arange(m) - np.repeat(np.cumsum(c) - c, c)
        lo = hi
