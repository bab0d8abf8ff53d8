"""The emitters as polygons, and exact point-to-polygon form factors (Lambert's contour formula).

For the direct light (direct.gather_analytic): the unoccluded form factor from a
point x on a receiver to an emitter of uniform exitance is a sum over the edges of
its outline,

    F(x) = -1/(2 pi) sum_k theta_k n_x . (u_k x u_k+1) / |u_k x u_k+1|,

u_k the outline's vertices relative to x (counter-clockwise about the emitter's
front), theta_k the angle between u_k and u_k+1, after the outline is clipped to
x's horizon (Sutherland-Hodgman).  An edge's term depends on its two ends only,
so the edges two triangles of an emitter share cancel: a planar emitter meshed
into many patches is the loop of its outline, with collinear boundary edges
merged (the Cornell light, 128 patches, is 4 edges; each office lamp, 24 patches, 4).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dcrad.meshing.patches import Patches

__all__ = ["Lights", "light_polygons", "triangle_lights", "polygon_form_factor", "form_factors", "MAX_LOOP_VERTICES"]

#: outline vertices of all lights above which no polygons are built (the sampled gather is used)
MAX_LOOP_VERTICES = 20_000


@dataclass
class Lights:
    """Emitters of one object, one exitance and one plane form a light: its outline loop(s);
    other emitters are a light each (their triangle)."""

    loops: np.ndarray  #: (P, V, 3) m, each loop counter-clockwise about its light's front, padded by its last vertex
    loop_light: np.ndarray  #: (P,) the light of each loop
    normal: np.ndarray  #: (L, 3) each light's front
    exitance: np.ndarray  #: (L, 3) W/m^2
    area: np.ndarray  #: (L,) m^2
    of_emitter: np.ndarray  #: (e,) light of each emitter (index into the ``emitters`` given)
    #: (L,) True for a light whose outline is one parallelogram, sampled as o + s e1 + t e2
    #: (``corner``, ``edges``): stratified over the whole light, not triangle by triangle
    parallelogram: np.ndarray | None = None
    corner: np.ndarray | None = None  #: (L, 3) m
    edges: np.ndarray | None = None  #: (L, 2, 3) m
    #: derived data kept between calls (direct.light_lists: the receivers' light lists)
    cache: dict = field(default_factory=dict, repr=False)

    def __len__(self) -> int:
        return len(self.normal)


def _loops(faces: np.ndarray, pos: np.ndarray) -> list[np.ndarray] | None:
    """Outline loops (vertex positions (m,3), in order) of consistently oriented triangles
    ``faces`` (t,3) into ``pos``; None when the outline is not a set of simple loops."""
    a = faces.reshape(-1)
    b = np.roll(faces, -1, axis=1).reshape(-1)
    n = len(pos)
    interior = np.isin(a * n + b, b * n + a)
    a, b = a[~interior], b[~interior]
    if len(a) == 0 or len(np.unique(a)) != len(a):
        return None
    nxt = np.full(n, -1, np.int64)
    nxt[a] = b
    left = set(a.tolist())
    loops = []
    while left:
        start = left.pop()
        loop = [start]
        v = int(nxt[start])
        while v != start:
            if v < 0 or v not in left:
                return None
            left.discard(v)
            loop.append(v)
            v = int(nxt[v])
        p = pos[loop]
        # drop vertices between collinear edges (the terms of collinear pieces add up)
        e_in = p - np.roll(p, 1, axis=0)
        e_out = np.roll(p, -1, axis=0) - p
        bend = np.linalg.norm(np.cross(e_in, e_out), axis=1)
        keep = bend > 1e-9 * np.linalg.norm(e_in, axis=1) * np.linalg.norm(e_out, axis=1)
        loops.append(p[keep] if keep.sum() >= 3 else p)
    return loops


def light_polygons(patches: Patches, emitters: np.ndarray, power: np.ndarray) -> Lights | None:
    """The lights of ``emitters`` (e,) shooting ``power`` (e,3) W; None past MAX_LOOP_VERTICES."""
    area = patches.area[emitters]
    exitance = power / area[:, None]
    scale = patches.scale
    v = patches.vertices
    key = np.concatenate([patches.obj[emitters][:, None].astype(np.float64), np.round(exitance, 9)], axis=1)
    _, gid = np.unique(key, axis=0, return_inverse=True)
    gid = np.asarray(gid).reshape(-1)
    loops: list[np.ndarray] = []
    loop_light: list[int] = []
    normals: list[np.ndarray] = []
    first_emitter: list[int] = []
    of_emitter = np.zeros(len(emitters), np.int64)
    vertices = 0
    for g in range(int(gid.max(initial=-1)) + 1):
        members = np.flatnonzero(gid == g)
        faces = patches.faces[emitters[members]]
        nrm = patches.normal[emitters[members]]
        mean = nrm.mean(axis=0)
        mean = mean / max(float(np.linalg.norm(mean)), 1e-300)
        corners = v[faces.reshape(-1)]
        planar = bool(np.all(nrm @ mean > 1.0 - 1e-9)) and bool(
            np.all(np.abs((corners - corners[0]) @ mean) < 1e-7 * scale))
        found = None
        if planar and len(members) > 1:
            # weld corners by position (a mesh need not share vertex rows)
            q = np.round((corners - corners.min(axis=0)) / (1e-9 * scale)).astype(np.int64)
            uq, inv = np.unique(q, axis=0, return_inverse=True)
            inv = np.asarray(inv).reshape(-1)
            pos = np.zeros((len(uq), 3))
            pos[inv] = corners
            found = _loops(inv.reshape(-1, 3), pos)
        if found is None:  # each triangle a light of its own
            for j, m in enumerate(members):
                of_emitter[m] = len(normals)
                loop_light.append(len(normals))
                loops.append(v[faces[j]])
                normals.append(nrm[j])
                first_emitter.append(int(m))
            vertices += 3 * len(members)
        else:
            of_emitter[members] = len(normals)
            for p in found:
                loops.append(p)
                loop_light.append(len(normals))
                vertices += len(p)
            normals.append(mean)
            first_emitter.append(int(members[0]))
        if vertices > MAX_LOOP_VERTICES:
            return None
    width = max(len(p) for p in loops)
    padded = np.stack([np.concatenate([p, np.repeat(p[-1:], width - len(p), axis=0)]) for p in loops])
    first = np.asarray(first_emitter, np.int64)
    lights = Lights(padded, np.asarray(loop_light, np.int64), np.asarray(normals), exitance[first],
                    np.bincount(of_emitter, weights=area, minlength=len(normals)), of_emitter)
    _parallelograms(lights, loops)
    return lights


def triangle_lights(patches: Patches, emitters: np.ndarray, power: np.ndarray) -> Lights:
    """Every emitter (e,) shooting ``power`` (e,3) W a light of its own (its triangle): the lights
    when ``light_polygons`` gives up (past MAX_LOOP_VERTICES), still exact per triangle."""
    emitters = np.asarray(emitters, np.int64)
    area = patches.area[emitters]
    exitance = power / np.where(area > 0, area, 1.0)[:, None]
    n = len(emitters)
    lights = Lights(patches.corners(emitters).copy(), np.arange(n, dtype=np.int64), patches.normal[emitters].copy(),
                    exitance, area.copy(), np.arange(n, dtype=np.int64))
    lights.parallelogram, lights.corner, lights.edges = np.zeros(n, bool), np.zeros((n, 3)), np.zeros((n, 2, 3))
    return lights


def _parallelograms(lights: Lights, loops: list[np.ndarray]) -> None:
    """Mark the lights that are one parallelogram loop whose area is the light's own."""
    n = len(lights)
    para = np.zeros(n, bool)
    corner = np.zeros((n, 3))
    edges = np.zeros((n, 2, 3))
    count = np.bincount(lights.loop_light, minlength=n)
    for i, p in enumerate(loops):
        g = int(lights.loop_light[i])
        if count[g] != 1 or len(p) != 4:
            continue
        e1, e2 = p[1] - p[0], p[3] - p[0]
        size = float(np.linalg.norm(e1) + np.linalg.norm(e2))
        if np.linalg.norm(p[2] - p[0] - e1 - e2) > 1e-9 * size:
            continue
        if abs(float(np.linalg.norm(np.cross(e1, e2))) - lights.area[g]) > 1e-6 * lights.area[g]:
            continue
        para[g], corner[g], edges[g] = True, p[0], (e1, e2)
    lights.parallelogram, lights.corner, lights.edges = para, corner, edges


def polygon_form_factor(x: np.ndarray, nx: np.ndarray, loops: np.ndarray, ny: np.ndarray) -> np.ndarray:
    """(P,) form factor from points x (P,3) facing nx (P,3) to the front of loops (P,V,3)
    facing ny (P,3) (signed: a hole's loop runs the other way and subtracts).

    The loop is clipped to x's horizon; zero when x is behind the loop's plane.
    Exact for a planar emitter without occlusion (visibility is the shadow rays' job).
    """
    return form_factors(x[:, None, :], nx, loops, ny)[:, 0]


def form_factors(x: np.ndarray, nx: np.ndarray, loops: np.ndarray, ny: np.ndarray) -> np.ndarray:
    """(P,m) ``polygon_form_factor`` from m points x (P,m,3) that share a facing nx (P,3) and a
    loop (P,V,3) facing ny (P,3): the points of one receiver to one light's loop.

    Written out per component on (P,m,V) arrays (no einsum, cross or gather): an outline
    wholly above a point's horizon (most pairs: nothing to clip) takes Lambert's sum as it
    stands; the points whose horizon cuts the outline are clipped (``_clipped_form_factor``,
    Sutherland-Hodgman), the points with no vertex above it get 0.  Float64 throughout: the
    terms of a far light cancel to its form factor (a light of angular size t leaves about
    eps / t of relative round-off), which float32 would raise to 1e-7 / t.
    """
    p, m, _ = x.shape
    w = loops.shape[1]
    # the pairs on the last axis (long contiguous rows for every ufunc): (V+1, m, P) per component
    n0, n1, n2 = (np.ascontiguousarray(nx[:, j]) for j in range(3))
    xt = [np.ascontiguousarray(x[:, :, j].T) for j in range(3)]  # (m,P)
    # u_k = y_k - x, closed (vertex V is vertex 0 again)
    ux, uy, uz = (np.empty((w + 1, m, p)) for _ in range(3))
    for u, j in ((ux, 0), (uy, 1), (uz, 2)):
        np.subtract(loops[:, :, j].T[:, None, :], xt[j][None], out=u[:w])
        u[w] = u[0]
    # heights above the horizon n.u_k: how many vertices are above it
    h = ux[:w] * n0
    h += uy[:w] * n1
    h += uz[:w] * n2
    above = np.count_nonzero(h > 0.0, axis=0)  # (m,P)
    del h
    ax, ay, az = ux[:-1], uy[:-1], uz[:-1]
    bx, by, bz = ux[1:], uy[1:], uz[1:]
    cx = ay * bz
    cx -= az * by
    cy = az * bx
    cy -= ax * bz
    cz = ax * by
    cz -= ay * bx
    dot = ax * bx
    dot += ay * by
    dot += az * bz
    del ux, uy, uz, ax, ay, az, bx, by, bz
    cn = cx * cx
    cn += cy * cy
    cn += cz * cz
    np.sqrt(cn, out=cn)
    theta = np.arctan2(cn, dot)
    nc = cx * n0
    nc += cy * n1
    nc += cz * n2
    cn[cn <= 0.0] = 1.0  # a zero-length edge (a padded vertex): nc = 0 too
    theta *= nc
    theta /= cn
    ff = theta[0]
    for k in range(1, w):
        ff += theta[k]
    ff = -ff / (2.0 * math.pi)  # (m,P)
    front = ((xt[0] - loops[:, 0, 0]) * ny[:, 0] + (xt[1] - loops[:, 0, 1]) * ny[:, 1]
             + (xt[2] - loops[:, 0, 2]) * ny[:, 2]) > 0.0
    ff[(above == 0) | ~front] = 0.0
    ff = np.ascontiguousarray(ff.T)  # (P,m)
    cut = np.nonzero(((above > 0) & (above < w) & front).T)
    if len(cut[0]):
        pair = cut[0]
        ff[cut] = _clipped_form_factor(x[cut], nx[pair], loops[pair], ny[pair])
    return ff


def _clipped_form_factor(x: np.ndarray, nx: np.ndarray, loops: np.ndarray, ny: np.ndarray) -> np.ndarray:
    """``polygon_form_factor`` by clipping every loop to the horizon (any loop; the general path)."""
    p, w, _ = loops.shape
    u = loops - x[:, None, :]
    h = np.einsum("pvk,pk->pv", u, nx)
    inside = h > 0.0
    u_next = np.roll(u, -1, axis=1)
    h_next = np.roll(h, -1, axis=1)
    crossing = inside != np.roll(inside, -1, axis=1)
    t = h / np.where(crossing, h - h_next, 1.0)
    meet = u + t[..., None] * (u_next - u)
    # Sutherland-Hodgman against the horizon: slot 2k is vertex k (when above), 2k+1 the
    # crossing of edge k (when it crosses); a missing slot repeats the one before it (an
    # edge of length zero adds nothing), cyclically
    pts = np.stack([u, meet], axis=2).reshape(p, 2 * w, 3)
    valid = np.stack([inside, crossing], axis=2).reshape(p, 2 * w)
    idx = np.maximum.accumulate(np.where(valid, np.arange(2 * w)[None, :], -1), axis=1)
    last = idx[:, -1]
    idx = np.where(idx < 0, last[:, None], idx)
    q = np.take_along_axis(pts, np.maximum(idx, 0)[..., None], axis=1)
    qn = np.roll(q, -1, axis=1)
    c = np.cross(q, qn)
    cn = np.sqrt(np.einsum("pvk,pvk->pv", c, c))
    theta = np.arctan2(cn, np.einsum("pvk,pvk->pv", q, qn))
    term = theta * np.einsum("pvk,pk->pv", c, nx) / np.where(cn > 0, cn, 1.0)
    ff = -term.sum(axis=1) / (2.0 * math.pi)
    front = np.einsum("pk,pk->p", x - loops[:, 0], ny) > 0.0
    return np.where((last >= 0) & front, ff, 0.0)
