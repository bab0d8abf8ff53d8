"""File writers: images through OpenImageIO, the PLY through trimesh, the GLB in trimesh's layout
written in chunks here (write_glb), arrays as npz.

Every writer creates missing parent directories and raises ``OSError`` naming
the path when the file cannot be written.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from dcrad.errors import SolveError
from dcrad.outputs.render import luminance, tonemap

__all__ = ["write_png", "write_exr", "write_patches_ply", "write_glb", "write_radiosity_npz"]

#: names write_radiosity_npz uses itself; ``extra`` may not reuse them
NPZ_KEYS = (
    "B",
    "valid",
    "patch_B",
    "patch_unshot",
    "patch_area",
    "patch_source",
    "patch_rho",
    "patch_emission",
    "patch_twin",
    "B_back",
)


def _prepare(path) -> str:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    return str(p)


def _write_image(path, pixels: np.ndarray, fmt, attrs: dict) -> None:
    import OpenImageIO as oiio  # noqa: PLC0415  lazy: `dcrad jobs/watch` imports this module and must not load OpenImageIO

    path = _prepare(path)
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    if pixels.ndim != 3 or pixels.shape[2] not in (1, 3, 4):
        raise ValueError(f"{path}: image must be (H, W, 1|3|4), got {pixels.shape}")
    h, w, c = pixels.shape
    out = oiio.ImageOutput.create(path)
    if out is None:
        raise OSError(f"{path}: no OpenImageIO writer: {oiio.geterror()}")
    spec = oiio.ImageSpec(w, h, c, fmt)
    for k, v in attrs.items():
        spec.attribute(k, v)
    try:
        if not out.open(path, spec):
            raise OSError(f"{path}: cannot open for writing: {out.geterror()}")
        if not out.write_image(np.ascontiguousarray(pixels)):
            raise OSError(f"{path}: write failed: {out.geterror()}")
    finally:
        out.close()


def write_png(path, img_uint8: np.ndarray) -> None:
    """img_uint8 : (H, W, 3|4) uint8, already sRGB-encoded (see render.tonemap)."""
    import OpenImageIO as oiio  # noqa: PLC0415  lazy: `dcrad jobs/watch` imports this module and must not load OpenImageIO

    img = np.asarray(img_uint8)
    if img.dtype != np.uint8:
        raise ValueError(f"{path}: write_png wants uint8, got {img.dtype}")
    _write_image(path, img, oiio.UINT8, {"oiio:ColorSpace": "sRGB"})


def write_exr(path, img_float32: np.ndarray, half: bool = True) -> None:
    """img_float32 : (H, W, 3|4) linear float; stored as half (default) or float, zip."""
    import OpenImageIO as oiio  # noqa: PLC0415  lazy: `dcrad jobs/watch` imports this module and must not load OpenImageIO

    img = np.asarray(img_float32, np.float32)
    if not np.all(np.isfinite(img)):
        raise ValueError(f"{path}: image holds non-finite values")
    fmt = oiio.HALF if half else oiio.FLOAT
    _write_image(path, img, fmt, {"compression": "zip", "oiio:ColorSpace": "lin_rec709"})


# ---------------------------------------------------------------------------------
def _frame(vertices: np.ndarray, rotation) -> np.ndarray:
    """Internal (Y-up) vertices back in the input file's frame (``Scene.rotation``).

    Scene rotations are signed permutations: columns are moved and negated (exact, and no
    BLAS call: a threaded 3x3 product stalled for seconds on a busy machine), ``+ 0.0``
    so that a negated zero is written as the product gave it, +0.
    """
    if rotation is None:
        return vertices
    r = np.asarray(rotation, np.float64)
    v = np.asarray(vertices, np.float64)
    nz = r != 0
    if np.all(nz.sum(axis=0) == 1) and np.all(np.abs(r[nz]) == 1):
        rows = np.argmax(nz, axis=0)  # the input axis feeding each output axis
        return v[:, rows] * r[rows, np.arange(3)] + 0.0
    return v @ r


def write_patches_ply(path, patches, dtype=np.float32, rotation=None) -> None:
    """Binary little-endian PLY of the patch mesh, one face per patch, in order.

    Face properties: ``radiosity_r``, ``radiosity_g``, ``radiosity_b`` (``dtype``,
    W/m^2), ``source`` and ``obj`` (int32), ``back`` (uint8, 1 for the back side of
    a two-sided triangle).  ``rotation`` (Scene.rotation): vertices are written in
    the input file's frame.  Written by trimesh with
    ``process=False`` so nothing is merged or reordered.  trimesh stores the
    vertices as float32.  Read back with ``trimesh.load(path, process=False)``;
    the face properties are in ``mesh.metadata['_ply_raw']['face']['data']``.
    """
    import trimesh  # noqa: PLC0415  lazy: `dcrad jobs/watch` imports this module; trimesh costs 0.5 s

    path = _prepare(path)
    b = np.asarray(patches.radiosity, np.float64)
    attrs = {
        "radiosity_r": b[:, 0].astype(dtype),
        "radiosity_g": b[:, 1].astype(dtype),
        "radiosity_b": b[:, 2].astype(dtype),
        "source": patches.source.astype(np.int32),
        "obj": patches.obj.astype(np.int32),
        "back": patches.is_back.astype(np.uint8),
    }
    mesh = trimesh.Trimesh(
        vertices=_frame(patches.vertices, rotation),
        faces=patches.faces,
        face_attributes=attrs,
        process=False,
        validate=False,
    )
    data = trimesh.exchange.ply.export_ply(mesh, encoding="binary", include_attributes=True)
    with open(path, "wb") as fh:
        fh.write(data)


#: glTF's unlit, single-sided, white material (write_glb with ``unlit``)
_UNLIT = {
    "name": "radiosity",
    "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0,
                             "roughnessFactor": 1.0},
    "doubleSided": False,
    "extensions": {"KHR_materials_unlit": {}},
}
#: corners per chunk of write_glb's buffers (about 20 bytes of output and 200 of temporaries each)
GLB_CHUNK = 1 << 18


def write_glb(
    path, patches, corner_values: np.ndarray, srgb: bool = False, exposure=None, unlit: bool = True,
    rotation=None,
):
    """Binary glTF with baked colours: 3 unshared vertices per patch, COLOR_0 RGBA uint8.

    corner_values : (n, 3, 3) radiosity per corner (render.corner_radiosity), float64 or float32.
    Colours are ``tonemap(corner_values / pi)`` (same exposure rule as the
    images).  The glTF spec defines COLOR_0 as *linear*, so by default the
    values are not sRGB-encoded (viewers encode on display); ``srgb=True``
    stores sRGB-encoded bytes instead.  With ``unlit`` (default) the material
    is unlit (KHR_materials_unlit, white base colour) and single-sided, so
    viewers neither shade the baked light again nor show walls from behind;
    trimesh then re-imports the colours as ``visual.vertex_attributes['color']``
    (with ``unlit=False``, no material: as ``visual.vertex_colors``).  Two-sided
    triangles are written twice, once per side, so each side shows its own light.
    ``rotation`` (Scene.rotation): vertices in the input file's frame.

    The file has the layout trimesh's exporter gives this mesh (indices, float32
    positions, colours; the same JSON but the generator), written ``GLB_CHUNK`` corners
    at a time: trimesh held the whole buffer three times (at 1.27M patches 410 MB
    above the corner values; now about 60).

    returns the exposure used (float)
    """
    path = _prepare(path)
    n = len(patches)
    m = 3 * n
    if m >= 2**32:
        raise ValueError(f"{path}: {n} patches are more than glTF's uint32 indices can address")
    cv = np.asarray(corner_values).reshape(m, 3)
    chunks = [(lo, min(lo + GLB_CHUNK, m)) for lo in range(0, m, GLB_CHUNK)]

    def lin(lo, hi):
        return cv[lo:hi].astype(np.float64) / math.pi

    if exposure is None:
        lum = np.concatenate([luminance(lin(lo, hi)) for lo, hi in chunks]) if m else np.zeros(0)
        lum = lum[lum > 0]
        ref = float(np.percentile(lum, 99.0)) if lum.size else 0.0
        exposure = 0.9 / ref if ref > 0 else 1.0

    def positions(lo, hi):  # corners lo..hi: those of patches lo // 3 .. (hi + 2) // 3, trimmed
        tri = patches.corners(slice(lo // 3, (hi + 2) // 3)).reshape(-1, 3)[lo % 3:]
        return _frame(tri[: hi - lo], rotation).astype(np.float32)

    rgba = np.full((m, 4), 255, np.uint8)  # 4 bytes a corner: kept, the positions are not
    pmin, pmax = np.full(3, np.inf, np.float32), np.full(3, -np.inf, np.float32)
    for lo, hi in chunks:  # the accessors' min/max come before the buffers in the file
        rgba[lo:hi, :3] = tonemap(lin(lo, hi), exposure=exposure, srgb=srgb)
        v = positions(lo, hi)  # per column: numpy's axis-0 reductions of (k, 3) arrays are 10x slower
        pmin = np.minimum(pmin, [v[:, c].min() for c in range(3)])
        pmax = np.maximum(pmax, [v[:, c].max() for c in range(3)])
    cmin = np.array([rgba[:, c].min() for c in range(4)]) if m else np.full(4, 255, np.uint8)
    cmax = np.array([rgba[:, c].max() for c in range(4)]) if m else np.zeros(4, np.uint8)
    sizes = [4 * m, 12 * m, 4 * m]  # indices uint32, positions 3 x float32, colours 4 x uint8
    offsets = np.cumsum([0] + sizes[:-1]).tolist()
    primitive: dict = {"attributes": {"POSITION": 1, "COLOR_0": 2}, "indices": 0, "mode": 4}
    if unlit:
        primitive["material"] = 0
    tree: dict = {
        "scene": 0, "scenes": [{"nodes": [0]}], "asset": {"version": "2.0", "generator": "dcrad"},
        "accessors": [
            {"componentType": 5125, "type": "SCALAR", "bufferView": 0, "count": m,
             "max": [m - 1], "min": [0]},
            {"componentType": 5126, "type": "VEC3", "byteOffset": 0, "bufferView": 1, "count": m,
             "max": [float(x) for x in pmax], "min": [float(x) for x in pmin]},
            {"componentType": 5121, "normalized": True, "type": "VEC4", "byteOffset": 0, "bufferView": 2,
             "count": m, "max": [int(x) for x in cmax], "min": [int(x) for x in cmin]},
        ],
        "meshes": [{"name": "geometry_0", "extras": {}, "primitives": [primitive]}],
        "nodes": [{"name": "geometry_0", "mesh": 0}],
        "buffers": [{"byteLength": sum(sizes)}],
        "bufferViews": [{"buffer": 0, "byteOffset": o, "byteLength": z} for o, z in zip(offsets, sizes)],
    }
    if unlit:
        tree["materials"] = [_UNLIT]
        tree["extensionsUsed"] = ["KHR_materials_unlit"]
    content = json.dumps(tree, separators=(",", ":"))
    content += " " * (4 - (len(content) + 20) % 4)  # the binary chunk starts 4-byte aligned (as trimesh pads)
    head = content.encode("utf-8")
    with open(path, "wb") as fh:
        fh.write(np.array([0x46546C67, 2, len(head) + sum(sizes) + 28, len(head), 0x4E4F534A], "<u4").tobytes())
        fh.write(head)
        fh.write(np.array([sum(sizes), 0x004E4942], "<u4").tobytes())
        for lo, hi in chunks:
            fh.write(np.arange(lo, hi, dtype="<u4").tobytes())
        for lo, hi in chunks:
            fh.write(positions(lo, hi).astype("<f4").tobytes())
        fh.write(rgba.tobytes())
    return float(exposure)


# ---------------------------------------------------------------------------------
def input_triangle_radiosity(patches, n_input_triangles: int, back: bool = False, values=None):
    """Area-weighted mean B of the patches of each input triangle, on its front side.

    ``back``: the back sides of two-sided triangles instead (one-sided ones: 0, invalid).
    ``values`` (n, 3): another per-patch quantity than ``patches.radiosity``.
    returns (B (T, 3) float64, valid (T,) bool); triangles without patches get 0
    and valid False; triangles whose patches all have zero area get their plain mean.
    """
    T = int(n_input_triangles)
    side = patches.is_back == back
    src = patches.source[side]
    if len(src) and (src.min() < 0 or src.max() >= T):
        raise SolveError(
            f"patch source indices span [{src.min()}, {src.max()}], outside [0, {T})"
        )
    area = patches.area[side]
    b = np.asarray(patches.radiosity if values is None else values, np.float64)[side]
    count = np.bincount(src, minlength=T)
    den = np.bincount(src, weights=area, minlength=T)
    plain = den <= 0
    w = np.where(plain[src], 1.0, area)  # zero-area groups: plain mean
    den = np.bincount(src, weights=w, minlength=T)
    out = np.zeros((T, 3))
    valid = count > 0
    for c in range(3):
        num = np.bincount(src, weights=w * b[:, c], minlength=T)
        out[valid, c] = num[valid] / den[valid]
    return out, valid


def write_radiosity_npz(path, patches, n_input_triangles: int, extra: dict | None = None):
    """Compressed npz of the solution.

    ==============  ========  ======================================================
    key             dtype     meaning
    ==============  ========  ======================================================
    B               (T,3) f8  per input triangle: area-weighted mean of its patches
                              (front side)
    valid           (T,) ?    False for input triangles without patches (B = 0)
    B_back          (T,3) f8  two-sided triangles: B of the back side (only when the
                              scene has two-sided triangles; others 0)
    patch_B         (n,3) f8  radiosity per patch (W/m^2)
    patch_unshot    (n,3) f8  unshot radiosity per patch (W/m^2)
    patch_area      (n,) f8   m^2
    patch_source    (n,) i8   input triangle of each patch
    patch_rho       (n,3) f8  reflectance
    patch_emission  (n,3) f8  emitted exitance (W/m^2)
    patch_twin      (n,) i8   the other side of a two-sided patch, -1 for one-sided
    ==============  ========  ======================================================

    plus every item of ``extra`` (``np.asarray`` of each value).  Raises
    SolveError if any floating array is not finite, ValueError if an ``extra``
    key collides with the names above.
    """
    b, valid = input_triangle_radiosity(patches, n_input_triangles)
    arrays = {
        "B": b,
        "valid": valid,
        "patch_B": np.asarray(patches.radiosity, np.float64),
        "patch_unshot": np.asarray(patches.unshot, np.float64),
        "patch_area": patches.area,
        "patch_source": patches.source,
        "patch_rho": patches.rho,
        "patch_emission": patches.emission,
        "patch_twin": patches.twin,
    }
    if patches.is_back.any():
        arrays["B_back"] = input_triangle_radiosity(patches, n_input_triangles, back=True)[0]
    for k, v in (extra or {}).items():
        if k in arrays:
            raise ValueError(f"{path}: extra key {k!r} collides with a standard key")
        arrays[k] = np.asarray(v)
    for k, v in arrays.items():
        if v.dtype.kind in "fc" and not np.all(np.isfinite(v)):
            raise SolveError(f"{path}: array {k!r} holds non-finite values")
    path = _prepare(path)
    with open(path, "wb") as fh:  # a file object keeps the exact name (no .npz added)
        np.savez_compressed(fh, **arrays)
