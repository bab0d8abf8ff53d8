"""glTF 2.0 scenes (.gltf, .glb): the header checked before any buffer is read, the files a
.gltf refers to, and the loader (trimesh for the geometry; materials, textures, glass, cameras and
the nodes' transforms read here from the header)."""

from __future__ import annotations

import base64
import json
import math
import os
import struct
import tempfile
from urllib.parse import unquote

import numpy as np

from dcrad.errors import SceneFormatError, SceneValueError
from dcrad.io.materials import DEFAULT_RHO, TextureMap, check_emission, check_rho, fmt, near, texture, textured_rho
from dcrad.io.objfile import inside_folder

__all__ = ["gltf_header", "gltf_structure", "gltf_files", "load_gltf"]


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


#: the glTF extension placing IES light profiles (read by transport.luminaires.read_gltf_ies)
IES_EXTENSION = "EXT_lights_ies"


def gltf_files(header: dict, path: str) -> list[str]:
    """The files (buffers, images, EXT_lights_ies profiles) a glTF header refers to by URI, as
    written; each must lie inside the scene's folder (data: URIs are inline, not files)."""
    folder = os.path.dirname(os.path.abspath(path))
    refs = []
    ies = header.get("extensions", {}).get(IES_EXTENSION) if isinstance(header.get("extensions"), dict) else None
    listed = {"buffers": header.get("buffers", []), "images": header.get("images", []),
              f"{IES_EXTENSION} lights": ies.get("lights", []) if isinstance(ies, dict) else []}
    for kind, items in listed.items():
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
            rho = check_rho(base, where, f"baseColorFactor {fmt(base)}", factor=textured)
        if not (math.isfinite(strength) and strength >= 0):
            raise SceneValueError(f"{where}: emissiveStrength {strength!r} must be finite and >= 0")
        em = check_emission(
            np.multiply(emis, strength), where, f"emissiveFactor {fmt(emis)} x strength {strength!r}"
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
        and near(np.multiply(table[i][1][0] or (1.0, 1.0, 1.0), 255), u8, 1.0)
        and any(near(e, te, 1e-9, 1e-9) for e in (table[i][1][1], np.multiply(*table[i][1][1:])))
    ]
    if len({repr(table[i][1]) for i in cands}) != 1:
        name = mat.name or "(unnamed)"
        where = f"material '{name}' in {path}"
        warnings.append(
            f"{path}: cannot match trimesh material '{name}' to one glTF material; "
            f"using trimesh's 8-bit baseColorFactor / 255"
        )
        return (name, check_rho(u8 / 255, where, f"baseColorFactor {fmt(u8 / 255)}"),
                check_emission(te, where, f"emissiveFactor {fmt(te)}"))
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
        cache[name] = texture({}, inside_folder(folder, uri, path, f"image {src}"), uri, where,
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
        img = texture({}, tmp_path, name, where, "baseColorFactor", warnings)
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


def load_gltf(path: str, warnings: list, scale: float):
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
            rho = textured_rho(rho, image, uv, where, "baseColorTexture", warnings)
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
    if IES_EXTENSION in (header.get("extensionsUsed") or []) or IES_EXTENSION in (header.get("extensions") or {}):
        from dcrad.transport import luminaires  # noqa: PLC0415  lazy, as punctual

        lights += luminaires.read_gltf_ies(header, path, scale, _gltf_nodes(header, path), warnings,
                                           lambda view: _gltf_blob(path, header, None, {"bufferView": view}))
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
