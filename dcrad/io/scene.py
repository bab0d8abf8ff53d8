"""Load a scene file into input triangles with materials, validate, mesh into patches.

Formats
-------
``.obj`` (+ ``.mtl``)
    Parsed by :mod:`dcrad.io.objfile` (faces keep file order, ``Kd``/``Ke`` stay
    exact floats).  ``Kd`` -> reflectance, ``Ke`` -> emitted exitance (W/m^2,
    missing -> 0).  Faces before any ``usemtl``, with an unknown material, or
    a material without ``Kd`` get the default reflectance 0.5 and a warning.
``.gltf`` / ``.glb``
    Read by :mod:`dcrad.io.gltf`.  Geometry via ``trimesh.load(path, force="scene")``, flattened with world
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
triangle (:mod:`dcrad.io.texture`).  Both formats check their materials' values alike
(:mod:`dcrad.io.materials`).
"""

from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np

from dcrad.config import TOL
from dcrad.errors import ConfigError, SceneFormatError, SceneValueError
from dcrad.io.gltf import load_gltf
from dcrad.io.materials import (
    DEFAULT_RHO,
    MAX_COORDINATE,
    RHO_MAX_TEXTURE,
    TextureMap,
    check_emission,
    check_rho,
    listing,
    texture,
    textured_rho,
)
from dcrad.io.objfile import inside_folder, mtllib_files, parse_obj, read_mtl
from dcrad.io.texture import uv_at, uv_means
from dcrad.meshing.mesh import ADAPT_MOST, clusters, refine
from dcrad.meshing.mesh import adapt as adapt_mesh
from dcrad.meshing.patches import Patches, triangle_areas, triangle_normals
from dcrad.transport.optics import DEFAULT_IOR, Glazing

__all__ = ["Scene", "load_scene", "DEFAULT_RHO", "UP_AXES", "detect_up"]

#: the scene's warning when nothing in it emits: not given when the file places point or spot lights,
#: and dropped by a run given light sources (pipeline.finish_run)
NO_EMITTERS = "no emitters: the solution is zero"

log = logging.getLogger(__name__)

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
    if not (np.isfinite(tau).all() and (tau >= 0).all() and (tau < 1).all()):
        raise SceneValueError(f"{where}: {given} is a pane's transmittance outside [0, 1): a pane passes less than "
                              f"all (Fresnel reflection alone keeps 8% at index 1.52; 6 mm clear glass: Tf 0.88)")
    ni = DEFAULT_IOR if m.ni is None else float(m.ni)
    if not (math.isfinite(ni) and ni >= 1.0):
        raise SceneValueError(f"{where}: {m.ni_text} is not a refractive index (a finite number >= 1)")
    return tau, ni


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
            rho[g] = check_rho(m.kd, where, m.kd_text, factor=bool(kd_map))
        if m.ke is not None:
            em[g] = check_emission(m.ke, where, m.ke_text)
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
            f"{path}: faces before any usemtl in {listing(no_mtl)} use the default reflectance {DEFAULT_RHO}"
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
        image = texture(images, full, written, where, "Kd factor", warnings)
        if image is None or not len(rows):
            continue
        uv = data.uv[rows] if data.uv is not None else np.full((len(rows), 3, 2), np.nan)
        rho_t[rows] = textured_rho(rho[k], image, uv, where, written, warnings)
        textured.append(names[k])
        tex_maps.append(TextureMap(rows, rho[k].copy(), image, uv))
    extras = {"two_sided": sided[grp], "textured": list(dict.fromkeys(textured)), "maps": tex_maps}
    if tau.any():
        extras["tau"], extras["ior"] = tau[grp], ior[grp]
    return data.vertices, data.faces, rho_t, em[grp], gmap[grp], list(label_ix), None, extras


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
    if os.path.isdir(path):
        raise SceneFormatError(f"{path} is a folder, not a scene file: give the .obj, .gltf or .glb in it")
    if ext not in (".obj", ".gltf", ".glb"):
        raise SceneFormatError(f"unsupported scene format '{ext}' for {path}; use .obj, .gltf or .glb")
    if not os.path.isfile(path):
        raise SceneFormatError(f"cannot read scene file {path}: no such file")
    warnings: list[str] = []
    loader = _load_obj(path, warnings) if ext == ".obj" else load_gltf(path, warnings, scale)
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
            f"in {listing(names[i] for i in obj[bad])}"
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
        from dcrad.transport import punctual  # noqa: PLC0415  lazy, as in load_gltf

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
