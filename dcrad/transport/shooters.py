"""Shooter selection without a pass over all patches per batch: a lazily rebuilt pool.

Progressive refinement shoots the K patches with the most unshot power,
``priority_i = sum_c |dB_ic| * A_i`` (W).  Sorting the whole table for every
batch made selection O(patches) per batch.  ``ShooterPool`` keeps the rows
that can be among the top K:

* ``rebuild`` (one O(n) pass) takes the ``size`` largest rows and remembers
  ``bound``, the largest priority left outside.
* Invariant: every row outside the pool has priority <= ``bound``.  Between
  rebuilds only two things change priorities: shooting and deposits, and the
  solver reports both rows (``update``); an updated row outside the pool whose
  priority now exceeds ``bound`` joins it.  Priorities are kept per row, so
  ranking the pool is a gather, not a recomputation.
* ``candidates(k)`` drops pool rows that fell to <= ``bound`` (the invariant
  still holds for them) and returns the rest.  When fewer than ``k`` remain
  above ``bound`` the pool has run dry and is rebuilt first.

So the top K taken from the candidates is the top K of the whole table (rows
of equal priority may swap), at O(pool + touched rows) per batch plus one O(n)
rebuild every (size - K) / K batches or more (``rebuilds`` counts them).
"""

from __future__ import annotations

import numpy as np

from dcrad.arrays import rowsum, take_rows
from dcrad.meshing.patches import Patches

__all__ = ["ShooterPool", "priority", "pool_size", "spatial_order"]


def pool_size(n: int, k: int) -> int:
    """Rows a pool takes at a rebuild for n patches and K shooters a batch: 2 sqrt(n K), in [4K, n].

    A batch costs O(pool) to rank the candidates plus O(n) per rebuild, and a pool of
    P rows lasts about P / K batches, so P ~ sqrt(n K) balances the two: O(sqrt(n K))
    per batch (144k rows for 1.27M patches and K = 4096, a rebuild every ~35 batches).
    """
    return int(min(max(n, 1), max(4 * k, 2.0 * (n * k) ** 0.5)))


def priority(patches: Patches, rows: np.ndarray | None = None, unshot: np.ndarray | None = None,
             area: np.ndarray | None = None) -> np.ndarray:
    """(m,) W: sum over channels of |dB * A| of ``rows`` (all patches when None).

    The same arithmetic as ``Solver.rank`` (so the pool's order is rank's order);
    ``unshot``, ``area``: dB (k,3) and A (k,) of those rows when the caller has them
    (no gather).
    """
    if rows is None:
        return rowsum(np.abs(patches.unshot * patches.area[:, None]))
    u = take_rows(patches.unshot, rows) if unshot is None else unshot
    a = take_rows(patches.area, rows) if area is None else area
    return rowsum(np.abs(u * a[:, None]))


class ShooterPool:
    """Rows that can be among the top-K shooters (see the module doc).

    patches : the table (its ``unshot`` is read, never written)
    size    : rows taken at a rebuild
    memory  : 9 bytes a patch (the priority of every row, kept current for the rows
              ``update`` is told about, and a membership flag) + 8 bytes a pool row
    """

    def __init__(self, patches: Patches, size: int):
        self.patches = patches
        self.size = max(1, int(size))
        self.rows = np.zeros(0, np.int64)
        self.member = np.zeros(len(patches), bool)
        self.prio = np.zeros(0)  #: (n,) W, every row's priority as of the last rebuild or update
        self.bound = np.inf  #: no rebuild yet: nothing is known about the rows outside
        self.rebuilds = 0

    def rebuild(self, at_least: int = 0) -> None:
        """One pass over all patches: the ``size`` (or ``at_least``) largest and the bound on the rest."""
        n = len(self.patches)
        size = max(self.size, at_least)
        pr = self.prio = priority(self.patches)
        if n <= size:
            rows, bound = np.arange(n), 0.0
        else:
            part = np.argpartition(-pr, size)
            rows, bound = part[:size], float(pr[part[size]])
        self.member[:] = False
        self.member[rows] = True
        self.rows = np.sort(rows)
        self.bound = bound
        self.rebuilds += 1

    def invalidate(self) -> None:
        """The unshot array changed behind the pool's back: rebuild on the next request."""
        self.bound = np.inf

    def update(self, rows: np.ndarray, unshot: np.ndarray | None = None, area: np.ndarray | None = None) -> None:
        """Rows (distinct) whose unshot radiosity changed (shots, deposits): their priorities
        now, and those outside the pool that now beat the bound join it.

        ``unshot``, ``area``: their dB now (k,3) and A (k,), when the caller has them
        (no gather).  O(k).
        """
        if not np.isfinite(self.bound) or len(rows) == 0:
            return
        pr = priority(self.patches, rows, unshot, area)
        self.prio[rows] = pr
        join = rows[~self.member[rows] & (pr > self.bound)]
        if len(join):
            self.member[join] = True
            self.rows = np.concatenate([self.rows, join])

    def candidates(self, k: int, negligible: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(rows, their priorities): a superset of the top ``k`` rows of the whole table.

        Rows at or below ``negligible`` W may be left out (they are never shot).
        """
        if len(self.rows) > 4 * self.size:
            self.invalidate()  # deposits grew the pool: one pass shrinks it again
        fresh = not np.isfinite(self.bound)
        if fresh:
            self.rebuild(k)
        pr = self.prio[self.rows]
        keep = pr > self.bound
        if self.bound > negligible and np.count_nonzero(keep) < k:
            if not fresh:  # run dry: fewer than k rows are known to beat the rest
                self.rebuild(k)
                pr = self.prio[self.rows]
                keep = pr > self.bound
            if self.bound > negligible and np.count_nonzero(keep) < k:
                keep = pr >= self.bound  # the k-th largest ties with the bound
        self.member[self.rows[~keep]] = False
        self.rows = self.rows[keep]
        return self.rows, pr[keep]


def _spread(x: np.ndarray) -> np.ndarray:
    """The low 10 bits of x with two zero bits after each (Morton interleave)."""
    x = x & 0x3FF
    x = (x | (x << 16)) & 0x30000FF
    x = (x | (x << 8)) & 0x300F00F
    x = (x | (x << 4)) & 0x30C30C3
    return (x | (x << 2)) & 0x9249249


def spatial_order(patches: Patches, rows: np.ndarray) -> np.ndarray:
    """Positions 0..k-1 of ``rows`` sorted along a Morton (Z-order) curve of their first corners.

    Shooting a batch's patches in this order makes neighbouring rays start near each
    other, so Embree walks the same BVH nodes while they are in cache: 1.3-1.6x the
    rays/s of the same rays in priority order on the 201k- and 1.27M-patch offices
    (bench/RESULTS.md).  O(k log k) for k rows.
    """
    lo, hi = patches.bounds
    corner = patches.vertices[patches.faces[rows, 0]]
    q = np.clip(((corner - lo) * (1023.0 / max(float((hi - lo).max()), 1e-300))).astype(np.int64), 0, 1023)
    code = _spread(q[:, 0]) | (_spread(q[:, 1]) << 1) | (_spread(q[:, 2]) << 2)
    return np.argsort(code, kind="stable")
