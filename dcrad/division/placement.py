"""How many subscenes a scene may be cut into, and which worker runs which.

``subscene_limit`` bounds k by the patches; ``expected_work`` predicts a subscene's iterate work
from its own lamps before it runs; ``placement`` spreads the subscenes over the workers by it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from dcrad.errors import ConfigError
from dcrad.meshing.patches import Patches
from dcrad.transport.emitters import sources_power

__all__ = [
    "MAX_SUBSCENES", "MIN_PATCHES_PER_SUBSCENE", "SUBSCENES_PER_WORKER", "WORK_PER_PATCH_W", "check_subscenes",
    "expected_work", "placement", "subscene_limit"
]


#: the most subscenes of one job, and the fewest patches a subscene must have on average
#: (64 subscenes of a 4-triangle scene, 4,352 patches: 47 s against 4.4 s unsplit; 256: 120 s)
MAX_SUBSCENES, MIN_PATCHES_PER_SUBSCENE = 64, 16


def subscene_limit(n_patches: int) -> int:
    """The most subscenes a scene of ``n_patches`` patches may be cut into."""
    return max(1, min(MAX_SUBSCENES, n_patches // MIN_PATCHES_PER_SUBSCENE))


def check_subscenes(k: int, n_patches: int) -> None:
    """ConfigError when k subscenes are more than the scene can use (``subscene_limit``)."""
    limit = subscene_limit(n_patches)
    if k > limit:
        raise ConfigError(f"{k} subscenes for {n_patches} patches: at most {limit} (each subscene needs "
                          f"{MIN_PATCHES_PER_SUBSCENE} patches on average, and a job at most {MAX_SUBSCENES}); "
                          f"use fewer subscenes or a smaller --patch-size")


#: subscenes per worker when --subscenes is not given: over-decomposed, so one worker's two
#: subscenes even out (office 8x8 on 2 workers: 238 s with 2 subscenes, 192 s with 4;
#: bench_scaling's model on the 3x3 office: 1.27x and 2.05x on 2 machines).  Four per worker
#: (office 8x8, 2 workers) pays only when placed by expected work (``placement``: 2-worker
#: critical path 165M rays, round-robin 183M) and then ties two per worker (163M) with more rays
SUBSCENES_PER_WORKER = 2

#: expected_work: W of emitted power a patch counts as (a cell with no lamp still shoots
#: the light its neighbours hand it; office 8x8, k=8: the unlit cell's iterates took 0.34 s
#: for its 25k patches, the lit ones 0.030 s per W of their lamps, so a patch ~ 4.5e-4 W)
WORK_PER_PATCH_W = 4.5e-4

def expected_work(patches: Patches) -> float:
    """A subscene's expected iterate work before it runs, in W of emitted power equivalents.

    Progressive refinement at a fixed power per ray traces rays in proportion to the power
    it shoots, and a cell shoots its lamps' light and what that light reflects there: on
    the 8x8 office at the default accuracy each cell's iterate CPU seconds were 0.028-0.033 s
    per W of its own lamps at k = 4 and k = 8 (bench/RESULTS.md).  Light that crosses
    in from neighbours is about what crosses out, so the cell's own lamps predict its work (its
    luminaires' and point lights' too).
    """
    own = float(patches.emitted_power.sum()) + float(sources_power(patches.sources).sum())
    return own + WORK_PER_PATCH_W * len(patches)


def placement(work: Sequence[float], workers: int) -> list[int]:
    """Worker slot (0..workers-1) for each subscene so that the slots' expected work evens out.

    Largest first to the least loaded slot (LPT), then single moves and pairwise swaps
    between the most and the least loaded slot while they lower the maximum.  Deterministic
    (ties: the lower index).  Placement does not change the numerics (each subscene's
    iterates are the same on any worker), only which worker waits at each barrier.
    """
    w = np.asarray(work, np.float64)
    if workers < 1:
        raise ConfigError(f"placement needs at least one worker, not {workers}")
    slot = np.zeros(len(w), np.int64)
    load = np.zeros(workers)
    for i in np.argsort(-w, kind="stable"):
        j = int(np.argmin(load))
        slot[i] = j
        load[j] += w[i]
    for _ in range(4 * len(w)):  # each step strictly lowers the pair's maximum
        hi, lo = int(np.argmax(load)), int(np.argmin(load))
        gap = load[hi] - load[lo]
        a = np.flatnonzero(slot == hi)
        b = np.flatnonzero(slot == lo)
        # moving a (d = w_a) or swapping a <-> b (d = w_a - w_b) lowers the maximum when 0 < d < gap;
        # the best d is the one nearest gap / 2
        cand = [(abs(gap / 2 - w[i]), int(i), -1) for i in a if 0 < w[i] < gap]
        cand += [(abs(gap / 2 - (w[i] - w[j])), int(i), int(j)) for i in a for j in b if 0 < w[i] - w[j] < gap]
        if not cand:
            break
        _, i, j = min(cand)
        d = w[i] - (w[j] if j >= 0 else 0.0)
        slot[i] = lo
        if j >= 0:
            slot[j] = hi
        load[hi] -= d
        load[lo] += d
    return slot.tolist()
