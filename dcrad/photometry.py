"""What lighting engineers read: illuminance in lux, luminance, per-surface statistics, false colour.

Radiometric to photometric: dcrad's RGB channels are linear Rec. 709, so the
photometric weight of a radiometric RGB value is its CIE Y (0.2126 R + 0.7152 G +
0.0722 B) times a luminous efficacy of ``EFFICACY`` = 179 lm/W, Radiance's
convention for white light (the efficacy of equal-energy white over the visible
band).  Illuminance E_v = 179 Y(H) lux with H the irradiance (W/m^2 incident);
luminance L_v = 179 Y(B) / pi cd/m^2 (a Lambertian surface of radiosity B).

Irradiance of a patch: the solver deposits rho_j * (power received) on B_j, so
H_j = (B_j - E_j) / rho_j exactly, per channel.  Where a channel's rho is below
``RHO_GATHER`` (black surfaces keep nothing of what they receive, so B tells
nothing), H is *gathered*: ``GATHER_RAYS`` cosine-distributed rays from
stratified points of the patch see the converged B of what they hit, and H is
their mean (the cosine-weighted integral of B / pi over the hemisphere).  The
work plane (``workplane``) is gathered the same way, from a grid of points
facing up.
"""

from __future__ import annotations

import math

import numpy as np

from .errors import ConfigError
from .rays import MISS, Tracer
from .render import tonemap
from .sampling import cosine_hemisphere, lattice, onb, triangle_points

__all__ = [
    "EFFICACY", "Y_WEIGHTS", "RHO_GATHER", "GATHER_RAYS", "irradiance", "to_lux", "luminance_cd",
    "surface_groups", "surface_stats", "workplane", "check_workplane", "stats", "false_colour", "legend_scale",
]

#: lm/W: luminous efficacy of white light (Radiance's convention)
EFFICACY = 179.0
#: CIE Y of linear Rec. 709 RGB
Y_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])
#: channels with rho below this get their irradiance gathered, not read from B
RHO_GATHER = 1e-3
#: rays per gathered patch or work-plane point
GATHER_RAYS = 256


def to_lux(h: np.ndarray) -> np.ndarray:
    """(..., 3) irradiance W/m^2 -> (...) illuminance lux."""
    return EFFICACY * (np.asarray(h, np.float64) @ Y_WEIGHTS)


def luminance_cd(b: np.ndarray) -> np.ndarray:
    """(..., 3) radiosity W/m^2 -> (...) luminance cd/m^2 of a Lambertian surface."""
    return EFFICACY * (np.asarray(b, np.float64) @ Y_WEIGHTS) / math.pi


def _gather(patches, tracer: Tracer, origins: np.ndarray, normals: np.ndarray, rays: int,
            seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Cosine-gathered irradiance (k,3) at points facing ``normals``, and the fraction of rays
    that met a one-sided surface from behind (k,) (a point inside a wall sees only backs)."""
    k = len(origins)
    if k == 0:
        return np.zeros((0, 3)), np.zeros(0)
    rng = np.random.default_rng(seed)
    owner = np.repeat(np.arange(k), rays)
    u = lattice(np.tile(np.arange(rays), k), np.repeat(rng.random((k, 2)), rays, axis=0), 2)
    t, b = onb(normals)
    frames = np.stack([t, b, normals], axis=1)
    d = np.einsum("mi,mij->mj", cosine_hemisphere(u), frames[owner])
    prim, _ = tracer.intersect(origins[owner], d)
    n = len(patches)
    hit = (prim != MISS) & (prim < n)
    p = np.where(hit, prim, 0)
    behind = hit & (np.einsum("ij,ij->i", d, patches.normal[p]) > 0)
    twin = patches.twin[p]
    p = np.where(behind & (twin >= 0), twin, p)
    lost = behind & (twin < 0)
    seen = np.where((hit & ~lost)[:, None], patches.radiosity[p], 0.0)
    h = np.stack([np.bincount(owner, weights=seen[:, c], minlength=k) for c in range(3)], axis=1) / rays
    return h, np.bincount(owner, weights=lost.astype(np.float64), minlength=k) / rays


def irradiance(patches, tracer: Tracer | None = None, rays: int = GATHER_RAYS, seed: int = 0):
    """(H (n,3) W/m^2 incident on each patch, gathered (n,) bool: patches whose H was gathered)."""
    rho = patches.rho
    with np.errstate(divide="ignore", invalid="ignore"):
        h = np.where(rho >= RHO_GATHER, (patches.radiosity - patches.emission) / rho, 0.0)
    gathered = np.any(rho < RHO_GATHER, axis=1)
    idx = np.flatnonzero(gathered)
    if len(idx):
        tracer = tracer or Tracer.mesh(patches)
        tri = patches.corners(idx)
        rng = np.random.default_rng(seed + 1)
        u = rng.random((len(idx), 2))
        pts = triangle_points(tri[:, 0], tri[:, 1], tri[:, 2], u)
        nrm = patches.normal[idx]
        pts = pts + 2e-6 * patches.scale * nrm
        g, _ = _gather(patches, tracer, pts, nrm, rays, seed)
        low = rho[idx] < RHO_GATHER
        h[idx] = np.where(low, g, h[idx])
    return np.maximum(h, 0.0), gathered


def surface_groups(patches, lux: np.ndarray | None = None) -> tuple[list[str], np.ndarray]:
    """(names, group (n,) int): one group per object, per material when objects are unnamed
    (OBJ's "default").  Two-sided surfaces: of each triangle's two sides the one with more
    ``lux`` counts for the object (the room side, whatever the winding), the other for
    "name (other side)"; without ``lux`` the back side is the other one."""
    labels = []
    for full in patches.names:
        obj, _, mat = full.rpartition("/")
        labels.append(mat if obj in ("", "default") else obj)
    labels = labels or ["scene"]
    unique = list(dict.fromkeys(labels))
    of_obj = np.array([unique.index(x) for x in labels], np.int64)
    other = patches.is_back.copy()
    pair = np.flatnonzero(patches.twin >= 0)
    if lux is not None and len(pair):
        mine, theirs = lux[pair], lux[patches.twin[pair]]
        other[pair] = (mine < theirs) | ((mine == theirs) & patches.is_back[pair])
    code = of_obj[np.clip(patches.obj, 0, len(labels) - 1)] + len(unique) * other
    used, group = np.unique(code, return_inverse=True)
    names = [unique[c % len(unique)] + (" (other side)" if c >= len(unique) else "") for c in used]
    return names, group.reshape(-1)


def stats(lux: np.ndarray, area: np.ndarray | None = None) -> dict:
    """E_avg (area-weighted), E_min, E_max (lux) and uniformity E_min / E_avg of some values."""
    lux = np.asarray(lux, np.float64)
    if not lux.size:
        return {"E_avg_lux": 0.0, "E_min_lux": 0.0, "E_max_lux": 0.0, "uniformity": 0.0}
    w = np.ones_like(lux) if area is None else np.asarray(area, np.float64)
    return _stats_of((lux * w).sum(), w.sum(), lux.mean(), lux.min(), lux.max())


def _stats_of(weighted, weight, mean, lo, hi) -> dict:
    """``stats`` from its sums: sum of lux x weight, sum of weight, plain mean, min and max."""
    avg = float(weighted / weight) if weight > 0 else float(mean)
    return {"E_avg_lux": avg, "E_min_lux": float(lo), "E_max_lux": float(hi),
            "uniformity": float(lo) / avg if avg > 0 else 0.0}


def surface_stats(patches, lux: np.ndarray) -> list[dict]:
    """``photometry.surfaces``: one entry per surface group (see surface_groups), as ``stats`` of
    its patches.  One pass over the patches for all groups (a mask per group was 2.6 s of the
    20x20 office's 6.1 s of outputs: hundreds of groups x 1.27M patches)."""
    names, group = surface_groups(patches, lux)
    lux = np.asarray(lux, np.float64)
    lum = luminance_cd(patches.radiosity)
    a = np.asarray(patches.area, np.float64)
    m = len(names)
    count = np.bincount(group, minlength=m)
    area = np.bincount(group, a, m)
    lux_a, lum_a, lux_sum = np.bincount(group, lux * a, m), np.bincount(group, lum * a, m), np.bincount(group, lux, m)
    order = np.argsort(group, kind="stable")
    used = np.flatnonzero(count)
    starts = (np.cumsum(count) - count)[used]
    lo, hi = np.full(m, 0.0), np.full(m, 0.0)
    lo[used] = np.minimum.reduceat(lux[order], starts)
    hi[used] = np.maximum.reduceat(lux[order], starts)
    return [{"name": names[g], "area_m2": float(area[g]),
             **_stats_of(lux_a[g], area[g], lux_sum[g] / count[g], lo[g], hi[g]),
             "L_avg_cd_m2": float(lum_a[g] / area[g]) if area[g] > 0 else 0.0} for g in used]


def check_workplane(height: float, patches) -> None:
    """ConfigError unless a work plane ``height`` m above the floor is inside the scene's box
    (0: none): above it every grid point looks at the outside, and the grid is empty."""
    top = float(patches.bounds[1][1] - patches.bounds[0][1]) if len(patches) else 0.0
    if not (math.isfinite(height) and 0.0 <= height < max(top, 1e-300)) and height != 0.0:
        raise ConfigError(f"--workplane {height:g} m: must be at least 0 and below the scene's height above its "
                          f"floor, {top:.4g} m (0: no work plane)")


def workplane(patches, height: float, spacing: float | None = None, tracer: Tracer | None = None,
              rays: int = GATHER_RAYS, seed: int = 0, border: float | None = None) -> dict:
    """Illuminance on a horizontal grid ``height`` m above the floor (the bottom of the box), facing up.

    ``spacing`` default: the box's larger horizontal extent / 64.  Left out: points
    closer than ``border`` (default 0.5 m, EN 12464-1's border zone, at most a tenth of
    the smaller horizontal extent) to a surface along +-X or +-Z (walls, furniture; this
    also drops points inside them), and points that see mostly one-sided surfaces from
    behind (inside solids, outside the building).  Returns {"points" (k,3), "lux" (k,),
    and the statistics}.
    """
    lo, hi = patches.bounds
    ext = hi - lo
    spacing = spacing or max(ext[0], ext[2]) / 64.0
    xs = np.arange(lo[0] + 0.5 * spacing, hi[0], spacing)
    zs = np.arange(lo[2] + 0.5 * spacing, hi[2], spacing)
    xx, zz = np.meshgrid(xs, zs)
    pts = np.stack([xx.ravel(), np.full(xx.size, lo[1] + height), zz.ravel()], axis=1)
    tracer = tracer or Tracer.mesh(patches)
    border = min(0.5, 0.1 * min(ext[0], ext[2])) if border is None else border
    near = np.zeros(len(pts), bool)
    for d in ([1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0], [0, 0, -1.0]):
        prim, t = tracer.intersect(pts, np.broadcast_to(np.array(d), pts.shape).copy())
        near |= (prim != MISS) & (t < border)
    pts = pts[~near]
    up = np.broadcast_to(np.array([0.0, 1.0, 0.0]), pts.shape).copy()
    h, lost = _gather(patches, tracer, pts, up, rays, seed)
    keep = lost < 0.5
    lux = to_lux(h[keep])
    return {"height_m": float(height), "spacing_m": float(spacing), "border_m": float(border),
            "points": pts[keep], "lux": lux,
            "n_points": int(keep.sum()), **stats(lux)}


# -- false colour -----------------------------------------------------------------------------
#: colour map stops (linear RGB), low to high: dark blue, blue, cyan, green, yellow, orange, red
_STOPS = np.array([[0.0, 0.0, 0.25], [0.0, 0.1, 1.0], [0.0, 0.8, 1.0], [0.0, 0.8, 0.1],
                   [1.0, 1.0, 0.0], [1.0, 0.45, 0.0], [0.8, 0.0, 0.0]])


def colour_map(x: np.ndarray) -> np.ndarray:
    """(...) values in [0, 1] -> (..., 3) linear RGB along _STOPS."""
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0) * (len(_STOPS) - 1)
    i = np.minimum(np.floor(x).astype(np.int64), len(_STOPS) - 2)
    f = (x - i)[..., None]
    return _STOPS[i] * (1 - f) + _STOPS[i + 1] * f


def legend_scale(lux: np.ndarray, area: np.ndarray) -> float:
    """Top of the false-colour scale: a round number (1, 1.5, 2, 2.5, 3, 4, 5, 6, 7.5 x 10^k)
    at or above the area-weighted 99th percentile of the values."""
    ok = lux > 0
    if not ok.any():
        return 1.0
    order = np.argsort(lux[ok])
    cum = np.cumsum(area[ok][order])
    top = float(lux[ok][order][min(int(np.searchsorted(cum, 0.99 * cum[-1])), len(cum) - 1)])
    k = 10.0 ** math.floor(math.log10(top))
    return next(m * k for m in (1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 7.5, 10.0) if m * k >= top * (1 - 1e-12))


def false_colour(value: np.ndarray, front: np.ndarray, back: np.ndarray, top: float,
                 legend_width: int = 110, ticks: int = 6) -> np.ndarray:
    """(H, W) lux, front-hit and back-hit coverage -> (H, W + legend_width, 3) uint8 sRGB image.

    Pixels: the colour map of value / top where surfaces face the camera, grey where a
    one-sided surface is seen from behind, black for nothing.  At the right a colour bar
    (top at the top) with ``ticks`` labels in lux, drawn with OpenImageIO's text renderer.
    """
    import OpenImageIO as oiio  # noqa: PLC0415  lazy: `dcrad jobs/watch` imports this module and must not load OpenImageIO

    h, w = value.shape
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = np.where(front > 0, value / np.where(front > 0, front, 1.0), 0.0)
    img = np.zeros((h, w + legend_width, 3))
    img[:, :w] = colour_map(mean / top) * front[..., None] + 0.35 * back[..., None]
    img[:, w:] = 0.08
    bar_x0, bar_x1 = w + 10, w + 34
    y0, y1 = 20, h - 20
    ys = np.arange(y0, y1)
    img[y0:y1, bar_x0:bar_x1] = colour_map(1.0 - (ys - y0) / max(y1 - 1 - y0, 1))[:, None, :]
    buf = oiio.ImageBuf(oiio.ImageSpec(w + legend_width, h, 3, oiio.FLOAT))
    buf.set_pixels(oiio.ROI(0, w + legend_width, 0, h, 0, 1, 0, 3), img.astype(np.float32))
    size = max(10, min(16, h // 20))
    for i in range(ticks):
        frac = i / (ticks - 1)
        y = int(round(y1 - 1 - frac * (y1 - 1 - y0)))
        oiio.ImageBufAlgo.fill(buf, (1.0, 1.0, 1.0), oiio.ROI(bar_x1, bar_x1 + 6, y, y + 1))
        label = f"{frac * top:.4g}"
        oiio.ImageBufAlgo.render_text(buf, bar_x1 + 9, y + size // 3, label, size, "", (1.0, 1.0, 1.0))
    oiio.ImageBufAlgo.render_text(buf, w + 8, 14, "lux", size, "", (1.0, 1.0, 1.0))
    out = np.asarray(buf.get_pixels(oiio.FLOAT)).reshape(h, w + legend_width, 3)
    return tonemap(out, exposure=1.0)
