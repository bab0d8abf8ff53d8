"""Pictures of a solved patch table: cameras, smooth radiosity, ray-cast images.

Numerics only; files are written by :mod:`dcrad.io.export`.  Conventions: Y is
up, lengths in metres, B in W/m^2.  :func:`render` returns *radiance*
``L = B / pi`` (W m^-2 sr^-1, the radiance of a Lambertian surface of
radiosity B), linear, float32.  Every primary ray goes through
:class:`dcrad.transport.rays.Tracer`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dcrad.errors import ConfigError
from dcrad.transport.rays import MISS, Tracer

__all__ = [
    "Camera",
    "check_image_size",
    "MAX_IMAGE_SIDE",
    "BACKFACE_COLOR",
    "corner_radiosity",
    "CornerSmoother",
    "ViewHits",
    "trace_view",
    "shade_view",
    "auto_camera",
    "camera_from_dict",
    "topdown_camera",
    "cutaway_mask",
    "render",
    "tonemap",
    "luminance",
    "scene_exposure",
    "marks_in_view",
    "draw_marks",
]

#: the largest preview side in pixels (a 8192 x 8192 view is 67M primary rays and 1.6 GB of hits)
MAX_IMAGE_SIDE = 8192


def check_image_size(width: int, height: int) -> None:
    """ConfigError unless both sides of a preview are whole pixels in 1 .. MAX_IMAGE_SIDE."""
    for name, v in (("width", width), ("height", height)):
        if not 1 <= v <= MAX_IMAGE_SIDE:
            raise ConfigError(f"preview {name} {v} pixels: must be 1 to {MAX_IMAGE_SIDE}")


#: colour of one-sided surfaces seen from behind (flipped normals, or the outside of a
#: room): a flat neutral grey, as a fraction of the reference radiance (the radiance the
#: exposure maps to white) when ``render(backface_color=None)``
BACKFACE_COLOR = (0.3, 0.3, 0.3)
#: jittered samples per pixel of the previews (a 2 x 2 stratified pattern)
SAMPLES = 4
#: previews: luminance above this (after exposure) rolls off toward white (tonemap)
SHOULDER = 0.8
_LUMA = np.array([0.2126, 0.7152, 0.0722])
#: render() shades this many hits at a time (bounded temporaries; the image does not depend on it)
RENDER_CHUNK = 1 << 16


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 0, n, 1.0)


def _vec3(x) -> tuple:
    a = np.asarray(x, np.float64).reshape(3)
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"camera vector {a} is not finite")
    return tuple(float(c) for c in a)


@dataclass(frozen=True)
class Camera:
    """A pinhole (or orthographic) camera.

    eye, target, up : 3 floats (stored as tuples; ``np.asarray`` them freely)
    fov_y           : vertical field of view in degrees (perspective only)
    width, height   : image size in pixels; row 0 is the top of the image
    orthographic_height : if set, an orthographic view this many metres tall
    """

    eye: tuple
    target: tuple
    up: tuple = (0.0, 1.0, 0.0)
    fov_y: float = 45.0
    width: int = 640
    height: int = 480
    orthographic_height: float | None = None

    def __post_init__(self) -> None:
        for name in ("eye", "target", "up"):
            object.__setattr__(self, name, _vec3(getattr(self, name)))
        if int(self.width) < 1 or int(self.height) < 1:
            raise ConfigError(f"image size {self.width}x{self.height} must be positive")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        if self.orthographic_height is None and not 0.0 < self.fov_y < 180.0:
            raise ConfigError(f"fov_y {self.fov_y} must be in (0, 180) degrees")
        if self.orthographic_height is not None and not self.orthographic_height > 0:
            raise ConfigError(f"orthographic_height {self.orthographic_height} must be > 0")
        f = np.subtract(self.target, self.eye)
        if not np.linalg.norm(f) > 0:
            raise ConfigError("camera eye and target coincide")
        if np.linalg.norm(np.cross(_unit(f), _unit(np.asarray(self.up)))) < 1e-6:
            raise ConfigError("camera up is parallel to the view direction")

    def basis(self):
        """(forward, right, up) as (3,) float64 unit vectors, right-handed."""
        fwd = _unit(np.subtract(self.target, self.eye))
        right = _unit(np.cross(fwd, self.up))
        return fwd, right, np.cross(right, fwd)

    def rays(self, jitter=(0.5, 0.5)):
        """Primary rays through one point of each pixel, row-major from the top-left pixel.

        jitter : (dx, dy) in [0, 1): where in the pixel, from its top-left corner
        (default the centre); or (H*W, 2) one offset per pixel
        returns (origins (H*W, 3) float64, dirs (H*W, 3) float64 unit)
        """
        w, h = self.width, self.height
        fwd, right, up = self.basis()
        jit = np.broadcast_to(np.asarray(jitter, np.float64), (h * w, 2)).reshape(h, w, 2)
        x = (np.arange(w)[None, :] + jit[:, :, 0]) / w * 2.0 - 1.0  # -1 .. 1 left to right
        y = 1.0 - (np.arange(h)[:, None] + jit[:, :, 1]) / h * 2.0  # 1 .. -1 top to bottom
        xx, yy = x.reshape(-1, 1), y.reshape(-1, 1)
        eye = np.asarray(self.eye)
        if self.orthographic_height is not None:
            half_h = 0.5 * self.orthographic_height
            half_w = half_h * w / h
            origins = eye + xx * half_w * right + yy * half_h * up
            dirs = np.broadcast_to(fwd, origins.shape).copy()
            return origins, dirs
        half_h = math.tan(math.radians(self.fov_y) / 2.0)
        half_w = half_h * w / h
        dirs = _unit(fwd + xx * half_w * right + yy * half_h * up)
        return np.broadcast_to(eye, dirs.shape).copy(), dirs

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where ``points`` (k,3) fall in the image, as ``rays`` casts it: (xy (k,2) pixel coordinates,
        x to the right and y down from the image's top-left corner, pixel (row i, column j) covering
        [j, j+1) x [i, i+1); depth (k,) m along the view direction, <= 0 behind the camera)."""
        fwd, right, up = self.basis()
        d = np.asarray(points, np.float64).reshape(-1, 3) - np.asarray(self.eye)
        depth = d @ fwd
        if self.orthographic_height is not None:
            half_h = 0.5 * self.orthographic_height
            scale = np.ones(len(d))
        else:
            half_h = math.tan(math.radians(self.fov_y) / 2.0)
            scale = np.where(depth > 0, depth, 1.0)
        half_w = half_h * self.width / self.height
        x = (d @ right) / (scale * half_w)
        y = (d @ up) / (scale * half_h)
        return np.column_stack([(x + 1.0) / 2.0 * self.width, (1.0 - y) / 2.0 * self.height]), depth


# ---------------------------------------------------------------------------------
def _position_groups(points: np.ndarray, tol: float, origin: np.ndarray):
    """Group points by position on a grid of cell size ``tol`` whose cells are centred on
    ``origin`` + integer multiples of ``tol``.

    returns (group (m,) int64 id per point, G groups); ids follow the lexicographic order
    of the cells, so sorting points by id sorts them by cell
    """
    # dense rank per axis (one axis at a time: no (m, 3) temporaries), then one int64 key
    # when the ranks fit (they nearly always do)
    ranks, sizes = [], []
    for ax in range(3):
        key = np.floor((points[:, ax] - origin[ax]) / tol + 0.5).astype(np.int64)
        u, r = np.unique(key, return_inverse=True)
        ranks.append(r.reshape(-1).astype(np.int64))
        sizes.append(len(u))
    if float(sizes[0]) * sizes[1] * sizes[2] < 2.0**62:
        lin = (ranks[0] * sizes[1] + ranks[1]) * sizes[2] + ranks[2]
        u, group = np.unique(lin, return_inverse=True)
        return group.reshape(-1).astype(np.int64), len(u)
    else:  # pragma: no cover - needs > 2^62 distinct coordinate triples
        order = np.lexsort((ranks[2], ranks[1], ranks[0]))
        srt = np.stack([r[order] for r in ranks], axis=1)
        new = np.concatenate([[True], np.any(srt[1:] != srt[:-1], axis=1)])
        group = np.empty(len(points), np.int64)
        group[order] = np.cumsum(new) - 1
        return group, int(new.sum())


#: a CornerSmoother keeps its pairs (12 bytes each) when there are at most this many (the office
#: 8x8: 3.6M); above, ``apply`` forms them again chunk by chunk (the 20x20 office: ~23M)
KEEP_PAIRS = 8_000_000


class CornerSmoother:
    """Which patches each corner averages over, and with what weights: ``corner_radiosity`` without
    the values, so the part that depends on the geometry only is done once (a coordinator does it
    while its workers solve) and each ``apply(values)`` is a gather and a segmented sum.

    The value at corner k of patch p is the area-weighted mean of ``values`` over every patch q
    having a corner at the same position (within ``merge_tol * patches.scale``, so duplicated
    vertices merge) whose normal is within ``crease_angle_deg`` of p's normal.  Patches facing
    away from each other (n_p . n_q <= 0, e.g. the two sides of a thin wall) never mix,
    whatever the angle.  Patches with no valid neighbour (degenerate) keep their own value.
    Pairs: sum over positions of (corners there)^2, formed ``max_pairs`` at a time (the result
    does not depend on it) and kept when there are at most ``keep_pairs`` of them.  With ``rows``
    only those patches' corners are smoothed (the others keep their patch's value): a live
    preview's visible patches, about a seventh of the 8x8 office's.
    """

    _coverage: np.ndarray | None = None  #: coverage(), once formed

    def __init__(self, patches, crease_angle_deg: float = 30.0, merge_tol: float = 1e-7,
                 max_pairs: int = 1 << 18, keep_pairs: int | None = None, rows: np.ndarray | None = None):
        n = len(patches)
        self.n = n
        self.m = m = 3 * n
        self._chunks: list[tuple] | None = []
        if n == 0:
            self.bounds = np.zeros(1, np.int64)
            return
        tol = max(merge_tol * patches.scale, 1e-300)
        faces = getattr(patches, "faces", None)
        if faces is not None:  # positions grouped per mesh vertex (a vertex has ~5 corners), not per corner
            vgroup, n_groups = _position_groups(patches.vertices, tol, patches.bounds[0])
            group = vgroup[np.asarray(faces).reshape(-1)]
            del vgroup
        else:
            corners = patches.triangles.reshape(-1, 3)
            group, n_groups = _position_groups(corners, tol, corners.min(axis=0))
        small = np.int32 if m < 2**31 else np.int64  # corner indices: half the bytes
        self.order = np.argsort(group, kind="stable").astype(small)
        counts = np.bincount(group, minlength=n_groups)
        starts = np.cumsum(counts) - counts
        gs = group[self.order]
        del group
        self.k = counts[gs].astype(small)  # partners of each sorted corner (itself included)
        self.first = starts[gs].astype(small)  # sorted position of its group's first corner
        del gs, starts, counts
        self.ps = (self.order // 3).astype(small)  # patch of each sorted corner
        self.normal, self.area = patches.normal, patches.area
        self.cos_t = math.cos(math.radians(min(max(crease_angle_deg, 0.0), 180.0))) - 1e-9
        # the sorted corners smoothed: all, or those of ``rows`` (a live preview's visible patches)
        self.sel = None if rows is None else np.flatnonzero(np.isin(self.ps, rows)).astype(small)
        k_sel = self.k if self.sel is None else self.k[self.sel]
        ends = np.cumsum(k_sel, dtype=np.int64)
        self.pairs = int(ends[-1]) if len(ends) else 0
        cuts = np.searchsorted(ends, np.arange(max_pairs, self.pairs, max_pairs), side="right")
        self.bounds = np.unique(np.concatenate([[0], cuts, [len(k_sel)]]))
        del ends, cuts, k_sel
        if self.pairs <= (KEEP_PAIRS if keep_pairs is None else keep_pairs):
            self.keep()
        else:
            self._chunks = None

    @property
    def kept(self) -> bool:
        """Every pair kept (``apply`` forms none)."""
        return self._chunks is not None and len(self._chunks) == len(self.bounds) - 1

    def keep(self, stop=None) -> None:
        """Form the pairs and keep them (12 bytes a pair: the 20x20 office's ~23M, 0.33 GB, in a
        process of their own), one chunk at a time, until every chunk is kept or ``stop`` (a
        ``threading.Event``) is set; ``apply`` uses the chunks kept so far and forms the rest (the
        same numbers), so it need not wait for this, even from another thread."""
        kept = self._chunks if self._chunks is not None else []
        self._chunks = kept
        for lo, hi in list(zip(self.bounds[:-1], self.bounds[1:]))[len(kept):]:
            if stop is not None and stop.is_set():
                return
            kept.append(self._pairs(lo, hi))
        if stop is not None:  # ahead of its use (not when kept in the constructor: pickled to the coordinator)
            self.coverage()

    def _pairs(self, lo: int, hi: int):
        """Smoothed corners lo .. hi (of the sorted corners, or of ``sel``): (their corners (c,), run
        starts (c,), partner patches (p,), weights (p,) normalised per run, whether the corner has a
        valid partner (c,))."""
        at = slice(lo, hi) if self.sel is None else self.sel[lo:hi]
        kk = self.k[at].astype(np.int64)
        seg = np.cumsum(kk) - kk  # where each corner's run of pairs starts
        ps = self.ps
        pb = ps[np.arange(int(kk.sum())) + np.repeat(self.first[at] - seg, kk)]  # partner's patch
        dot = np.einsum("ij,ij->i", np.repeat(self.normal[ps[at]], kk, axis=0), self.normal[pb])
        w = np.where((dot >= self.cos_t) & (dot > 0.0), self.area[pb], 0.0)
        den = np.add.reduceat(w, seg) if len(seg) else np.zeros(0)
        ok = den > 0
        w /= np.repeat(np.where(ok, den, 1.0), kk)
        return self.order[at], seg, pb, w, ok

    def apply(self, values: np.ndarray, dtype=np.float64, coverage: bool = False) -> np.ndarray:
        """(n, C) or (n,) values per patch -> (n, 3 corners, C) ``dtype``: the means in float64, stored
        as ``dtype`` (float32 halves the result: 1.27M patches, 6 channels, 91 MB instead of 183).

        ``coverage``: two channels more, the means of ones and of zeros (0): what the same call with
        two such columns appended gives, bit for bit (reduceat sums each column on its own); the
        ones are summed with the values unless ``coverage()`` has them already (formed ahead), and
        the zeros never."""
        vals = np.asarray(values, np.float64).reshape(self.n, -1)
        nch = vals.shape[1]
        ones = coverage and self._coverage is None  # summed in this pass: no second pass over the pairs
        if ones:
            vals = np.column_stack([vals, np.ones(self.n)])
        summed = vals.shape[1]
        out = np.empty((self.n, 3, nch + 2 * coverage), dtype)
        out[..., :summed] = vals[:, None, :]
        if coverage:
            if not ones:
                out[..., nch] = self._coverage
            out[..., nch + 1] = 0.0
        flat = out.reshape(self.m, -1)
        kept = self._chunks if self._chunks is not None else []
        for i, (lo, hi) in enumerate(zip(self.bounds[:-1], self.bounds[1:])):
            dest, seg, pb, w, ok = kept[i] if i < len(kept) else self._pairs(lo, hi)
            num = np.add.reduceat(w[:, None] * vals[pb], seg, axis=0)
            flat[dest[ok], :summed] = num[ok]
        return out

    def coverage(self) -> np.ndarray:
        """(n, 3) float64 means of ones (the weights' sums: 1 up to round-off), computed once: it
        depends on the geometry only (a views process forms it ahead, with its pairs)."""
        if self._coverage is None:
            self._coverage = self.apply(np.ones(self.n))[..., 0]
        return self._coverage


def corner_radiosity(
    patches,
    crease_angle_deg: float = 30.0,
    values: np.ndarray | None = None,
    merge_tol: float = 1e-7,
    max_pairs: int = 1 << 18,
    dtype=np.float64,
) -> np.ndarray:
    """Smooth per-corner radiosity that does not bleed across creases (``CornerSmoother``, once).

    returns (n, 3 corners, C channels) ``dtype``, C = 3 for radiosity (``values``: default
    ``patches.radiosity``)
    """
    vals = patches.radiosity if values is None else values
    return CornerSmoother(patches, crease_angle_deg, merge_tol, max_pairs, keep_pairs=0).apply(vals, dtype)


# ---------------------------------------------------------------------------------
def _escape_share(tracer: Tracer, lo: np.ndarray, hi: np.ndarray, axis: int, sign: float, k=9):
    """Fraction of rays leaving the box centre region toward a side that escape."""
    c = 0.5 * (lo + hi)
    others = [i for i in range(3) if i != axis]
    s = (np.arange(k) + 0.5) / k * 0.9 + 0.05
    uu, vv = np.meshgrid(s, s)
    o = np.tile(c, (k * k, 1))
    o[:, others[0]] = lo[others[0]] + uu.ravel() * (hi - lo)[others[0]]
    o[:, others[1]] = lo[others[1]] + vv.ravel() * (hi - lo)[others[1]]
    d = np.zeros_like(o)
    d[:, axis] = sign
    prim, _ = tracer.intersect(o, d)
    return float(np.mean(prim == MISS))


def auto_camera(patches, width: int = 640, height: int = 480, tracer: Tracer | None = None) -> Camera:
    """A perspective view of the whole scene.

    Rays are cast from a grid on the mid-plane of the bounding box toward each
    of the four vertical sides (+-X, +-Z) and toward +Y; the fraction that
    escapes is that side's escape share (not partition.openness, which is the
    share of a cutting plane in open space).

    * Some vertical side is mostly open (>= 50%; a Cornell box, or any scene
      that is not a closed room): the eye stands outside the most open side on
      the box's mid-height, looking at the centre, fov_y = 40 deg, far enough
      back that the whole cross-section of the box fits the frame.  If the top
      is open as well the eye is lifted 30 deg so the floor shows.
    * Closed (a room, or a floor of rooms): the camera looks at lit space.  The
      brightest floor spot (non-emitting up-facing patches in the bottom quarter,
      by luminance of B; the 90th percentile by area among them, so a single
      noisy patch does not decide) is found, and the room around it is measured
      by casting rays from 40% and 90% of the height above it along +-X and +-Z to the
      walls.  The eye stands inside that room near a top corner (80% of the
      height, 8% in from the two walls), looking at the diagonally opposite
      corner at 20% of the height, fov_y = 65 deg.  Of the four corners the one
      with the clearest line of sight from the room's centre is used.  Without
      lit floor the whole box is the room.

    ``tracer``: a Tracer over ``patches.triangles`` to cast with (the solve's: at 1.27M
    patches a second one cost 2 s and 160 MB at its build); None: build one.
    """
    lo, hi = patches.bounds
    ext = np.maximum(hi - lo, 1e-9 * patches.scale)
    c = 0.5 * (lo + hi)
    if tracer is None:
        tracer = Tracer.mesh(patches)
    elif tracer.n != len(patches):
        raise ValueError(f"tracer holds {tracer.n} triangles, the table {len(patches)} patches")
    sides = [(0, 1.0), (0, -1.0), (2, 1.0), (2, -1.0)]
    escape = [_escape_share(tracer, lo, hi, ax, sg) for ax, sg in sides]
    best = int(np.argmax(escape))
    aspect = width / height
    if escape[best] >= 0.5:
        ax, sg = sides[best]
        across = ext[2 - ax]  # the horizontal extent seen across the image
        fov = 40.0
        half = max(0.5 * ext[1], 0.5 * across / aspect)
        dist = 0.5 * ext[ax] + 1.05 * half / math.tan(math.radians(fov / 2))
        d = np.zeros(3)
        d[ax] = sg
        if _escape_share(tracer, lo, hi, 1, 1.0) >= 0.5:
            el = math.radians(30.0)
            d = d * math.cos(el) + np.array([0.0, math.sin(el), 0.0])
            dist += 0.5 * ext[1] * math.tan(el)  # step back: the box looks taller
        return Camera(c + dist * d, c, (0, 1, 0), fov, width, height)
    rlo, rhi = _lit_room(patches, tracer, lo, hi)
    rext = rhi - rlo
    rc = 0.5 * (rlo + rhi)
    inset = 0.08 * rext
    best_eye, best_t = None, -1.0
    for sx in (-1.0, 1.0):
        for sz in (-1.0, 1.0):
            s = np.array([sx, 0.0, sz])
            eye = np.where(s > 0, rhi - inset, rlo + inset)
            eye[1] = rlo[1] + 0.8 * rext[1]
            _, t = tracer.intersect(rc[None], (eye - rc)[None])
            if min(float(t[0]), 1.0) > best_t + 1e-9:
                best_eye, best_t = eye, min(float(t[0]), 1.0)
    assert best_eye is not None  # the first corner always beats best_t = -1 (t >= 0)
    target = rlo + rhi - best_eye
    target[1] = rlo[1] + 0.2 * rext[1]
    return Camera(tuple(best_eye), tuple(target), (0, 1, 0), 65.0, width, height)


def _lit_room(patches, tracer: Tracer, lo: np.ndarray, hi: np.ndarray):
    """(lo, hi) of the room around the brightest floor spot (see auto_camera); the box if none."""
    ext = hi - lo
    floor = (patches.normal[:, 1] > 0.7) & (patches.centroid[:, 1] <= lo[1] + 0.25 * ext[1])
    floor &= ~np.any(patches.emission > 0, axis=1)
    lum = luminance(np.asarray(patches.radiosity, np.float64))
    idx = np.flatnonzero(floor & (lum > 0))
    if not len(idx):
        return lo, hi
    order = idx[np.argsort(lum[idx])]
    cum = np.cumsum(patches.area[order])
    spot = order[min(int(np.searchsorted(cum, 0.9 * cum[-1])), len(order) - 1)]
    p = patches.centroid[spot].copy()
    # rays along +-X and +-Z at 40% and 90% of the height: a doorway rarely reaches the
    # ceiling, so the nearer of the two hits per direction is the room's wall
    heights = p[1] + np.array([0.4, 0.9]) * ext[1]
    dirs = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 1.0], [0, 0, -1.0]])
    origins = np.repeat(p[None], 8, axis=0)
    origins[:, 1] = np.repeat(heights, 4)
    prim, t = tracer.intersect(origins, np.tile(dirs, (2, 1)))
    far = np.array([hi[0] - p[0], p[0] - lo[0], hi[2] - p[2], p[2] - lo[2]])
    t = np.where(prim == MISS, np.tile(far, 2), np.minimum(t, np.tile(far, 2))).reshape(2, 4).min(axis=0)
    p[1] = heights[0]
    rlo, rhi = lo.copy(), hi.copy()
    rhi[0], rlo[0], rhi[2], rlo[2] = p[0] + t[0], p[0] - t[1], p[2] + t[2], p[2] - t[3]
    if np.any(rhi - rlo <= 1e-6 * patches.scale):
        return lo, hi
    return rlo, rhi


def camera_from_dict(cam: dict, width: int = 640, height: int = 480) -> Camera:
    """A Camera from a scene file's camera ``{"eye", "target", "up", "fov_y"}`` (glTF)."""
    return Camera(
        eye=cam["eye"], target=cam["target"], up=cam.get("up", (0.0, 1.0, 0.0)),
        fov_y=float(cam.get("fov_y", 45.0)), width=width, height=height,
    )


def topdown_camera(patches, width: int = 640, height: int = 480) -> Camera:
    """Orthographic view straight down -Y framing the box in X/Z (+X right, -Z up)."""
    lo, hi = patches.bounds
    ext = np.maximum(hi - lo, 1e-9 * patches.scale)
    c = 0.5 * (lo + hi)
    eye = np.array([c[0], hi[1] + 0.1 * patches.scale, c[2]])
    tall = 1.04 * max(ext[2], ext[0] * height / width)
    return Camera(tuple(eye), (c[0], lo[1], c[2]), (0, 0, -1), 45.0, width, height, tall)


def cutaway_mask(patches) -> np.ndarray:
    """(n,) bool, False for ceilings and ceiling lights, to look in from above.

    Hidden: horizontal patches (|n_y| > 0.7, facing down or, on two-sided or wrongly
    wound ceilings, up) with centroid in the top 25% of the box height (ceilings,
    the undersides of light fixtures), and emitters anywhere in that top 25% (lamps
    hung under the ceiling).
    """
    lo, hi = patches.bounds
    top = patches.centroid[:, 1] >= lo[1] + 0.75 * (hi[1] - lo[1])
    flat = np.abs(patches.normal[:, 1]) > 0.7
    lamp = np.any(patches.emission > 0, axis=1)
    return ~(top & (flat | lamp))


# ---------------------------------------------------------------------------------
def luminance(img: np.ndarray) -> np.ndarray:
    """(..., 3) linear RGB -> (...) Rec. 709 luminance."""
    return np.asarray(img, np.float64) @ _LUMA


def barycentric(tri: np.ndarray, p: np.ndarray) -> np.ndarray:
    """tri (m,3,3), p (m,3) -> (m,3) barycentrics of p projected on each plane.

    Clipped to the triangle and renormalised; degenerate triangles get 1/3 each.
    """
    a = tri[:, 0]
    v0, v1, v2 = tri[:, 1] - a, tri[:, 2] - a, p - a
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    ok = den > 1e-30 * np.maximum(d00 * d11, 1e-300)
    safe = np.where(ok, den, 1.0)
    v = (d11 * d20 - d01 * d21) / safe
    w = (d00 * d21 - d01 * d20) / safe
    bc = np.clip(np.stack([1.0 - v - w, v, w], axis=1), 0.0, None)
    s = bc.sum(axis=1, keepdims=True)
    bc = np.where(s > 0, bc / np.where(s > 0, s, 1.0), 1.0 / 3.0)
    bc[~ok] = 1.0 / 3.0
    return bc


def _jitter(samples: int) -> np.ndarray:
    """(samples, 2) sub-pixel offsets: a stratified k x k pattern, jittered with a fixed seed."""
    k = max(1, int(round(math.sqrt(max(samples, 1)))))
    cells = (np.stack(np.meshgrid(np.arange(k), np.arange(k)), axis=-1).reshape(-1, 2) + 0.5) / k
    if k == 1:
        return cells
    rng = np.random.default_rng(12345)
    return np.clip(cells + (rng.random(cells.shape) - 0.5) / k, 0.0, 1.0 - 1e-9)


@dataclass
class ViewHits:
    """A view's primary hits, every jitter sample: what a render does not need B for.

    ``trace_view`` casts them once; ``shade_view`` turns corner values into an image from
    them (a coordinator traces its output views while its workers solve, and a live
    preview traces its view once for all its renders).
    """

    width: int
    height: int
    samples: int
    pixel: np.ndarray  #: (m,) int32 pixel of each hit (row-major)
    patch: np.ndarray  #: (m,) patch shown (a two-sided patch seen from behind: its back side)
    bc: np.ndarray  #: (m, 3) float32 barycentrics of the hit point on that patch
    back: np.ndarray  #: (m,) bool: a one-sided patch seen from behind (the flag colour)


def trace_view(patches, camera: Camera, mask: np.ndarray | None = None, tracer: Tracer | None = None,
               samples: int = 1) -> ViewHits:
    """The primary hits of ``camera``'s view of ``patches`` (``mask``, ``tracer``, ``samples`` as in
    :func:`render`)."""
    n = len(patches)
    idx = np.arange(n) if mask is None else np.flatnonzero(np.asarray(mask, bool).reshape(n))
    if tracer is None:
        tracer = Tracer.mesh(patches, idx)
    elif tracer.n != len(idx):
        raise ValueError(f"tracer holds {tracer.n} triangles but the mask selects {len(idx)}")
    twin = getattr(patches, "twin", None)
    pixel, patch, bcs, backs = [], [], [], []
    for jit in _jitter(samples):
        origins, dirs = camera.rays(jit)
        prim, t = tracer.intersect(origins, dirs)
        hits = np.flatnonzero(prim != MISS)
        # RENDER_CHUNK hits at a time: the triangles and barycentrics of a whole 640 x 480 view
        # were 120 MB of temporaries
        for lo in range(0, len(hits), RENDER_CHUNK):
            hit = hits[lo:lo + RENDER_CHUNK]
            p = idx[prim[hit]]
            back = np.einsum("ij,ij->i", dirs[hit], patches.normal[p]) > 0
            if twin is not None:
                other = twin[p]
                seen = back & (other >= 0)
                p = np.where(seen, other, p)  # a two-sided patch from behind: its back side
                back &= ~seen
            point = origins[hit] + t[hit, None] * dirs[hit]
            bcs.append(barycentric(patches.corners(p), point).astype(np.float32))
            pixel.append(hit.astype(np.int32))
            patch.append(p)
            backs.append(back)
    if not pixel:
        return ViewHits(camera.width, camera.height, len(_jitter(samples)), np.zeros(0, np.int32),
                        np.zeros(0, np.int64), np.zeros((0, 3), np.float32), np.zeros(0, bool))
    return ViewHits(camera.width, camera.height, len(_jitter(samples)), np.concatenate(pixel),
                    np.concatenate(patch), np.concatenate(bcs), np.concatenate(backs))


def marks_in_view(camera: Camera, points: np.ndarray, tracer: Tracer | None = None) -> np.ndarray:
    """(m,2) pixel coordinates (``Camera.project``) of those ``points`` (k,3) the view shows: in front
    of the camera, inside the image and, with ``tracer`` (the view's Embree scene), not hidden behind
    a surface (a point on a surface, a luminaire's centre on its ceiling, counts as seen)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    xy, depth = camera.project(points)
    keep = (depth > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < camera.width) & (xy[:, 1] >= 0) & (xy[:, 1] < camera.height)
    rows = np.flatnonzero(keep)
    if tracer is not None and len(rows):
        fwd = np.asarray(camera.basis()[0])
        if camera.orthographic_height is not None:  # from the image plane straight along the view
            origins = points[rows] - depth[rows, None] * fwd
            dirs = np.broadcast_to(fwd, origins.shape).copy()
            dist = depth[rows]
        else:
            origins = np.broadcast_to(np.asarray(camera.eye), (len(rows), 3)).copy()
            d = points[rows] - origins
            dist = np.linalg.norm(d, axis=1)
            dirs = d / dist[:, None]
        rows = rows[~tracer.occluded(origins, dirs, dist * (1.0 - 1e-4))]
    return xy[rows]


#: the marks' rings (``draw_marks``): (outer radius in pixels at a 480-pixel image, white or black),
#: from the outside in: a white ring and dot outlined in black, seen on every colour of the map
_MARK_RINGS = ((7.0, 0), (5.5, 255), (3.5, 0), (1.5, 255))


def draw_marks(img: np.ndarray, xy: np.ndarray, width: int | None = None) -> np.ndarray:
    """``img`` (H, W', 3) uint8 with a small bullseye (a white ring and centre in black outlines,
    scaled with the image's height) centred on each pixel coordinate of ``xy`` (m,2), drawn in the
    first ``width`` columns only (the picture, not a legend beside it).  Returns ``img``, changed."""
    h = img.shape[0]
    width = img.shape[1] if width is None else width
    size = max(1.0, h / 480.0)
    reach = int(math.ceil(_MARK_RINGS[0][0] * size)) + 1
    offsets = np.arange(-reach, reach + 1)
    for x, y in np.asarray(xy, np.float64).reshape(-1, 2):
        cols = np.floor(x).astype(np.int64) + offsets
        rows = np.floor(y).astype(np.int64) + offsets
        cols, rows = cols[(cols >= 0) & (cols < width)], rows[(rows >= 0) & (rows < h)]
        if not (len(cols) and len(rows)):
            continue
        # distance from the point to each pixel's centre
        r = np.hypot(cols[None, :] + 0.5 - x, rows[:, None] + 0.5 - y)
        block = img[rows[0]: rows[-1] + 1, cols[0]: cols[-1] + 1]
        for radius, value in _MARK_RINGS:  # outermost first, each inner one painted over it
            block[r <= radius * size] = value
    return img


def shade_view(view: ViewHits, corner_values: np.ndarray, backface_color=None,
               exposure: float | None = None) -> np.ndarray:
    """(H, W, C) float32 radiance values / pi of a traced view (``corner_values`` (n, 3, C) for the
    whole table; ``backface_color``, ``exposure`` as in :func:`render`)."""
    cv = np.asarray(corner_values)
    cv = cv.reshape(cv.shape[0], 3, -1)
    nch = cv.shape[2]
    size = view.width * view.height
    total = np.zeros((nch, size))  # a row per channel: bincount's weights and sums contiguous
    fronts = []
    need_fronts = backface_color is None and not (exposure is not None and exposure > 0)
    for lo in range(0, len(view.pixel), RENDER_CHUNK):
        sl = slice(lo, lo + RENDER_CHUNK)
        back = view.back[sl]
        corners = cv[view.patch[sl]].astype(np.float64, copy=False)
        value = np.einsum("ik,ikc->ic", view.bc[sl].astype(np.float64), corners)
        value /= math.pi
        value[back] = 0.0  # shown as the flag colour below
        if need_fronts:
            fronts.append(value[~back])
        # summed over the pixels the chunk's hits fall on (a chunk is a run of pixels of one jitter
        # sample, or two): the other pixels would gain +0.0, which leaves any sum as it is (none is
        # -0.0), and a 640 x 480 bincount per channel and chunk was half of the shading
        pix = view.pixel[sl]
        first = int(pix.min()) if len(pix) else 0
        span = int(pix.max()) - first + 1 if len(pix) else 0
        rows = np.ascontiguousarray(value.T)
        for c in range(nch):
            total[c, first:first + span] += np.bincount(pix - first, weights=rows[c], minlength=span)
    if backface_color is None:
        if exposure is not None and exposure > 0:
            ref = 0.9 / exposure
        else:
            front = luminance(np.concatenate(fronts)) if nch == 3 and fronts else np.zeros(0)
            ref = float(np.percentile(front, 99.0)) if front.size else 0.0
        flag = np.resize(np.asarray(BACKFACE_COLOR), nch) * (ref if ref > 0 else 1.0)
    else:
        flag = np.resize(np.asarray(backface_color, np.float64), nch)
    behind = np.bincount(view.pixel[view.back], minlength=size).astype(np.float64)
    total = total.T + behind[:, None] * flag  # the flag colour stands in for those samples' (zero) value
    img = total / view.samples
    return img.reshape(view.height, view.width, nch).astype(np.float32)


def render(
    patches,
    camera: Camera,
    mask: np.ndarray | None = None,
    corner_values: np.ndarray | None = None,
    tracer: Tracer | None = None,
    backface_color=None,
    samples: int = 1,
    exposure: float | None = None,
) -> np.ndarray:
    """Ray-cast image of the patch table (``trace_view``, then ``shade_view``).

    mask          : (n,) bool, patches to draw (default all)
    corner_values : (n, 3, C) values per corner for the *whole* table (default
                    :func:`corner_radiosity`, C = 3), float64 or float32;
                    interpolated barycentrically (in float64) over each hit triangle
    tracer        : a Tracer built on ``patches.triangles[mask]`` in that order
                    (reuse it across views); built here when None
    backface_color: RGB for pixels that see a one-sided patch from behind
                    (flipped normals, the outside of a room).  None:
                    ``BACKFACE_COLOR`` times the reference radiance: 0.9 / ``exposure``
                    if given, else the 99th percentile of the front-face
                    luminance (1 if none), so it shows as the same grey after
                    :func:`tonemap`.  A two-sided patch seen from behind shows its
                    back side (``Patches.twin``).
    samples       : rays per pixel (1: the centre; 4: a jittered 2 x 2 pattern), averaged

    returns (H, W, C) float32 radiance B / pi (values / pi); misses are 0.
    """
    view = trace_view(patches, camera, mask, tracer, samples)
    if corner_values is None:
        corner_values = corner_radiosity(patches)
    return shade_view(view, np.asarray(corner_values).reshape(len(patches), 3, -1), backface_color, exposure)


def scene_exposure(patches, percentile: float = 99.0, white: float = 0.9) -> float:
    """One exposure for every view and mesh: from the lit surfaces, not the lamps.

    The ``percentile`` of the luminance of B / pi over the *area* of the patches that
    do not emit maps to ``white``; emitters are left out (they would darken everything
    when in frame).  1 when nothing is lit.
    """
    lamp = np.any(patches.emission > 0, axis=1)
    lum = luminance(np.asarray(patches.radiosity, np.float64)[~lamp]) / math.pi
    area = patches.area[~lamp]
    ok = lum > 0
    if not ok.any():
        return 1.0
    lum, area = lum[ok], area[ok]
    order = np.argsort(lum)
    cum = np.cumsum(area[order])
    ref = float(lum[order][min(np.searchsorted(cum, percentile / 100.0 * cum[-1]), len(cum) - 1)])
    return white / ref if ref > 0 else 1.0


def _srgb_oetf(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def tonemap(
    img: np.ndarray,
    exposure: float | None = None,
    percentile: float = 99.0,
    white: float = 0.9,
    srgb: bool = True,
    shoulder: float | None = None,
) -> np.ndarray:
    """Linear (..., 3) image -> (..., 3) uint8, sRGB-encoded unless ``srgb=False``.

    ``exposure`` multiplies the image; by default the ``percentile`` of the
    luminance of the non-black pixels maps to ``white`` (an all-black image
    keeps exposure 1).  ``shoulder`` (e.g. 0.8, the previews' SHOULDER): luminance
    above it rolls off smoothly toward 1 instead of clipping (colour ratios kept),
    so bright surfaces under lamps keep their shading.  Values are then clamped to
    [0, 1]; NaN become 0.
    """
    x = np.nan_to_num(np.asarray(img, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if exposure is None:
        lum = luminance(x).ravel()
        lum = lum[lum > 0]
        ref = float(np.percentile(lum, percentile)) if lum.size else 0.0
        exposure = white / ref if ref > 0 else 1.0
    x = x * float(exposure)
    if shoulder is not None and 0.0 < shoulder < 1.0:
        lum = luminance(x)
        k = float(shoulder)
        high = lum > k
        t = (lum[high] - k) / (1.0 - k)
        rolled = k + (1.0 - k) * t / (1.0 + t)  # slope 1 at the knee, 1 reached only at infinity
        x[high] *= (rolled / lum[high])[..., None]
    x = np.clip(x, 0.0, 1.0)
    if srgb:
        x = _srgb_oetf(x)
    return np.round(x * 255.0).astype(np.uint8)
