"""Wavefront OBJ / MTL reading for :mod:`dcrad.io.scene`.

The OBJ parser keeps faces in file order (trimesh's OBJ loader regroups them
by material) and leaves colours as exact floats.  Statements read: ``v``,
``f`` (``v``, ``v/vt``, ``v//vn``, ``v/vt/vn``; negative indices; polygons
fan-triangulated in place), ``vt`` (texture coordinates, kept per face
corner), ``o``, ``g``, ``usemtl``, ``mtllib``.  Everything else (``vn``,
``s``, ``l``, ``p``, free-form curves, comments) is ignored.  Backslash line continuation is not supported.

Tokens are split per line in Python; number conversion, index resolution and
fan triangulation are done once over whole arrays.
"""

from __future__ import annotations

import bisect
import ntpath
import os
import posixpath
import re
import warnings
from dataclasses import dataclass, field
from urllib.parse import unquote

import numpy as np

from dcrad.errors import SceneFormatError, SceneValueError

__all__ = ["ObjData", "parse_obj", "MtlMaterial", "read_mtl", "inside_folder"]

#: MTL statements that name a texture / map file (checked for escapes, then ignored)
_MAP_KEYS = ("bump", "disp", "decal", "refl", "norm")


@dataclass
class ObjData:
    vertices: np.ndarray  # (V, 3) float64, as written
    faces: np.ndarray  # (T, 3) int64, 0-based, file order
    group: np.ndarray  # (T,) int32 index into ``groups``
    line: np.ndarray  # (T,) int64 line number of the ``f`` statement
    groups: list  # [(object name, material name or None)]
    mtllibs: list  # [(path as written, line number)]
    uv: np.ndarray | None = None  # (T, 3, 2) float64 texture coordinates per corner; NaN: none given


_SLASH = re.compile(r"/\S*")


def _numbers(text: str, dtype, n: int):
    """Parse ``n`` whitespace-separated numbers in one go; None if any is malformed."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # old numpy warns instead of raising
            out = np.fromstring(text, dtype=dtype, sep=" ") if n else np.zeros(0, dtype)
    except (ValueError, DeprecationWarning):
        return None
    return out if len(out) == n else None


def _fail(label: str, no: int, what: str, raw: str) -> SceneFormatError:
    return SceneFormatError(f"{label} line {no}: {what}: {raw.strip()!r}")


def parse_obj(text: str, label: str) -> ObjData:
    """Parse OBJ ``text``; ``label`` names the file in error messages."""
    vtok: list[str] = []
    vline: list[int] = []
    ttok: list[str] = []
    fnt: list[int] = []
    ftok: list[str] = []
    fcount: list[int] = []
    fline: list[int] = []
    fnv: list[int] = []
    fgroup: list[int] = []
    groups: dict[tuple, int] = {}
    mtllibs: list[tuple[str, int]] = []
    obj_at: list[tuple[int, str]] = [(0, "default")]  # (line, object) changes
    obj, mtl, gid = "default", None, -1
    lines = text.splitlines()
    for no, raw in enumerate(lines, 1):
        parts = (raw.split("#", 1)[0] if "#" in raw else raw).split()
        if not parts:
            continue
        key = parts[0]
        if key == "v":
            if len(parts) < 4:
                raise _fail(label, no, f"'v' needs 3 coordinates, got {len(parts) - 1}", raw)
            vtok += parts[1:4]
            vline.append(no)
        elif key == "vt":
            if len(parts) < 2:
                raise _fail(label, no, "'vt' needs at least 1 coordinate", raw)
            ttok += (parts[1:3] + ["0"])[:2]
        elif key == "f":
            if len(parts) < 4:
                raise _fail(label, no, f"'f' needs at least 3 vertices, got {len(parts) - 1}", raw)
            if gid < 0:
                gid = groups.setdefault((obj, mtl), len(groups))
            ftok += parts[1:]
            fcount.append(len(parts) - 1)
            fline.append(no)
            fnv.append(len(vline))
            fnt.append(len(ttok) // 2)
            fgroup.append(gid)
        elif key in ("o", "g"):
            obj, gid = " ".join(parts[1:]) or "default", -1
            obj_at.append((no, obj))
        elif key == "usemtl":
            mtl, gid = " ".join(parts[1:]) or None, -1
        elif key == "mtllib":
            if len(parts) < 2:
                raise _fail(label, no, "'mtllib' needs a file name", raw)
            mtllibs.append((mtllib_name(raw), no))

    # -- vertices ------------------------------------------------------------------
    v = _numbers(" ".join(vtok), np.float64, len(vtok))
    if v is None:
        for i, no in enumerate(vline):
            if _numbers(" ".join(vtok[3 * i : 3 * i + 3]), np.float64, 3) is None:
                raise _fail(label, no, "vertex coordinate is not a number", lines[no - 1])
    v = v.reshape(-1, 3)
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        no = vline[int(np.argmax(bad))]
        name = obj_at[bisect.bisect_right(obj_at, (no, "\uffff")) - 1][1]
        raise SceneValueError(
            f"{label} line {no}: object '{name}' has a non-finite vertex coordinate: "
            f"{lines[no - 1].strip()!r}"
        )

    # -- faces: resolve indices, fan-triangulate -------------------------------------
    count = np.asarray(fcount, np.int64)
    # keep the vertex index of v, v/vt, v//vn, v/vt/vn
    idx = _numbers(_SLASH.sub("", " ".join(ftok)), np.int64, len(ftok))
    if idx is None:
        ends = np.cumsum(count)
        for i, no in enumerate(fline):
            one = " ".join(ftok[ends[i] - count[i] : ends[i]])
            if _numbers(_SLASH.sub("", one), np.int64, int(count[i])) is None:
                raise _fail(label, no, "face vertex index is not an integer", lines[no - 1])
    nv_tok = np.repeat(np.asarray(fnv, np.int64), count)
    res = np.where(idx > 0, idx - 1, nv_tok + idx)
    out = (idx == 0) | (res < 0) | (res >= len(v))
    if out.any():
        bad_at = int(np.argmax(out))
        face = int(np.searchsorted(np.cumsum(count), bad_at, side="right"))
        raise _fail(
            label, fline[face],
            f"face index {int(idx[bad_at])} out of range ({len(v)} vertices in file, "
            f"{int(nv_tok[bad_at])} defined before this line)", lines[fline[face] - 1],
        )
    start = np.cumsum(count) - count
    ntri = count - 2
    face_of = np.repeat(np.arange(len(count)), ntri)
    k = np.arange(len(face_of)) - np.repeat(np.cumsum(ntri) - ntri, ntri)
    a = start[face_of]
    faces = np.stack([res[a], res[a + k + 1], res[a + k + 2]], axis=1).reshape(-1, 3)
    uv = None
    if ttok:
        nt_tok = np.repeat(np.asarray(fnt, np.int64), count)
        uv = _corner_uv(ttok, ftok, nt_tok, np.asarray(fline, np.int64), count, label)
        uv = np.stack([uv[a], uv[a + k + 1], uv[a + k + 2]], axis=1).reshape(-1, 3, 2)
    return ObjData(
        vertices=v,
        faces=np.ascontiguousarray(faces, np.int64),
        group=np.asarray(fgroup, np.int32)[face_of],
        line=np.asarray(fline, np.int64)[face_of],
        groups=list(groups),
        mtllibs=mtllibs,
        uv=uv,
    )


def _corner_uv(ttok: list, ftok: list, nt_tok: np.ndarray, fline: np.ndarray, count: np.ndarray,
               label: str) -> np.ndarray:
    """(corners, 2) texture coordinates of every face token; NaN where none is given."""
    vt = _numbers(" ".join(ttok), np.float64, len(ttok))
    if vt is None:
        raise SceneFormatError(f"{label}: a 'vt' texture coordinate is not a number")
    vt = vt.reshape(-1, 2)
    # the second field of v/vt, v/vt/vn; 0 (none) for v and v//vn
    second = [t.split("/", 2)[1] if "/" in t else "" for t in ftok]
    idx = _numbers(" ".join(x or "0" for x in second), np.int64, len(second))
    if idx is None:
        raise SceneFormatError(f"{label}: a face texture-coordinate index is not an integer")
    res = np.where(idx > 0, idx - 1, nt_tok + idx)  # negative: back from the vt read so far
    bad = (idx != 0) & ((res < 0) | (res >= len(vt)))
    if bad.any():
        face = int(np.searchsorted(np.cumsum(count), int(np.argmax(bad)), side="right"))
        raise SceneFormatError(
            f"{label} line {fline[face]}: texture coordinate index {int(idx[np.argmax(bad)])} out of range "
            f"({len(vt)} vt in file)"
        )
    out = np.full((len(idx), 2), np.nan)
    ok = idx != 0
    out[ok] = vt[res[ok]]
    return out


# -- paths ----------------------------------------------------------------------------
def inside_folder(folder: str, name: str, label: str, what: str) -> str:
    """Resolve ``name`` (as written in a file) against ``folder``.

    Raises :class:`SceneFormatError` when it is absolute or ``..`` escapes the
    folder.  The test is lexical (symlinks are not followed).
    """
    p = unquote(name.strip().strip('"')).replace("\\", "/")
    if not p or posixpath.isabs(p) or ntpath.splitdrive(p)[0] or ntpath.isabs(p):
        raise SceneFormatError(
            f"{label}: {what} path '{name}' is absolute; it must stay inside the scene folder"
        )
    norm = posixpath.normpath(p)
    if norm == ".." or norm.startswith("../"):
        raise SceneFormatError(f"{label}: {what} path '{name}' resolves outside the scene folder")
    return os.path.join(folder, *norm.split("/"))


def mtllib_name(raw: str) -> str:
    """What an ``mtllib`` line names: the rest of the line (a '#' comment cut off, words then
    joined by single spaces); "" when the line is not an mtllib line."""
    parts = raw.split("#", 1)[0].split()
    if len(parts) < 2 or parts[0] != "mtllib":
        return ""
    return " ".join(parts[1:]) if "#" in raw else raw.strip()[6:].strip()


def mtllib_files(name: str, where: str, folder: str) -> list[str]:
    """The material files an ``mtllib`` line names (``mtllib_name``): the whole name when
    that file exists, else its space-separated names; each must lie inside ``folder``."""
    names = [name] if os.path.isfile(inside_folder(folder, name, where, "mtllib")) else name.split()
    for one in names:
        inside_folder(folder, one, where, "mtllib")
    return names


# -- MTL ------------------------------------------------------------------------------
@dataclass
class MtlMaterial:
    name: str
    file: str  # label of the MTL file, for messages
    kd: list | None = None  # exact floats (from trimesh's parse_mtl)
    kd_text: str = ""  # "Kd 1.0 0.5 0.5" as written
    ke: list | None = None
    ke_text: str = ""
    textures: list = field(default_factory=list)  # [(key, path as written)]
    two_sided: bool = False  # ``two_sided 1`` (a dcrad extension; other readers ignore it)
    tf: list | None = None  # ``Tf r g b``: transmission filter (glass: its normal transmittance)
    tf_text: str = ""
    d: float | None = None  # ``d`` dissolve (1 opaque), or 1 - ``Tr``
    d_text: str = ""
    ni: float | None = None  # ``Ni`` refractive index
    ni_text: str = ""
    illum: int | None = None  # ``illum`` model: 4, 6, 7 and 9 are transparent (glass)


def _floats(tokens, mat: MtlMaterial, key: str, text: str, no: int):
    try:
        vals = [float(t) for t in tokens]
    except ValueError:
        vals = []
    if len(vals) == 1:
        vals *= 3
    if len(vals) != 3:
        raise SceneFormatError(
            f"material '{mat.name}' in {mat.file} line {no}: cannot read '{text}'; expected {key} r g b"
        )
    return vals


def read_mtl(path: str, label: str, folder: str, exact: bool = True) -> dict[str, MtlMaterial]:
    """Read one MTL file.  Texture paths are checked against ``folder``.

    ``exact``: take Kd's floats from trimesh's ``parse_mtl`` (the loader's); False leaves the
    ones read here (what an upload needs, its texture files: no trimesh import, 0.5-0.9 s of
    `dcrad solve --workers N`'s start-up before the upload)."""
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            lines = [ln.split("#", 1)[0].rstrip() for ln in fh.read().splitlines()]
    except OSError as exc:
        raise SceneFormatError(f"cannot read material library {label}: {exc.strerror or exc}") from None
    out: dict[str, MtlMaterial] = {}
    mat = None
    for no, s in enumerate(lines, 1):
        parts = s.split()
        if len(parts) < 2:
            continue
        key = parts[0].lower()
        if key == "newmtl":
            name = " ".join(parts[1:])
            mat = out[name] = MtlMaterial(name=name, file=label)
        elif mat is None:
            continue
        elif key == "kd":  # syntax checked here, value taken from parse_mtl below
            mat.kd_text = " ".join(parts)
            mat.kd = _floats(parts[1:], mat, "Kd", mat.kd_text, no)
        elif key == "ke":
            mat.ke_text = " ".join(parts)
            mat.ke = _floats(parts[1:], mat, "Ke", mat.ke_text, no)
        elif key == "tf":
            mat.tf_text = " ".join(parts)
            if parts[1].lower() in ("spectral", "xyz"):
                raise SceneFormatError(f"material '{mat.name}' in {label} line {no}: '{mat.tf_text}': only "
                                       f"Tf r g b is read (not spectral or xyz)")
            mat.tf = _floats(parts[1:], mat, "Tf", mat.tf_text, no)
        elif key in ("d", "tr", "ni"):
            text = " ".join(parts)
            try:
                value = float(parts[-1])  # ``d -halo 0.5``: the factor is last
            except ValueError:
                raise SceneFormatError(f"material '{mat.name}' in {label} line {no}: cannot read '{text}'; "
                                       f"expected {parts[0]} and a number") from None
            if key == "ni":
                mat.ni, mat.ni_text = value, text
            else:
                mat.d, mat.d_text = (value if key == "d" else 1.0 - value), text
        elif key == "illum":
            try:
                mat.illum = int(parts[1])
            except ValueError:
                raise SceneFormatError(f"material '{mat.name}' in {label} line {no}: cannot read "
                                       f"'{' '.join(parts)}'; expected illum and a model number") from None
        elif key == "two_sided":
            mat.two_sided = parts[1].lower() in ("1", "on", "true", "yes")
        elif key.startswith("map_") or key in _MAP_KEYS:
            rest = s.strip()[len(parts[0]):].strip()
            name = parts[-1] if rest.startswith("-") else rest
            inside_folder(folder, name, f"material '{mat.name}' in {label} line {no}", f"texture {parts[0]}")
            mat.textures.append((parts[0], name))
    if not exact:
        return out
    from trimesh.exchange.obj import parse_mtl  # noqa: PLC0415  lazy: `dcrad jobs/watch` imports this module; trimesh costs 0.5 s

    parsed = parse_mtl("\n".join(lines), resolver=None)
    for name, mat in out.items():
        got = parsed.get(name, {}).get("kd")  # exact floats (last Kd statement wins)
        if mat.kd is not None and got is not None:
            kd = np.asarray(got, np.float64)
            mat.kd = [float(kd)] * 3 if kd.ndim == 0 else [float(x) for x in kd]
    return out
