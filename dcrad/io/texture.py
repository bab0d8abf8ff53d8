"""Diffuse textures: read an image (OpenImageIO), average it over UV triangles.

A textured material's reflectance on a triangle is the factor (``Kd``,
``baseColorFactor``) times the mean of the linear texture over the UV
triangle the triangle covers.  Images are read with OpenImageIO; 8- and 16-bit
images are taken as sRGB-encoded (the glTF rule for base colour, and what
OBJ/MTL exporters write) and linearised, float images (EXR, HDR) as linear.
Texels are looked up nearest-neighbour with wrap-around (repeat), so the mean
is the integral of the piecewise-constant image, estimated by the midpoint rule
on a regular grid: each UV triangle is cut into m^2 congruent sub-triangles whose
centroids are looked up, about 16 per covered texel (m from 2 to 64: 4 to 4096
points).  A triangle inside one texel takes that texel.  UV origin is the lower-left corner
of the image (OBJ; trimesh flips glTF's upper-left origin to the same).
"""

from __future__ import annotations

import numpy as np

__all__ = ["read_texture", "srgb_to_linear", "uv_means", "uv_at"]

#: sample points per covered texel, and the bounds of the grid side m (m^2 points per triangle)
_PER_TEXEL, _MIN_SIDE, _MAX_SIDE = 16, 2, 64
#: points processed at once (memory)
_CHUNK = 1 << 21


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear (IEC 61966-2-1)."""
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def read_texture(path: str) -> np.ndarray:
    """(H, W, 3) float32 linear RGB of an image file (12 bytes a texel); raises OSError naming the file.

    Grey images are repeated to three channels; alpha and further channels are dropped.
    """
    import OpenImageIO as oiio  # noqa: PLC0415  lazy: `dcrad jobs/watch` imports this module and must not load OpenImageIO

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise OSError(f"cannot read texture {path}: {oiio.geterror() or 'unknown format'}")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
    finally:
        inp.close()
    if pixels is None or spec.width < 1 or spec.height < 1:
        raise OSError(f"cannot read texture {path}: no pixels")
    img = np.asarray(pixels, np.float32).reshape(spec.height, spec.width, spec.nchannels)
    img = np.repeat(img[:, :, :1], 3, axis=2) if spec.nchannels < 3 else img[:, :, :3]
    space = str(spec.getattribute("oiio:ColorSpace") or "").lower()
    encoded = spec.format.basetype in (oiio.UINT8, oiio.UINT16, oiio.INT8, oiio.INT16)
    if encoded and "lin" not in space:
        img = srgb_to_linear(np.clip(img, 0.0, 1.0)).astype(np.float32)
    if not np.isfinite(img).all():
        raise OSError(f"cannot use texture {path}: it holds non-finite values")
    return np.clip(img, 0.0, None).astype(np.float32, copy=False)


def uv_at(points: np.ndarray, tri: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """UV of points (m, k, 3) lying in triangles tri (m, 3, 3) with corner UVs uv (m, 3, 2).

    Barycentric coordinates from the 2x2 normal equations of each triangle's plane (points
    are projected onto it); NaN UVs stay NaN.  Returns (m, k, 2).
    """
    a = tri[:, None, 0]
    e1, e2 = (tri[:, 1] - tri[:, 0])[:, None], (tri[:, 2] - tri[:, 0])[:, None]
    d = points - a
    d00, d01, d11 = (e1 * e1).sum(-1), (e1 * e2).sum(-1), (e2 * e2).sum(-1)
    d20, d21 = (d * e1).sum(-1), (d * e2).sum(-1)
    den = d00 * d11 - d01 * d01
    den = np.where(den > 0, den, 1.0)
    s = (d11 * d20 - d01 * d21) / den
    t = (d00 * d21 - d01 * d20) / den
    u0 = uv[:, None, 0]
    return u0 + s[..., None] * (uv[:, None, 1] - u0) + t[..., None] * (uv[:, None, 2] - u0)


def _grid_centroids(k: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Barycentric (x, y) of the centroid of sub-triangle k (0 <= k < m^2) of a triangle cut
    into m^2 congruent ones: row r (y from r/m) holds m - r lower and m - r - 1 upper ones."""
    kf, mf = k.astype(np.float64), m.astype(np.float64)
    r = np.floor(mf - np.sqrt(np.maximum(mf * mf - kf, 0.0))).astype(np.int64)
    before = lambda rr: 2 * m * rr - rr * rr  # noqa: E731  sub-triangles in the rows below rr
    r = np.where(before(r) > k, r - 1, r)
    r = np.where(before(r + 1) <= k, r + 1, r)
    o = k - before(r)
    upper = o >= m - r
    i = np.where(upper, o - (m - r), o)
    third = np.where(upper, 2.0 / 3.0, 1.0 / 3.0)
    return np.stack([(i + third) / m, (r + third) / m], axis=1)


def uv_means(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Mean of ``image`` (H, W, 3) over each UV triangle ``uv`` (T, 3, 2) -> (T, 3).

    A triangle inside one texel gets that texel (exact, no sampling: the common case for
    fine meshes).  Others are sampled on a stratified lattice (see the module docstring).
    Triangles with a non-finite UV corner (no ``vt`` given) get the image's mean.
    """
    h, w = image.shape[:2]
    flat = np.ascontiguousarray(image.reshape(-1, 3))
    t = len(uv)
    out = np.empty((t, 3))
    ok = np.isfinite(uv).all(axis=(1, 2))
    out[~ok] = flat.mean(axis=0, dtype=np.float64)
    col = np.floor(uv[..., 0] * w)
    row = np.floor((1.0 - uv[..., 1]) * h)
    one = ok & (col.min(axis=1) == col.max(axis=1)) & (row.min(axis=1) == row.max(axis=1))
    if one.any():
        out[one] = flat[(row[one, 0].astype(np.int64) % h) * w + col[one, 0].astype(np.int64) % w]
    idx = np.flatnonzero(ok & ~one)
    if not len(idx):
        return out
    tri = uv[idx]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    texels = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) * w * h
    side = np.clip(np.ceil(np.sqrt(_PER_TEXEL * texels)), _MIN_SIDE, _MAX_SIDE).astype(np.int64)
    counts = side * side
    ends = np.cumsum(counts)
    start = 0
    while start < len(idx):
        stop = int(np.searchsorted(ends, ends[start] - counts[start] + _CHUNK, side="right"))
        stop = max(stop, start + 1)
        c = counts[start:stop]
        owner = np.repeat(np.arange(stop - start), c)
        k = np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
        b = _grid_centroids(k, np.repeat(side[start:stop], c))
        p = tri[start:stop][owner]
        q = p[:, 0] + b[:, :1] * (p[:, 1] - p[:, 0]) + b[:, 1:] * (p[:, 2] - p[:, 0])
        texel = (np.floor((1.0 - q[:, 1]) * h).astype(np.int64) % h) * w + np.floor(q[:, 0] * w).astype(np.int64) % w
        val = flat[texel]
        for ch in range(3):
            out[idx[start:stop], ch] = np.bincount(owner, weights=val[:, ch], minlength=stop - start) / c
        start = stop
    return out
