"""Ray casting: one module owns Embree, float32 conversion and the self-hit offset.

``Tracer(triangles)`` builds an Embree scene once (embreex), then answers many
batched queries.  Coordinates are shifted to the box centre and scaled by the
power of two nearest to 1/diagonal before the float32 conversion, so that
kilometre-wide scenes keep their precision and a scene at 1e30 m or 1e-30 m
traces like one at 1 m (a power of two is exact: at ordinary sizes the float32
coordinates are the same numbers, scaled).  A numpy
fallback with the same interface (brute-force Moller-Trumbore, for tiny scenes
and for checking Embree) is used when embreex cannot be imported or when asked.
"""

from __future__ import annotations

import numpy as np

from dcrad.config import TOL
from dcrad.transport.optics import MAX_PANES, Glazing

__all__ = ["Tracer", "MISS", "embree_available"]

MISS = -1

try:  # defer the failure: only a Tracer that needs Embree raises
    from embreex import rtcore_scene as _rtcs
    from embreex.mesh_construction import TriangleMesh as _TriangleMesh

    _EMBREE_ERROR: ImportError | None = None
except ImportError as exc:  # pragma: no cover - exercised only without embreex
    _rtcs = None
    _EMBREE_ERROR = exc


def embree_available() -> bool:
    return _rtcs is not None


class Tracer:
    """Closest-hit and occlusion queries against a fixed set of triangles.

    triangles : (n, 3, 3) float  corner positions
    backend   : "embree" (default when available) or "numpy"
    """

    def __init__(self, triangles: np.ndarray | None, backend: str | None = None, *,
                 vertices: np.ndarray | None = None, faces: np.ndarray | None = None):
        """From (n, 3, 3) ``triangles``, or (``triangles`` None) from shared ``vertices`` (v, 3) and
        ``faces`` (n, 3) indices into them (``Tracer.mesh``): the same float32 corners, so the same
        hits, and embreex copies v + n rows instead of 3n + n (its copy is most of the build: 0.4
        against 0.2 s on the 8x8 office's 201k patches)."""
        verts: np.ndarray  #: (v, 3) float64 corners, and ``index`` (n, 3) into them
        if triangles is None:
            if vertices is None or faces is None:
                raise ValueError("Tracer: give triangles, or vertices and faces")
            verts = np.asarray(vertices, np.float64).reshape(-1, 3)
            index = np.asarray(faces, np.int64).reshape(-1, 3)
            used = np.zeros(len(verts), np.bool_)
            used[index.ravel()] = True  # the corners' box (vertices no face uses do not count)
            corners = verts[used]
        else:
            verts = np.asarray(triangles, np.float64).reshape(-1, 3)
            index = np.arange(len(verts), dtype=np.int64).reshape(-1, 3)
            corners = verts
        self.n = len(index)
        if backend is None:
            backend = "embree" if embree_available() else "numpy"
        if backend == "embree" and not embree_available():
            raise ImportError(f"embreex is not importable: {_EMBREE_ERROR}")
        self.backend = backend
        #: the panes among the primitives (optics.Glazing; None: no glass): ``transmittance``
        self.glazing: Glazing | None = None
        if self.n:
            lo, hi = corners.min(axis=0), corners.max(axis=0)
        else:
            lo = hi = np.zeros(3)
        self.center = 0.5 * (lo + hi)
        self.scale = max(float(np.linalg.norm(hi - lo)), 1e-300)
        #: exact float32 conversion at any size: Embree sees a box of diagonal in [0.7, 1.4]
        self.unit = float(np.ldexp(1.0, int(np.round(np.log2(self.scale))))) if self.n else 1.0
        if backend == "embree":
            self._scene = _rtcs.EmbreeScene()
            if self.n:
                # shifted, scaled and rounded to float32 in chunks: no whole float64 copy
                # (70 MB at 1.27M triangles; the same numbers as converting it whole)
                flat = np.empty(verts.shape, np.float32)
                for lo in range(0, len(verts), 1 << 18):
                    flat[lo:lo + (1 << 18)] = (verts[lo:lo + (1 << 18)] - self.center) / self.unit
                _TriangleMesh(self._scene, flat, index.astype(np.int32))
        else:
            self._tri = (verts[index] - self.center) / self.unit

    @classmethod
    def mesh(cls, patches, rows: np.ndarray | None = None, backend: str | None = None) -> "Tracer":
        """The tracer of ``patches`` (its rows ``rows``: primitive i is rows[i]) from its shared
        vertices: the same hits as ``Tracer(patches.corners(rows))``, built in half the time."""
        faces = patches.faces if rows is None else patches.faces[rows]
        tracer = cls(None, backend, vertices=patches.vertices, faces=faces)
        glazing = getattr(patches, "glazing", None)
        if glazing is not None:
            tracer.glazing = glazing if rows is None else glazing.take(rows)
        return tracer

    # ------------------------------------------------------------------------------
    def intersect(self, origins: np.ndarray, dirs: np.ndarray, normals: bool = False):
        """Closest hit of each ray.

        origins, dirs : (m, 3) float (dirs need not be unit)
        returns (prim (m,) int64, MISS where nothing is hit; t (m,) float64 in units of |dir|),
        and with ``normals`` also ng (m, 3) float32: the hit triangle's geometric normal,
        not unit, on the side of its right-hand-rule normal (zeros for a miss).  Embree
        computes it anyway; reading it per ray is cheaper than gathering patch normals
        at random rows (shoot.trace's front/back test).
        """
        origins = (np.asarray(origins, np.float64) - self.center) / self.unit
        m = len(origins)
        if m == 0 or self.n == 0:
            empty = (np.full(m, MISS, np.int64), np.full(m, np.inf))
            return empty + (np.zeros((m, 3), np.float32),) if normals else empty
        if self.backend == "embree":
            res = self._scene.run(
                np.ascontiguousarray(origins, np.float32),
                np.ascontiguousarray(dirs, np.float32),
                output=1,
            )
            prim = res["primID"].astype(np.int64)
            t = res["tfar"].astype(np.float64) * self.unit
            t[prim < 0] = np.inf
            prim[prim < 0] = MISS
            return (prim, t, res["Ng"]) if normals else (prim, t)
        prim, t = _numpy_intersect(self._tri, origins, np.asarray(dirs, np.float64))
        if not normals:
            return prim, t * self.unit
        tri = self._tri[np.maximum(prim, 0)]
        ng = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]).astype(np.float32)
        ng[prim == MISS] = 0.0
        return prim, t * self.unit, ng

    def transmittance(self, origins: np.ndarray, dirs: np.ndarray, tmax: np.ndarray) -> np.ndarray:
        """(m,3) the share of light that gets from ``origins`` to t = ``tmax`` along unit ``dirs``:
        0 where an opaque surface is in the way, else the product of tau(theta) of the panes
        crossed (optics.py); 1 where nothing is.  Without glass it is ``occluded``'s complement."""
        origins = np.asarray(origins, np.float64)
        dirs = np.asarray(dirs, np.float64)
        m = len(origins)
        tmax = np.array(np.broadcast_to(np.asarray(tmax, np.float64), (m,)))
        glazing = self.glazing
        if glazing is None:
            return np.repeat((~self.occluded(origins, dirs, tmax)).astype(np.float64)[:, None], 3, axis=1)
        out = np.ones((m, 3))
        active = np.arange(m)
        o, left = origins.copy(), tmax
        step = TOL.ray_offset * self.scale
        for _ in range(MAX_PANES + 1):
            if not len(active):
                break
            prim, t, ng = self.intersect(o, dirs[active], normals=True)
            blocked = (prim != MISS) & (t < left)
            pane = blocked & glazing.panes(prim)
            out[active[blocked & ~pane]] = 0.0
            rows = np.flatnonzero(pane)
            if not len(rows):
                break
            d = dirs[active[rows]]
            out[active[rows]] *= glazing.crossing(prim[rows], ng[rows], d)
            o = o[rows] + (t[rows] + step)[:, None] * d
            left = left[rows] - t[rows] - step
            active = active[rows]
        else:
            out[active] = 0.0  # more panes than MAX_PANES: what is left stays on them
        return out

    def visible(self, origins: np.ndarray, dirs: np.ndarray, tmax: np.ndarray) -> np.ndarray:
        """(m,) float: the visibility a shadow ray finds, 1 or 0 (``occluded``), and through glass the
        mean over the channels of ``transmittance`` (exact for grey glass, which the gathers' single
        visibility per ray can carry; a tinted pane's channels are averaged there)."""
        if self.glazing is None:
            return (~self.occluded(origins, dirs, tmax)).astype(np.float64)
        return self.transmittance(origins, dirs, tmax).mean(axis=1)

    def through(self, origins: np.ndarray, dirs: np.ndarray):
        """(prim, t, ng, tau): the first hit of each ray that is not a pane (MISS where none), as
        ``intersect(normals=True)``, t from the origin, and (m,3) the product of tau(theta) of the panes
        crossed before it (1 without glass).  A gather ray reads what lies beyond the glass times tau
        (a pane's own diffuse reflection, its Kd, is not read: 0 for clear glass)."""
        prim, t, ng = self.intersect(origins, dirs, normals=True)
        m = len(prim)
        tau = np.ones((m, 3))
        glazing = self.glazing
        if glazing is None or m == 0:
            return prim, t, ng, tau
        prim, t, ng = prim.copy(), t.copy(), np.array(ng)
        step = TOL.ray_offset * self.scale
        dirs = np.asarray(dirs, np.float64)
        active = np.arange(m)
        o = np.asarray(origins, np.float64)
        base = np.zeros(m)
        cur_prim, cur_t, cur_ng = prim, t, ng
        for _ in range(MAX_PANES + 1):
            rows = np.flatnonzero(glazing.panes(cur_prim))
            if not len(rows):
                break
            idx = active[rows]
            d = dirs[idx]
            tau[idx] *= glazing.crossing(cur_prim[rows], cur_ng[rows], d)
            o = o[rows] + (cur_t[rows] + step)[:, None] * d
            base = base[rows] + cur_t[rows] + step
            active = idx
            cur_prim, cur_t, cur_ng = self.intersect(o, d, normals=True)
            prim[active], t[active], ng[active] = cur_prim, base + cur_t, cur_ng
        else:
            prim[active], t[active] = MISS, np.inf  # more panes than MAX_PANES: nothing read beyond
            tau[active] = 0.0
        return prim, t, ng, tau

    def occluded(self, origins: np.ndarray, dirs: np.ndarray, tmax: np.ndarray) -> np.ndarray:
        """(m,) bool: is anything hit with 0 < t < tmax (t in units of |dir|)?"""
        origins = (np.asarray(origins, np.float64) - self.center) / self.unit
        dirs = np.asarray(dirs, np.float64)
        m = len(origins)
        if m == 0 or self.n == 0:
            return np.zeros(m, bool)
        tmax = np.broadcast_to(np.asarray(tmax, np.float64), (m,)) / self.unit
        if self.backend == "embree":
            res = self._scene.run(
                np.ascontiguousarray(origins, np.float32),
                np.ascontiguousarray(dirs, np.float32),
                dists=np.ascontiguousarray(tmax, np.float32),
                query="OCCLUDED",
            )
            return np.asarray(res) != MISS
        prim, t = _numpy_intersect(self._tri, origins, dirs)
        return (prim != MISS) & (t < tmax)


def _numpy_intersect(tri: np.ndarray, origins: np.ndarray, dirs: np.ndarray, chunk: int = 2048):
    """Brute-force Moller-Trumbore over all triangles, vectorised in ray chunks."""
    m = len(origins)
    prim = np.full(m, MISS, np.int64)
    tbest = np.full(m, np.inf)
    v0 = tri[:, 0]
    e1 = tri[:, 1] - v0
    e2 = tri[:, 2] - v0
    for s in range(0, m, chunk):
        o = origins[s : s + chunk, None, :]
        d = dirs[s : s + chunk, None, :]
        p = np.cross(d, e2[None])
        det = np.einsum("rtk,tk->rt", p, e1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            tv = o - v0[None]
            u = np.einsum("rtk,rtk->rt", tv, p) * inv
            q = np.cross(tv, e1[None])
            v = np.einsum("rtk,rtk->rt", d, q) * inv
            t = np.einsum("rtk,tk->rt", q, e2) * inv
        ok = (np.abs(det) > 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        t = np.where(ok, t, np.inf)
        j = np.argmin(t, axis=1)
        tj = t[np.arange(len(j)), j]
        hit = np.isfinite(tj)
        prim[s : s + chunk][hit] = j[hit]
        tbest[s : s + chunk][hit] = tj[hit]
    return prim, tbest
