"""subDivideScene: split the scene's box into k axis-aligned cells (van Liere, 1.3).

Automatic partitions are a k-d tree built top-down (:func:`split_planes`): a
cell that must become k cells is split into ``k_lo`` and ``k - k_lo`` cells, with
``k_lo`` = ``k // 2``, ``k - k // 2`` or any count within ``SPLIT_SLACK`` of k/2
(k = 8: 3, 4 or 5), whichever fits the plane's work, so k need not be a power of
two and a plane in a wall need not halve the work.  Candidate
planes on all three axes get ``score = openness + balance * 2|w_lo/W - k_lo/k|``
(lower is better; for k = 2 the balance term is ``|w_lo - w_hi| / W``), where
``w_lo/W`` is the share of the cell's work below the plane (work = patch area,
or ``work="count"`` for patch count; a patch counts on its centroid's side).

Openness is the share of jittered grid points (about ``samples**2``) on the
plane's rectangle, within the cell and the scene bounds, that are in open
space: from each point a ray goes along +n and one along -n, and the point is
solid when both nearest hits are back faces closer than ``solid_depth`` (2 % of
the diagonal): it is inside a wall.  A plane inside an interior wall is open
only at its doorways; a plane across a room is open almost everywhere.  The rays
trace the input triangles, rebuilt from the patches (``_surfaces``; a two-sided
surface by its front only), not the patches: the same surface in 50 times fewer
triangles on the 20x20 office.

Candidates on an axis: ``candidates`` even positions between the 25 % and 75 %
work quantiles (and area quantiles, when the work is not area), plus the
midpoints between consecutive distinct coordinates of surfaces perpendicular to
the axis in that range (wall centres, which an even grid steps over; the most
surface area beside them first).  No plane is placed within ``1e-4 * diagonal`` of a surface
lying in (or nearly in) it: such offsets move to the nearest free position.

Explicit partitions: ``planes`` form a grid (each splits every cell it
crosses); ``boxes`` must tile a box that contains the scene.  To reproduce an
automatic k-d partition, pass its cells as boxes.
"""

from __future__ import annotations

import itertools
from dataclasses import asdict, dataclass, field

import numpy as np

from dcrad.config import TOL
from dcrad.errors import PartitionError
from dcrad.meshing.patches import Patches, remap_twin, triangle_areas
from dcrad.transport.rays import MISS, Tracer

__all__ = ["Cell", "Face", "Partition", "split_planes", "partition", "clip", "faces_between",
           "openness"]

AXES = "xyz"
_NUDGE = 1e-4  # planes stay this fraction of the diagonal away from coplanar surfaces
_PAD = 1e-3  # the root box is the scene bounds enlarged by this fraction of the diagonal
_GENERIC = np.array([0.5377, 0.6211, 0.5702])  # a direction no axis-aligned or 45-degree edge is normal to


@dataclass(frozen=True)
class Cell:
    """An axis-aligned box ``lo`` .. ``hi`` (metres)."""

    id: int
    lo: tuple
    hi: tuple

    def contains(self, points: np.ndarray) -> np.ndarray:
        """(m,) bool: points inside the closed box."""
        p = np.asarray(points, np.float64)
        return np.all((p >= self.lo) & (p <= self.hi), axis=-1)


@dataclass(frozen=True)
class Face:
    """The shared face of two adjacent cells: a rectangle on the plane
    ``x[axis] = offset`` spanning ``lo`` .. ``hi`` in axes
    ``((axis + 1) % 3, (axis + 2) % 3)``; ``side_a`` is the cell below the
    plane, ``side_b`` the one above (the boundary normal points from A to B)."""

    axis: int
    offset: float
    lo: tuple
    hi: tuple
    side_a: int
    side_b: int

    @property
    def area(self) -> float:
        return float((self.hi[0] - self.lo[0]) * (self.hi[1] - self.lo[1]))


@dataclass
class Partition:
    """Cells, the boundaries between them, the planes made and why."""

    cells: list
    faces: list
    planes: list
    log: list = field(default_factory=list)
    work: list = field(default_factory=list)  # per cell, in the unit of ``work_unit``
    work_unit: str = "m^2"

    def locate(self, points: np.ndarray) -> np.ndarray:
        """(m,) int64 id of the first cell (in list order) containing each point, -1 if none."""
        p = [np.ascontiguousarray(np.asarray(points, np.float64)[:, a]) for a in range(3)]
        out = np.full(len(points), -1, np.int64)
        for c in self.cells[::-1]:  # Cell.contains, a column at a time
            m = (p[0] >= c.lo[0]) & (p[0] <= c.hi[0])
            for a in (1, 2):
                m &= (p[a] >= c.lo[a]) & (p[a] <= c.hi[a])
            out[m] = c.id
        return out

    def as_dict(self) -> dict:
        return {"k": len(self.cells), "cells": [asdict(c) for c in self.cells],
                "faces": [{**asdict(f), "area": f.area} for f in self.faces],
                "planes": [{"axis": AXES[a], "offset": float(o)} for a, o in self.planes],
                "work": [float(w) for w in self.work], "work_unit": self.work_unit,
                "log": list(self.log)}


# -- helpers ---------------------------------------------------------------------------------
#: ``work="light"``: a subscene's rays ~ 35 per patch + 5800 per W it emits (office 8x8, k=2,
#: 2e5 rays per power: 100.8k patches and 900 W traced 8.8M rays, 101.0k and 1718 W 13.6M),
#: i.e. the light term is about twice the patch term over the whole office
LIGHT_WEIGHT = 2.0


#: a cell of kk cells may split into k_lo + (kk - k_lo) with k_lo / kk this far from 1/2 (kk >= 8),
#: whichever fits the work below the plane best: the plane stays in a wall and the count follows
#: the work (20x20 office by light, k=16: the best wall halving the building held 0.57 of the
#: work, so all 8 cells on that side carried 14% more than their share; 9 + 7 carries 1-2%)
SPLIT_SLACK = 0.125


def _work(patches: Patches, work: str) -> np.ndarray:
    if work == "light":  # expected rays: a share per patch plus LIGHT_WEIGHT times the emitted share
        e, a = patches.emission, patches.area  # the sum over RGB of E * area, in that order
        n, phi = len(patches), (e[:, 0] * a + e[:, 1] * a) + e[:, 2] * a
        total = float(phi.sum())
        return np.full(n, 1.0 / max(n, 1)) + (LIGHT_WEIGHT * phi / total if total > 0 else 0.0)
    if work not in ("area", "count"):
        raise PartitionError(f"unknown work measure {work!r}: use 'area', 'count' or 'light'")
    return patches.area if work == "area" else np.ones(len(patches))


def _root_box(patches: Patches) -> tuple[np.ndarray, np.ndarray]:
    pad = _PAD * patches.scale
    return patches.bounds[0] - pad, patches.bounds[1] + pad


def _extents(patches: Patches) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per axis, each patch's (min, max) coordinate (from vertex columns: no (n, 3, 3) array)."""
    f = [np.ascontiguousarray(patches.faces[:, j]) for j in range(3)]
    out = []
    for a in range(3):
        v = np.ascontiguousarray(patches.vertices[:, a])
        x0, x1, x2 = v[f[0]], v[f[1]], v[f[2]]
        out.append((np.minimum(np.minimum(x0, x1), x2), np.maximum(np.maximum(x0, x1), x2)))
    return out


def _forbidden(patches: Patches, axis: int, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Merged intervals of offsets within ``eps`` of a patch thinner than eps along ``axis``."""
    c = patches.triangles[:, :, axis]
    return _forbidden_of(c.min(axis=1), c.max(axis=1), eps)


def _forbidden_of(mn: np.ndarray, mx: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """``_forbidden`` from the patches' extents ``mn`` .. ``mx`` along the axis."""
    thin = (mx - mn) < eps
    order = np.argsort(mn[thin])
    lo, hi = mn[thin][order] - eps, mx[thin][order] + eps
    if not len(lo):
        return lo, hi
    idx = np.flatnonzero(np.concatenate([[True], lo[1:] > np.maximum.accumulate(hi)[:-1]]))
    return lo[idx], np.maximum.reduceat(hi, idx)


def _nudge(offsets, forbidden) -> np.ndarray:
    """Move offsets lying in a forbidden interval to its nearer end (ties go up)."""
    off = np.array(offsets, np.float64, ndmin=1)
    flo, fhi = forbidden
    if not len(flo):
        return off
    i = np.searchsorted(flo, off, side="right") - 1
    j = np.maximum(i, 0)
    inside = (i >= 0) & (off < fhi[j])
    down = (off - flo[j]) < (fhi[j] - off)
    return np.where(inside, np.where(down, flo[j], fhi[j]), off)


def _surfaces(patches: Patches) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3, 3) triangles whose union is the patches' surface, and (T, 3) front normals (not
    unit): what the openness traces.  Back sides (``twin`` rows after their fronts) are left
    out: a two-sided surface counts by its front, as a one-sided one (with both, which of the
    two coincident triangles a ray hits is Embree's choice, and so was "inside a wall").

    Per input triangle (``source``) its patches give way to the triangle of their extreme
    corners (the farthest along a generic direction, the farthest against it, and the farthest
    from the line through those two) when the areas agree and every patch centre lies in it:
    meshed by midpoint subdivision, that is the input triangle, its very corner coordinates.
    Other groups (a clipped piece, patches sharing a source by chance) stay as patches.  The
    20x20 office: 1.27M patches, 26,750 triangles (an Embree scene over the patches took 1.3-3 s
    of its partition).  Only the openness, a heuristic, sees these."""
    fronts = np.flatnonzero((patches.twin < 0) | (patches.twin > np.arange(len(patches))))
    n = len(fronts)
    if n == 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    order = fronts[np.argsort(patches.source[fronts], kind="stable")]
    k = patches.source[order]
    start = np.flatnonzero(np.concatenate([[True], k[1:] != k[:-1]]))
    size = np.diff(np.concatenate([start, [n]]))
    vid = patches.faces[order]  # (n, 3) the corners' vertex rows, grouped
    verts = patches.vertices

    def per_patch(x):
        return np.repeat(x, size)

    def far(d):  # d (n, 3) per corner: per group, its first corner with the largest d (an extreme point)
        best = per_patch(np.maximum.reduceat(np.maximum(np.maximum(d[:, 0], d[:, 1]), d[:, 2]), start))
        hit = np.flatnonzero(d == best[:, None])
        g = np.searchsorted(start, hit // 3, side="right")
        return verts[vid.ravel()[hit[np.concatenate([[True], g[1:] != g[:-1]])]]]

    along = verts @ _GENERIC
    a, b = far(along[vid]), far(-along[vid])
    first = verts[vid[start]]  # a patch of each group: which way it faces
    front = np.cross(first[:, 1] - first[:, 0], first[:, 2] - first[:, 0])
    m = np.cross(front, b - a)  # in the plane, across the line ab
    dist = (verts[:, 0][vid] * per_patch(m[:, 0])[:, None] + verts[:, 1][vid] * per_patch(m[:, 1])[:, None]
            + verts[:, 2][vid] * per_patch(m[:, 2])[:, None])
    c = far(np.abs(dist - per_patch(np.einsum("ij,ij->i", m, a))[:, None]))
    nrm = np.cross(b - a, c - a)
    flip = np.einsum("ij,ij->i", nrm, front) < 0
    b[flip], c[flip], nrm[flip] = c[flip], b[flip], -nrm[flip]
    # the check, per patch: its centre lies in the triangle (in its plane, inside its edges)
    n2 = np.maximum(np.einsum("ij,ij->i", nrm, nrm), 1e-300)
    cen = patches.centroid[order] - np.repeat(a, size, axis=0)
    lb = np.einsum("ij,ij->i", cen, np.repeat(np.cross(c - a, nrm) / n2[:, None], size, axis=0))
    lc = np.einsum("ij,ij->i", cen, np.repeat(np.cross(nrm, b - a) / n2[:, None], size, axis=0))
    off = np.einsum("ij,ij->i", cen, np.repeat(nrm / np.sqrt(n2)[:, None], size, axis=0))
    fits = (np.minimum(np.minimum(lb, lc), 1.0 - lb - lc) >= -1e-7) & (np.abs(off) <= 1e-7 * patches.scale)
    total = 2.0 * np.add.reduceat(patches.area[order], start)
    ok = (np.abs(np.sqrt(n2) - total) <= 1e-6 * total) & np.logical_and.reduceat(fits, start)
    rest = order[~np.repeat(ok, size)]
    tri = patches.corners(rest)
    return (np.concatenate([np.stack([a[ok], b[ok], c[ok]], axis=1), tri]),
            np.concatenate([nrm[ok], np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])]))


def _openness(tracer, normals, axis, offsets, lo, hi, samples, depth, rng) -> np.ndarray:
    """(C,) share of jittered grid points on each plane ``x[axis] = offset``
    within box lo..hi that are not inside solid (see the module docstring)."""
    u, v = (axis + 1) % 3, (axis + 2) % 3
    eu, ev = max(hi[u] - lo[u], 1e-12), max(hi[v] - lo[v], 1e-12)
    nu = int(np.clip(round(samples * np.sqrt(eu / ev)), 2, 4 * samples))
    nv = int(np.clip(round(samples * samples / nu), 2, 4 * samples))
    gu, gv = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    pu = lo[u] + (gu.ravel() + rng.random(nu * nv)) / nu * (hi[u] - lo[u])
    pv = lo[v] + (gv.ravel() + rng.random(nu * nv)) / nv * (hi[v] - lo[v])
    c, g = len(offsets), nu * nv
    grid = np.empty((c, g, 3))
    grid[:, :, axis] = np.asarray(offsets)[:, None]
    grid[:, :, u], grid[:, :, v] = pu, pv
    org = grid.reshape(-1, 3)
    blocked = np.ones(len(org), bool)
    for sign in (1.0, -1.0):
        d = np.zeros_like(org)
        d[:, axis] = sign
        prim, t = tracer.intersect(org, d)
        hit = prim != MISS
        back = np.zeros(len(org), bool)
        back[hit] = normals[prim[hit], axis] * sign > 0
        blocked &= hit & (t < depth) & back
    return 1.0 - blocked.reshape(c, g).mean(axis=1)


def openness(patches: Patches, axis: int, offsets, box=None, samples: int = 24,
             solid_depth: float = 0.02, rng_seed=0) -> np.ndarray:
    """(C,) openness of the planes ``x[axis] = offset`` within ``box`` = (lo, hi)
    (default: the scene bounds); ``solid_depth`` is a fraction of the diagonal."""
    lo, hi = patches.bounds if box is None else (np.maximum(box[0], patches.bounds[0]),
                                                   np.minimum(box[1], patches.bounds[1]))
    tri, normals = _surfaces(patches)
    return _openness(Tracer(tri), normals, axis, np.array(offsets, np.float64, ndmin=1),
                     lo, hi, samples, solid_depth * patches.scale, np.random.default_rng(rng_seed))


def _fmt_box(lo, hi) -> str:
    return "[" + ", ".join(f"{a:.3f}..{b:.3f}" for a, b in zip(lo, hi)) + "]"


# -- automatic k-d split --------------------------------------------------------------------
def _kd_split(patches, k, candidates=33, balance=1.0, rng_seed=0, work="area",
              samples=24, solid_depth=0.02):
    """Cells (list of (lo, hi)), planes and log of the automatic k-d tree."""
    if k < 1:
        raise PartitionError(f"k={k}: need at least one cell")
    if len(patches) == 0:
        raise PartitionError("cannot partition an empty scene")
    eps, depth = _NUDGE * patches.scale, solid_depth * patches.scale
    w_all, area = _work(patches, work), patches.area
    cent = [np.ascontiguousarray(patches.centroid[:, a]) for a in range(3)]
    forb, thin = [], []
    for mn, mx in _extents(patches):
        forb.append(_forbidden_of(mn, mx, eps))
        thin.append((mx - mn) < eps)
    if k > 1:  # openness: traced against the input triangles, not the patches (_surfaces)
        surfaces, normals = _surfaces(patches)
        tracer = Tracer(surfaces)
        # each axis sorted once: a cell's patches in order are these, masked (no sort per cell)
        by_axis = [np.argsort(cent[a], kind="stable") for a in range(3)]
    rng = np.random.default_rng(rng_seed)
    blo, bhi = patches.bounds
    cells, planes, log = [], [], []

    def best_split(lo, hi, kk):
        inside = np.ones(len(patches), bool)
        for a in range(3):
            inside &= (cent[a] >= lo[a]) & (cent[a] < hi[a])
        total = w_all[inside].sum()
        splits = sorted({kk // 2, kk - kk // 2} | {k_ for k_ in range(1, kk) if abs(k_ / kk - 0.5) <= SPLIT_SLACK})
        rlo, rhi = np.maximum(lo, blo), np.minimum(hi, bhi)
        found = []
        for a in range(3):
            if total <= 0 or hi[a] - lo[a] <= 4 * eps:
                continue
            order = by_axis[a][inside[by_axis[a]]]
            xs, cw = cent[a][order], np.cumsum(w_all[order])
            q25, q75 = np.interp([0.25 * total, 0.75 * total], cw, xs)
            if work != "area":  # and the area's: where one room holds all the lamps, its walls too
                ca = np.cumsum(area[order])
                a25, a75 = np.interp([0.25 * ca[-1], 0.75 * ca[-1]], ca, xs)
                q25, q75 = min(q25, a25), max(q75, a75)
            cand = [np.linspace(q25, q75, candidates)]
            s = xs[thin[a][order]]
            s = s[np.concatenate([[True], np.diff(s) > eps])] if len(s) else s
            if len(s) > 1:
                gap, mid = np.diff(s), 0.5 * (s[1:] + s[:-1])
                # wall centres: gaps of at most a wall's thickness (2% of the diagonal); when
                # there are too many, those between the most surface area (thinnest-first kept
                # furniture slits and dropped the walls of an 8x8 office; evenly spread, the
                # 20x20 office's furniture left out its wall at z=41.14 and the cut took 0.57 of
                # the light: a wall's faces span a whole row of rooms, a desk's a metre)
                keep = np.flatnonzero((mid >= q25) & (mid <= q75) & (gap <= 0.02 * patches.scale))
                if len(keep) > 8 * candidates:
                    pos = np.searchsorted(s, cent[a][inside & thin[a]], side="right") - 1  # its merged s
                    at = np.bincount(pos, patches.area[inside & thin[a]], len(s))
                    flank = at[keep] + at[keep + 1]
                    keep = np.sort(keep[np.argsort(-flank, kind="stable")[:8 * candidates]])
                cand.append(mid[keep])
            off = np.unique(_nudge(np.concatenate(cand), forb[a]))
            off = off[(off > lo[a] + eps) & (off < hi[a] - eps)]
            if not len(off):
                continue
            op = _openness(tracer, normals, a, off, rlo, rhi, samples, depth, rng)
            frac = np.interp(off, xs, cw, left=0.0, right=total) / total
            imb = np.array([2 * np.abs(frac - s_ / kk) for s_ in splits])
            score = op + balance * imb.min(axis=0)
            i = int(np.argmin(score))
            found.append((score[i], a, off[i], op[i], frac[i], splits[imb[:, i].argmin()], len(off)))
        return found, total

    def split(lo, hi, kk):
        if kk == 1:
            cells.append((lo, hi))
            return
        found, total = best_split(lo, hi, kk)
        if not found:  # no work or no room for candidates: halve the longest side
            a = int(np.argmax(hi - lo))
            off = float(_nudge([0.5 * (lo[a] + hi[a])], forb[a])[0])
            if not lo[a] + eps < off < hi[a] - eps:
                raise PartitionError(f"cell {_fmt_box(lo, hi)} is too small to split into {kk} cells")
            k_lo, why = kk // 2, "no candidate plane with work on both sides: halved the longest side"
        else:
            found.sort(key=lambda f: f[0])
            score, a, off, op, frac, k_lo, n = found[0]
            others = "; ".join(f"{AXES[f[1]]}={f[2]:.4f} score {f[0]:.3f}" for f in found[1:])
            why = (f"openness {op:.3f} (share of the plane in open space), work below "
                   f"{frac:.3f} of {total:.4g} for target {k_lo}/{kk}, score {score:.3f} "
                   f"(best of {n} on {AXES[a]}); best on other axes: {others or 'none'}")
        planes.append((a, float(off)))
        log.append(f"plane {len(planes)}: {AXES[a]}={off:.4f} splits cell {_fmt_box(lo, hi)} "
                   f"into {k_lo}+{kk - k_lo}: {why}")
        mid_hi, mid_lo = hi.copy(), lo.copy()
        mid_hi[a] = mid_lo[a] = off
        split(lo, mid_hi, k_lo)
        split(mid_lo, hi, kk - k_lo)

    lo, hi = _root_box(patches)
    split(lo, hi, int(k))
    return cells, planes, log


def split_planes(patches: Patches, k: int, candidates: int = 33, balance: float = 1.0,
                 rng_seed=0, **kw) -> list[tuple[int, float]]:
    """The (axis, offset) planes of the automatic k-d tree, in the order made
    (pre-order: a plane, then the planes of its low side, then its high side).
    Keywords: ``work`` ("area" | "count" | "light"), ``samples`` (openness grid side),
    ``solid_depth`` (fraction of the diagonal).  See the module docstring."""
    return _kd_split(patches, k, candidates, balance, rng_seed, **kw)[1]


# -- explicit partitions ----------------------------------------------------------------------
def _grid_boxes(patches, planes, log):
    lo, hi = _root_box(patches)
    eps = _NUDGE * patches.scale
    cuts, out = [[], [], []], []
    for a, off in planes:
        if a not in (0, 1, 2) or not np.isfinite(off):
            raise PartitionError(f"plane ({a!r}, {off!r}): axis must be 0, 1 or 2 and offset finite")
        new = float(_nudge([off], _forbidden(patches, a, eps))[0])
        if not lo[a] + eps < new < hi[a] - eps:
            raise PartitionError(f"plane {AXES[a]}={off} lies outside the scene box "
                                 f"{_fmt_box(lo, hi)} (or on its edge)")
        if new != off:
            log.append(f"plane {AXES[a]}={off} nudged to {new:.6f}: a surface lies in that plane")
        cuts[a].append(new)
        out.append((a, new))
    edges = [np.unique(np.concatenate([[lo[a]], cuts[a], [hi[a]]])) for a in range(3)]
    boxes = [(np.array([edges[0][i], edges[1][j], edges[2][m]]),
              np.array([edges[0][i + 1], edges[1][j + 1], edges[2][m + 1]]))
             for i, j, m in itertools.product(*(range(len(e) - 1) for e in edges))]
    return boxes, out


def _check_boxes(patches, boxes, log):
    """Validate that ``boxes`` tile a box containing the scene; nudge interior coordinates."""
    try:
        lo = np.array([np.asarray(b[0], np.float64).reshape(3) for b in boxes])
        hi = np.array([np.asarray(b[1], np.float64).reshape(3) for b in boxes])
    except (ValueError, TypeError, IndexError) as exc:
        raise PartitionError(f"boxes must be a list of (lo, hi) 3-vectors: {exc}") from None
    bad = ~(np.isfinite(lo).all(axis=1) & np.isfinite(hi).all(axis=1) & (hi > lo).all(axis=1))
    if bad.any():
        i = int(np.argmax(bad))
        raise PartitionError(f"box {i} {_fmt_box(lo[i], hi[i])}: need finite lo < hi on every axis")
    hlo, hhi = lo.min(axis=0), hi.max(axis=0)
    tol = 1e-9 * max(float(np.linalg.norm(hhi - hlo)), patches.scale)
    if (patches.bounds[0] < hlo - tol).any() or (patches.bounds[1] > hhi + tol).any():
        raise PartitionError(f"boxes cover {_fmt_box(hlo, hhi)} but the scene spans "
                             f"{_fmt_box(*patches.bounds)}")
    inter = np.clip(np.minimum(hi[:, None], hi[None]) - np.maximum(lo[:, None], lo[None]), 0, None).prod(2)
    vol = (hi - lo).prod(axis=1)
    np.fill_diagonal(inter, 0.0)
    i, j = np.unravel_index(np.argmax(inter), inter.shape)
    if inter[i, j] > 1e-9 * vol.sum():
        raise PartitionError(f"box {i} {_fmt_box(lo[i], hi[i])} and box {j} {_fmt_box(lo[j], hi[j])} "
                             f"overlap (volume {inter[i, j]:.6g} m^3)")
    cells = [Cell(n, tuple(lo[n]), tuple(hi[n])) for n in range(len(boxes))]
    faces = faces_between(cells, tol)
    for n, a, side in itertools.product(range(len(cells)), range(3), (0, 1)):
        at = (lo, hi)[side][n, a]
        if abs(at - (hlo, hhi)[side][a]) <= tol:
            continue
        u, v = (a + 1) % 3, (a + 2) % 3
        need = (hi[n, u] - lo[n, u]) * (hi[n, v] - lo[n, v])
        got = sum(f.area for f in faces if f.axis == a and (f.side_a, f.side_b)[1 - side] == n)
        if got < need * (1 - 1e-9):
            raise PartitionError(f"box {n} {_fmt_box(lo[n], hi[n])}: its {'-+'[side]}{AXES[a]} side at "
                                 f"{AXES[a]}={at:.6g} is only {got / need:.1%} covered by other boxes; "
                                 f"the boxes leave a gap")
    if abs(vol.sum() - (hhi - hlo).prod()) > 1e-9 * vol.sum():
        raise PartitionError(f"box volumes sum to {vol.sum():.6g} m^3 but their hull "
                             f"{_fmt_box(hlo, hhi)} holds {(hhi - hlo).prod():.6g}: gap")
    eps = _NUDGE * patches.scale
    planes = []
    for a in range(3):  # nudge every interior coordinate the same way in all boxes
        forb = _forbidden(patches, a, eps)
        for x in np.unique(np.concatenate([lo[:, a], hi[:, a]])):
            if abs(x - hlo[a]) <= tol or abs(x - hhi[a]) <= tol:
                continue
            new = float(_nudge([x], forb)[0])
            if new != x:
                log.append(f"box faces at {AXES[a]}={x} nudged to {new:.6f}: a surface lies there")
                lo[lo[:, a] == x, a], hi[hi[:, a] == x, a] = new, new
            planes.append((a, new))
    return list(zip(lo, hi)), planes


def faces_between(cells, tol: float | None = None) -> list[Face]:
    """Shared faces of adjacent boxes: for every pair whose boxes touch on a
    plane (``a.hi == b.lo`` on an axis, within ``tol``, default 1e-9 times the
    hull diagonal) and whose rectangles overlap with positive area."""
    if len(cells) < 2:
        return []
    lo, hi = (np.array([getattr(c, n) for c in cells], np.float64) for n in ("lo", "hi"))
    ids = [c.id for c in cells]
    if tol is None:
        tol = 1e-9 * max(float(np.linalg.norm(hi.max(axis=0) - lo.min(axis=0))), 1e-30)
    out = []
    for a in range(3):
        u, v = (a + 1) % 3, (a + 2) % 3
        olo = np.maximum(lo[:, None, [u, v]], lo[None, :, [u, v]])
        ohi = np.minimum(hi[:, None, [u, v]], hi[None, :, [u, v]])
        touch = (np.abs(hi[:, None, a] - lo[None, :, a]) <= tol) & np.all(ohi - olo > tol, axis=2)
        for i, j in zip(*np.nonzero(touch)):
            out.append(Face(a, float(0.5 * (hi[i, a] + lo[j, a])), tuple(map(float, olo[i, j])),
                            tuple(map(float, ohi[i, j])), ids[i], ids[j]))
    return out


def partition(patches: Patches, k: int | None = None, planes=None, boxes=None, **kw) -> Partition:
    """Split the scene into cells.

    automatic (planes and boxes None): a k-d tree of ``k`` cells, see
        :func:`split_planes` (``**kw`` go there).
    ``planes``: list of (axis, offset); a grid, each plane splits every cell it
        crosses (so k = product over axes of (planes on the axis + 1)); k is ignored.
    ``boxes``: list of (lo, hi) that must tile a box containing the scene
        (no overlap, no gap; else PartitionError naming the box); k is ignored.
    """
    log: list[str] = []
    if boxes is not None:
        if planes is not None:
            raise PartitionError("give planes or boxes, not both")
        box_list, made = _check_boxes(patches, boxes, log)
        log.insert(0, f"explicit boxes: {len(box_list)} cells")
    elif planes is not None:
        box_list, made = _grid_boxes(patches, planes, log)
        log.insert(0, f"explicit planes (grid): {len(box_list)} cells")
    else:
        if k is None:
            raise PartitionError("automatic partition needs k")
        box_list, made, log = _kd_split(patches, int(k), **kw)
    cells = [Cell(i, tuple(map(float, lo)), tuple(map(float, hi))) for i, (lo, hi) in enumerate(box_list)]
    w_all = _work(patches, kw.get("work", "area"))
    part = Partition(cells, faces_between(cells), made, log)
    part.work = np.bincount(part.locate(patches.centroid) + 1, w_all, len(cells) + 1)[1:].tolist()
    part.work_unit = {"area": "m^2", "count": "patches", "light": "expected work (patch share + 2 x emitted share)"}[
        kw.get("work", "area")]
    return part


# -- clipping -------------------------------------------------------------------------------------
def _clip_plane(P, cnt, axis, sign, off):
    """Sutherland-Hodgman against the half space sign * (x[axis] - off) >= 0,
    for n convex polygons at once: P (n, m, 3), cnt (n,) vertex counts."""
    n, m = P.shape[:2]
    idx = np.arange(m)[None]
    valid = idx < cnt[:, None]
    nxt = np.where(idx + 1 < cnt[:, None], idx + 1, 0)
    Q = np.take_along_axis(P, nxt[..., None], axis=1)
    d, dq = sign * (P[..., axis] - off), sign * (Q[..., axis] - off)
    keep = valid & (d >= 0)
    cross = valid & ((d >= 0) != (dq >= 0))
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(cross, d / (d - dq), 0.0)
    X = P + s[..., None] * (Q - P)
    X[..., axis] = off  # exactly on the plane
    pts = np.stack([P, X], axis=2).reshape(n, 2 * m, 3)
    mask = np.stack([keep, cross], axis=2).reshape(n, 2 * m)
    new = mask.sum(axis=1)
    R = np.zeros((n, max(m, int(new.max(initial=0))), 3))
    rows, cols = np.nonzero(mask)
    R[rows, (np.cumsum(mask, axis=1) - 1)[rows, cols]] = pts[rows, cols]
    return R, new


def clip(patches: Patches, part: Partition) -> list[tuple[Patches, np.ndarray]]:
    """Per cell: its patches and ``parent`` (m,) int64 rows of the input table.

    Triangles inside a cell are kept as they are (sharing input vertices);
    triangles crossing its box are clipped (Sutherland-Hodgman against the six
    box planes) and fan-triangulated.  Pieces below the degenerate area are
    dropped.  Each piece copies rho, emission, source, obj, radiosity and
    unshot (per-area values) from its parent, so area and emitted power are
    conserved to round-off.  Rows are in parent order.
    """
    # per axis, each patch's extent: a patch inside a cell is inside all its six planes
    ext = _extents(patches)
    inside_all = [np.ones(len(patches), bool) for _ in part.cells]
    for c, inside in zip(part.cells, inside_all):
        for a, (mn, mx) in enumerate(ext):
            inside &= (mn >= c.lo[a]) & (mx <= c.hi[a])
    # the rest cross a plane: the cells' cut patches are among them (one inside a cell and
    # touching another's box would clip there to nothing but slivers below the degenerate area)
    crossing = np.flatnonzero(~np.logical_or.reduce(inside_all))
    tri = patches.corners(crossing)
    tmin, tmax = tri.min(axis=1), tri.max(axis=1)
    min_area = TOL.degenerate_area * patches.scale ** 2
    used = np.zeros(len(patches.vertices), bool)
    out = []
    for c, inside in zip(part.cells, inside_all):
        lo, hi = np.asarray(c.lo), np.asarray(c.hi)
        hit = np.flatnonzero(np.all((tmax >= lo) & (tmin <= hi), axis=1))
        cut = crossing[hit]
        P = np.zeros((len(cut), 9, 3))
        P[:, :3] = tri[hit]
        cnt = np.full(len(cut), 3)
        for a in range(3):
            P, cnt = _clip_plane(P, cnt, a, 1.0, lo[a])
            P, cnt = _clip_plane(P, cnt, a, -1.0, hi[a])
        fan_pieces, fan_owner = [], []
        for j in range(1, P.shape[1] - 1):  # fan (0, j, j + 1)
            ok = j + 1 < cnt
            fan_pieces.append(np.stack([P[ok, 0], P[ok, j], P[ok, j + 1]], axis=1))
            fan_owner.append(cut[ok])
        pieces = np.concatenate(fan_pieces) if fan_pieces else np.zeros((0, 3, 3))
        owner = np.concatenate(fan_owner).astype(np.int64) if fan_owner else np.zeros(0, np.int64)
        piece_area = triangle_areas(pieces)
        big = piece_area > min_area
        pieces, owner, piece_area = pieces[big], owner[big], piece_area[big]
        keep = np.flatnonzero(inside)
        # the vertices they use, in order (as np.unique would give them, without a sort)
        used[:] = False
        used[patches.faces[keep]] = True
        rows = np.flatnonzero(used)
        vidx = (np.cumsum(used) - 1)[patches.faces[keep]]
        pv, pinv = np.unique(pieces.reshape(-1, 3), axis=0, return_inverse=True)
        verts = np.concatenate([patches.vertices[rows], pv])
        faces = np.concatenate([vidx, len(rows) + pinv.reshape(-1, 3)])
        parent = np.concatenate([keep, owner])
        order = np.argsort(parent, kind="stable")
        parent, faces = parent[order], faces[order]
        sub = Patches(
            vertices=verts, faces=faces, rho=patches.rho[parent], emission=patches.emission[parent],
            source=patches.source[parent], obj=patches.obj[parent], names=patches.names,
            radiosity=patches.radiosity[parent], unshot=patches.unshot[parent],  # gathered: copies
            twin=remap_twin(patches.twin, parent),
            glazing=None if patches.glazing is None else patches.glazing.take(parent),
        )
        # its areas are known: a whole patch's from the table, a piece's just measured (the same
        # corners in the same order, so the numbers ``area`` would compute from ``triangles``)
        sub.__dict__["area"] = np.concatenate([patches.area[keep], piece_area])[order]
        out.append((sub, parent))
    return out
