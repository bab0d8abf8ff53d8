"""Load a scene file into input triangles with materials, validate, mesh into patches.

Formats
-------
``.obj`` (+ ``.mtl``)
    Parsed by :mod:`dcrad.objfile` (faces keep file order, ``Kd``/``Ke`` stay
    exact floats).  ``Kd`` -> reflectance, ``Ke`` -> emitted exitance (W/m^2,
    missing -> 0).  Faces before any ``usemtl``, with an unknown material, or
    a material without ``Kd`` get the default reflectance 0.5 and a warning.
``.gltf`` / ``.glb``
    Geometry via ``trimesh.load(path, force="scene")``, flattened with world
    transforms in the order of ``scene.graph.nodes_geometry`` (trimesh's
    insertion order: a depth-first walk of the glTF node tree that visits
    siblings last to first; one entry per primitive).  Mirroring transforms
    (det < 0) flip the winding so normals stay outward, as glTF specifies.
    Material factors are read from the raw glTF JSON, because trimesh keeps
    ``baseColorFactor`` only as uint8 and ignores
    ``KHR_materials_emissive_strength``: rho = baseColorFactor[:3] (missing ->
    0.5 and a warning, since the glTF default 1.0 is not a valid
    reflectance), E = emissiveFactor * emissiveStrength.  A primitive without
    a material gets the default 0.5 and a warning.  The first perspective
    camera (depth-first over the scene's nodes) gives ``Scene.camera``.

Coordinates are metres, Y up (glTF's convention; OBJ is taken as is).
"""

from __future__ import annotations

import json
import logging
import math
import os
import struct
from dataclasses import dataclass, field

import numpy as np

from .config import TOL
from .errors import ConfigError, SceneFormatError, SceneValueError
from .objfile import inside_folder, parse_obj, read_mtl
from .patches import Patches, subdivide, triangle_areas

__all__ = ["Scene", "load_scene", "DEFAULT_RHO"]

log = logging.getLogger(__name__)

#: reflectance of faces without a usable material
DEFAULT_RHO = 0.5
#: most object names listed in one warning
_LIST = 8


@dataclass
class Scene:
    """Input triangles and their materials, as loaded (see module docstring)."""

    path: str
    vertices: np.ndarray  # (V, 3) float64, metres, Y up
    faces: np.ndarray  # (T, 3) int64 input triangles, file order
    rho: np.ndarray  # (T, 3) float64 in [0, 1)
    emission: np.ndarray  # (T, 3) float64 W/m^2, >= 0
    obj: np.ndarray  # (T,) int32 index into names
    names: list  # "object/material" labels
    valid: np.ndarray  # (T,) bool, False for dropped degenerate triangles
    warnings: list = field(default_factory=list)
    camera: dict | None = None  # {"eye", "target", "up": [x,y,z], "fov_y": degrees}

    def __len__(self) -> int:
        return len(self.faces)

    def patches(self, max_edge: float | None = None) -> Patches:
        """Mesh the valid triangles into patches.

        ``max_edge`` None or 0: one patch per valid triangle.  Otherwise every
        triangle is split (trimesh midpoint subdivision) until no edge is
        longer than ``max_edge`` metres.  ``Patches.source`` is the input
        triangle index; ``obj`` and ``names`` are carried over.
        """
        if max_edge is not None and (not math.isfinite(max_edge) or max_edge < 0):
            raise ConfigError(f"invalid max_edge={max_edge!r}: must be a finite number >= 0 (0: no meshing)")
        keep = np.flatnonzero(self.valid)
        try:
            v, f, idx = subdivide(self.vertices, self.faces[keep], max_edge or 0.0)
        except ValueError as exc:  # subdivide_to_size gives up after max_iter
            raise ConfigError(f"cannot mesh {self.path} with max_edge={max_edge}: {exc}") from None
        src = keep[idx]
        return Patches(
            vertices=v, faces=f, rho=self.rho[src], emission=self.emission[src],
            source=src, obj=self.obj[src], names=list(self.names),
        )


# -- helpers -------------------------------------------------------------------------------
def _check_rho(values, where: str, text: str) -> np.ndarray:
    rho = np.asarray(values, np.float64)[:3]
    problem = (
        "a non-finite channel" if not np.isfinite(rho).all()
        else "a channel >= 1" if (rho >= 1).any()
        else "a negative channel" if (rho < 0).any() else None
    )
    if problem:
        raise SceneValueError(f"{where}: {text} has {problem}; reflectance must be in [0, 1)")
    return rho


def _check_emission(values, where: str, text: str) -> np.ndarray:
    e = np.asarray(values, np.float64)[:3]
    if not np.isfinite(e).all() or (e < 0).any():
        what = "a non-finite" if not np.isfinite(e).all() else "a negative"
        raise SceneValueError(f"{where}: {text} has {what} channel; emission must be finite and >= 0")
    return e


def _near(a, b, atol: float, rtol: float = 0.0) -> bool:
    """|a - b| <= atol + rtol * |b| everywhere; NaN counts as near (validated later)."""
    b = np.asarray(b, np.float64)
    return not np.any(np.abs(np.subtract(a, b)) > atol + rtol * np.abs(b))


def _fmt(values) -> str:
    return " ".join(repr(float(x)) for x in values)


def _listing(names) -> str:
    names = list(dict.fromkeys(names))
    more = f" and {len(names) - _LIST} more" if len(names) > _LIST else ""
    return ", ".join(f"'{n}'" for n in names[:_LIST]) + more


# -- OBJ -----------------------------------------------------------------------------------
def _load_obj(path: str, warnings: list):
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            text = fh.read()
    except OSError as exc:
        raise SceneFormatError(f"cannot read scene file {path}: {exc.strerror or exc}") from None
    data = parse_obj(text, path)
    folder = os.path.dirname(os.path.abspath(path))
    materials = {}
    for name, no in data.mtllibs:
        where = f"{path} line {no}"
        files = [name] if os.path.isfile(inside_folder(folder, name, where, "mtllib")) else name.split()
        for one in files:
            full = inside_folder(folder, one, where, "mtllib")
            if not os.path.isfile(full):
                raise SceneFormatError(f"{where}: mtllib file '{one}' not found next to the scene")
            materials.update(read_mtl(full, one, folder))

    ng = len(data.groups)
    rho, em = np.full((ng, 3), DEFAULT_RHO), np.zeros((ng, 3))
    names, no_mtl, unknown = [], [], []
    for g, (obj, mname) in enumerate(data.groups):
        names.append(f"{obj}/{mname if mname is not None else '(default)'}")
        m = materials.get(mname) if mname is not None else None
        if mname is None:
            no_mtl.append(obj)
            continue
        if m is None:
            unknown.append(mname)
            continue
        where = f"material '{m.name}' in {m.file}"
        if m.kd is None:
            warnings.append(f"{where} has no Kd; using reflectance {DEFAULT_RHO}")
        else:
            rho[g] = _check_rho(m.kd, where, m.kd_text)
        if m.ke is not None:
            em[g] = _check_emission(m.ke, where, m.ke_text)
        if m.textures:
            warnings.append(f"{where}: textures ignored ({', '.join(k for k, _ in m.textures)}); using Kd")
    if no_mtl:
        warnings.append(
            f"{path}: faces before any usemtl in {_listing(no_mtl)} use the default reflectance {DEFAULT_RHO}"
        )
    for mname in dict.fromkeys(unknown):
        warnings.append(
            f"{path}: material '{mname}' is not defined in any mtllib; using reflectance {DEFAULT_RHO}"
        )
    # one label per group; groups with equal labels share an index
    label_ix = {n: i for i, n in enumerate(dict.fromkeys(names))}
    gmap = np.array([label_ix[n] for n in names], np.int32)
    g = data.group
    return data.vertices, data.faces, rho[g], em[g], gmap[g], list(label_ix), None


# -- glTF ----------------------------------------------------------------------------------
def _gltf_json(path: str) -> dict:
    try:
        with open(path, "rb") as fh:
            blob = fh.read()
    except OSError as exc:
        raise SceneFormatError(f"cannot read scene file {path}: {exc.strerror or exc}") from None
    try:
        if path.lower().endswith(".glb"):
            magic, version, _ = struct.unpack_from("<4sII", blob, 0)
            length, kind = struct.unpack_from("<I4s", blob, 12)
            if magic != b"glTF" or version != 2 or kind != b"JSON":
                raise ValueError("not a glTF 2.0 binary (bad header or first chunk is not JSON)")
            blob = blob[20 : 20 + length]
        header = json.loads(blob.decode("utf-8"))
        if not isinstance(header, dict):
            raise ValueError("top level is not a JSON object")
    except (ValueError, struct.error, UnicodeDecodeError) as exc:
        raise SceneFormatError(f"cannot parse glTF {path}: {exc}") from None
    folder = os.path.dirname(os.path.abspath(path))
    for kind in ("buffers", "images"):
        for i, item in enumerate(header.get(kind, [])):
            uri = item.get("uri") if isinstance(item, dict) else None
            if isinstance(uri, str) and not uri.startswith("data:"):
                inside_folder(folder, uri, path, f"{kind[:-1]} {i}")
    return header


def _node_matrix(node: dict) -> np.ndarray:
    import trimesh.transformations as tf

    if "matrix" in node:
        return np.array(node["matrix"], np.float64).reshape(4, 4).T
    m = np.eye(4)
    if "translation" in node:
        m = m @ tf.translation_matrix(node["translation"])
    if "rotation" in node:
        m = m @ tf.quaternion_matrix(np.asarray(node["rotation"], np.float64)[[3, 0, 1, 2]])
    if "scale" in node:
        m = m @ np.diag([*node["scale"], 1.0])
    return m


def _gltf_camera(header: dict, scale: float, warnings: list, path: str) -> dict | None:
    """First camera node, depth-first from the default scene's roots."""
    nodes = header.get("nodes", [])
    scenes = header.get("scenes", [])
    roots = scenes[header.get("scene", 0)].get("nodes", []) if scenes else []
    stack, seen = [(r, np.eye(4)) for r in reversed(roots)], set()
    while stack:
        i, parent = stack.pop()
        if i in seen or not 0 <= i < len(nodes):
            continue
        seen.add(i)
        world = parent @ _node_matrix(nodes[i])
        if "camera" in nodes[i]:
            cam = header.get("cameras", [])[nodes[i]["camera"]]
            if "perspective" not in cam:
                name = cam.get("name", nodes[i]["camera"])
                warnings.append(f"{path}: camera '{name}' is not perspective; ignored")
                continue
            rot = world[:3, :3]
            fwd, up = rot @ [0.0, 0.0, -1.0], rot @ [0.0, 1.0, 0.0]
            fwd /= np.linalg.norm(fwd)
            up -= fwd * (up @ fwd)
            up /= np.linalg.norm(up)
            eye = world[:3, 3] * scale
            out = {"eye": eye, "target": eye + fwd, "up": up,
                   "fov_y": float(np.degrees(float(cam["perspective"]["yfov"])))}
            if not all(np.isfinite(x).all() for x in out.values()):
                warnings.append(f"{path}: camera node {i} has a degenerate transform; ignored")
                continue
            return {k: x if k == "fov_y" else [float(c) for c in x] for k, x in out.items()}
        stack += [(c, world) for c in reversed(nodes[i].get("children", []))]
    return None


def _gltf_materials(header: dict, path: str, warnings: list) -> list:
    """Validate every glTF material as written; [(label, facts, rho, emission)].

    ``facts`` = (baseColorFactor[:3] or None, emissiveFactor, emissiveStrength).
    Done before trimesh sees the file (trimesh rejects some bad factors itself).
    """
    out = []
    for i, m in enumerate(header.get("materials", [])):
        label = m.get("name") or f"material{i}"
        where = f"material '{label}' in {path}"
        try:
            base = m.get("pbrMetallicRoughness", {}).get("baseColorFactor")
            base = None if base is None else tuple(float(x) for x in base[:3])
            emis = tuple(float(x) for x in m.get("emissiveFactor", [0.0, 0.0, 0.0]))
            ext = m.get("extensions", {}).get("KHR_materials_emissive_strength", {})
            strength = float(ext.get("emissiveStrength", 1.0))
            if (base is not None and len(base) != 3) or len(emis) != 3:
                raise ValueError("expected 3 channels")
        except (TypeError, ValueError, AttributeError) as exc:
            raise SceneFormatError(f"{where}: cannot read its factors ({exc})") from None
        if base is None:
            warnings.append(f"{where} has no baseColorFactor; using reflectance {DEFAULT_RHO}")
            rho = np.full(3, DEFAULT_RHO)
        else:
            rho = _check_rho(base, where, f"baseColorFactor {_fmt(base)}")
        if not (math.isfinite(strength) and strength >= 0):
            raise SceneValueError(f"{where}: emissiveStrength {strength!r} must be finite and >= 0")
        em = _check_emission(
            np.multiply(emis, strength), where, f"emissiveFactor {_fmt(emis)} x strength {strength!r}"
        )
        out.append((label, (base, emis, strength), rho, em))
    return out


def _gltf_material(header: dict, table: list, mat, path: str, warnings: list):
    """(label, rho, emission) of the glTF material behind a trimesh material.

    trimesh keeps the material name, an 8-bit baseColorFactor and a float
    emissiveFactor (without emissiveStrength), but not the material index: match
    by name, then by those factors; fall back to trimesh's values with a warning.
    """
    if mat is None or not hasattr(mat, "baseColorFactor"):
        warnings.append(f"{path}: a primitive has no material; using reflectance {DEFAULT_RHO}")
        return "(default)", np.full(3, DEFAULT_RHO), np.zeros(3)
    u8 = np.asarray(mat.baseColorFactor if mat.baseColorFactor is not None else [255] * 3, np.float64)[:3]
    te = np.zeros(3) if mat.emissiveFactor is None else np.asarray(mat.emissiveFactor, np.float64)[:3]
    cands = [
        i for i, m in enumerate(header.get("materials", []))
        if m.get("name") == mat.name
        and _near(np.multiply(table[i][1][0] or (1.0, 1.0, 1.0), 255), u8, 1.0)
        and any(_near(e, te, 1e-9, 1e-9) for e in (table[i][1][1], np.multiply(*table[i][1][1:])))
    ]
    if len({repr(table[i][1]) for i in cands}) != 1:
        name = mat.name or "(unnamed)"
        where = f"material '{name}' in {path}"
        warnings.append(
            f"{path}: cannot match trimesh material '{name}' to one glTF material; "
            f"using trimesh's 8-bit baseColorFactor / 255"
        )
        return (name, _check_rho(u8 / 255, where, f"baseColorFactor {_fmt(u8 / 255)}"),
                _check_emission(te, where, f"emissiveFactor {_fmt(te)}"))
    label, _, rho, em = table[cands[0]]
    return label, rho, em


def _load_gltf(path: str, warnings: list, scale: float):
    import trimesh

    header = _gltf_json(path)
    table = _gltf_materials(header, path, warnings)
    try:
        scene = trimesh.load(path, force="scene")
    except Exception as exc:  # trimesh raises many kinds
        raise SceneFormatError(f"cannot load glTF {path}: {type(exc).__name__}: {exc}") from None
    parents = scene.graph.transforms.parents
    vs, fs, rhos, ems, objs, labels = [], [], [], [], [], {}
    nv = 0
    for node in scene.graph.nodes_geometry:
        matrix, gname = scene.graph[node]
        geom = scene.geometry[gname]
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            warnings.append(f"{path}: node '{node}' holds no triangles ({type(geom).__name__}); ignored")
            continue
        # a node with several primitives gets one child per primitive, named with a random suffix
        obj = f"{parents.get(node, node)}:{gname}" if geom.metadata.get("from_gltf_primitive") else node
        mname, rho, em = _gltf_material(header, table, getattr(geom.visual, "material", None), path, warnings)
        v = np.asarray(geom.vertices, np.float64)
        if not np.isfinite(v).all():
            raise SceneValueError(
                f"{path}: object '{obj}' (mesh '{gname}') has a non-finite vertex coordinate"
            )
        v = v @ matrix[:3, :3].T + matrix[:3, 3]
        f = np.asarray(geom.faces, np.int64)
        if np.linalg.det(matrix[:3, :3]) < 0:
            f = f[:, [0, 2, 1]]
        k = labels.setdefault(f"{obj}/{mname}", len(labels))
        vs.append(v)
        fs.append(f + nv)
        nv += len(v)
        rhos.append(np.broadcast_to(rho, (len(f), 3)))
        ems.append(np.broadcast_to(em, (len(f), 3)))
        objs.append(np.full(len(f), k, np.int32))
    try:
        camera = _gltf_camera(header, scale, warnings, path)
    except (KeyError, IndexError, TypeError, ValueError, AttributeError) as exc:
        warnings.append(f"{path}: camera not usable ({type(exc).__name__}: {exc}); ignored")
        camera = None
    cat = lambda a, shape, dt: np.concatenate(a).astype(dt) if a else np.zeros(shape, dt)  # noqa: E731
    return (
        cat(vs, (0, 3), np.float64), cat(fs, (0, 3), np.int64), cat(rhos, (0, 3), np.float64),
        cat(ems, (0, 3), np.float64), cat(objs, (0,), np.int32), list(labels),
        camera,
    )


# -- entry point ---------------------------------------------------------------------------
def load_scene(path, scale: float = 1.0) -> Scene:
    """Load ``path`` (.obj, .gltf, .glb); ``scale`` multiplies every coordinate.

    Raises :class:`~dcrad.errors.SceneFormatError` (unreadable / malformed /
    unsupported), :class:`~dcrad.errors.SceneValueError` (bad values, empty
    scene) or :class:`~dcrad.errors.ConfigError` (bad ``scale``).
    """
    try:
        scale = float(scale)
    except (TypeError, ValueError):
        raise ConfigError(f"invalid scale {scale!r}: must be a finite number > 0") from None
    if not (math.isfinite(scale) and scale > 0):
        raise ConfigError(f"invalid scale {scale!r}: must be a finite number > 0")
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".obj", ".gltf", ".glb"):
        raise SceneFormatError(f"unsupported scene format '{ext}' for {path}; use .obj, .gltf or .glb")
    if not os.path.isfile(path):
        raise SceneFormatError(f"cannot read scene file {path}: no such file")
    warnings: list[str] = []
    loader = _load_obj(path, warnings) if ext == ".obj" else _load_gltf(path, warnings, scale)
    vertices, faces, rho, emission, obj, names, camera = loader
    vertices = np.ascontiguousarray(vertices * scale, np.float64)
    if len(faces) == 0:
        raise SceneValueError(f"{path}: the scene has no faces")

    used = vertices[np.unique(faces)]
    diag = float(np.linalg.norm(used.max(axis=0) - used.min(axis=0)))
    area = triangle_areas(vertices[faces])
    repeated = (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    valid = ~repeated & (area >= TOL.degenerate_area * diag**2) & (area > 0)
    if not valid.any():
        raise SceneValueError(
            f"{path}: all {len(faces)} triangles are degenerate (zero area); nothing to solve"
        )
    if not valid.all():
        bad = np.flatnonzero(~valid)
        warnings.append(
            f"{path}: dropped {len(bad)} degenerate triangle(s) (zero area or repeated vertices) "
            f"in {_listing(names[i] for i in obj[bad])}"
        )
    if not (emission[valid] > 0).any():
        warnings.append("no emitters: the solution is zero")
    warnings = list(dict.fromkeys(warnings))  # one line per distinct warning
    for w in warnings:
        log.info("%s", w)
    return Scene(
        path=path, vertices=vertices, faces=np.ascontiguousarray(faces, np.int64),
        rho=np.ascontiguousarray(rho, np.float64), emission=np.ascontiguousarray(emission, np.float64),
        obj=np.ascontiguousarray(obj, np.int32), names=names, valid=valid,
        warnings=warnings, camera=camera,
    )
