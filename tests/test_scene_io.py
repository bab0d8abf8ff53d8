"""Scene loading: OBJ/MTL and glTF/GLB parsing, validation, meshing into patches."""

from __future__ import annotations

import base64
import json
import math
import struct

import numpy as np
import pytest

from dcrad.errors import ConfigError, SceneFormatError, SceneValueError
from dcrad.io.gltf import gltf_header
from dcrad.io.scene import DEFAULT_RHO, load_scene
from dcrad.meshing.mesh import AREA_SHARE, SLIVER_EDGES
from dcrad.meshing.patches import triangle_areas

MTL = """\
newmtl white
Kd 0.999 0.5 0.25   # trailing comment
newmtl red
Kd 0.7 0.1 0.1
newmtl lamp
Kd 0.2
Ke 10 20 30.5
"""


def write(tmp_path, obj: str, mtl: str | None = MTL, name="room"):
    if mtl is not None:
        (tmp_path / f"{name}.mtl").write_text(mtl)
    path = tmp_path / f"{name}.obj"
    path.write_text((f"mtllib {name}.mtl\n" if mtl is not None else "") + obj)
    return path


GRID = "".join(f"v {x} {y} 0\n" for y in range(3) for x in range(3))  # 9 vertices, 1-based r*3+c+1


# -- OBJ: order, triangulation, indices, exact values ------------------------------------------
def test_order_preserved_across_usemtl_switches(tmp_path):
    faces = [(1, 2, 5), (1, 5, 4), (2, 3, 6), (2, 6, 5), (4, 5, 8), (4, 8, 7)]
    body = GRID + "o walls\n"
    for i, f in enumerate(faces):
        body += f"usemtl {'white' if i % 2 == 0 else 'red'}\nf {f[0]} {f[1]} {f[2]}\n"
    s = load_scene(write(tmp_path, body))
    np.testing.assert_array_equal(s.faces, np.array(faces) - 1)
    assert [s.names[k] for k in s.obj] == ["walls/white", "walls/red"] * 3
    np.testing.assert_array_equal(s.rho[0::2], [[0.999, 0.5, 0.25]] * 3)
    np.testing.assert_array_equal(s.rho[1::2], [[0.7, 0.1, 0.1]] * 3)
    assert s.obj.dtype == np.int32 and s.faces.dtype == np.int64 and s.rho.dtype == np.float64
    assert s.valid.all() and s.camera is None and s.path == str(tmp_path / "room.obj")


def test_polygons_fan_triangulated_in_place(tmp_path):
    body = GRID + "usemtl white\nf 1 2 3\nf 1 2 5 4\nf 1 2 3 6 5\nf 4/1 5/2/3 8//1\n"
    s = load_scene(write(tmp_path, body))
    expect = [[1, 2, 3], [1, 2, 5], [1, 5, 4], [1, 2, 3], [1, 3, 6], [1, 6, 5], [4, 5, 8]]
    np.testing.assert_array_equal(s.faces, np.array(expect) - 1)


def test_negative_indices_are_relative_to_vertices_so_far(tmp_path):
    body = "usemtl white\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\nv 1 1 0\nf -3/1/1 -1//2 -2\n"
    s = load_scene(write(tmp_path, body))
    np.testing.assert_array_equal(s.faces, [[0, 1, 2], [1, 3, 2]])


def test_exact_kd_grey_kd_and_ke(tmp_path):
    body = GRID + "usemtl white\nf 1 2 5\nusemtl lamp\nf 1 5 4\n"
    s = load_scene(write(tmp_path, body))
    assert s.rho[0].tolist() == [0.999, 0.5, 0.25]  # exact, not via uint8
    assert s.rho[1].tolist() == [0.2, 0.2, 0.2]
    assert s.emission.tolist() == [[0, 0, 0], [10.0, 20.0, 30.5]]
    assert s.names == ["default/white", "default/lamp"]
    assert not any("no emitters" in w for w in s.warnings)


def test_scale_multiplies_coordinates(tmp_path):
    path = write(tmp_path, GRID + "usemtl lamp\nf 1 2 5\n")
    np.testing.assert_array_equal(load_scene(path, scale=0.01).vertices, load_scene(path).vertices * 0.01)


def test_default_material_warnings(tmp_path):
    mtl = MTL + "newmtl nokd\nKs 1 1 1\n"
    body = GRID + "o a\nf 1 2 5\nusemtl ghost\nf 1 5 4\nusemtl nokd\nf 2 3 6\n"
    s = load_scene(write(tmp_path, body, mtl))
    np.testing.assert_array_equal(s.rho, np.full((3, 3), DEFAULT_RHO))
    text = "\n".join(s.warnings)
    assert "'ghost'" in text and "'nokd'" in text and "usemtl" in text and "'a'" in text
    assert "no emitters: the solution is zero" in s.warnings


def test_obj_without_mtllib(tmp_path):
    s = load_scene(write(tmp_path, GRID + "f 1 2 5\n", mtl=None))
    assert s.rho.tolist() == [[DEFAULT_RHO] * 3]


def test_degenerate_dropped_and_warned(tmp_path):
    body = GRID + "o good\nusemtl lamp\nf 1 2 5\no flat\nf 1 2 3\no twice\nf 1 1 5\n"
    s = load_scene(write(tmp_path, body))
    assert s.valid.tolist() == [True, False, False]
    (w,) = [w for w in s.warnings if "degenerate" in w]
    assert "2 degenerate" in w and "flat/lamp" in w and "twice/lamp" in w and "good" not in w
    assert len(s.patches()) == 1


# -- OBJ: bad input ------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "body, needles",
    [
        ("v 1 2\n", ["line 1", "3 coordinates"]),
        ("v 0 0 0\nv 1 0 0\nf 1 2\n", ["line 3", "at least 3"]),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", ["line 4", "out of range"]),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -4\n", ["line 4", "-4"]),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 0\n", ["line 4"]),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\n\nf 1 2 x\n", ["line 5", "not an integer"]),
        ("v 0 0 zero\n", ["line 1", "not a number"]),
    ],
)
def test_malformed_obj_lines(tmp_path, body, needles):
    path = write(tmp_path, body, mtl=None)
    with pytest.raises(SceneFormatError) as exc:
        load_scene(path)
    msg = str(exc.value)
    assert str(path) in msg and "\n" not in msg
    for n in needles:
        assert n in msg


@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_non_finite_vertex(tmp_path, bad):
    path = write(tmp_path, f"o chair\nv 0 0 0\nv 1 {bad} 0\nv 0 1 0\nf 1 2 3\n", mtl=None)
    with pytest.raises(SceneValueError, match=r"line 3: object 'chair' has a non-finite"):
        load_scene(path)


@pytest.mark.parametrize(
    "kd, problem",
    [("1.0 0.5 0.5", ">= 1"), ("0.5 -0.1 0.5", "negative"), ("0.5 nan 0.5", "non-finite"), ("1", ">= 1")],
)
def test_bad_reflectance(tmp_path, kd, problem):
    mtl = f"newmtl white\nKd {kd}\n"
    with pytest.raises(SceneValueError) as exc:
        load_scene(write(tmp_path, GRID + "usemtl white\nf 1 2 5\n", mtl))
    msg = str(exc.value)
    assert msg.startswith(f"material 'white' in room.mtl: Kd {kd} has ")
    assert problem in msg and msg.endswith("reflectance must be in [0, 1)")


def test_reflectance_message_matches_spec(tmp_path):
    with pytest.raises(SceneValueError) as exc:
        load_scene(write(tmp_path, GRID + "usemtl white\nf 1 2 5\n", "newmtl white\nKd 1.0 0.5 0.5\n"))
    assert str(exc.value) == (
        "material 'white' in room.mtl: Kd 1.0 0.5 0.5 has a channel >= 1; reflectance must be in [0, 1)"
    )


@pytest.mark.parametrize("ke", ["-1 0 0", "inf 1 1", "nan"])
def test_bad_emission(tmp_path, ke):
    mtl = f"newmtl lamp\nKd 0.5 0.5 0.5\nKe {ke}\n"
    with pytest.raises(SceneValueError, match=r"material 'lamp' in room.mtl: Ke .*emission"):
        load_scene(write(tmp_path, GRID + "usemtl lamp\nf 1 2 5\n", mtl))


@pytest.mark.parametrize("line", ["Kd 0.5 0.5", "Kd spectral white.spd", "Ke 1 2"])
def test_malformed_mtl_values(tmp_path, line):
    mtl = f"newmtl white\nKd 0.5 0.5 0.5\n{line}\n"
    with pytest.raises(SceneFormatError, match=r"material 'white' in room.mtl line 3"):
        load_scene(write(tmp_path, GRID + "usemtl white\nf 1 2 5\n", mtl))


def test_empty_scenes(tmp_path):
    with pytest.raises(SceneValueError, match="no faces"):
        load_scene(write(tmp_path, GRID, mtl=None))
    with pytest.raises(SceneValueError, match="degenerate"):
        load_scene(write(tmp_path, GRID + "f 1 2 3\nf 4 4 5\n", mtl=None))


def test_missing_and_unsupported_files(tmp_path):
    with pytest.raises(SceneFormatError, match="nothere.obj"):
        load_scene(tmp_path / "nothere.obj")
    (tmp_path / "scene.xyz").write_text("")
    with pytest.raises(SceneFormatError) as exc:
        load_scene(tmp_path / "scene.xyz")
    assert str(exc.value) == f"unsupported scene format '.xyz' for {tmp_path / 'scene.xyz'}; use .obj, .gltf or .glb"


@pytest.mark.parametrize("lib", ["../outside.mtl", "/etc/passwd", "sub/../../x.mtl", "C:\\x.mtl"])
def test_mtllib_outside_folder(tmp_path, lib):
    path = tmp_path / "room.obj"
    path.write_text(f"mtllib {lib}\n" + GRID + "f 1 2 5\n")
    with pytest.raises(SceneFormatError) as exc:
        load_scene(path)
    assert lib in str(exc.value) and "line 1" in str(exc.value)


def test_mtllib_missing_and_in_subfolder(tmp_path):
    path = tmp_path / "room.obj"
    path.write_text("mtllib missing.mtl\n" + GRID + "f 1 2 5\n")
    with pytest.raises(SceneFormatError, match="missing.mtl"):
        load_scene(path)
    (tmp_path / "mat").mkdir()
    (tmp_path / "mat" / "m.mtl").write_text(MTL)
    path.write_text("mtllib ./mat/m.mtl\n" + GRID + "usemtl lamp\nf 1 2 5\n")
    assert load_scene(path).emission[0].tolist() == [10, 20, 30.5]


@pytest.mark.parametrize("tex", ["../t.png", "-s 1 1 1 ../../t.png", "/abs/t.png"])
def test_texture_outside_folder(tmp_path, tex):
    mtl = f"newmtl white\nKd 0.5 0.5 0.5\nmap_Kd {tex}\n"
    with pytest.raises(SceneFormatError) as exc:
        load_scene(write(tmp_path, GRID + "usemtl white\nf 1 2 5\n", mtl))
    assert "material 'white'" in str(exc.value) and tex.split()[-1] in str(exc.value)


@pytest.mark.parametrize("scale", [0, -1.0, float("nan"), float("inf"), "abc"])
def test_bad_scale(tmp_path, scale):
    with pytest.raises(ConfigError):
        load_scene(write(tmp_path, GRID + "f 1 2 5\n"), scale=scale)


# -- patches ---------------------------------------------------------------------------------------
def test_patches_subdivide(tmp_path):
    body = (
        "v 0 0 0\nv 2 0 0\nv 2 3 0\nv 0 3 0\nv 0 0 1.5\nv 3 3 3\n"
        "o floor\nusemtl white\nf 1 2 3 4\no light\nusemtl lamp\nf 1 5 6\no bad\nf 1 1 2\n"
    )
    s = load_scene(write(tmp_path, body))
    for max_edge in (0.37, 1.0):
        p = s.patches(max_edge)
        tri = p.triangles
        edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)
        # no element larger than the size (mesh.refine): small in area or short, and no long sliver
        small = (triangle_areas(tri) <= AREA_SHARE * max_edge ** 2 * (1 + 1e-12)) | \
            (edges.max(axis=1) <= max_edge * (1 + 1e-12))
        assert small.all() and edges.max() <= SLIVER_EDGES * max_edge * (1 + 1e-12)
        # none split that did not need it: a piece is at least a quarter of the area bound (bisection
        # halves; the closure of hanging vertices halves once more)
        assert triangle_areas(tri).min() >= 0.25 * 0.5 * AREA_SHARE * max_edge ** 2 or len(p) < 8
        # no hanging vertex: no edge is shared by more than two pieces
        und = np.sort(np.concatenate([p.faces[:, [0, 1]], p.faces[:, [1, 2]], p.faces[:, [2, 0]]]), axis=1)
        _, count = np.unique(und, axis=0, return_counts=True)
        assert count.max() <= 2
        valid_area = triangle_areas(s.vertices[s.faces[s.valid]]).sum()
        assert abs(p.area.sum() - valid_area) <= 1e-12 * valid_area
        assert set(p.source.tolist()) == set(np.flatnonzero(s.valid).tolist())
        np.testing.assert_array_equal(p.rho, s.rho[p.source])
        np.testing.assert_array_equal(p.emission, s.emission[p.source])
        np.testing.assert_array_equal(p.obj, s.obj[p.source])
        assert p.names == s.names
        # each patch lies inside its source triangle (barycentric coordinates in [0, 1])
        src = s.vertices[s.faces[p.source]]
        a, b, c = src[:, 0], src[:, 1] - src[:, 0], src[:, 2] - src[:, 0]
        for q in (p.centroid, tri[:, 0], tri[:, 1], tri[:, 2]):
            sol = np.array([np.linalg.lstsq(np.stack([b[i], c[i]], 1), q[i] - a[i], rcond=None)[0]
                            for i in range(len(q))])
            assert (sol >= -1e-9).all() and (sol.sum(axis=1) <= 1 + 1e-9).all()
            np.testing.assert_allclose(a + sol[:, :1] * b + sol[:, 1:] * c, q, atol=1e-12)
        # same orientation as the source
        n_src = np.cross(b, c)
        assert (np.einsum("ij,ij->i", p.normal, n_src) > 0).all()
    p = s.patches()
    assert len(p) == 3 and p.source.tolist() == [0, 1, 2]
    with pytest.raises(ConfigError):
        s.patches(-1.0)


# -- glTF ----------------------------------------------------------------------------------------------
def glb_json(data: bytes) -> dict:
    length, kind = struct.unpack_from("<I4s", data, 12)
    assert kind == b"JSON"
    return json.loads(data[20 : 20 + length])


def glb_with_json(data: bytes, header: dict) -> bytes:
    """Replace the JSON chunk of a GLB, keeping the binary chunk."""
    length = struct.unpack_from("<I", data, 12)[0]
    rest = data[20 + length :]
    js = json.dumps(header).encode()
    js += b" " * (-len(js) % 4)
    body = struct.pack("<I4s", len(js), b"JSON") + js + rest
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def trimesh_glb():
    import trimesh
    from trimesh.visual.material import PBRMaterial

    wall = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    wall.visual = trimesh.visual.TextureVisuals(
        material=PBRMaterial(name="wall", baseColorFactor=[0.6, 0.4, 0.2, 1.0], emissiveFactor=[0, 0, 0])
    )
    lamp = trimesh.Trimesh([[0, 0, 1], [1, 0, 1], [0, 1, 1]], [[0, 2, 1]], process=False)
    lamp.visual = trimesh.visual.TextureVisuals(
        material=PBRMaterial(name="lamp", baseColorFactor=[0.1, 0.1, 0.1, 1.0], emissiveFactor=[0.5, 0.25, 1.0])
    )
    scene = trimesh.Scene()
    scene.add_geometry(wall, node_name="wall", geom_name="wall",
                       transform=trimesh.transformations.translation_matrix([0, 2, 0]))
    scene.add_geometry(lamp, node_name="lamp", geom_name="lamp")
    return scene.export(file_type="glb")


def by_name(s):
    return {s.names[k].split("/")[-1]: i for i, k in enumerate(s.obj)}


def test_glb_round_trip(tmp_path):
    data = trimesh_glb()
    (tmp_path / "a.glb").write_bytes(data)
    s = load_scene(tmp_path / "a.glb")
    header = glb_json(data)
    mats = {m["name"]: m for m in header["materials"]}
    idx = by_name(s)
    assert len(s) == 3 and sorted(idx) == ["lamp", "wall"]
    for name, i in idx.items():
        assert s.rho[i].tolist() == mats[name]["pbrMetallicRoughness"]["baseColorFactor"][:3]
        assert s.emission[i].tolist() == mats[name]["emissiveFactor"]
    assert s.emission[idx["lamp"]].tolist() == [0.5, 0.25, 1.0]
    wall = s.faces[s.obj == s.obj[idx["wall"]]]
    assert np.allclose(s.vertices[wall][..., 1].min(), 2.0)  # world transform applied
    assert not any("cannot match" in w for w in s.warnings)

    # factors beyond 8 bits survive: trimesh's own copy is uint8, ours comes from the JSON
    mats["wall"]["pbrMetallicRoughness"]["baseColorFactor"] = [0.999, 0.123456789, 0.5, 1.0]
    mats["lamp"]["emissiveFactor"] = [0.1, 0.2, 1 / 3]
    (tmp_path / "b.glb").write_bytes(glb_with_json(data, header))
    s = load_scene(tmp_path / "b.glb")
    idx = by_name(s)
    assert s.rho[idx["wall"]].tolist() == [0.999, 0.123456789, 0.5]
    assert s.emission[idx["lamp"]].tolist() == [0.1, 0.2, 1 / 3]

    mats["wall"]["pbrMetallicRoughness"]["baseColorFactor"] = [1.0, 0.5, 0.5, 1.0]
    (tmp_path / "c.glb").write_bytes(glb_with_json(data, header))
    with pytest.raises(SceneValueError, match=r"material 'wall' in .*c\.glb: baseColorFactor 1\.0 .*>= 1"):
        load_scene(tmp_path / "c.glb")


def hand_gltf(materials, nodes=None, extra=None):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
    f = np.array([0, 1, 2, 1, 3, 2], np.uint16)
    buf = v.tobytes() + f.tobytes()
    prims = [{"attributes": {"POSITION": 0}, "indices": 1, **({"material": m} if m is not None else {})}
             for m in range(len(materials))]
    g = {
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0, 2]}],
        "nodes": nodes or [
            {"name": "parent", "translation": [0, 1, 0], "children": [1]},
            {"name": "mirror", "mesh": 0, "scale": [-2, 2, 2]},
            {"name": "cam", "camera": 0, "translation": [0, 0, 5],
             "rotation": [0, math.sin(math.pi / 8), 0, math.cos(math.pi / 8)]},
        ],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.5, "znear": 0.1}}],
        "meshes": [{"name": "quad", "primitives": prims}],
        "materials": materials,
        "extensionsUsed": ["KHR_materials_emissive_strength"],
        "buffers": [{"byteLength": len(buf),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(buf).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 48},
                        {"buffer": 0, "byteOffset": 48, "byteLength": 12}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
                       "min": [0, 0, 0], "max": [1, 1, 0]},
                      {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"}],
    }
    g.update(extra or {})
    return g


def test_hand_written_gltf_emissive_strength_camera_mirror(tmp_path):
    mats = [
        {"pbrMetallicRoughness": {"baseColorFactor": [0.999, 0.3, 0.7, 1]},
         "emissiveFactor": [1, 0.5, 0.1],
         "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": 7.5}}},
        {"name": "grey", "pbrMetallicRoughness": {"baseColorFactor": [0.2, 0.2, 0.2, 1]}},
        {"name": "plain"},
    ]
    path = tmp_path / "h.gltf"
    path.write_text(json.dumps(hand_gltf(mats)))
    s = load_scene(path, scale=2.0)
    assert len(s) == 6
    got = {s.names[k].split("/")[-1]: (s.rho[i].tolist(), s.emission[i].tolist()) for i, k in enumerate(s.obj)}
    assert got["material0"] == ([0.999, 0.3, 0.7], [7.5, 0.5 * 7.5, 0.1 * 7.5])
    assert got["grey"] == ([0.2, 0.2, 0.2], [0, 0, 0])
    assert got["plain"] == ([DEFAULT_RHO] * 3, [0, 0, 0])
    assert any("'plain' in" in w and "baseColorFactor" in w for w in s.warnings)
    # x mirrored, scaled by 2 (node) and 2 (load), shifted up 1 * 2; winding flipped -> normals still +z
    assert np.allclose(s.vertices[:, 0].min(), -4) and np.allclose(s.vertices[:, 1].min(), 2)
    p = s.patches()
    assert np.allclose(p.normal, [0, 0, 1])
    cam = s.camera
    assert cam["eye"] == pytest.approx([0, 0, 10])
    d = math.sqrt(0.5)
    assert cam["target"] == pytest.approx([-d, 0, 10 - d])
    assert cam["up"] == pytest.approx([0, 1, 0])
    assert cam["fov_y"] == pytest.approx(math.degrees(0.5))


def test_gltf_primitive_without_material_and_bad_values(tmp_path):
    g = hand_gltf([{"name": "m"}])
    g["meshes"][0]["primitives"][0].pop("material")
    (tmp_path / "n.gltf").write_text(json.dumps(g))
    s = load_scene(tmp_path / "n.gltf")
    assert (s.rho == DEFAULT_RHO).all() and any("no material" in w for w in s.warnings)
    assert "no emitters: the solution is zero" in s.warnings

    bad = {"name": "hot", "emissiveFactor": [1, -1, 0]}
    (tmp_path / "e.gltf").write_text(json.dumps(hand_gltf([bad])))
    with pytest.raises(SceneValueError, match="material 'hot'.*emission"):
        load_scene(tmp_path / "e.gltf")
    bad = {"name": "hot", "emissiveFactor": [1, 1, 0],
           "extensions": {"KHR_materials_emissive_strength": {"emissiveStrength": -2}}}
    (tmp_path / "s.gltf").write_text(json.dumps(hand_gltf([bad])))
    with pytest.raises(SceneValueError, match="material 'hot'.*emissiveStrength"):
        load_scene(tmp_path / "s.gltf")


def test_gltf_bad_files(tmp_path):
    g = hand_gltf([{"name": "m"}])
    g["buffers"][0]["uri"] = "../escape.bin"
    (tmp_path / "u.gltf").write_text(json.dumps(g))
    with pytest.raises(SceneFormatError, match=r"'\.\./escape\.bin'"):
        load_scene(tmp_path / "u.gltf")
    (tmp_path / "x.glb").write_bytes(b"nope" + b"\0" * 30)
    with pytest.raises(SceneFormatError, match="x.glb"):
        load_scene(tmp_path / "x.glb")
    (tmp_path / "j.gltf").write_text("{not json")
    with pytest.raises(SceneFormatError, match="j.gltf"):
        load_scene(tmp_path / "j.gltf")
    empty = {"asset": {"version": "2.0"}, "scenes": [{"nodes": []}], "scene": 0}
    (tmp_path / "e.gltf").write_text(json.dumps(empty))
    with pytest.raises(SceneValueError, match="no faces"):
        load_scene(tmp_path / "e.gltf")


BROKEN_GLTF = {
    # what is broken: (change to hand_gltf's dict, words the error must hold)
    "attribute accessor": (lambda g: g["meshes"][0]["primitives"][0]["attributes"].update(POSITION=5),
                           "mesh 0 primitive 0's POSITION refers to accessor 5, but the file has 2 accessors"),
    "indices accessor": (lambda g: g["meshes"][0]["primitives"][0].update(indices=-1),
                         "primitive 0's indices refers to accessor -1"),
    "no POSITION": (lambda g: g["meshes"][0]["primitives"][0].update(attributes={}),
                    "mesh 0 primitive 0 has no POSITION attribute"),
    "node mesh": (lambda g: g["nodes"][1].update(mesh=3), "node 1 refers to mesh 3, but the file has 1 mesh"),
    "child node": (lambda g: g["nodes"][0].update(children=[9]), "node 0's children refers to node 9"),
    "view past buffer": (lambda g: g["bufferViews"][1].update(byteLength=40),
                         "bufferView 1 (bytes 48 to 88) runs past the end of buffer 0 (60 bytes)"),
    "accessor past view": (lambda g: g["accessors"][0].update(count=40),
                           "accessor 0 (40 x VEC3) needs 480 bytes of bufferView 0, which has 48"),
    "component type": (lambda g: g["accessors"][1].update(componentType=7),
                       "accessor 1 has componentType 7"),
    "buffer short of its length": (lambda g: g["buffers"][0].update(byteLength=100),
                                   "buffer 0 holds 60 bytes, less than its byteLength 100"),
    "buffer file missing": (lambda g: g["buffers"][0].update(uri="gone.bin"), "buffer 0's file 'gone.bin'"),
    "material": (lambda g: g["meshes"][0]["primitives"][0].update(material=4), "refers to material 4"),
}


@pytest.mark.parametrize("case", sorted(BROKEN_GLTF))
def test_gltf_broken_structure_names_the_item(tmp_path, case):
    """A glTF whose indices or byte ranges do not hold is refused naming the item: trimesh's own
    errors on these (an UnboundLocalError for a missing accessor) name nothing."""
    g = hand_gltf([{"name": "m"}])
    change, words = BROKEN_GLTF[case]
    change(g)
    (tmp_path / "b.gltf").write_text(json.dumps(g))
    with pytest.raises(SceneFormatError) as exc:
        load_scene(tmp_path / "b.gltf")
    assert words in str(exc.value) and "b.gltf" in str(exc.value)


@pytest.mark.parametrize("uri", ["my%20quad.bin", "my quad.bin"])
def test_gltf_buffer_file_named_as_a_uri_is_read(tmp_path, uri):
    """A buffer file named with percent-escapes (a URI, as glTF writes them: trimesh alone looked
    for 'my%20quad.bin' literally and failed) or as written is found and read."""
    g = hand_gltf([{"name": "m"}])
    data = base64.b64decode(g["buffers"][0]["uri"].split(",", 1)[1])
    (tmp_path / "my quad.bin").write_bytes(data)
    g["buffers"][0]["uri"] = uri
    (tmp_path / "q.gltf").write_text(json.dumps(g))
    assert gltf_header(str(tmp_path / "q.gltf"))["buffers"][0]["uri"] == uri
    (tmp_path / "d.gltf").write_text(json.dumps(hand_gltf([{"name": "m"}])))  # the same, its buffer inline
    got, inline = load_scene(tmp_path / "q.gltf"), load_scene(tmp_path / "d.gltf")
    assert len(got) == 2 and np.array_equal(got.vertices, inline.vertices)


def test_truncated_glb_is_refused_naming_its_buffer(tmp_path):
    import trimesh

    whole = trimesh.creation.box().export(file_type="glb")
    (tmp_path / "ok.glb").write_bytes(whole)
    assert len(load_scene(tmp_path / "ok.glb")) == 12
    (tmp_path / "cut.glb").write_bytes(whole[:-100])
    with pytest.raises(SceneFormatError, match=r"cut\.glb: buffer 0 holds \d+ bytes, less than its byteLength"):
        load_scene(tmp_path / "cut.glb")


# -- textures (issue 15) ----------------------------------------------------------------------
def _png(path, rgb_bytes):
    """Write a tiny RGB PNG (uint8 sRGB values, shape (h, w, 3)) with OpenImageIO."""
    import OpenImageIO as oiio

    px = np.asarray(rgb_bytes, np.uint8)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(px.shape[1], px.shape[0], 3, oiio.UINT8))
    assert out.write_image(px)
    out.close()


def _linear(byte):
    x = np.asarray(byte, np.float64) / 255.0
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


TEX = [[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [128, 128, 128]]]  # 2x2: red green / blue grey
QUAD_UV = ("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
           "usemtl tex\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")


def test_obj_map_kd_gives_the_texture_mean_times_kd(tmp_path):
    _png(tmp_path / "t.png", TEX)
    mtl = "newmtl tex\nKd 0.8 0.5 1.0\nmap_Kd t.png\n"
    s = load_scene(write(tmp_path, QUAD_UV, mtl))
    mean = _linear(TEX).reshape(-1, 3).mean(axis=0)
    area_mean = (s.rho * triangle_areas(s.vertices[s.faces])[:, None]).sum(axis=0) / 1.0
    np.testing.assert_allclose(area_mean, np.array([0.8, 0.5, 1.0]) * mean, atol=0.01)
    assert s.textured == ["default/tex"]
    # per triangle: the texture varies over UV, so the two halves of the quad differ
    assert not np.allclose(s.rho[0], s.rho[1], atol=0.02)
    # a uniform texture gives exactly its value
    _png(tmp_path / "t.png", [[[200, 100, 50]] * 2] * 2)
    s = load_scene(write(tmp_path, QUAD_UV, mtl))
    np.testing.assert_allclose(s.rho, np.broadcast_to([0.8, 0.5, 1.0] * _linear([200, 100, 50]), (2, 3)),
                               rtol=1e-6)


def test_missing_texture_warns_naming_the_file_and_uses_the_factor(tmp_path):
    mtl = "newmtl tex\nKd 0.3 0.4 0.5\nmap_Kd nothere.png\n"
    s = load_scene(write(tmp_path, QUAD_UV, mtl))
    assert np.allclose(s.rho, [0.3, 0.4, 0.5]) and s.textured == []
    assert any("nothere.png" in w and "Kd factor alone" in w for w in s.warnings), s.warnings
    (tmp_path / "bad.png").write_bytes(b"not a png")
    s = load_scene(write(tmp_path, QUAD_UV, mtl.replace("nothere", "bad")))
    assert np.allclose(s.rho, [0.3, 0.4, 0.5])
    assert any("bad.png" in w for w in s.warnings)


def _textured_gltf(tmp_path, image_uri="tex.png"):
    pos = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)  # glTF: v down from the top
    idx = np.array([0, 1, 2, 0, 2, 3], np.uint16)
    blob = pos.tobytes() + uv.tobytes() + idx.tobytes()
    header = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "panel"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2,
                                    "material": 0}]}],
        "materials": [{"name": "painted", "doubleSided": True,
                       "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.9, 0.7, 1.0],
                                                "baseColorTexture": {"index": 0}}}],
        "textures": [{"source": 0}], "images": [{"uri": image_uri}],
        "buffers": [{"byteLength": len(blob),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 48},
                        {"buffer": 0, "byteOffset": 48, "byteLength": 32},
                        {"buffer": 0, "byteOffset": 80, "byteLength": 12}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
            {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"},
        ],
    }
    path = tmp_path / "panel.gltf"
    path.write_text(json.dumps(header))
    return path


def test_gltf_base_colour_texture_mean_and_double_sided(tmp_path):
    _png(tmp_path / "tex.png", TEX)
    s = load_scene(_textured_gltf(tmp_path))
    mean = _linear(TEX).reshape(-1, 3).mean(axis=0)
    area = triangle_areas(s.vertices[s.faces])
    np.testing.assert_allclose((s.rho * area[:, None]).sum(axis=0) / area.sum(), [0.5, 0.9, 0.7] * mean,
                               atol=0.01)
    assert s.textured == ["painted"]
    assert s.two_sided is not None and s.two_sided.all()  # doubleSided
    p = s.patches()
    assert len(p) == 4 and p.is_back.sum() == 2
    # the two triangles see different texels: the orientation of V is honoured (glTF: from
    # the top); the triangle (0,1,2) covers the image's bottom-right half (blue/grey + green)
    tri0 = _linear(TEX)
    expect0 = (tri0[0, 1] + tri0[1, 0] + 2 * tri0[1, 1]) / 4  # green, blue, grey twice (diagonal)
    assert np.allclose(s.rho[0], [0.5, 0.9, 0.7] * expect0, atol=0.06)


def test_gltf_missing_texture_warns_and_uses_the_factor(tmp_path):
    s = load_scene(_textured_gltf(tmp_path, "gone.png"))
    assert np.allclose(s.rho, [0.5, 0.9, 0.7]) and s.textured == []
    assert any("gone.png" in w for w in s.warnings), s.warnings


def test_glb_embedded_texture_is_read(tmp_path):
    """A GLB whose image lives in the binary chunk (a buffer view), as exporters write them."""
    _png(tmp_path / "t.png", [[[200, 100, 50]] * 2] * 2)
    png = (tmp_path / "t.png").read_bytes()
    pos = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32).tobytes()
    uv = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32).tobytes()
    idx = np.array([0, 1, 2, 0, 2, 3], np.uint16).tobytes() + b"\0\0"
    blob = pos + uv + idx + png
    blob += b"\0" * (-len(blob) % 4)
    views = [(0, 48), (48, 32), (80, 12), (94, len(png))]
    header = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "indices": 2, "material": 0}]}],
        "materials": [{"name": "tiles", "pbrMetallicRoughness": {"baseColorFactor": [0.5, 0.5, 0.5, 1.0],
                                                                 "baseColorTexture": {"index": 0}}}],
        "textures": [{"source": 0}], "images": [{"bufferView": 3, "mimeType": "image/png"}],
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": [{"buffer": 0, "byteOffset": o, "byteLength": n} for o, n in views],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
            {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"},
        ],
    }
    js = json.dumps(header).encode()
    js += b" " * (-len(js) % 4)
    glb = struct.pack("<4sII", b"glTF", 2, 12 + 8 + len(js) + 8 + len(blob))
    glb += struct.pack("<I4s", len(js), b"JSON") + js + struct.pack("<I4s", len(blob), b"BIN\0") + blob
    (tmp_path / "a.glb").write_bytes(glb)
    s = load_scene(tmp_path / "a.glb")
    np.testing.assert_allclose(s.rho, np.broadcast_to(0.5 * _linear([200, 100, 50]), (2, 3)), rtol=1e-6)
    assert s.textured == ["tiles"] and s.two_sided is None


def test_mtl_two_sided_flag_marks_its_material_only(tmp_path):
    mtl = "newmtl a\nKd 0.5 0.5 0.5\ntwo_sided 1\nnewmtl b\nKd 0.5 0.5 0.5\n"
    body = GRID + "usemtl a\nf 1 2 5\nusemtl b\nf 1 5 4\n"
    s = load_scene(write(tmp_path, body, mtl))
    assert s.two_sided.tolist() == [True, False]
    p = s.patches()
    assert len(p) == 3 and p.twin.tolist() == [2, -1, 0]
    np.testing.assert_allclose(p.normal[2], -p.normal[0])
    assert p.emission[2].tolist() == [0.0, 0.0, 0.0]
    assert load_scene(write(tmp_path, body, mtl), two_sided=True).two_sided.all()


def test_meshed_patches_take_their_own_part_of_the_texture(tmp_path):
    """Meshed finer than the input, each patch's rho is the texture over its own UV
    sub-triangle: the left half of a red|blue texture is red, the right half blue, and the
    patches of an input triangle average (by area) to that triangle's mean."""
    _png(tmp_path / "t.png", [[[255, 0, 0], [0, 0, 255]]])  # 2 x 1: red | blue
    mtl = "newmtl tex\nKd 0.9 0.9 0.9\nmap_Kd t.png\n"
    quad = ("v 0 0 0\nv 2 0 0\nv 2 2 0\nv 0 2 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
            "usemtl tex\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")
    s = load_scene(write(tmp_path, quad, mtl))
    p = s.patches(0.2)
    x = p.centroid[:, 0]
    inside = np.abs(x - 1.0) > 0.2  # patches clear of the red|blue edge
    left, right = inside & (x < 1.0), inside & (x > 1.0)
    np.testing.assert_allclose(p.rho[left], np.broadcast_to([0.9, 0.0, 0.0], (left.sum(), 3)), atol=1e-12)
    np.testing.assert_allclose(p.rho[right], np.broadcast_to([0.0, 0.0, 0.9], (right.sum(), 3)), atol=1e-12)
    for t in range(2):
        own = p.source == t
        mean = (p.rho[own] * p.area[own, None]).sum(axis=0) / p.area[own].sum()
        np.testing.assert_allclose(mean, s.rho[t], atol=0.01)


def test_gltf_with_up_override_rotates_geometry_and_camera_together(tmp_path):
    """--up z on a glTF: vertices and the file's camera go into the Y-up frame by the same
    exact rotation (x, y, z) -> (x, z, -y); the camera still looks at the same geometry."""
    path = tmp_path / "h.gltf"
    path.write_text(json.dumps(hand_gltf([{"name": "grey", "pbrMetallicRoughness": {"baseColorFactor": [0.2] * 4}}])))
    a, b = load_scene(path), load_scene(path, up="z")
    assert a.up == "y" and a.up_source.startswith("glTF") and b.up == "z" and b.up_source == "given"
    rot = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], np.float64)
    np.testing.assert_array_equal(b.vertices, a.vertices @ rot.T)
    for k in ("eye", "target", "up"):
        assert b.camera[k] == pytest.approx(list(rot @ np.array(a.camera[k])))
    np.testing.assert_allclose(b.to_input_frame(b.vertices), a.vertices, atol=0)
