"""A final gather of the reflected light over a shot solution, with the books kept exact.

Shooting leaves each patch with the few rays that happened to hit it: after the
direct light is gathered (direct.py), most of the noise left is the indirect light
(Cornell at 4e6 rays per power: 3.4% of the reflected light, against 0.4% for the
direct).  A final gather re-estimates it per receiver i from N cosine-distributed
rays from stratified points of i, each reading the reflected radiosity B - E of the
patch it hits (0 for a miss or a back face):

    G_i = 1/N sum_s (B - E)(hit_s)        (W/m^2: the indirect irradiance)

Each ray reads the noise of many shooters' rays at once, so G_i is far smoother than
the hits i got while shooting.  The rays of half A read half-solution A (B + D/2),
those of half B read B - D/2 (noise.py), so the difference of the two half-solutions
after the gather is measured as before: sampling noise and the noise of what is read.

The books: B - E = rho P / A with P the power a patch received.  The gather replaces
each receiver's indirect part P_ind (its received power less the direct light it was
given) by P'_i = s Q_i, Q_i = A_i G_i, with one scale s per channel such that the
reflected light kept, sum rho P = sum A (B - E), is the shooting's (s is 1 within
0.5% on Cornell).  The ledger's accounts (absorbed, unshot, escaped, back faces) are
the shooting's, untouched, and close as before; what the gather moves is which patch
holds the reflected light.  The one figure it leaves inexact is the indirect power
landed, sum P' against sum P (returned as ``mismatch``, W: the share of the absorbed
power a patch-by-patch recount (1 - rho) P' would differ by; 0.1-0.3% of it on
Cornell).  A fit of landed and kept both (s Q + t A) was tried: nearly collinear
where rho hardly varies, it turned 0.2% mismatches into 4% scale errors.

Where a few patches carry much brighter reflected light than the rest (Cornell's block
tops), they are drawn by area as well and the two techniques are combined by the
balance heuristic (``Bright``): Cornell's sampling noise per ray fell 2.4x in variance
(0.188 -> 0.122 per sqrt(ray) at ~216 rays a receiver).
Each receiver half's directions are a Korobov lattice of exactly its rays (sampling.
rank1_lattice; the R2 sequence's first points before): the sampling noise at 164 rays a
receiver fell 1.34x in variance on Cornell (0.0102 -> 0.0088 of the reflected light).
A directional histogram per receiver group (path guiding, a defensive mixture with the
cosine) gained at most 1.24x there even learned from 64 uncounted rays a patch, and lost
when its pilot was part of the round (splitting the lattice cost 1.3x): not kept.
"""

from __future__ import annotations

import numpy as np

from dcrad.arrays import colsum
from dcrad.meshing.patches import Patches
from dcrad.transport.rays import MISS, Tracer
from dcrad.transport.sampling import cosine_hemisphere_columns, lattice, onb, rank1_lattice, triangle_points
from dcrad.transport.shoot import ray_offset

#: the position lattice runs through its points in this order (index * STRIDE mod m): a prime,
#: so that positions and directions are not one lattice (a bijection for any m < STRIDE)
STRIDE = 7919
#: Bright: patches with B - E above BRIGHT_FACTOR x its mean are also sampled by area when they
#: are at most BRIGHT_AREA of the receiving area; BRIGHT_SHARE area samples per cosine sample,
#: patch j drawn with chance ~ A_j |B - E|_j^BRIGHT_POWER.  Cornell, sampling noise per sqrt(ray)
#: at ~216 rays a receiver: factor 3 0.122 (2.5: 0.128, 4: 0.126), share 0.2 (0.15 and 0.35
#: alike), power 2 (1: 0.126, 3: 0.127); the power heuristic instead of the balance one 0.126
BRIGHT_FACTOR = 3.0
BRIGHT_AREA = 0.05
BRIGHT_SHARE = 0.2
BRIGHT_POWER = 2.0

__all__ = ["final_gather", "read_hits", "gather_rays", "FinalGather", "Bright"]


def read_hits(tracer: Tracer, patches: Patches, origins: np.ndarray, dirs: np.ndarray, distance: bool = False):
    """(m,) patch whose front each ray meets first (a two-sided patch's twin from behind), -1 for
    a miss, a back face or a boundary primitive; with ``distance`` also the hit distance (m,)
    in units of |dir|."""
    prim, t, ng = tracer.intersect(origins, dirs, normals=True)
    n = len(patches)
    ok = (prim != MISS) & (prim < n)
    front = ok & (np.einsum("ij,ij->i", dirs, ng) < 0.0)
    out = np.where(front, prim, -1)
    if patches.two_sided:
        behind = np.flatnonzero(ok & ~front)
        out[behind] = patches.twin[prim[behind]]
    return (out, t) if distance else out


def _half_samples(patches: Patches, rows: np.ndarray, m: int, dims: int, rng: np.random.Generator):
    """``m`` samples per half of each receiver of ``rows``, each half its own randomly shifted
    lattice: (u (M,dims), owner (M,), in half A (M,), points on the receivers (M,3) lifted off them,
    their normals (M,3)); the points run through the R_2 sequence's first m points in another order
    (STRIDE).  In 2-D (the cosine gather's directions) u is a Korobov lattice of exactly m points
    (``rank1_lattice``), else the R_dims sequence's first m points."""
    k = len(rows)
    sets = 2 * k
    index = np.tile(np.arange(m), sets)
    shift = rng.random((sets, dims + 2))
    if dims == 2:
        u = rank1_lattice(index, m, np.repeat(shift[:, :dims], m, axis=0))
    else:
        u = lattice(index, np.repeat(shift[:, :dims], m, axis=0), dims)
    u_pos = lattice((index * STRIDE) % m, np.repeat(shift[:, dims:], m, axis=0), 2)
    owner = np.repeat(np.arange(k), 2 * m)
    in_a = np.tile(np.repeat([True, False], m), k)
    # corners and edges per receiver, then per sample (fewer gathers, the same numbers)
    f = patches.faces[rows]
    v = patches.vertices
    n = patches.normal[rows][owner]
    points = triangle_points(v[f[:, 0]], v[f[:, 1]], v[f[:, 2]], u_pos, owner) + ray_offset(patches) * n
    return u, owner, in_a, points, n


def gather_rays(patches: Patches, rows: np.ndarray, half: int, rng: np.random.Generator):
    """Gather rays of ``rows`` (k,), 2 x ``half`` each: (origins (m,3), dirs (m,3), owner (m,), in half A (m,)).

    Each half of a receiver is its own randomly shifted 2-D rank-1 lattice of ``half``
    cosine directions (a Korobov lattice of exactly that many points, ``rank1_lattice``),
    the hemisphere being what the gather integrates over, and of points on the triangle
    (the R2 sequence run through in another order, STRIDE), so both are stratified in 2-D.
    (The shooting's 4-D lattice has coarser 2-D projections: its sampling noise on Cornell
    at 256 rays was 1.35%, the R2 sequence's 1.25%.  At 164 rays the Korobov lattice's was
    0.88% against R2's 1.02%.)
    """
    u_dir, owner, in_a, origins, n = _half_samples(patches, rows, half, 2, rng)
    t, b = onb(patches.normal[rows])  # per receiver (row by row: the same frames)
    x, y, z = cosine_hemisphere_columns(u_dir[:, 0], u_dir[:, 1])
    dirs = x[:, None] * t[owner] + y[:, None] * b[owner] + z[:, None] * n
    return origins, dirs, owner, in_a


class Bright:
    """The brightest reflectors, sampled by area as well as by the cosine (multiple importance sampling).

    Cornell's gather noise is mostly rays that happen to hit the tops of the blocks (the
    tall one's B - E is 6x the mean, over 1% of the area): reading the 346 patches above
    3x the mean as 0 cut the sampling noise per ray 2.9x in variance.  So when the patches
    whose reflected radiosity is above BRIGHT_FACTOR x its (area-weighted) mean are a small
    part of the receiving area (at most BRIGHT_AREA), they are also drawn as area samples:
    patch j with probability P_j ~ A_j |B - E|_j^2 (BRIGHT_POWER; the first power measured
    0.126 against 0.122 per sqrt(ray)), a uniform point y on it, and a shadow ray
    from the receiver's point x to y (read only if j is what it meets first).  The two
    techniques are combined by the balance heuristic: with h cosine and m area samples per
    half, every sample (of either technique) adds

        f / (h + m rho),   rho = p_area / p_cos = pi P_j r^2 / (A_j cos_y cos_x),

    (rho = 0 for a cosine ray that meets no bright patch), an unbiased estimate of the
    cosine integral whatever P is.  Near a bright patch (r small) rho is small and the
    cosine rays carry the weight; far, the area samples do.  Area samples from the back of
    x or at the back of y read 0 without a ray.  P depends on the shot solution only (the
    B both halves read), so the halves stay independent given it.

    When the bright set is a larger share of the area (the office 3x3: above 5%, walls
    near the lamps of nine rooms) the area samples were worse than cosine rays (sampling
    noise per ray 0.141 -> 0.179 at 256 rays), per-group lists with probe rays no better:
    no set then (``rows`` empty).
    """

    def __init__(self, patches: Patches, rec: np.ndarray, refl: np.ndarray):
        level = np.abs(refl).mean(axis=1)
        area = patches.area
        total_area = max(float(area[rec].sum()), 1e-300)
        mean = float(np.dot(level[rec], area[rec])) / total_area
        rows = rec[level[rec] > BRIGHT_FACTOR * mean] if mean > 0 else rec[:0]
        if float(area[rows].sum()) > BRIGHT_AREA * total_area:
            rows = rec[:0]
        self.rows = rows
        w = level[rows] ** BRIGHT_POWER * area[rows]
        self.cdf = np.cumsum(w / max(float(w.sum()), 1e-300))
        if len(self.cdf):
            self.cdf[-1] = 1.0
        self.p_area = np.zeros(len(patches))  #: P_j / A_j per patch (0 outside the set)
        self.p_area[rows] = w / max(float(w.sum()), 1e-300) / area[rows]

    def __len__(self) -> int:
        return len(self.rows)

    def draw(self, u: np.ndarray) -> np.ndarray:
        """(m,) uniform in [0,1) -> (m,) bright patch (stratified: the inverse of P's CDF)."""
        return self.rows[np.minimum(np.searchsorted(self.cdf, u, side="right"), len(self.rows) - 1)]


class FinalGather:
    """The final gather of one shot solution, in rounds: each round's rays add to the sums.

    ``shot`` keeps the shot solution's B and D (what every round reads); ``round(rays)``
    traces ``rays`` (even) more gather rays per receiver and returns the solution of all
    rounds so far (``final_gather``'s B, D and mismatch).  Rounds are independent rays
    reading the same solution, so the gather's sampling noise falls with their total and
    the noise of what is read stays.
    """

    def __init__(self, patches: Patches, tracer: Tracer | None, diff: np.ndarray, direct: np.ndarray,
                 direct_a: np.ndarray, batch_rays: int = 262144, bright: float | None = None,
                 rows: np.ndarray | None = None):
        self.patches, self.tracer, self.batch_rays = patches, tracer, batch_rays
        every = np.flatnonzero(patches.rho.any(axis=1))
        #: the receivers gathered (``rows``: a share of them; the bright set is the whole table's)
        self.rec = every if rows is None else np.asarray(rows, np.int64)
        self.radiosity = patches.radiosity.copy()
        self.diff = diff.copy()
        self.direct, self.direct_a = direct, direct_a
        self.sum_a = np.zeros((len(self.rec), 3))  #: sum over half A's rays of what they read (W/m^2)
        self.sum_b = np.zeros((len(self.rec), 3))
        self.per_half = 0  #: rays per receiver and half so far (a round that was stopped: not counted)
        #: (len(rec),) rays per half each receiver has had: a stopped round leaves them unequal
        self.counts = np.zeros(len(self.rec), np.int64)
        self.stopped = False  #: a round was stopped before it reached every receiver
        #: area samples of the bright set per cosine sample (Bright; 0: cosine only)
        self.bright_share = BRIGHT_SHARE if bright is None else bright
        self.bright: Bright | None = None
        if self.bright_share > 0 and len(every):
            b = Bright(patches, every, self.radiosity - patches.emission)
            self.bright = b if len(b) else None

    def _trace(self, half: int, rng: np.random.Generator, refl: np.ndarray, should_stop=None) -> int:
        """``half`` more cosine rays per receiver and half into the sums, with the bright set's area
        samples beside them (Bright); returns the rays traced.  ``should_stop()`` True between two
        batches ends the round there (a round of the 34k-triangle office took minutes, and the first
        Ctrl-C waited for it): the receivers it reached count their rays, the others keep what they had."""
        p, rec, bright = self.patches, self.rec, self.bright
        tracer = self.tracer
        assert tracer is not None, "a FinalGather without a tracer only combines sums (solution)"
        m = int(round(self.bright_share * half)) if bright is not None else 0
        kappa = m / half
        per = max(self.batch_rays // (2 * (half + m)), 1)
        traced = 0
        for lo in range(0, len(rec), per):
            if lo and should_stop is not None and should_stop():
                self.stopped = True
                return traced
            rows = rec[lo:lo + per]
            k = len(rows)
            origins, dirs, owner, in_a = gather_rays(p, rows, half, rng)
            hit, dist = read_hits(tracer, p, origins, dirs, distance=True)
            del origins
            traced += len(hit)
            got = hit >= 0
            weight = None
            if m and bright is not None:  # the balance heuristic's weight of a cosine ray meeting a bright patch
                at = np.flatnonzero(got)
                at = at[bright.p_area[hit[at]] > 0]
                j = hit[at]
                density = bright.p_area[j]
                cos_x = np.einsum("ij,ij->i", dirs[at], p.normal[rows[owner[at]]])
                cos_y = -np.einsum("ij,ij->i", dirs[at], p.normal[j])
                ratio = np.pi * density * dist[at] ** 2 / np.maximum(cos_x * cos_y, 1e-300)
                weight = np.ones(len(hit))
                weight[at] = 1.0 / (1.0 + kappa * ratio)
            del dirs, dist
            self._add(lo, k, hit, got, owner, in_a, weight, refl)
            if m and bright is not None:
                traced += self._area(lo, rows, m, kappa, rng, refl, bright, tracer)
            self.counts[lo:lo + k] += half
        self.per_half += half
        return traced

    def _add(self, lo: int, k: int, hit: np.ndarray, got: np.ndarray, owner: np.ndarray, in_a: np.ndarray,
             weight: np.ndarray | None, refl: np.ndarray) -> None:
        """Add what the rays read (times their weight) to the half sums of receivers lo .. lo + k."""
        # half A reads B + D/2, half B reads B - D/2 (per hit: no (n,3) copies of either)
        for which, sign, q in ((True, 0.5, self.sum_a), (False, -0.5, self.sum_b)):
            sel = np.flatnonzero(got & (in_a == which))
            at = hit[sel]
            values = refl[at] + sign * self.diff[at]
            if weight is not None:
                values *= weight[sel, None]
            for c in range(3):
                q[lo:lo + k, c] += np.bincount(owner[sel], weights=values[:, c], minlength=k)

    def _area(self, lo: int, rows: np.ndarray, m: int, kappa: float, rng: np.random.Generator,
              refl: np.ndarray, bright: Bright, tracer: Tracer) -> int:
        """``m`` area samples of the bright set per receiver and half (Bright); returns the rays traced."""
        p = self.patches
        k = len(rows)
        u, owner, in_a, x, n = _half_samples(p, rows, m, 3, rng)
        j = bright.draw(u[:, 0])
        v = p.vertices
        f = p.faces[j]
        y = triangle_points(v[f[:, 0]], v[f[:, 1]], v[f[:, 2]], u[:, 1:])
        d = y - x
        dist = np.sqrt(np.einsum("ij,ij->i", d, d))
        d /= np.maximum(dist, 1e-300)[:, None]
        cos_x = np.einsum("ij,ij->i", d, n)
        cos_y = -np.einsum("ij,ij->i", d, p.normal[j])
        ok = np.flatnonzero((cos_x > 0) & (cos_y > 0) & (dist > 0))
        hit = np.full(len(j), -1)
        hit[ok] = read_hits(tracer, p, x[ok], d[ok])
        seen = hit == j
        ratio = np.pi * bright.p_area[j] * dist ** 2 / np.maximum(cos_x * cos_y, 1e-300)
        weight = np.where(seen, 1.0 / (1.0 + kappa * ratio), 0.0)
        self._add(lo, k, hit, seen, owner, in_a, weight, refl)
        return len(ok)

    def round(self, rays: int, rng: np.random.Generator, should_stop=None):
        """(B (n,3), D (n,3), rays traced, mismatch (3,) W) after ``rays`` more rays per receiver
        (fewer where ``should_stop`` ended the round: ``_trace``)."""
        traced = self.add(rays, rng, should_stop)
        b, d, mismatch = self.solution()
        return b, d, traced, mismatch

    def add(self, rays: int, rng: np.random.Generator, should_stop=None) -> int:
        """``rays`` (even) more rays per receiver into the sums; returns the rays traced."""
        return self._trace(max(rays // 2, 1), rng, self.radiosity - self.patches.emission, should_stop)

    def solution(self):
        """(B (n,3), D (n,3), mismatch (3,) W) of the sums so far (sum_a, sum_b over each receiver's
        rays).  Receivers a stopped first round did not reach keep the shot solution's B and D, and
        the gathered ones keep their own reflected total (the scale below is over them alone)."""
        p = self.patches
        if self.stopped:  # by each receiver's own rays; those a stopped first round missed: none
            done = self.counts > 0
            rec, sum_a, sum_b, rays = self.rec[done], self.sum_a[done], self.sum_b[done], self.counts[done, None]
        else:
            rec, sum_a, sum_b, rays = self.rec, self.sum_a, self.sum_b, self.per_half
        refl = self.radiosity - p.emission
        area = p.area[rec][:, None]
        rho = p.rho[rec]
        q_a = sum_a * area / rays
        q_b = sum_b * area / rays
        q = 0.5 * (q_a + q_b)
        refl_rec = refl[rec]
        del refl
        received = np.where(rho > 0, refl_rec * area / np.where(rho > 0, rho, 1.0), 0.0)
        del refl_rec
        direct = self.direct[rec]
        ind = received - direct
        del received
        kept, got_q = colsum(rho * ind), colsum(rho * q)
        scale = np.where(got_q != 0, kept / np.where(got_q != 0, got_q, 1.0), 1.0)
        new_ind = scale * q
        del q
        mismatch = colsum(new_ind - ind)
        del ind
        b = self.radiosity.copy()
        b[rec] = p.emission[rec] + rho * (direct + new_ind) / area
        del new_ind
        d = self.diff.copy()
        dir_diff = 2.0 * (2.0 * self.direct_a[rec] - direct)  # P_A - P_B of the direct light
        del direct
        q_a -= q_b
        del q_b
        d[rec] = rho * (dir_diff + scale * q_a) / area
        return b, d, mismatch


def final_gather(patches: Patches, tracer: Tracer, rays: int, rng: np.random.Generator, diff: np.ndarray,
                 direct: np.ndarray, direct_a: np.ndarray, batch_rays: int = 262144):
    """Re-estimate the indirect light of every receiver with ``rays`` (even) gather rays each.

    diff (n,3) W/m^2: the half-solutions' difference D (noise.py); direct, direct_a (n,3) W:
    the direct light each patch received, and the part half A's samples gave (its
    ``received_a``).  Returns (B (n,3), D (n,3), rays traced, mismatch (3,) W) or None when
    there is no indirect light to re-estimate.  B - E keeps its sum (per channel,
    area-weighted); ``mismatch`` is the indirect power landed, gathered less shot (module doc).
    """
    if not patches.rho.any() or rays < 2:
        return None
    return FinalGather(patches, tracer, diff, direct, direct_a, batch_rays).round(rays, rng)
