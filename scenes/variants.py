"""Copies of a written OBJ/MTL scene as other tools export them: Z-up, textured, mixed winding.

``variant(src, folder, up="z", flip=0.3, texture=True)`` reads a built-in
scene's OBJ/MTL (as :mod:`scenes.objwriter` writes them) and writes a copy
whose coordinates are in another up frame (an exact signed permutation, so
rotating it back gives the original floats), with a seeded fraction of the
faces wound the other way, and with a ``map_Kd`` texture on every material:
a 4x4 checker of linear greys 0.6 and 1.0 (sRGB-encoded PNG; mean about 0.8,
so the copy reflects Kd x 0.8 on average), mapped by planar UVs of 1 m tiles.
Used by the tests and for the before/after pictures in ``docs/``.
"""

from __future__ import annotations

import pathlib

import numpy as np
import OpenImageIO as oiio

from dcrad.scene import UP_AXES

__all__ = ["variant", "CHECKER_LINEAR", "write_checker"]

#: the two linear values of the checker; sRGB-encoded into the PNG
CHECKER_LINEAR = (0.6, 1.0)


def _to_frame(up: str) -> np.ndarray:
    """Rotation taking Y-up coordinates to a frame whose up axis is ``up`` (inverse of dcrad's)."""
    return np.array(UP_AXES[up], np.float64).T


def write_checker(path, lo: float, hi: float, n: int = 4) -> None:
    """An n x n RGB checker PNG of two linear grey values (clipped to [0, 1], sRGB-encoded)."""
    ij = np.add.outer(np.arange(n), np.arange(n)) % 2
    lin = np.where(ij == 0, lo, hi)
    lin = np.clip(lin, 0.0, 1.0)
    enc = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
    px = np.repeat(np.round(enc * 255)[:, :, None], 3, axis=2).astype(np.uint8)
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise OSError(f"cannot write {path}: {oiio.geterror()}")
    out.open(str(path), oiio.ImageSpec(n, n, 3, oiio.UINT8))
    out.write_image(px)
    out.close()


def variant(src, folder, up: str = "z", flip: float = 0.0, texture: bool = False, seed: int = 0,
            stem: str | None = None) -> pathlib.Path:
    """Write a transformed copy of OBJ ``src`` (and its MTL) into ``folder``; return the OBJ path.

    up      : the copy's up axis ("y" keeps the coordinates)
    flip    : fraction of faces whose winding is reversed (seeded); emitters keep theirs
    texture : add ``map_Kd checker.png`` (see CHECKER_LINEAR) after every material's Kd
    """
    src = pathlib.Path(src)
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    stem = stem or f"{src.stem}_{up.replace('-', 'm')}up"
    rot = _to_frame(up)
    rng = np.random.default_rng(seed)
    mtl = (src.parent / f"{src.stem}.mtl").read_text().splitlines()
    lamps, current = set(), None
    for line in mtl:  # emitters keep their winding: they emit from the front only
        parts = line.split()
        if parts and parts[0] == "newmtl":
            current = " ".join(parts[1:])
        elif parts and parts[0] == "Ke" and any(float(x) > 0 for x in parts[1:]):
            lamps.add(current)
    out_lines, verts, material = [], [], None
    for line in src.read_text().splitlines():
        parts = line.split()
        if parts and parts[0] == "usemtl":
            material = " ".join(parts[1:])
        if parts and parts[0] == "v":
            p = np.array([float(x) for x in parts[1:4]]) @ rot.T
            verts.append(p)
            out_lines.append("v " + " ".join(repr(float(x)) for x in p))
        elif parts and parts[0] == "f":
            idx = [t.split("/")[0] for t in parts[1:]]
            if flip > 0 and rng.random() < flip and material not in lamps:
                idx = idx[::-1]
            if texture:
                out_lines.append("f " + " ".join(f"{i}/{i}" for i in idx))
            else:
                out_lines.append("f " + " ".join(idx))
        elif parts and parts[0] == "mtllib":
            out_lines.append(f"mtllib {stem}.mtl")
        else:
            out_lines.append(line)
    if texture:
        # planar UVs (1 m tiles) from the two horizontal coordinates of the Y-up original
        back = np.array(verts) @ rot
        uv = back[:, [0, 2]] + 0.5 * back[:, [1, 1]]
        out_lines = out_lines[:1] + [f"vt {float(u)!r} {float(v)!r}" for u, v in uv] + out_lines[1:]
    (folder / f"{stem}.obj").write_text("\n".join(out_lines) + "\n")
    if texture:
        write_checker(folder / "checker.png", *CHECKER_LINEAR)
        out, current = [], None
        for line in mtl:
            parts = line.split()
            out.append(line)
            if parts and parts[0] == "newmtl":
                current = " ".join(parts[1:])
            elif parts and parts[0] == "Kd" and current is not None:
                out.append("map_Kd checker.png")
        mtl = out
    (folder / f"{stem}.mtl").write_text("\n".join(mtl) + "\n")
    return folder / f"{stem}.obj"
