"""Load a scene file into input triangles with materials, validate, mesh into patches.

Formats
-------
``.obj`` (+ ``.mtl``)
    Parsed by :mod:`dcrad.io.objfile` (faces keep file order, ``Kd``/``Ke`` stay
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
    camera (depth-first over the scene's nodes) gives ``Scene.camera``; the
    nodes' ``KHR_lights_punctual`` point and spot lights give ``Scene.sources``
    (:mod:`dcrad.transport.punctual`).

Coordinates are metres.  Internally Y is up: a scene whose up axis is another
(``up`` given, or detected by :func:`detect_up`) is rotated at load by an exact
signed permutation (``Scene.rotation``, input -> internal), and written back
in its own frame by the mesh writers.

Two-sided surfaces (``two_sided=True`` for all, MTL ``two_sided 1`` or glTF
``doubleSided`` per material) get a second patch per triangle for the back
side (:attr:`Patches.twin`).  Textures: the reflectance of a material with
``map_Kd`` / ``baseColorTexture`` is its factor (``Kd``, 1 when absent;
``baseColorFactor``) times the linear texture's mean over each triangle's UV
triangle (:mod:`dcrad.io.texture`).
"""

from __future__ import annotations

import base64
import json
import logging
import math
import os
import struct
import tempfile
import time
from dataclasses import dataclass, field
from urllib.parse import unquote

import numpy as np

from dcrad.config import TOL
from dcrad.errors import ConfigError, SceneFormatError, SceneValueError
from dcrad.io.objfile import inside_folder, mtllib_files, parse_obj, read_mtl
from dcrad.io.texture import read_texture, uv_at, uv_means
from dcrad.meshing.mesh import ADAPT_MOST, clusters, refine
from dcrad.meshing.mesh import adapt as adapt_mesh
from dcrad.meshing.patches import Patches, triangle_areas, triangle_normals
from dcrad.transport.optics import DEFAULT_IOR, Glazing

__all__ = ["Scene", "load_scene", "DEFAULT_RHO", "UP_AXES", "detect_up"]

#: the scene's warning when nothing in it emits: not given when the file places point or spot lights,
#: and dropped by a run given light sources (pipeline.finish_run)
NO_EMITTERS = "no emitters: the solution is zero"

log = logging.getLogger(__name__)

#: reflectance of faces without a usable material
DEFAULT_RHO = 0.5
#: most object names listed in one warning
_LIST = 8
#: highest reflectance a texture may give (a white texel is 1.0, which no real surface reflects)
RHO_MAX_TEXTURE = 0.99
#: up axis -> rotation (input -> internal, Y up): exact signed permutations, det +1
UP_AXES = {
    "y": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "-y": ((1, 0, 0), (0, -1, 0), (0, 0, -1)),
    "z": ((1, 0, 0), (0, 0, 1), (0, -1, 0)),
    "-z": ((1, 0, 0), (0, 0, -1), (0, 1, 0)),
    "x": ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
    "-x": ((0, 1, 0), (-1, 0, 0), (0, 0, 1)),
}


@dataclass
class TextureMap:
    """A textured material's triangles: their rows in the scene, the factor, the linear image
    and the UV corners (len(rows), 3, 2), kept so patches can take their own UV sub-triangles."""

    rows: np.ndarray
    factor: np.ndarray
    image: np.ndarray
    uv: np.ndarray


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
    camera: dict | None = None  # {"eye", "target", "up": [x,y,z], "fov_y": degrees}, internal frame
    up: str = "y"  # the input's up axis (a key of UP_AXES)
    up_source: str = "default"  # "given" (--up), "detected: ..." or "default"
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))  # input -> internal frame
    two_sided: np.ndarray | None = None  # (T,) bool, None: all one-sided
    textured: list = field(default_factory=list)  # material labels whose reflectance came from a texture
    texture_maps: list = field(default_factory=list)  # [TextureMap]: per-patch texture means when meshing
    #: (automatic element size m, how it was found): pipeline.mesh_choice's cache
    element_choice: tuple | None = None
    #: glass (optics.py): (T,3) normal transmittance of each input triangle (0: opaque) and (T,)
    #: refractive index; None when the file has no glass
    tau: np.ndarray | None = None
    ior: np.ndarray | None = None
    #: light sources the file holds besides its emitting surfaces (glTF KHR_lights_punctual point and
    #: spot lights: punctual.py), in the internal frame; every mesh of the scene carries them
    sources: tuple = ()

    def __len__(self) -> int:
        return len(self.faces)

    def patches(self, max_edge: float | None = None, adapt: bool = False, sources: tuple = ()) -> Patches:
        """Mesh the valid triangles into patches.

        ``max_edge`` None or 0: one patch per valid triangle.  Otherwise every
        triangle larger than an element of that size (m) is bisected until it
        is not (mesh.refine); smaller ones are kept whole.  ``adapt``: then split
        further where the direct light varies fast (mesh.adapt: shadow edges, near
        lamps; ``Patches.adapted`` says what was done).  ``Patches.source`` is the input
        triangle index; ``obj`` and ``names`` are carried over.  ``sources``: light sources
        besides the file's (luminaires, emitters.Emitter), which the patches carry after the
        file's own and the refinement follows too.
        """
        if max_edge is not None and (not math.isfinite(max_edge) or max_edge < 0):
            raise ConfigError(f"invalid max_edge={max_edge!r}: must be a finite number >= 0 (0: no meshing)")
        keep = np.flatnonzero(self.valid)
        v, f, idx = refine(self.vertices, self.faces[keep], max_edge or 0.0)
        sources = (*self.sources, *sources)
        built = self._built(keep, v, f, idx, max_edge or 0.0, sources)
        if not adapt or not max_edge or not (built.emission.any() or built.sources):
            return built
        if len(built) > ADAPT_MOST:
            built.adapted = {"split": 0, "added": 0, "levels": 0, "points": 0, "rays": 0, "seconds": 0.0,
                             "extra": np.zeros(len(self.faces), np.int64),
                             "skipped": f"{len(built)} elements, more than the {ADAPT_MOST} its look is sized for "
                                        f"(mesh.ADAPT_MOST)"}
            return built
        from dcrad.outputs.photometry import Y_WEIGHTS, direct_look  # noqa: PLC0415  embreex on first use

        t0 = time.perf_counter()
        fixed = np.zeros(len(keep), bool)  # lamps, panes and clustered triangles are not split
        fixed[np.searchsorted(keep, built.source[(built.emission.max(axis=1) > 0) | (built.cluster >= 0)])] = True
        if built.glazing is not None:
            fixed[np.searchsorted(keep, built.source[built.glazing.mask])] = True
        two = self.two_sided[keep] if self.two_sided is not None else None
        before = np.bincount(keep[idx], minlength=len(self.faces))
        v, f, idx, done = adapt_mesh(v, f, idx, direct_look(built), max_edge, fixed, two,
                                     float(built.mean_rho @ Y_WEIGHTS))
        if done["added"]:
            built = self._built(keep, v, f, idx, max_edge, sources)
        extra = np.bincount(keep[idx], minlength=len(self.faces)) - before  # per input triangle
        built.adapted = {**done, "seconds": time.perf_counter() - t0, "extra": extra}
        return built

    def _built(self, keep: np.ndarray, v: np.ndarray, f: np.ndarray, idx: np.ndarray, size: float,
               sources: tuple) -> Patches:
        """The patch table of a mesh of the valid triangles ``keep`` (``idx``: the row of ``keep`` of
        each face): materials, back sides, clusters, panes."""
        src = keep[idx]
        whole = np.bincount(idx, minlength=len(keep)) == 1
        group = clusters(self.vertices[self.faces[keep]], self.obj[keep], whole, size,
                         np.asarray(self.emission[keep].any(axis=1)))[idx]
        emission = self.emission[src]
        rho = self._patch_rho(v, f, src) if self.texture_maps and len(f) != len(keep) else self.rho[src]
        twin = np.full(len(f), -1, np.int64)  # no back sides: what Patches fills in for None
        if self.two_sided is not None and self.two_sided[src].any():
            # back sides: the same triangles reversed, after every front patch; they reflect
            # like the front (same rho) and emit nothing (Ke / emissive is the front's)
            back = np.flatnonzero(self.two_sided[src])
            n = len(f)
            twin = np.full(n + len(back), -1, np.int64)
            twin[back], twin[n:] = n + np.arange(len(back)), back
            f = np.concatenate([f, f[back][:, [0, 2, 1]]])
            group = np.concatenate([group, np.where(group[back] >= 0, group[back] + group.max() + 1, -1)])
            src = np.concatenate([src, src[back]])
            emission = np.concatenate([emission, np.zeros((len(back), 3))])
            rho = np.concatenate([rho, rho[back]])
        glazing = None
        if self.tau is not None and self.tau[src].any():
            tau_n = self.tau[src]
            ior = self.ior[src] if self.ior is not None else np.full(len(src), DEFAULT_IOR)
            glazing = Glazing(tau_n.any(axis=1), tau_n, ior)
            group = np.where(glazing.mask, -1, group)  # a pane's light is what passes: not pooled
        return Patches(
            vertices=v, faces=f, rho=rho, emission=emission,
            source=src, obj=self.obj[src], names=list(self.names), twin=twin, cluster=group,
            sources=sources, glazing=glazing,
        )

    def _patch_rho(self, v: np.ndarray, f: np.ndarray, src: np.ndarray) -> np.ndarray:
        """rho per patch; a textured patch takes the factor x the texture's mean over its own
        UV sub-triangle (its corners mapped through its source triangle's UVs)."""
        rho = self.rho[src].copy()
        which = np.full(len(self.faces), -1, np.int64)
        slot = np.zeros(len(self.faces), np.int64)
        for i, tm in enumerate(self.texture_maps):
            which[tm.rows], slot[tm.rows] = i, np.arange(len(tm.rows))
        capped = False
        for i, tm in enumerate(self.texture_maps):
            sel = np.flatnonzero(which[src] == i)
            if not len(sel):
                continue
            s = src[sel]
            uv = uv_at(v[f[sel]], self.vertices[self.faces[s]], tm.uv[slot[s]])
            got = tm.factor[None, :] * uv_means(tm.image, uv)
            capped |= bool((got > RHO_MAX_TEXTURE).any())
            rho[sel] = np.minimum(got, RHO_MAX_TEXTURE)
        if capped:
            self.warnings.append(f"{self.path}: some patches' texture means give reflectance above "
                                 f"{RHO_MAX_TEXTURE}; capped")
        return rho

    def to_input_frame(self, points: np.ndarray) -> np.ndarray:
        """Internal (Y-up) points or vectors (..., 3) -> the input file's frame."""
        return np.asarray(points, np.float64) @ self.rotation

    def planes_to_internal(self, planes):
        """Axis-aligned planes [(axis, offset)] given in the input's frame (as a user writes
        ``--planes`` for the file) -> the internal frame's [(axis, offset)]."""
        if planes is None:
            return None
        out = []
        for axis, offset in planes:
            row = int(np.flatnonzero(self.rotation[:, axis])[0])  # internal axis fed by this input axis
            out.append((row, float(self.rotation[row, axis]) * float(offset)))
        return out



# -- helpers -------------------------------------------------------------------------------
def _check_rho(values, where: str, text: str, factor: bool = False) -> np.ndarray:
    """A reflectance in [0, 1), or with ``factor`` (it multiplies a texture) in [0, 1]."""
    rho = np.asarray(values, np.float64)[:3]
    problem = (
        "a non-finite channel" if not np.isfinite(rho).all()
        else "a channel > 1" if factor and (rho > 1).any()
        else "a channel >= 1" if not factor and (rho >= 1).any()
        else "a negative channel" if (rho < 0).any() else None
    )
    if problem:
        raise SceneValueError(f"{where}: {text} has {problem}; reflectance must be in [0, 1)")
    return rho


#: MTL illumination models whose Tf / d make a transparent surface (glass): 4, 6, 7 and 9
GLASS_ILLUM = (4, 6, 7, 9)


def _mtl_glass(m, where: str, warnings: list) -> tuple[np.ndarray, float] | None:
    """(normal transmittance (3,), refractive index) of an MTL material that is glass (optics.py):
    ``illum`` 4, 6, 7 or 9 with ``Tf`` (its normal transmittance) or ``d`` below 1 (1 - d), ``Ni``
    (1.52 when absent); None for an opaque one.  Tf or d on another illum model is reported, not
    silently taken or dropped."""
    if m.tf is None and (m.d is None or m.d >= 1.0):
        return None
    given = m.tf_text or m.d_text
    if m.illum not in GLASS_ILLUM:
        warnings.append(f"{where}: '{given}' with illum {m.illum} is not glass (illum 4, 6, 7 or 9 make it "
                        f"transmit); the surface is opaque")
        return None
    tau = np.asarray(m.tf if m.tf is not None else [1.0 - float(m.d)] * 3, np.float64)[:3]
    if not (np.isfinite(tau).all() and (tau >= 0).all() and (tau <= 1).all()):
        raise SceneValueError(f"{where}: {given} is a transmittance outside [0, 1]")
    ni = DEFAULT_IOR if m.ni is None else float(m.ni)
    if not (math.isfinite(ni) and ni >= 1.0):
        raise SceneValueError(f"{where}: {m.ni_text} is not a refractive index (a finite number >= 1)")
    return tau, ni


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
        for one in mtllib_files(name, where, folder):
            full = inside_folder(folder, one, where, "mtllib")
            if not os.path.isfile(full):
                raise SceneFormatError(f"{where}: mtllib file '{one}' not found next to the scene")
            materials.update(read_mtl(full, one, folder))

    ng = len(data.groups)
    rho, em = np.full((ng, 3), DEFAULT_RHO), np.zeros((ng, 3))
    names, no_mtl, unknown = [], [], []
    sided = np.zeros(ng, bool)
    tau, ior = np.zeros((ng, 3)), np.full(ng, DEFAULT_IOR)
    maps: dict[int, tuple] = {}  # group -> (material, texture path as written, full path)
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
        kd_map = [name for k, name in m.textures if k.lower() == "map_kd"]
        if m.kd is None:
            if kd_map:
                rho[g] = 1.0  # the factor of map_Kd when Kd is absent
            else:
                warnings.append(f"{where} has no Kd; using reflectance {DEFAULT_RHO}")
        else:
            rho[g] = _check_rho(m.kd, where, m.kd_text, factor=bool(kd_map))
        if m.ke is not None:
            em[g] = _check_emission(m.ke, where, m.ke_text)
        sided[g] = m.two_sided
        glass = _mtl_glass(m, where, warnings)
        if glass is not None:
            tau[g], ior[g] = glass
            sided[g] = True  # a pane is met from both sides alike: what it keeps lands on the side met
        if kd_map:
            maps[g] = (m, kd_map[-1], inside_folder(folder, kd_map[-1], where, "texture map_Kd"))
        others = [k for k, _ in m.textures if k.lower() != "map_kd"]
        if others:
            warnings.append(f"{where}: maps ignored ({', '.join(others)}); only map_Kd is used")
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
    grp = data.group
    rho_t, textured, tex_maps = rho[grp], [], []
    images: dict = {}
    for k, (m, written, full) in maps.items():
        rows = np.flatnonzero(grp == k)
        where = f"material '{m.name}' in {m.file}"
        image = _texture(images, full, written, where, "Kd factor", warnings)
        if image is None or not len(rows):
            continue
        uv = data.uv[rows] if data.uv is not None else np.full((len(rows), 3, 2), np.nan)
        rho_t[rows] = _textured_rho(rho[k], image, uv, where, written, warnings)
        textured.append(names[k])
        tex_maps.append(TextureMap(rows, rho[k].copy(), image, uv))
    extras = {"two_sided": sided[grp], "textured": list(dict.fromkeys(textured)), "maps": tex_maps}
    if tau.any():
        extras["tau"], extras["ior"] = tau[grp], ior[grp]
    return data.vertices, data.faces, rho_t, em[grp], gmap[grp], list(label_ix), None, extras


def _texture(cache: dict, full: str, written: str, where: str, factor: str, warnings: list):
    """The linear image of a texture file (cached), or None with a warning naming it."""
    if full not in cache:
        try:
            cache[full] = read_texture(full)
        except OSError as exc:
            warnings.append(f"{where}: texture '{written}' not usable ({exc}); using the {factor} alone")
            cache[full] = None
    return cache[full]


def _textured_rho(factor, image, uv, where: str, written: str, warnings: list) -> np.ndarray:
    """factor (3,) x the texture's mean over each UV triangle (T, 3, 2) -> (T, 3), capped below 1."""
    rho = np.asarray(factor, np.float64)[None, :] * uv_means(image, uv)
    if (rho > RHO_MAX_TEXTURE).any():
        warnings.append(f"{where}: texture '{written}' gives reflectance above {RHO_MAX_TEXTURE} "
                        f"(max {rho.max():.3f}); capped at {RHO_MAX_TEXTURE}")
        rho = np.minimum(rho, RHO_MAX_TEXTURE)
    return rho


# -- glTF ----------------------------------------------------------------------------------
def gltf_header(path: str) -> dict:
    """The JSON header of a .gltf or .glb file, its file references checked (``gltf_files``)."""
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
            chunk = _glb_bin(blob)
            glb_bin = None if chunk is None else len(chunk)
            blob = blob[20 : 20 + length]
        else:
            glb_bin = None
        header = json.loads(blob.decode("utf-8"))
        if not isinstance(header, dict):
            raise ValueError("top level is not a JSON object")
    except (ValueError, struct.error, UnicodeDecodeError) as exc:
        raise SceneFormatError(f"cannot parse glTF {path}: {exc}") from None
    gltf_files(header, path)
    gltf_structure(header, path, glb_bin)
    return header


def _glb_bin(glb: bytes) -> bytes | None:
    """A GLB's binary chunk (after its JSON chunk; None without one), as much of it as the file
    holds (a truncated file holds less than its chunk claims)."""
    at = 20 + struct.unpack_from("<I", glb, 12)[0]
    if len(glb) < at + 8:
        return None
    length, kind = struct.unpack_from("<I4s", glb, at)
    return glb[at + 8: at + 8 + length] if kind == b"BIN\0" else None


#: bytes of a glTF accessor's component types, and components of its element types
_GLTF_COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
_GLTF_TYPE_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def gltf_structure(header: dict, path: str, glb_bin: int | None = None) -> None:
    """Every index the scenes, nodes and meshes use names an item the file has, every accessor
    fits in its buffer view, every view in its buffer and every buffer in its data: else a
    SceneFormatError naming the first item that does not (trimesh fails on these with its
    own internal errors).  ``glb_bin``: the length of a GLB's binary chunk."""
    where = f"cannot load glTF {path}"

    def items(kind: str) -> list:
        got = header.get(kind, [])
        if not isinstance(got, list):
            raise SceneFormatError(f"{where}: '{kind}' is not a list")
        for i, item in enumerate(got):
            if not isinstance(item, dict):
                raise SceneFormatError(f"{where}: item {i} of '{kind}' is not a JSON object")
        return got

    def ref(kind: str, value, what: str) -> dict:
        have = items(kind)
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < len(have):
            one = "mesh" if kind == "meshes" else kind[:-1]
            raise SceneFormatError(f"{where}: {what} refers to {one} {value!r}, but the file has "
                                   f"{len(have)} {one if len(have) == 1 else kind}")
        return have[value]

    def count(item: dict, key: str, what: str, default=None) -> int:
        value = item.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise SceneFormatError(f"{where}: {what} has {key} {value!r}, not a whole number >= 0")
        return value

    def indices(item: dict, key: str, what: str) -> list:
        got = item.get(key, [])
        if not isinstance(got, list):
            raise SceneFormatError(f"{where}: {what}'s {key} is not a list")
        return got

    if "scene" in header:
        ref("scenes", header["scene"], "the default scene")
    for i, sc in enumerate(items("scenes")):
        for n in indices(sc, "nodes", f"scene {i}"):
            ref("nodes", n, f"scene {i}")
    for i, node in enumerate(items("nodes")):
        for n in indices(node, "children", f"node {i}"):
            ref("nodes", n, f"node {i}'s children")
        if "mesh" in node:
            ref("meshes", node["mesh"], f"node {i}")
    for i, mesh in enumerate(items("meshes")):
        for j, prim in enumerate(indices(mesh, "primitives", f"mesh {i}")):
            what = f"mesh {i} primitive {j}"
            if not isinstance(prim, dict):
                raise SceneFormatError(f"{where}: {what} is not a JSON object")
            attrs = prim.get("attributes")
            if not isinstance(attrs, dict) or "POSITION" not in attrs:
                raise SceneFormatError(f"{where}: {what} has no POSITION attribute")
            for name, a in attrs.items():
                ref("accessors", a, f"{what}'s {name}")
            if "indices" in prim:
                ref("accessors", prim["indices"], f"{what}'s indices")
            if "material" in prim:
                ref("materials", prim["material"], what)
    sizes = []
    for i, buf in enumerate(items("buffers")):
        size = count(buf, "byteLength", f"buffer {i}")
        uri = buf.get("uri")
        if isinstance(uri, str) and uri.startswith("data:"):
            try:
                held = len(base64.b64decode(uri.split(",", 1)[1]))
            except (ValueError, IndexError):
                raise SceneFormatError(f"{where}: buffer {i}'s data: URI is not base64") from None
        elif isinstance(uri, str):
            folder = os.path.dirname(os.path.abspath(path))
            # percent-decoded as a URI (inside_folder), or as written (trimesh reads either)
            full = [inside_folder(folder, uri, path, f"buffer {i}"), os.path.join(folder, uri)]
            held = next((os.path.getsize(f) for f in full if os.path.isfile(f)), -1)
            if held < 0:
                raise SceneFormatError(f"{where}: buffer {i}'s file '{uri}' cannot be read")
        elif i == 0 and glb_bin is not None:
            held = glb_bin
        else:
            raise SceneFormatError(f"{where}: buffer {i} has no data (no uri, and no GLB binary chunk)")
        if held < size:
            raise SceneFormatError(f"{where}: buffer {i} holds {held} bytes, less than its byteLength {size}")
        sizes.append(size)
    views = []
    for i, view in enumerate(items("bufferViews")):
        ref("buffers", view.get("buffer"), f"bufferView {i}")
        start, length = count(view, "byteOffset", f"bufferView {i}", 0), count(view, "byteLength", f"bufferView {i}")
        if start + length > sizes[view["buffer"]]:
            raise SceneFormatError(f"{where}: bufferView {i} (bytes {start} to {start + length}) runs past the end "
                                   f"of buffer {view['buffer']} ({sizes[view['buffer']]} bytes)")
        views.append(length)
    for i, acc in enumerate(items("accessors")):
        what = f"accessor {i}"
        comp = _GLTF_COMPONENT_BYTES.get(acc.get("componentType"))
        parts = _GLTF_TYPE_COMPONENTS.get(acc.get("type"))
        if comp is None or parts is None:
            raise SceneFormatError(f"{where}: {what} has componentType {acc.get('componentType')!r} and type "
                                   f"{acc.get('type')!r}, not a glTF 2.0 pair")
        n = count(acc, "count", what)
        if "bufferView" not in acc:
            continue  # all zeros (or sparse): nothing to read
        view = ref("bufferViews", acc["bufferView"], what)
        stride = count(view, "byteStride", f"bufferView {acc['bufferView']}", 0) or comp * parts
        end = count(acc, "byteOffset", what, 0) + (stride * (n - 1) + comp * parts if n else 0)
        if end > views[acc["bufferView"]]:
            raise SceneFormatError(f"{where}: {what} ({n} x {acc['type']}) needs {end} bytes of bufferView "
                                   f"{acc['bufferView']}, which has {views[acc['bufferView']]}")


def gltf_files(header: dict, path: str) -> list[str]:
    """The files (buffers, images) a glTF header refers to by URI, as written; each must lie
    inside the scene's folder (data: URIs are inline, not files)."""
    folder = os.path.dirname(os.path.abspath(path))
    refs = []
    for kind in ("buffers", "images"):
        items = header.get(kind, [])
        for i, item in enumerate(items if isinstance(items, list) else []):
            uri = item.get("uri") if isinstance(item, dict) else None
            if isinstance(uri, str) and not uri.startswith("data:"):
                inside_folder(folder, uri, path, f"{kind[:-1]} {i}")
                refs.append(uri)
    return refs


def _node_matrix(node: dict) -> np.ndarray:
    import trimesh.transformations as tf  # noqa: PLC0415  lazy: `dcrad jobs/watch` imports this module; trimesh costs 0.5 s

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


def _gltf_nodes(header: dict, path: str):
    """(index, node, world 4x4) of the default scene's nodes, depth-first from its roots (every node
    no other node holds, when the file has no scenes); each node once."""
    nodes = header.get("nodes", [])
    scenes = header.get("scenes", [])
    if scenes:
        roots = scenes[header.get("scene", 0)].get("nodes", [])
    else:
        held = {c for n in nodes for c in n.get("children", [])}
        roots = [i for i in range(len(nodes)) if i not in held]
    stack, seen = [(r, np.eye(4)) for r in reversed(roots)], set()
    while stack:
        i, parent = stack.pop()
        if i in seen or not 0 <= i < len(nodes):
            continue
        seen.add(i)
        try:
            world = parent @ _node_matrix(nodes[i])
        except (KeyError, IndexError, TypeError, ValueError) as exc:
            raise SceneFormatError(f"cannot load glTF {path}: node {i}'s transform is malformed ({exc})") from None
        yield i, nodes[i], world
        stack += [(c, world) for c in reversed(nodes[i].get("children", []))]


def _gltf_camera(header: dict, scale: float, warnings: list, path: str) -> dict | None:
    """First perspective camera node, depth-first from the default scene's roots (``_gltf_nodes``)."""
    for i, node, world in _gltf_nodes(header, path):
        if "camera" not in node:
            continue
        cam = header.get("cameras", [])[node["camera"]]
        if "perspective" not in cam:
            name = cam.get("name", node["camera"])
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
        textured = isinstance(m.get("pbrMetallicRoughness", {}).get("baseColorTexture"), dict)
        if base is None and textured:
            rho = np.ones(3)  # glTF's default factor, times the texture
        elif base is None:
            warnings.append(f"{where} has no baseColorFactor; using reflectance {DEFAULT_RHO}")
            rho = np.full(3, DEFAULT_RHO)
        else:
            rho = _check_rho(base, where, f"baseColorFactor {_fmt(base)}", factor=textured)
        if not (math.isfinite(strength) and strength >= 0):
            raise SceneValueError(f"{where}: emissiveStrength {strength!r} must be finite and >= 0")
        em = _check_emission(
            np.multiply(emis, strength), where, f"emissiveFactor {_fmt(emis)} x strength {strength!r}"
        )
        out.append((label, (base, emis, strength), rho, em))
    return out


def _transmission(material: dict) -> float:
    """``KHR_materials_transmission.transmissionFactor`` of a glTF material (0 without it)."""
    ext = (material.get("extensions") or {}).get("KHR_materials_transmission") or {}
    return float(ext.get("transmissionFactor", 0.0))


def _gltf_glass(material: dict, base, where: str) -> tuple[np.ndarray, float]:
    """(normal transmittance (3,), refractive index) of a glTF material: transmissionFactor times its
    base colour (glTF tints what passes by it) and ``KHR_materials_ior`` (1.5, glTF's default); zeros
    for an opaque one.  Out-of-range factors are refused by name."""
    try:
        t = _transmission(material)
        ior = float(((material.get("extensions") or {}).get("KHR_materials_ior") or {}).get("ior", 1.5))
    except (TypeError, ValueError, AttributeError) as exc:
        raise SceneFormatError(f"{where}: cannot read its transmission ({exc})") from None
    if not (math.isfinite(t) and 0.0 <= t <= 1.0):
        raise SceneValueError(f"{where}: transmissionFactor {t!r} is a transmittance outside [0, 1]")
    if t > 0 and not (math.isfinite(ior) and ior >= 1.0):
        raise SceneValueError(f"{where}: ior {ior!r} is not a refractive index (a finite number >= 1)")
    return t * np.asarray(base, np.float64)[:3], ior


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


def _gltf_image(path: str, header: dict, material: dict, where: str, cache: dict, warnings: list):
    """The linear base-colour texture of a glTF material (OpenImageIO), None if it has none.

    Images are files next to the scene, data: URIs or buffer views (GLB); the
    latter two are written to a temporary file for OpenImageIO.  An unusable image
    gives a warning naming it, and None.
    """
    ref = material.get("pbrMetallicRoughness", {}).get("baseColorTexture")
    if not isinstance(ref, dict):
        return None
    try:
        src = header["textures"][int(ref["index"])]["source"]
        image = header["images"][int(src)]
    except (KeyError, IndexError, TypeError, ValueError):
        warnings.append(f"{where}: baseColorTexture does not name an image; using the baseColorFactor alone")
        return None
    name = image.get("uri") or image.get("name") or f"image {src}"
    name = "embedded data" if name.startswith("data:") else name
    if name in cache:
        return cache[name]
    folder = os.path.dirname(os.path.abspath(path))
    uri = image.get("uri")
    if isinstance(uri, str) and not uri.startswith("data:"):
        cache[name] = _texture({}, inside_folder(folder, uri, path, f"image {src}"), uri, where,
                               "baseColorFactor", warnings)
        return cache[name]
    try:
        blob = _gltf_blob(path, header, uri, image)
    except (KeyError, IndexError, TypeError, ValueError, OSError) as exc:
        warnings.append(f"{where}: texture '{name}' not readable ({exc}); using the baseColorFactor alone")
        cache[name] = None
        return None
    suffix = ".jpg" if image.get("mimeType", "").endswith("jpeg") or blob[:2] == b"\xff\xd8" else ".png"
    with tempfile.TemporaryDirectory(prefix="dcrad-tex-") as tmp:
        tmp_path = os.path.join(tmp, "texture" + suffix)
        with open(tmp_path, "wb") as fh:
            fh.write(blob)
        img = _texture({}, tmp_path, name, where, "baseColorFactor", warnings)
    cache[name] = img
    return img


def _gltf_blob(path: str, header: dict, uri, image: dict) -> bytes:
    """Bytes of an embedded glTF image: a data: URI or a buffer view."""
    if isinstance(uri, str):
        return base64.b64decode(uri.split(",", 1)[1])
    view = header["bufferViews"][int(image["bufferView"])]
    buf = header["buffers"][int(view.get("buffer", 0))]
    if "uri" in buf:
        buri = buf["uri"]
        data = (base64.b64decode(buri.split(",", 1)[1]) if buri.startswith("data:") else
                open(inside_folder(os.path.dirname(os.path.abspath(path)), buri, path, "buffer"), "rb").read())
    else:  # the GLB binary chunk
        with open(path, "rb") as fh:
            data = _glb_bin(fh.read()) or b""
    off = int(view.get("byteOffset", 0))
    return data[off: off + int(view["byteLength"])]


def _uri_resolver(trimesh, path: str):
    """trimesh's file resolver for a glTF's folder that also reads a buffer or image named as a URI
    (percent-escaped, as glTF writes them: trimesh looked for 'my%20quad.bin' literally)."""

    class UriResolver(trimesh.resolvers.FilePathResolver):
        def get(self, name: str):
            try:
                return super().get(name)
            except FileNotFoundError:
                if unquote(name) == name:
                    raise
                return super().get(unquote(name))

    return UriResolver(os.path.dirname(os.path.abspath(path)))


def _load_gltf(path: str, warnings: list, scale: float):
    import trimesh  # noqa: PLC0415  lazy: `dcrad jobs/watch` imports this module; trimesh costs 0.5 s

    header = gltf_header(path)
    table = _gltf_materials(header, path, warnings)
    by_label: dict[str, dict] = {}
    for i, m in enumerate(header.get("materials", [])):
        by_label.setdefault(m.get("name") or f"material{i}", m)
    images: dict = {}
    sides, textured, tex_maps, nf = [], [], [], 0
    try:
        scene = trimesh.load(path, force="scene", resolver=_uri_resolver(trimesh, path))
    except Exception as exc:  # trimesh raises many kinds
        raise SceneFormatError(f"cannot load glTF {path}: {type(exc).__name__}: {exc}") from None
    if not isinstance(scene, trimesh.Scene):  # force="scene" always gives one; the stub says Geometry
        raise SceneFormatError(f"cannot load glTF {path}: trimesh returned a {type(scene).__name__}, not a scene")
    parents = scene.graph.transforms.parents
    vs, fs, rhos, ems, objs = [], [], [], [], []
    taus: list[np.ndarray] = []
    iors: list[np.ndarray] = []
    labels: dict[str, int] = {}
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
        gm = by_label.get(mname, {})
        where = f"material '{mname}' in {path}"
        tau, ior = _gltf_glass(gm, rho, where)
        if tau.any():
            rho = np.asarray(rho, np.float64) * (1.0 - _transmission(gm))  # what is not passed on is diffuse
        sides.append(np.full(len(f), bool(gm.get("doubleSided", False)) or bool(tau.any())))
        image = _gltf_image(path, header, gm, where, images, warnings) if gm else None
        uv = getattr(geom.visual, "uv", None)
        if image is not None:
            uv = np.asarray(uv, np.float64)[f] if uv is not None and len(uv) == len(v) else None
            if uv is None:
                warnings.append(f"{where}: textured, but object '{obj}' has no texture coordinates; "
                                f"using the texture's mean")
                uv = np.full((len(f), 3, 2), np.nan)
            tex_maps.append(TextureMap(nf + np.arange(len(f)), np.asarray(rho, np.float64).copy(), image, uv))
            rho = _textured_rho(rho, image, uv, where, "baseColorTexture", warnings)
            textured.append(mname)
        nf += len(f)
        vs.append(v)
        fs.append(f + nv)
        nv += len(v)
        rhos.append(np.broadcast_to(rho, (len(f), 3)))
        taus.append(np.broadcast_to(tau, (len(f), 3)))
        iors.append(np.full(len(f), ior))
        ems.append(np.broadcast_to(em, (len(f), 3)))
        objs.append(np.full(len(f), k, np.int32))
    try:
        camera = _gltf_camera(header, scale, warnings, path)
    except (KeyError, IndexError, TypeError, ValueError, AttributeError) as exc:
        warnings.append(f"{path}: camera not usable ({type(exc).__name__}: {exc}); ignored")
        camera = None
    from dcrad.transport import punctual  # noqa: PLC0415  lazy: `dcrad jobs/watch` imports this module, not the photometry

    lights = punctual.read_gltf(header, path, scale, _gltf_nodes(header, path), warnings)
    cat = lambda a, shape, dt: np.concatenate(a).astype(dt) if a else np.zeros(shape, dt)  # noqa: E731
    extras = {"two_sided": cat(sides, (0,), bool), "textured": list(dict.fromkeys(textured)), "maps": tex_maps,
              "lights": lights}
    tau_t = cat(taus, (0, 3), np.float64)
    if tau_t.any():
        extras["tau"], extras["ior"] = tau_t, cat(iors, (0,), np.float64)
    return (
        cat(vs, (0, 3), np.float64), cat(fs, (0, 3), np.int64), cat(rhos, (0, 3), np.float64),
        cat(ems, (0, 3), np.float64), cat(objs, (0,), np.int32), list(labels),
        camera, extras,
    )


# -- up axis -------------------------------------------------------------------------------
#: m: the farthest a vertex may lie from the origin after scaling.  The solver works in the scene's
#: own scale (a Cornell box at 1e30 m solves like one in metres), but squared lengths and areas
#: overflow float64 beyond about 1e150 m (--scale 1e300 failed as "invalid max_edge=inf")
MAX_COORDINATE = 1e100


def detect_up(vertices: np.ndarray, faces: np.ndarray, emission: np.ndarray | None = None) -> tuple[str, str]:
    """The up axis of a model (a key of UP_AXES) and how it was found.

    Lamps hang on ceilings and face down: when at least half the emitted power leaves
    surfaces facing along one axis (|n| > 0.9), that is the axis.  Its sign: the way the
    lamps sit above the rest of the geometry (power-weighted lamp height against the
    area-weighted height of everything else, when they differ by 5% of the extent:
    this holds whatever the winding); else the way they face away from, when at least
    half faces one way; else as below.  Otherwise the axis is
    the one with the most area facing along it both ways (floors and ceilings: the
    lesser way at least 10% of the other), Y when its area is within 10% of the best
    (dcrad's own convention) or when no axis qualifies, and the sign, which normals
    alone cannot give (a closed room upside down is the same room), comes from where
    the geometry off the outer floor/ceiling slabs sits (furniture stands on floors:
    its area-weighted mean height is below the middle); + when nothing tells.
    """
    tri = vertices[faces]
    n, area = triangle_normals(tri), triangle_areas(tri)
    c = tri.mean(axis=1)
    if emission is not None and (emission > 0).any():
        lamp = emission.sum(axis=1) * area
        along = [float(lamp[np.abs(n[:, k]) > 0.9].sum()) for k in range(3)]
        axis = int(np.argmax(along))
        if along[axis] >= 0.5 * float(lamp.sum()):
            name = "xyz"[axis]
            down, up = float(lamp[n[:, axis] < -0.9].sum()), float(lamp[n[:, axis] > 0.9].sum())
            why = f"emitters face along {name} ({100 * along[axis] / lamp.sum():.0f}% of the emitted power)"
            rest = lamp <= 0
            if rest.any() and area[rest].sum() > 0:
                high = float((c[:, axis] * lamp).sum() / lamp.sum())
                low = float((c[rest, axis] * area[rest]).sum() / area[rest].sum())
                if abs(high - low) > 0.05 * max(float(np.ptp(c[:, axis])), 1e-300):
                    sign = "" if high > low else "-"
                    return sign + name, why + f", above the rest along {sign or '+'}{name}: lamps hang high"
            if max(down, up) >= 0.5 * float(lamp.sum()):
                sign = "" if down > up else "-"
                return sign + name, why + f", facing {'-' if down > up else '+'}{name}: lamps face down"
            return _up_sign(name, axis, c, area, why + ", both ways")
    pos = np.array([float(area[n[:, k] > 0.9].sum()) for k in range(3)])
    neg = np.array([float(area[n[:, k] < -0.9].sum()) for k in range(3)])
    # floors need ceilings (or the other way round): a lone plane tells nothing
    flat = np.where(np.minimum(pos, neg) >= 0.1 * np.maximum(pos, neg), pos + neg, 0.0)
    if flat.max() <= 0:
        return "y", "default (no floors facing ceilings, no emitters facing along an axis)"
    best = int(np.argmax(flat))
    axis = 1 if flat[1] >= 0.9 * flat[best] else best
    name = "xyz"[axis]
    return _up_sign(name, axis, c, area, f"floor and ceiling area along {name}: {flat[axis]:.3g} m^2 "
                                         f"of {sum(flat):.3g} m^2 facing an axis")


def _up_sign(name: str, axis: int, c: np.ndarray, area: np.ndarray, why: str) -> tuple[str, str]:
    lo, hi = c[:, axis].min(), c[:, axis].max()
    h = (c[:, axis] - lo) / max(hi - lo, 1e-300)
    inner = (h > 0.02) & (h < 0.98)
    if area[inner].sum() > 0:
        mean = float((h[inner] * area[inner]).sum() / area[inner].sum())
        if abs(mean - 0.5) > 0.01:
            sign = "" if mean < 0.5 else "-"
            return sign + name, why + f"; geometry sits low along {sign or '+'}{name} (mean height " \
                                      f"{min(mean, 1 - mean):.2f})"
    return name, why + f"; sign +{name} (nothing tells)"


def _rotate_camera(camera: dict | None, rotation: np.ndarray) -> dict | None:
    if camera is None:
        return None
    out = dict(camera)
    for k in ("eye", "target", "up"):
        if k in out:
            out[k] = [float(x) for x in rotation @ np.asarray(out[k], np.float64)]
    return out


# -- entry point ---------------------------------------------------------------------------
def load_scene(path, scale: float = 1.0, up: str | None = None, two_sided: bool = False) -> Scene:
    """Load ``path`` (.obj, .gltf, .glb); ``scale`` multiplies every coordinate.

    ``up``: the input's up axis (x, y, z, -x, -y, -z); None or "auto" detects it
    (:func:`detect_up`).  ``two_sided``: every surface receives and reflects on both
    sides (else only materials that ask for it).

    Raises :class:`~dcrad.errors.SceneFormatError` (unreadable / malformed /
    unsupported), :class:`~dcrad.errors.SceneValueError` (bad values, empty
    scene) or :class:`~dcrad.errors.ConfigError` (bad ``scale`` or ``up``).
    """
    if up is not None and str(up).strip().lower() not in (*UP_AXES, "+x", "+y", "+z", "auto", ""):
        raise ConfigError(f"invalid up axis {up!r}: use x, y, z, -x, -y, -z or auto")
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
    vertices, faces, rho, emission, obj, names, camera, extras = loader
    vertices = np.ascontiguousarray(vertices * scale, np.float64)
    if len(faces) == 0:
        raise SceneValueError(f"{path}: the scene has no faces")

    used = vertices[np.unique(faces)]
    reach = float(np.abs(used).max()) if len(used) else 0.0
    if not reach <= MAX_COORDINATE:
        raise SceneValueError(f"{path}: a vertex lies {reach:.3g} m from the origin (after scale {scale:g}); "
                              f"coordinates must stay within {MAX_COORDINATE:g} m (areas overflow beyond): check "
                              f"--scale and the file's units")
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
    lights = extras.get("lights", [])
    if not (emission[valid] > 0).any() and not lights:
        warnings.append(NO_EMITTERS)
    want = str(up).strip().lower().lstrip("+") if up is not None else "auto"
    if want in ("auto", "") and ext != ".obj":
        want, source = "y", "glTF convention (Y up)"
    elif want in ("auto", ""):
        want, source = detect_up(vertices, faces[valid], emission[valid])
        source = "detected: " + source
    else:
        source = "given"
    rotation = np.array(UP_AXES[want], np.float64)
    if want != "y":
        vertices = vertices @ rotation.T  # exact: a signed permutation
        camera = _rotate_camera(camera, rotation)
    sided = np.asarray(extras["two_sided"], bool) | bool(two_sided)
    if lights:
        from dcrad.transport import punctual  # noqa: PLC0415  lazy, as in _load_gltf

        sources = punctual.sources(lights, rotation)
    else:
        sources = ()
    warnings = list(dict.fromkeys(warnings))  # one line per distinct warning
    for w in warnings:
        log.info("%s", w)
    return Scene(
        path=path, vertices=vertices, faces=np.ascontiguousarray(faces, np.int64),
        rho=np.ascontiguousarray(rho, np.float64), emission=np.ascontiguousarray(emission, np.float64),
        obj=np.ascontiguousarray(obj, np.int32), names=names, valid=valid,
        warnings=warnings, camera=camera, up=want, up_source=source, rotation=rotation,
        two_sided=sided if sided.any() else None, textured=list(extras["textured"]),
        tau=extras.get("tau"), ior=extras.get("ior"),
        texture_maps=list(extras["maps"]), sources=sources,
    )
