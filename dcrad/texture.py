"""Diffuse textures: read an image (OpenImageIO), average it over UV triangles.

A textured material's reflectance on a triangle is the factor (``Kd``,
``baseColorFactor``) times the mean of the linear texture over the UV
triangle the triangle covers.  Images are read with OpenImageIO; 8- and 16-bit
images are taken as sRGB-encoded (the glTF rule for base colour, and what
OBJ/MTL exporters write) and linearised, float images (EXR, HDR) as linear.
Texels are looked up nearest-neighbour with wrap-around (repeat), so the mean
is the integral of the piecewise-constant image, estimated on a stratified
lattice of points over each UV triangle with about 256 points per covered texel
(at least 16, at most 4096 per triangle).  UV origin is the lower-left corner
of the image (OBJ; trimesh flips glTF's upper-left origin to the same).
"""

from __future__ import annotations

import numpy as np

from .sampling import lattice, triangle_points

__all__ = ["read_texture", "srgb_to_linear", "uv_means"]

#: lattice points per covered texel, and the bounds per triangle
_PER_TEXEL, _MIN_POINTS, _MAX_POINTS = 256, 16, 4096
#: points processed at once (memory)
_CHUNK = 1 << 21


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear (IEC 61966-2-1)."""
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def read_texture(path: str) -> np.ndarray:
    """(H, W, 3) float64 linear RGB of an image file; raises OSError naming the file.

    Grey images are repeated to three channels; alpha and further channels are dropped.
    """
    import OpenImageIO as oiio

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
    img = np.asarray(pixels, np.float64).reshape(spec.height, spec.width, spec.nchannels)
    img = np.repeat(img[:, :, :1], 3, axis=2) if spec.nchannels < 3 else img[:, :, :3]
    space = str(spec.getattribute("oiio:ColorSpace") or "").lower()
    encoded = spec.format.basetype in (oiio.UINT8, oiio.UINT16, oiio.INT8, oiio.INT16)
    if encoded and "lin" not in space:
        img = srgb_to_linear(np.clip(img, 0.0, 1.0))
    if not np.isfinite(img).all():
        raise OSError(f"cannot use texture {path}: it holds non-finite values")
    return np.clip(img, 0.0, None)


def uv_means(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Mean of ``image`` (H, W, 3) over each UV triangle ``uv`` (T, 3, 2) -> (T, 3).

    Triangles with a non-finite UV corner (no ``vt`` given) get the image's mean.
    """
    h, w = image.shape[:2]
    t = len(uv)
    out = np.empty((t, 3))
    ok = np.isfinite(uv).all(axis=(1, 2))
    out[~ok] = image.reshape(-1, 3).mean(axis=0)
    idx = np.flatnonzero(ok)
    if not len(idx):
        return out
    tri = uv[idx]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    texels = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) * w * h
    counts = np.clip(np.ceil(_PER_TEXEL * texels), _MIN_POINTS, _MAX_POINTS).astype(np.int64)
    ends = np.cumsum(counts)
    start = 0
    while start < len(idx):
        stop = int(np.searchsorted(ends, ends[start] - counts[start] + _CHUNK, side="right"))
        stop = max(stop, start + 1)
        c = counts[start:stop]
        owner = np.repeat(np.arange(stop - start), c)
        k = np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
        u = lattice(k, np.full((len(k), 2), 0.5), 2)
        p = tri[start:stop][owner]
        q = triangle_points(p[:, 0], p[:, 1], p[:, 2], u)
        col = np.floor(q[:, 0] * w).astype(np.int64) % w
        row = np.floor((1.0 - q[:, 1]) * h).astype(np.int64) % h
        val = image[row, col]
        for ch in range(3):
            out[idx[start:stop], ch] = np.bincount(owner, weights=val[:, ch], minlength=stop - start) / c
        start = stop
    return out
