"""Shooter selection without a pass over all patches per batch: a lazily rebuilt pool.

Progressive refinement shoots the K patches with the most unshot power,
``priority_i = sum_c |dB_ic| * A_i`` (W).  Sorting the whole table for every
batch made selection O(patches) per batch.  ``ShooterPool`` keeps the rows
that can be among the top K:

* ``rebuild`` (one O(n) pass) takes the ``size`` largest rows and remembers
  ``bound``, the largest priority left outside.
* Invariant: every row outside the pool has priority <= ``bound``.  Between
  rebuilds only two things change priorities: shooting (rows chosen from the
  pool) and deposits, which ``touch`` reports; a touched row outside the pool
  whose priority now exceeds ``bound`` joins it.
* ``candidates(k)`` drops pool rows that fell to <= ``bound`` (the invariant
  still holds for them) and returns the rest.  When fewer than ``k`` remain
  above ``bound`` the pool has run dry and is rebuilt first.

So the top K taken from the candidates is the top K of the whole table (rows
of equal priority may swap), at O(pool + touched rows) per batch plus one O(n)
rebuild every (size - K) / K batches or more (``rebuilds`` counts them).
"""

from __future__ import annotations

import numpy as np

from .patches import Patches

__all__ = ["ShooterPool", "priority"]


def priority(patches: Patches, rows: np.ndarray | None = None) -> np.ndarray:
    """(m,) W: sum over channels of |dB| * A of ``rows`` (all patches when None)."""
    if rows is None:
        return np.abs(patches.unshot).sum(axis=1) * patches.area
    return np.abs(patches.unshot[rows]).sum(axis=1) * patches.area[rows]


class ShooterPool:
    """Rows that can be among the top-K shooters (see the module doc).

    patches : the table (its ``unshot`` is read, never written)
    size    : rows taken at a rebuild (memory: 8 bytes a pool row + 1 byte a patch)
    """

    def __init__(self, patches: Patches, size: int):
        self.patches = patches
        self.size = max(1, int(size))
        self.rows = np.zeros(0, np.int64)
        self.member = np.zeros(len(patches), bool)
        self.bound = np.inf  #: no rebuild yet: nothing is known about the rows outside
        self.rebuilds = 0

    def rebuild(self, at_least: int = 0) -> None:
        """One pass over all patches: the ``size`` (or ``at_least``) largest and the bound on the rest."""
        n = len(self.patches)
        size = max(self.size, at_least)
        pr = priority(self.patches)
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

    def touch(self, rows: np.ndarray) -> None:
        """Rows whose unshot radiosity grew (a deposit): those now above the bound join."""
        if not np.isfinite(self.bound) or len(rows) == 0:
            return
        out = rows[~self.member[rows]]
        join = out[priority(self.patches, out) > self.bound]
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
        pr = priority(self.patches, self.rows)
        keep = pr > self.bound
        if self.bound > negligible and np.count_nonzero(keep) < k:
            if not fresh:  # run dry: fewer than k rows are known to beat the rest
                self.rebuild(k)
                pr = priority(self.patches, self.rows)
                keep = pr > self.bound
            if self.bound > negligible and np.count_nonzero(keep) < k:
                keep = pr >= self.bound  # the k-th largest ties with the bound
        self.member[self.rows[~keep]] = False
        self.rows = self.rows[keep]
        return self.rows, pr[keep]
