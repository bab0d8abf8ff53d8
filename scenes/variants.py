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

from dcrad.io.scene import UP_AXES

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
            stem: str | None = None, split: int = 0, scale: float = 1.0) -> pathlib.Path:
    """Write a transformed copy of OBJ ``src`` (and its MTL) into ``folder``; return the OBJ path.

    up      : the copy's up axis ("y" keeps the coordinates)
    flip    : fraction of faces whose winding is reversed (seeded); emitters keep theirs
    texture : add ``map_Kd checker.png`` (see CHECKER_LINEAR) after every material's Kd
    split   : rounds of midpoint 4-splits of every face first (2: each face into 16, in file
              order: face i of the source becomes faces 16 i .. 16 i + 15), as finely triangulating
              exporters write; polygons are fanned first
    scale   : coordinates multiplied by it (1000: millimetres)
    """
    if split or scale != 1.0:
        src = _refined(pathlib.Path(src), pathlib.Path(folder) / "_split", split, scale)
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


def _refined(src: pathlib.Path, folder: pathlib.Path, rounds: int, scale: float) -> pathlib.Path:
    """``src`` with every face fanned into triangles, each split by ``rounds`` of midpoint 4-splits
    and every coordinate times ``scale``, written (with its MTL) into ``folder``."""
    import trimesh  # noqa: PLC0415

    folder.mkdir(parents=True, exist_ok=True)
    lines = src.read_text().splitlines()
    verts = np.array([[float(x) for x in ln.split()[1:4]] for ln in lines if ln.startswith("v ")]) * scale
    out: list[str] = []
    new_v: list[list[float]] = []
    for ln in lines:
        if ln.startswith("v "):
            continue
        if not ln.startswith("f "):
            out.append(ln)
            continue
        idx = [int(t.split("/")[0]) - 1 for t in ln.split()[1:]]
        for k in range(1, len(idx) - 1):
            v, f = verts[[idx[0], idx[k], idx[k + 1]]], np.array([[0, 1, 2]])
            for _ in range(rounds):
                v, f = trimesh.remesh.subdivide(v, f)
            base = len(new_v)
            new_v.extend(np.asarray(v).tolist())
            out.extend(f"f {a + base + 1} {b + base + 1} {c + base + 1}" for a, b, c in f)
    (folder / src.name).write_text("\n".join([f"v {x!r} {y!r} {z!r}" for x, y, z in new_v] + out) + "\n")
    (folder / f"{src.stem}.mtl").write_text((src.parent / f"{src.stem}.mtl").read_text())
    return folder / src.name
