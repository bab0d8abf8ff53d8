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
"""

from __future__ import annotations

import numpy as np

from .arrays import colsum
from .patches import Patches
from .rays import MISS, Tracer
from .sampling import cosine_hemisphere_columns, lattice, onb, triangle_points
from .shoot import ray_offset

#: the position lattice runs through its points in this order (index * STRIDE mod m): a prime,
#: so that positions and directions are not one lattice (a bijection for any m < STRIDE)
STRIDE = 7919

__all__ = ["final_gather", "read_hits", "gather_rays", "FinalGather"]


def read_hits(tracer: Tracer, patches: Patches, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(m,) patch whose front each ray meets first (a two-sided patch's twin from behind), -1 for
    a miss, a back face or a boundary primitive."""
    prim, _, ng = tracer.intersect(origins, dirs, normals=True)
    n = len(patches)
    ok = (prim != MISS) & (prim < n)
    front = ok & (np.einsum("ij,ij->i", dirs, ng) < 0.0)
    out = np.where(front, prim, -1)
    if patches.two_sided:
        behind = np.flatnonzero(ok & ~front)
        out[behind] = patches.twin[prim[behind]]
    return out


def gather_rays(patches: Patches, rows: np.ndarray, half: int, rng: np.random.Generator):
    """Gather rays of ``rows`` (k,), 2 x ``half`` each: (origins (m,3), dirs (m,3), owner (m,), in half A (m,)).

    Each half of a receiver is its own randomly shifted 2-D rank-1 lattice (R2) of
    cosine directions, the hemisphere being what the gather integrates over, and of
    points on the triangle (the same lattice run through in another order, STRIDE),
    so both are stratified in 2-D.  (The shooting's 4-D lattice has coarser 2-D
    projections: its sampling noise on Cornell at 256 rays was 1.35%, these 1.25%.)
    """
    k = len(rows)
    sets = 2 * k
    index = np.tile(np.arange(half), sets)
    shift = rng.random((sets, 4))
    u_dir = lattice(index, np.repeat(shift[:, :2], half, axis=0), 2)
    u_pos = lattice((index * STRIDE) % half, np.repeat(shift[:, 2:], half, axis=0), 2)
    owner = np.repeat(np.arange(k), 2 * half)
    in_a = np.tile(np.repeat([True, False], half), k)
    r = rows[owner]
    f = patches.faces[r]
    v = patches.vertices
    n = patches.normal[r]
    origins = triangle_points(v[f[:, 0]], v[f[:, 1]], v[f[:, 2]], u_pos) + ray_offset(patches) * n
    t, b = onb(n)
    x, y, z = cosine_hemisphere_columns(u_dir[:, 0], u_dir[:, 1])
    dirs = x[:, None] * t + y[:, None] * b + z[:, None] * n
    return origins, dirs, owner, in_a


class FinalGather:
    """The final gather of one shot solution, in rounds: each round's rays add to the sums.

    ``shot`` keeps the shot solution's B and D (what every round reads); ``round(rays)``
    traces ``rays`` (even) more gather rays per receiver and returns the solution of all
    rounds so far (``final_gather``'s B, D and mismatch).  Rounds are independent rays
    reading the same solution, so the gather's sampling noise falls with their total and
    the noise of what is read stays.
    """

    def __init__(self, patches: Patches, tracer: Tracer | None, diff: np.ndarray, direct: np.ndarray,
                 direct_a: np.ndarray, batch_rays: int = 262144, rows: np.ndarray | None = None):
        self.patches, self.tracer, self.batch_rays = patches, tracer, batch_rays
        #: the receivers gathered: every patch with a reflectance, or ``rows`` of them (a shared
        #: run's share, share.py: its sums go to the one FinalGather that holds them all)
        self.rec = np.flatnonzero(patches.rho.any(axis=1)) if rows is None else np.asarray(rows, np.int64)
        self.radiosity = patches.radiosity.copy()
        self.diff = diff.copy()
        self.direct, self.direct_a = direct, direct_a
        self.sum_a = np.zeros((len(self.rec), 3))  #: sum over half A's rays of what they read (W/m^2)
        self.sum_b = np.zeros((len(self.rec), 3))
        self.per_half = 0  #: rays per receiver and half so far

    def round(self, rays: int, rng: np.random.Generator):
        """(B (n,3), D (n,3), rays traced, mismatch (3,) W) after ``rays`` more rays per receiver."""
        traced = self.add(rays, rng)
        b, d, mismatch = self.solution()
        return b, d, traced, mismatch

    def add(self, rays: int, rng: np.random.Generator) -> int:
        """Trace ``rays`` (even) more rays per receiver into the sums; return the rays traced."""
        if self.tracer is None:
            raise ValueError("a FinalGather without a tracer only combines sums (solution)")
        p, rec = self.patches, self.rec
        half = max(rays // 2, 1)
        refl = self.radiosity - p.emission
        per = max(self.batch_rays // (2 * half), 1)
        for lo in range(0, len(rec), per):
            rows = rec[lo:lo + per]
            k = len(rows)
            origins, dirs, owner, in_a = gather_rays(p, rows, half, rng)
            hit = read_hits(self.tracer, p, origins, dirs)
            got = hit >= 0
            # half A reads B + D/2, half B reads B - D/2 (per hit: no (n,3) copies of either)
            for which, sign, q in ((True, 0.5, self.sum_a), (False, -0.5, self.sum_b)):
                sel = np.flatnonzero(got & (in_a == which))
                at = hit[sel]
                values = refl[at] + sign * self.diff[at]
                for c in range(3):
                    q[lo:lo + k, c] += np.bincount(owner[sel], weights=values[:, c], minlength=k)
        self.per_half += half
        return int(len(rec)) * 2 * half

    def solution(self):
        """(B (n,3), D (n,3), mismatch (3,) W) of the sums so far."""
        p, rec = self.patches, self.rec
        refl = self.radiosity - p.emission
        area = p.area[rec][:, None]
        rho = p.rho[rec]
        q_a = self.sum_a * area / self.per_half
        q_b = self.sum_b * area / self.per_half
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
