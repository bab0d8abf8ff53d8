"""The error estimate of a run: Monte Carlo noise from two independent half-solutions, plus bias.

Most of the error of a shooting solution is noise, not the unshot residual.  We
measure it from the run itself.  Every patch shot sends its rays in two halves
with their own randomly shifted lattices (``shoot.ray_lattice(halves=True)``),
and each half is read as its own complete solution: half A shoots
U_A = U + V/2 with its M_A rays, half B shoots U_B = U - V/2 with its M_B, where
U is the patch's unshot power and V the difference of the two half-solutions'
unshot power.  The solver's B is their mean (B_A + B_B) / 2: a ray of half A
carries (U + V/2) / (2 M_A), one of half B (U - V/2) / (2 M_B), which sums to U,
so the ledger is exactly the one of plain shooting.  ``NoiseTally`` keeps the
difference D = B_A - B_B (and V, its unshot part) for every patch from one more
bincount per batch (``Tally.received_a``), on the rows the batch touched only.

The two half-solutions are independent (their rays are), so Var(B) = Var(D) / 4
and ``noise = sqrt(sum_i A_i |D_i|^2 / sum_i A_i) / 2`` estimates the RMS noise
of B, the noise that propagated through later bounces included (D is shot on
with the light, through V).  What it cannot see: light whose randomness is not
split (twin buffers of a divided run are shot with V = 0; their rays are split
at random, so the sampling noise of twin rays is counted but the noise the
power in the bins already carries is not shot on as a difference).

Bias: the light still unshot (and in twin buffers) will raise B.  The ambient
irradiance g = q U / ((1 - lambda) A) of solver.py says how much reflected power
is still to come; ``combine`` lays it out like the irradiance so far, smoothed over
cells of about a mean free path (``NoiseTally.layout``): unshot light lands within a free path
or so of the patches holding it, and by then it has been reflected at least once, so
it is smooth within a room and absent from rooms that are dark.  The estimate is
sqrt(noise^2 + bias^2), reported over RMS(B) and over RMS(B - E) (``Estimate``).

Which B: the one the user reads.  radiosity.npz gives B per input triangle, the area mean of
its elements, and the pictures and vertex colours show the elements.  The accuracy target holds
the reading per input triangle, with the elements at most ``SHOWN_SLACK`` times the target
(``held_factors``); the report gives all three.  Noise averages over the elements of a triangle
(a wall of two triangles in 800 elements reads far less noise than each element), bias does not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dcrad.arrays import colsum, put_rows, rowsum, take_rows

__all__ = ["Estimate", "NoiseTally", "NoiseSums", "combine", "half_mask", "split_power", "METHOD",
           "bias_ambient", "finite", "held_factors", "SHOWN_SLACK"]

METHOD = ("two independent half-solutions (noise, propagated noise included) + the unshot light laid out "
          "like the irradiance so far, smoothed over a mean free path (bias)")

#: the elements (the pictures, the vertex colours) may carry at most this many times the error the
#: target holds per input triangle: the pictures show each vertex as the mean of the four to six
#: elements around it (render.CornerSmoother), which about halves their noise again
SHOWN_SLACK = 2.0


def half_mask(counts: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
    """(m,) bool: True for the rays of half A (each shooter's first ceil(c/2) rays).

    A shooter with one ray cannot be split: its ray joins half A or B at random
    (with ``rng``; else A), which keeps the difference D unbiased.
    """
    counts = np.asarray(counts, np.int64)
    start = np.cumsum(counts) - counts
    index = np.arange(int(counts.sum())) - np.repeat(start, counts)
    half = index < np.repeat((counts + 1) // 2, counts)
    single = counts == 1
    if rng is not None and single.any():
        half[start[single]] = rng.random(int(single.sum())) < 0.5
    return half


def split_power(power: np.ndarray, counts: np.ndarray, diff: np.ndarray | None) -> np.ndarray:
    """(m,3) W per ray: half A carries (P + W/2) / (2 M_A), half B (P - W/2) / (2 M_B).

    power (k,3) W each shooter shoots, counts (k,) rays, diff (k,3) W the
    half-solutions' difference W = U_A - U_B of that power (None: 0).  A shooter
    with one ray is not split: the ray carries P.
    """
    counts = np.asarray(counts, np.int64)
    a = (counts + 1) // 2
    b = counts - a
    w = np.zeros_like(power) if diff is None else 0.5 * diff
    w = np.where((b > 0)[:, None], w, 0.0)
    pa = (power + w) / (np.where(b > 0, 2.0, 1.0) * a)[:, None]
    pb = (power - w) / (2.0 * np.maximum(b, 1)[:, None])
    both = np.stack([pa, pb], axis=1).reshape(-1, power.shape[1])
    return np.repeat(both, np.stack([a, b], axis=1).ravel(), axis=0)


def _zeros3() -> np.ndarray:
    return np.zeros(3)


@dataclass
class NoiseSums:
    """What a (sub)scene contributes to a job's estimate: area-weighted sums.

    d2: sum A |D|^2 (channel mean, W^2/m^2 m^2); b2: sum A |B|^2; r2: sum A |B - E|^2;
    rho2 (3,): sum A rho^2; area: sum A (m^2); r1 (3,): sum A (B - E), the reflected
    power (W); rho1 (3,): sum A rho (m^2); l1, l2 (3,): sum A rho H and sum A rho^2 H^2 of the
    irradiance so far smoothed per cell, H (NoiseTally.layout; 0 before any light: the bias is then
    laid out as a uniform irradiance).
    """

    d2: float = 0.0
    b2: float = 0.0
    r2: float = 0.0
    rho2: np.ndarray = field(default_factory=_zeros3)
    area: float = 0.0
    r1: np.ndarray = field(default_factory=_zeros3)
    rho1: np.ndarray = field(default_factory=_zeros3)
    l1: np.ndarray = field(default_factory=_zeros3)
    l2: np.ndarray = field(default_factory=_zeros3)

    def as_list(self) -> list[float]:
        return [self.d2, self.b2, self.r2, *map(float, self.rho2), self.area, *map(float, self.r1),
                *map(float, self.rho1), *map(float, self.l1), *map(float, self.l2)]

    @staticmethod
    def from_list(values) -> "NoiseSums":
        v = [float(x) for x in values] + [0.0] * max(0, 19 - len(values))
        return NoiseSums(v[0], v[1], v[2], np.array(v[3:6]), v[6], np.array(v[7:10]), np.array(v[10:13]),
                         np.array(v[13:16]), np.array(v[16:19]))

    def __add__(self, other: "NoiseSums") -> "NoiseSums":
        return NoiseSums(self.d2 + other.d2, self.b2 + other.b2, self.r2 + other.r2, self.rho2 + other.rho2,
                         self.area + other.area, self.r1 + other.r1, self.rho1 + other.rho1,
                         self.l1 + other.l1, self.l2 + other.l2)


@dataclass
class Estimate:
    """The estimated RMS error of B against the converged solution of the same discrete problem."""

    rms: float  #: W/m^2
    rms_norm: float  #: over RMS(B), the seed's normalisation
    rms_refl: float  #: over RMS(B - E), the reflected light, as the target holds it (module doc)
    noise_refl: float  #: the noise part, over RMS(B - E)
    bias_refl: float  #: the unshot part, over RMS(B - E)
    method: str = METHOD
    #: rms_refl of B per input triangle (radiosity.npz's B: the mean of its patches) and per element
    #: (the pictures'); None where not tracked (divided and shared runs' books)
    triangles_refl: float | None = None
    elements_refl: float | None = None

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def bias_ambient(tallies: np.ndarray, unshot: np.ndarray, area: float, mean_rho: np.ndarray) -> np.ndarray:
    """(3,) W/m^2: the irradiance the unshot power (3,) W will still bring, spread evenly.

    g = q U / ((1 - lambda) A) with q the share of shot power that lands and lambda
    the return ratio, both from the run's return tallies (stiffness.stiffness); before
    anything was shot, q = 1 and lambda = the mean rho (a closed scene).
    """
    shot, lost, landed, kept = np.asarray(tallies, np.float64)
    if shot.sum() > 0 and landed.sum() > 0:
        q = np.clip(1.0 - lost / np.maximum(shot, 1e-300), 0.0, 1.0)
        lam = q * kept / np.maximum(landed, 1e-300)
    else:
        q, lam = np.ones(3), np.asarray(mean_rho, np.float64)
    lam = np.clip(lam, 0.0, 1.0 - 1e-6)
    return q * np.abs(unshot) / ((1.0 - lam) * max(area, 1e-300))


def combine(sums: NoiseSums, ambient: np.ndarray, pooled: float = 0.0) -> Estimate:
    """The estimate from a job's summed ``NoiseSums`` and its bias irradiance ``ambient`` (3,) W/m^2.

    Bias: the light still to come, F = g_c * sum A rho_c (W) per channel, laid out as the
    irradiance so far smoothed per cell, H (``NoiseTally.layout``): patch i gets F rho_i H_i /
    sum A rho H, whose mean square is F^2 l2 / (l1^2 A).  Before any light was reflected
    (l1 = 0) H is uniform: g^2 sum A rho^2 / A.  (Measured at accuracy stops, bench_bias.py:
    office2's shortfall, shot from a lamp in a trough, is a uniform irradiance within its room,
    and the relative layout used before, F / sum A (B - E) times RMS(B - E), read 2.9x its
    systematic error; smoothed per cell it reads 1.3x, and Cornell and the office alike.)
    ``pooled`` (W^2/m^4 m^2): the clusters' own bias, their patches' spread beyond their noise
    (NoiseTally.settle), is added.
    """
    area = max(sums.area, 1e-300)
    noise_ms = max(sums.d2, 0.0) / area / 4.0
    rms_b = math.sqrt(max(sums.b2, 0.0) / area)
    rms_r = math.sqrt(max(sums.r2, 0.0) / area)
    ambient = np.asarray(ambient, np.float64)
    future = ambient * np.asarray(sums.rho1, np.float64)
    l1, l2 = np.asarray(sums.l1, np.float64), np.asarray(sums.l2, np.float64)
    laid = l1 > 0
    per_channel = np.where(laid, future ** 2 * l2 / np.where(laid, l1, 1.0) ** 2,
                           ambient ** 2 * np.asarray(sums.rho2, np.float64)) / area
    bias_ms = float(per_channel.mean())
    bias_ms += max(pooled, 0.0) / area
    rms = math.sqrt(noise_ms + bias_ms)

    def rel(x: float, ref: float) -> float:
        return x / ref if ref > 0 else (0.0 if x == 0 else math.inf)

    return Estimate(rms, rel(rms, rms_b), rel(rms, rms_r), rel(math.sqrt(noise_ms), rms_r),
                    rel(math.sqrt(bias_ms), rms_r))


def held_factors(triangle: tuple[float, float, float], element: tuple[float, float, float],
                 slack: float = SHOWN_SLACK) -> tuple[float, float, float]:
    """The (d2, b2, r2) factors of the reading the target holds: per input triangle, its noise raised
    where the elements would otherwise carry more than ``slack`` times it (the noise share of an
    element read over its RMS(B - E), divided by slack^2, in the triangles' RMS(B - E)).  The bias
    is not scaled: it is smooth, the same per element and per triangle."""
    fd_t, fb_t, fr_t = triangle
    fd_e, _, fr_e = element
    return max(fd_t, fd_e * fr_t / (max(fr_e, 1e-300) * slack * slack)), fb_t, fr_t


def finite(x: float) -> float | None:
    """x, or None when it is not finite (JSON has no inf)."""
    return float(x) if math.isfinite(x) else None


def _kept_spread(spread: np.ndarray, noise: np.ndarray, kept: np.ndarray) -> float:
    """The kept clusters' S - N summed, not each one's positive part: S - N is an unbiased estimate
    of a cluster's own spread, and over thousands of uniform clusters the positive parts add up their
    noise (the ice-cream store's 6,141 clusters read 1.5% of bias from a first pass's noise)."""
    return max(float((spread - noise)[kept].sum()), 0.0)


class NoiseTally:
    """Per-patch half-solution differences and the area-weighted sums of one (sub)scene.

    ``diff`` (n,3) W/m^2 is D = B_A - B_B; ``unshot`` (n,3) W/m^2 is its unshot part V.
    ``commit`` is called with each batch's tally before ``deposit`` and touches the
    rows the batch hit only; the sums are exact again after ``resync`` (called by
    ``Solver.recount``: at the start and end of a run and every 256 batches, and by
    whoever changes B or D outside ``commit``, like passes.blend).
    """

    def __init__(self, patches) -> None:
        n = len(patches)
        self.diff = np.zeros((n, 3))
        self.unshot = np.zeros((n, 3))
        #: (n,) rows that emit (E != 0; E is fixed for a run): the only ones whose B - E differs from B
        self._emits = rowsum(np.abs(patches.emission)) > 0 if n else np.zeros(0, bool)
        self._sums = NoiseSums(rho2=(patches.rho ** 2 * patches.area[:, None]).sum(axis=0),
                               area=float(patches.total_area) if n else 0.0,
                               rho1=(patches.rho * patches.area[:, None]).sum(axis=0))
        #: (d2, b2, r2) of the reading the target holds (``held_factors``), per element and per input
        #: triangle, over per patch, from the last ``resync``
        self.factors = (1.0, 1.0, 1.0)
        self.element_factors = (1.0, 1.0, 1.0)
        self.triangle_factors = (1.0, 1.0, 1.0)
        #: W^2/m^4 m^2: the kept clusters' spread beyond their noise (``settle``; 0 before)
        self.pool_bias = 0.0
        self.undone = 0  #: clusters ``settle`` has undone so far (it may run more than once near a stop)
        #: (n,) the layout cell of each patch, and the area of reflecting patches per cell and channel:
        #: geometry only, found at the first ``layout`` with light to lay out
        self._cell: np.ndarray | None = None
        self._cell_area: np.ndarray | None = None
        self._regroup(patches)

    def _regroup(self, patches) -> None:
        """Read the table's clusters (``_reads``: the element each patch's B is read in, Patches.reads;
        ``pooled``: some patches share one B, so the per-element factors are not 1) and resync."""
        self._reads = patches.reads() if len(patches) else np.zeros(0, np.int64)
        self._triangle_reads = patches.reads(per_triangle=True) if len(patches) else np.zeros(0, np.int64)
        self.pooled = bool(len(patches) and (patches.cluster >= 0).any())
        #: some input triangle is read as the mean of several elements
        self.split = bool(len(patches)) and len(np.unique(self._triangle_reads)) < len(np.unique(self._reads))
        self.resync(patches)

    def settle(self, patches, margin: float = 4.0) -> tuple[int, int]:
        """Keep a cluster's shared B only where its patches agree within their noise.

        Per cluster, the spread of its patches' B - E about their area mean, S = sum A |r_i - r_c|^2,
        against what their noise alone would spread, N = sum A |D_i|^2 / 4 (1 - A_i / A_c)
        (D_i / 2 is patch i's noise).  Where S > ``margin`` N the light varies across the cluster
        (a door lintel under the ceiling: 0.48 to 0.92 W/m^2 within one cell): its patches keep
        their own B (``patches.cluster`` set to -1).  The kept clusters' S - N, summed, is the bias
        pooling leaves (``pool_bias``, ``_kept_spread``).  Regroups and resyncs the sums.  Returns
        (clusters kept, clusters undone).  N is itself an estimate from the same rays: with a
        margin of 2, 19% of the clusters of a uniformly lit cube were undone; 4 undoes 5% there
        and still every lintel of the generated office (bench/RESULTS.md)."""
        got = self._spread(patches)
        if got is None:
            return 0, 0
        rows, c, spread, noise = got
        undo = spread > margin * noise
        patches.undo_clusters(rows[undo[c]])
        self.pool_bias = _kept_spread(spread, noise, ~undo)
        self._regroup(patches)
        self.undone += int(undo.sum())
        return int((~undo).sum()), self.undone

    def _spread(self, patches):
        """(rows, cluster of each row, S, N) of ``settle`` over the clustered patches, or None."""
        rows = np.flatnonzero(patches.cluster >= 0)
        if not len(rows):
            return None
        _, c = np.unique(patches.cluster[rows], return_inverse=True)
        a = patches.area[rows]
        r = (patches.radiosity - patches.emission)[rows]
        total = np.bincount(c, weights=a)
        mean = np.stack([np.bincount(c, weights=a * r[:, k]) for k in range(3)], axis=1) / \
            np.maximum(total, 1e-300)[:, None]
        spread = np.bincount(c, weights=a * ((r - mean[c]) ** 2).mean(axis=1))
        d2 = (self.diff[rows] ** 2).mean(axis=1) / 4.0
        noise = np.bincount(c, weights=a * d2 * (1.0 - a / np.maximum(total[c], 1e-300)))
        return rows, c, spread, noise

    # -- the per-batch hooks (Solver.step / Solver.commit) --------------------------
    def shot_diff(self, shooters: np.ndarray, area: np.ndarray) -> np.ndarray:
        """(k,3) W: the half-solutions' difference of the unshot power of ``shooters``."""
        return self.unshot[shooters] * area[shooters, None]

    def shot(self, shooters: np.ndarray, keep: np.ndarray | None = None) -> None:
        """Shooters gave up their unshot power, its half-difference with it (``keep`` (k,): the
        share each kept, when a shot was capped; None: none)."""
        if keep is None:
            self.unshot[shooters] = 0.0
        else:
            self.unshot[shooters] *= keep[:, None]

    def commit(self, patches, land, received_a: np.ndarray | None) -> None:
        """Book one batch before ``deposit``: D and V of the rows hit, and the sums; O(rows hit).

        land: the rows hit with what they hold before the deposit and what they
        reflect (``shoot.landing``: hit, area, rho, radiosity, reflected = rho *
        received W, gain = reflected / area W/m^2); received_a (k,3) W: what arrived
        there by rays of half A (``Tally.received_a``).

        The increments are flat sums of products, no (k,3) axis reductions (10-40x
        slower in numpy 2.4, arrays.py) and no BLAS calls (a multithreaded ``np.dot``
        took 0.04-16 ms for the same 450k products on the shared 2-core machine,
        ``(x * y).sum()`` a steady 0.22): with g = gain and A g = reflected,
        A mean_c(new^2 - old^2) summed over rows is sum reflected * (2 old + g) / 3,
        and |B - E|^2's increment is that minus 2/3 sum reflected * E, which only
        the emitting rows hit carry.
        """
        hit = land.hit
        if len(hit) == 0:
            return
        s = self._sums
        refl, gain = land.reflected, land.gain
        b2 = float((refl * (2.0 * land.radiosity + gain)).sum()) / 3.0
        s.b2 += b2
        s.r1 = s.r1 + colsum(refl)
        lit = np.flatnonzero(np.take(self._emits, hit))
        if len(lit):
            e = take_rows(patches.emission, hit[lit])
            b2 -= 2.0 * float((refl[lit] * e).sum()) / 3.0
        s.r2 += b2
        if received_a is None:
            return
        dref = land.rho * 2.0 * (2.0 * received_a - land.received)  # A * the gain of D
        gain_d = dref / land.area[:, None]
        old_d = take_rows(self.diff, hit)
        s.d2 += float((dref * (2.0 * old_d + gain_d)).sum()) / 3.0
        put_rows(self.diff, hit, old_d + gain_d)
        put_rows(self.unshot, hit, take_rows(self.unshot, hit) + gain_d)

    def resync(self, patches) -> None:
        """Recompute the sums from the arrays (drops the round-off of the increments).

        O(patches): channel sums by column (``arrays.rowsum``) and flat sums, no (n,3)
        axis reductions or BLAS calls (commit says why): 4-9 ms at 201k patches (was
        24-34), 61-69 ms at 1.27M (was 130-164), on the shared machine.
        """
        a = patches.area
        s = self._sums
        b = patches.radiosity
        r = b - patches.emission
        s.d2 = float((a * rowsum(self.diff * self.diff)).sum()) / 3.0
        s.b2 = float((a * rowsum(b * b)).sum()) / 3.0
        s.r2 = float((a * rowsum(r * r)).sum()) / 3.0
        s.r1 = np.array([float((a * r[:, c]).sum()) for c in range(r.shape[1])])
        s.l1, s.l2 = self.layout(patches, r)
        if self.pooled:
            self.element_factors = self._shares(self._reads, patches)
        self.triangle_factors = self._shares(self._triangle_reads, patches) if self.split else self.element_factors
        self.factors = held_factors(self.triangle_factors, self.element_factors)

    def layout(self, patches, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(l1, l2) (3,): sum A rho H and sum A rho^2 H^2, H the irradiance so far, (B - E) / rho, averaged
        over the reflecting patches of each cell (``layout_cells``): where ``combine`` lays out the
        light still to come.  Zeros while nothing is reflected (``combine`` then lays it out
        uniformly), so a solver that never sees light (a worker's direct share) finds no cells.
        O(patches): two bincounts a channel, by column (one bincount over the (patch, channel) entries
        took 4.6-4.9 ms at 156k patches against 3.5-4.0: the (n,3) copies, arrays.py)."""
        a, rho = patches.area, patches.rho
        l1, l2 = np.zeros(3), np.zeros(3)
        if not len(a) or not np.any(r):
            return l1, l2
        if self._cell is None or self._cell_area is None:
            self._cell = layout_cells(patches.centroid, a)
            self._cell_area = np.stack([np.bincount(self._cell, a * (rho[:, c] > 0)) for c in range(3)], axis=1)
        cell, cell_area = self._cell, self._cell_area
        for c in range(3):
            refl = rho[:, c] > 0
            h = np.bincount(cell, np.where(refl, a * r[:, c] / np.where(refl, rho[:, c], 1.0), 0.0),
                            len(cell_area)) / np.maximum(cell_area[:, c], 1e-300)
            lay = rho[:, c] * h[cell]
            l1[c], l2[c] = float((a * lay).sum()), float((a * lay * lay).sum())
        return l1, l2

    def _shares(self, reads: np.ndarray, patches) -> tuple[float, float, float]:
        """(d2, b2, r2) read in the units ``reads`` over per patch (``_read_share``), from the sums
        of the last resync."""
        s = self._sums
        b = patches.radiosity
        return (_read_share(reads, patches.area, self.diff, s.d2), _read_share(reads, patches.area, b, s.b2),
                _read_share(reads, patches.area, b - patches.emission, s.r2))

    def sums(self) -> NoiseSums:
        """The sums of B as the target holds it (``held_factors``), by the factors of the last resync
        (the increments between resyncs are the patches')."""
        return self._scaled(self.factors)

    def element_sums(self) -> NoiseSums:
        """The sums of B per element (a cluster's patches share one B, Patches.pool): the pictures'."""
        return self._scaled(self.element_factors)

    def triangle_sums(self) -> NoiseSums:
        """The sums of B per input triangle (the area-weighted mean of its patches: radiosity.npz's B)."""
        return self._scaled(self.triangle_factors)

    def estimate(self, ambient: np.ndarray) -> Estimate:
        """The estimate as the target holds it (``sums``) with the clusters' own bias (``pool_bias``),
        and B per input triangle and per element beside it; ``ambient``: ``bias_ambient``'s.  O(1)."""
        est = combine(self.sums(), ambient, self.pool_bias)
        est.triangles_refl = finite(combine(self.triangle_sums(), ambient, self.pool_bias).rms_refl)
        est.elements_refl = finite(combine(self.element_sums(), ambient, self.pool_bias).rms_refl)
        return est

    def _scaled(self, factors: tuple[float, float, float]) -> NoiseSums:
        s = self._sums
        fd, fb, fr = factors
        return NoiseSums(s.d2 * fd, s.b2 * fb, s.r2 * fr, s.rho2.copy(), s.area, s.r1.copy(), s.rho1.copy(),
                         s.l1.copy(), s.l2.copy())


#: at most this many layout cells a (sub)scene (larger cells beyond; 20x20 office: ~5,000)
MAX_CELLS = 1 << 20


def layout_cells(centroid: np.ndarray, area: np.ndarray) -> np.ndarray:
    """(n,) int64: the cell of each patch, cells of side 4V/S, the mean free path of a closed convex
    room with the volume V of the patches' bounding box and their area S (Cauchy): in a building,
    about a room (office2 2.45 m, the generated office 2.26 m, where rays measured 2.06 m and about as
    much).  At least 1/32 of the box's diagonal, so a flat scene still has cells."""
    lo, hi = centroid.min(axis=0), centroid.max(axis=0)
    ext = np.maximum(hi - lo, 0.0)
    size = max(4.0 * float(np.prod(ext)) / max(float(area.sum()), 1e-300), float(np.linalg.norm(ext)) / 32.0, 1e-12)
    while True:
        dims = np.floor(ext / size).astype(np.int64) + 1
        if int(np.prod(dims)) <= MAX_CELLS:
            break
        size *= 2.0
    k = np.minimum(np.floor((centroid - lo) / size).astype(np.int64), dims - 1)
    _, cell = np.unique(np.ravel_multi_index(k.T, tuple(dims)), return_inverse=True)
    return cell.ravel().astype(np.int64)


def _read_share(reads: np.ndarray, area: np.ndarray, x: np.ndarray, whole: float) -> float:
    """sum_t A_t |mean_t x|^2 / sum_i A_i |x_i|^2 (channel mean): the share of a per-patch square sum
    that the input triangles' area-weighted means keep (1 when nothing is split, or no sum yet).

    A cluster's patches share one B, and B per input triangle is the mean of its patches: both
    average the patches' noise (per patch, office2's estimate read 2.4x the error measured per
    input triangle)."""
    if whole <= 0 or not len(reads):
        return 1.0
    group = np.bincount(reads, weights=area)
    ok = group > 0
    total = 0.0
    for c in range(x.shape[1]):
        m = np.bincount(reads, weights=area * x[:, c])[ok] / group[ok]
        total += float((group[ok] * m * m).sum())
    return min(total / 3.0 / whole, 1.0)
