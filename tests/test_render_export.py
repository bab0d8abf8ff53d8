"""Tests for dcrad.outputs.render and dcrad.io.export on small hand-built patch tables."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from dcrad.io.export import (
    input_triangle_radiosity,
    write_exr,
    write_glb,
    write_patches_ply,
    write_png,
    write_radiosity_npz,
)
from dcrad.meshing.patches import Patches
from dcrad.outputs.render import (
    BACKFACE_COLOR,
    Camera,
    CornerSmoother,
    auto_camera,
    barycentric,
    corner_radiosity,
    cutaway_mask,
    render,
    shade_view,
    tonemap,
    topdown_camera,
    trace_view,
)


def _table(tris, B, E=None, source=None):
    tris = np.asarray(tris, np.float64).reshape(-1, 3, 3)
    n = len(tris)
    B = np.broadcast_to(np.asarray(B, np.float64), (n, 3)).copy()
    E = np.zeros((n, 3)) if E is None else E
    return Patches(
        vertices=tris.reshape(-1, 3),  # unshared: corner_radiosity must merge by position
        faces=np.arange(3 * n).reshape(n, 3),
        rho=0.5,
        emission=E,
        source=np.arange(n) if source is None else source,
        obj=np.zeros(n, np.int32),
        radiosity=B,
    )


def _quad(p0, p1, p2, p3):
    """Two CCW triangles of the quad p0 p1 p2 p3 (CCW seen from the front)."""
    return [[p0, p1, p2], [p0, p2, p3]]


def _floor_tris():
    """Unit square in y=0 facing +y: 2x2 cells, all diagonals through the centre."""
    c = (0.5, 0.0, 0.5)
    ring = [(0, 0, 0), (0, 0, 0.5), (0, 0, 1), (0.5, 0, 1), (1, 0, 1), (1, 0, 0.5), (1, 0, 0), (0.5, 0, 0)]
    return [[c, ring[i], ring[(i + 1) % 8]] for i in range(8)]  # CCW about +y


def _linear(p):
    return 2.0 + 3.0 * p[..., 0] - 1.0 * p[..., 2]


@pytest.fixture
def scene():
    floor = np.array(_floor_tris(), float)
    # wall x=0 facing +x, perpendicular to the floor, sharing the floor's edge
    wall = np.array(_quad((0, 0, 0), (0, 1, 0), (0, 1, 1), (0, 0, 1)), float)
    # thin wall standing on the floor at x=0.5: two quads 1 mm apart facing away
    a = np.array(_quad((0.4995, 0, 0), (0.4995, 0, 1), (0.4995, 1, 1), (0.4995, 1, 0)), float)  # -x
    b = np.array(_quad((0.5005, 0, 0), (0.5005, 1, 0), (0.5005, 1, 1), (0.5005, 0, 1)), float)  # +x
    # zero-thickness double wall at z=0.5 above the floor: same positions, opposite normals
    za = np.array(_quad((0, 1.2, 0.5), (1, 1.2, 0.5), (1, 2.2, 0.5), (0, 2.2, 0.5)), float)
    zb = za[:, ::-1]
    tris = np.concatenate([floor, wall, a, b, za, zb])
    B = np.zeros((len(tris), 3))
    B[:8] = _linear(floor.mean(axis=1))[:, None] * [1.0, 0.5, 0.25]
    B[8:10] = [100.0, 0, 0]
    B[10:12] = [0, 50.0, 0]
    B[12:14] = [0, 0, 70.0]
    B[14:16] = [7.0, 0, 0]
    B[16:18] = [0, 9.0, 0]
    return _table(tris, B)


def test_normals_of_fixture(scene):
    n = scene.normal
    assert np.allclose(n[:8], [0, 1, 0])
    assert np.allclose(n[8:10], [1, 0, 0])
    assert np.allclose(n[10:12], [-1, 0, 0]) and np.allclose(n[12:14], [1, 0, 0])
    assert np.allclose(n[14:16], [0, 0, 1]) and np.allclose(n[16:18], [0, 0, -1])


def test_corner_radiosity_no_bleeding(scene):
    cv = corner_radiosity(scene)
    B = scene.radiosity
    assert cv.shape == (len(scene), 3, 3)
    # walls with constant B keep exactly that B at every corner
    for sl in (slice(8, 10), slice(10, 12), slice(12, 14), slice(14, 16), slice(16, 18)):
        assert np.allclose(cv[sl], B[sl][:, None, :])
    # the floor never picks up the walls' channels (walls have zero in 1..2 or 0)
    assert np.allclose(cv[:8, :, 1], 0.5 * cv[:8, :, 0])
    assert np.allclose(cv[:8, :, 2], 0.25 * cv[:8, :, 0])
    # each floor corner lies within the range of the floor patches
    lo, hi = B[:8, 0].min(), B[:8, 0].max()
    assert np.all((cv[:8, :, 0] >= lo - 1e-12) & (cv[:8, :, 0] <= hi + 1e-12))


def test_corner_radiosity_linear_field_at_symmetric_vertex(scene):
    cv = corner_radiosity(scene)
    # corner 0 of every floor triangle is the centre, surrounded symmetrically
    assert np.allclose(cv[:8, 0, 0], _linear(np.array([0.5, 0.0, 0.5])))
    # with a crease of 100 deg the perpendicular wall mixes, but opposite faces never do
    cv2 = corner_radiosity(scene, crease_angle_deg=100.0)
    assert np.allclose(cv2[14:16], scene.radiosity[14:16][:, None, :])
    assert np.allclose(cv2[16:18], scene.radiosity[16:18][:, None, :])
    assert np.all(cv2[10:12, :, 2] == 0)  # -x side of the thin wall never sees +x side


def test_corner_radiosity_merges_near_duplicates():
    tris = np.array(_quad((0, 0, 0), (0, 0, 1), (1, 0, 1), (1, 0, 0)), float)
    tris[1] += 1e-12  # duplicated vertices off by round-off
    p = _table(tris, [[1.0, 1, 1], [3.0, 3, 3]])
    cv = corner_radiosity(p)
    # shared diagonal corners average the two equal-area triangles
    assert np.allclose(cv[0, 0], 2.0) and np.allclose(cv[0, 2], 2.0)
    assert np.allclose(cv[0, 1], 1.0) and np.allclose(cv[1, 2], 3.0)
    # chunked pair processing gives the same answer
    assert np.allclose(corner_radiosity(p, max_pairs=3), cv)


def test_barycentric():
    tri = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]]], float)
    bc = barycentric(np.repeat(tri, 2, 0), np.array([[0.25, 0.5, 0.0], [0.25, 0.5, 0.1]]))
    assert np.allclose(bc, [[0.25, 0.25, 0.5]] * 2)


def _emitter_square(B=10.0):
    # unit square at z=0 facing +z
    tris = _quad((-0.5, -0.5, 0), (0.5, -0.5, 0), (0.5, 0.5, 0), (-0.5, 0.5, 0))
    return _table(tris, B, E=np.full((2, 3), B))


def test_camera_rays():
    cam = Camera((0, 0, 5), (0, 0, 0), (0, 1, 0), 90.0, 4, 2)
    o, d = cam.rays()
    assert o.shape == d.shape == (8, 3)
    assert np.allclose(np.linalg.norm(d, axis=1), 1)
    assert d[0, 0] < 0 and d[0, 1] > 0  # top-left pixel looks left and up
    ortho = Camera((0, 5, 0), (0, 0, 0), (0, 0, -1), 45, 4, 2, orthographic_height=2.0)
    o, d = ortho.rays()
    assert np.allclose(d, [0, -1, 0])
    assert np.allclose(o[0], [-1.5, 5, -0.5])  # +x right, -z up


def test_render_emissive_square_head_on():
    sq = _emitter_square(10.0)
    cam = Camera((0, 0, 3), (0, 0, 0), (0, 1, 0), 40.0, 64, 48)
    img = render(sq, cam)
    assert img.shape == (48, 64, 3) and img.dtype == np.float32
    lum = img[..., 0]
    covered = lum > 0
    assert 0.1 < covered.mean() < 0.9
    assert np.allclose(img[covered], 10.0 / math.pi, rtol=1e-6)
    assert np.all(img[~covered] == 0)
    assert covered[24, 32] and not covered[0, 0]
    # orthographic head-on: the square covers exactly its area
    ortho = Camera((0, 0, 3), (0, 0, 0), (0, 1, 0), 40.0, 40, 40, orthographic_height=2.0)
    im2 = render(sq, ortho)
    assert (im2[..., 0] > 0).sum() == 400


def test_render_backface_flag_and_mask():
    sq = _emitter_square(10.0)
    cam = Camera((0, 0, -3), (0, 0, 0), (0, 1, 0), 40.0, 32, 32)
    img = render(sq, cam, backface_color=(0.05, 0.0, 0.05))
    hit = img.any(axis=2)
    assert hit.any()
    assert np.allclose(img[hit], [0.05, 0.0, 0.05])
    auto = render(sq, cam)  # relative flag: a neutral grey, BACKFACE_COLOR of the reference
    assert np.all(auto[hit] > 0) and np.allclose(auto[hit], auto[hit][:, :1])
    assert np.allclose(render(sq, cam, exposure=0.9 / 2.0)[hit], np.multiply(BACKFACE_COLOR, 2.0))
    none = render(sq, cam, mask=np.zeros(2, bool))
    assert np.all(none == 0)


def _box(open_front: bool):
    """Cornell-like box [0,1]^3 with inward normals; front is z=1."""
    q = []
    q += _quad((0, 0, 0), (0, 0, 1), (1, 0, 1), (1, 0, 0))  # floor, +y
    q += _quad((0, 1, 0), (1, 1, 0), (1, 1, 1), (0, 1, 1))  # ceiling, -y
    q += _quad((0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0))  # back z=0, +z
    q += _quad((0, 0, 0), (0, 1, 0), (0, 1, 1), (0, 0, 1))  # left x=0, +x
    q += _quad((1, 0, 0), (1, 0, 1), (1, 1, 1), (1, 1, 0))  # right x=1, -x
    if not open_front:
        q += _quad((0, 0, 1), (0, 1, 1), (1, 1, 1), (1, 0, 1))  # front z=1, -z
    q += _quad((0.4, 0.99, 0.4), (0.6, 0.99, 0.4), (0.6, 0.99, 0.6), (0.4, 0.99, 0.6))  # lamp, -y
    n = len(q)
    E = np.zeros((n, 3))
    E[-2:] = 50.0
    return _table(q, np.full((n, 3), 5.0) + E, E=E)


def test_auto_camera_open_and_closed_box():
    box = _box(open_front=True)
    cam = auto_camera(box, 64, 48)
    assert cam.eye[2] > 1.0 and abs(cam.eye[0] - 0.5) < 1e-9  # outside, in front
    img = render(box, cam)
    hit = img.max(axis=2) > 0
    assert hit.mean() > 0.5 and hit[24, 32]
    assert np.all(img[hit][:, 1] > 0)  # no back faces seen (the flag has no green)
    closed = _box(open_front=False)
    cam = auto_camera(closed, 64, 48)
    assert np.all((np.array(cam.eye) > 0) & (np.array(cam.eye) < 1))
    img = render(closed, cam)
    assert np.all(img[..., 1] > 0)


def test_topdown_cutaway():
    box = _box(open_front=False)
    mask = cutaway_mask(box)
    assert not mask[2:4].any() and not mask[-2:].any()  # ceiling and lamp hidden
    assert mask[:2].all() and mask[4:12].all()
    cam = topdown_camera(box, 50, 50)
    img = render(box, cam, mask=mask)
    assert np.all(img[..., 1] >= 0) and (img[..., 1] > 0).mean() > 0.8
    assert np.allclose(img[25, 25], 5.0 / math.pi)  # the floor in the middle


def test_views_and_mesh_without_the_cached_corners_and_with_the_solves_tracer(tmp_path):
    """The outputs drop the table's cached corner positions (Patches.release_corners) and
    reuse the solve's Embree scene: the camera, the images and the GLB are the same, and
    nothing they call rebuilds the cache."""
    from dcrad.transport.rays import Tracer

    box = _box(open_front=False)
    cam = auto_camera(box, 32, 24)
    img = render(box, cam, samples=4)
    mask = cutaway_mask(box)
    top = render(box, topdown_camera(box, 32, 32), mask=mask)
    write_glb(tmp_path / "cached.glb", box, corner_radiosity(box))
    corners, area, normal = box.triangles.copy(), box.area.copy(), box.normal.copy()
    box.release_corners()
    assert "triangles" not in vars(box)
    assert np.array_equal(box.corners(), corners) and np.array_equal(box.corners(mask), corners[mask])
    assert auto_camera(box, 32, 24, tracer=Tracer(box.corners())) == cam
    assert np.array_equal(render(box, cam, samples=4), img)
    assert np.array_equal(render(box, topdown_camera(box, 32, 32), mask=mask), top)
    write_glb(tmp_path / "released.glb", box, corner_radiosity(box))
    assert (tmp_path / "released.glb").read_bytes() == (tmp_path / "cached.glb").read_bytes()
    assert "triangles" not in vars(box)
    assert np.array_equal(box.area, area) and np.array_equal(box.normal, normal)
    assert np.array_equal(box.triangles, corners)  # rebuilt when read again
    with pytest.raises(ValueError, match="tracer holds"):
        auto_camera(box, 32, 24, tracer=Tracer(box.corners(mask)))


def test_tonemap():
    img = np.zeros((10, 10, 3), np.float32)
    img[:5] = 2.0
    out = tonemap(img)
    assert out.dtype == np.uint8 and out.shape == (10, 10, 3)
    assert np.all(out[5:] == 0)
    expect = round((1.055 * 0.9 ** (1 / 2.4) - 0.055) * 255)
    assert np.all(out[:5] == expect)
    assert np.all(tonemap(img, exposure=10.0)[:5] == 255)
    assert np.all(tonemap(np.zeros((2, 2, 3))) == 0)


def test_png_exr_roundtrip(tmp_path):
    import OpenImageIO as oiio

    rng = np.random.default_rng(1)
    u8 = rng.integers(0, 256, (7, 11, 3), dtype=np.uint8)
    write_png(tmp_path / "a" / "x.png", u8)
    back = oiio.ImageBuf(str(tmp_path / "a" / "x.png")).get_pixels(oiio.UINT8)
    assert np.array_equal(back, u8)
    f = (rng.random((7, 11, 3)) * 100).astype(np.float32)
    write_exr(tmp_path / "x.exr", f)
    back = oiio.ImageBuf(str(tmp_path / "x.exr")).get_pixels(oiio.FLOAT)
    assert back.shape == f.shape
    assert np.allclose(back, f, rtol=1e-3, atol=1e-4)
    write_exr(tmp_path / "y.exr", f, half=False)
    assert np.array_equal(oiio.ImageBuf(str(tmp_path / "y.exr")).get_pixels(oiio.FLOAT), f)
    with pytest.raises(OSError, match="nope"):
        write_png(tmp_path / "nope.unknownext", u8)


def test_ply_face_radiosity_roundtrip(tmp_path, scene):
    import trimesh

    write_patches_ply(tmp_path / "p.ply", scene)
    assert open(tmp_path / "p.ply", "rb").read(40).startswith(b"ply\nformat binary_little_endian")
    m = trimesh.load(tmp_path / "p.ply", process=False)
    assert np.array_equal(m.faces, scene.faces)
    assert np.allclose(m.vertices, scene.vertices, atol=1e-6)
    data = m.metadata["_ply_raw"]["face"]["data"]
    got = np.column_stack([data[f"radiosity_{c}"] for c in "rgb"])
    assert np.allclose(got, scene.radiosity, rtol=1e-6)
    assert np.array_equal(data["source"], scene.source)
    write_patches_ply(tmp_path / "d.ply", scene, dtype=np.float64)
    data = trimesh.load(tmp_path / "d.ply", process=False).metadata["_ply_raw"]["face"]["data"]
    assert np.array_equal(np.column_stack([data[f"radiosity_{c}"] for c in "rgb"]), scene.radiosity)


def test_glb_has_vertex_colours(tmp_path, scene):
    import trimesh

    cv = corner_radiosity(scene)
    write_glb(tmp_path / "s.glb", scene, cv)
    write_glb(tmp_path / "lit.glb", scene, cv, unlit=False)
    lit = trimesh.load(tmp_path / "lit.glb", process=False)
    (g,) = lit.geometry.values()
    assert g.visual.kind == "vertex"
    lit_col = np.asarray(g.visual.vertex_colors)
    loaded = trimesh.load(tmp_path / "s.glb", process=False)
    (g,) = loaded.geometry.values()
    assert len(g.faces) == len(scene) and len(g.vertices) == 3 * len(scene)
    assert np.allclose(g.vertices, scene.triangles.reshape(-1, 3), atol=1e-6)
    col = np.asarray(g.visual.vertex_attributes["color"])  # unlit material: kept here
    assert np.array_equal(col, lit_col)
    assert col.shape == (3 * len(scene), 4) and col.dtype == np.uint8
    assert col[:, :3].max() > 0 and np.all(col[:, 3] == 255)
    # the wall with B = (100, 0, 0) is pure red
    assert np.all(col[24:30, 1:3] == 0) and np.all(col[24:30, 0] > 0)
    raw = open(tmp_path / "s.glb", "rb").read()
    assert b"KHR_materials_unlit" in raw


def _glb_parts(data: bytes):
    """(JSON tree, binary chunk) of a GLB file's bytes."""
    import json
    import struct

    magic, version, length, clen, ctype = struct.unpack("<5I", data[:20])
    assert (magic, version, length, ctype) == (0x46546C67, 2, len(data), 0x4E4F534A)
    blen, btype = struct.unpack("<2I", data[20 + clen:28 + clen])
    assert btype == 0x004E4942 and 28 + clen + blen == len(data)
    return json.loads(data[20:20 + clen]), data[28 + clen:]


@pytest.mark.parametrize("unlit", [True, False])
def test_glb_is_what_trimesh_exports_for_the_same_mesh(tmp_path, scene, unlit, monkeypatch):
    """write_glb streams its buffers in chunks; the file must be the one trimesh's exporter
    writes for the same mesh and colours (but the generator), chunk boundaries anywhere."""
    import trimesh

    import dcrad.io.export as export

    monkeypatch.setattr(export, "GLB_CHUNK", 7)  # 54 corners: 8 chunks, the last one short
    rot = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # Y up to Z up
    cv = corner_radiosity(scene).astype(np.float32)
    exposure = write_glb(tmp_path / "s.glb", scene, cv, unlit=unlit, rotation=rot)
    lin = cv.reshape(-1, 3).astype(np.float64) / math.pi
    lum = lin @ [0.2126, 0.7152, 0.0722]
    assert exposure == pytest.approx(0.9 / np.percentile(lum[lum > 0], 99.0), rel=1e-12)
    rgba = np.full((len(lin), 4), 255, np.uint8)
    rgba[:, :3] = tonemap(lin, exposure=exposure, srgb=False)
    mesh = trimesh.Trimesh(vertices=scene.triangles.reshape(-1, 3) @ rot, faces=np.arange(len(lin)).reshape(-1, 3),
                           vertex_colors=rgba, process=False, validate=False)

    def unlit_material(tree):
        tree["materials"] = [{"name": "radiosity", "pbrMetallicRoughness": {
            "baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0},
            "doubleSided": False, "extensions": {"KHR_materials_unlit": {}}}]
        tree["extensionsUsed"] = ["KHR_materials_unlit"]
        for prim in tree["meshes"][0]["primitives"]:
            prim["material"] = 0

    ref = trimesh.exchange.gltf.export_glb(trimesh.Scene(mesh), include_normals=False,
                                           tree_postprocessor=unlit_material if unlit else None)
    tree, binary = _glb_parts((tmp_path / "s.glb").read_bytes())
    ref_tree, ref_binary = _glb_parts(ref)
    assert tree["asset"].pop("generator") == "dcrad"
    ref_tree["asset"].pop("generator")
    assert tree == ref_tree
    assert binary == ref_binary


def test_npz_area_weighted_per_input_triangle(tmp_path):
    # input triangle 0 -> 3 patches of areas 0.5, 0.25, 0.25; triangle 1 -> 1 patch;
    # triangle 2 dropped (no patch)
    t = [
        [(0, 0, 0), (1, 0, 0), (0, 1, 0)],
        [(0, 0, 0), (0.5, 0, 0), (0, 1, 0)],
        [(0, 0, 0), (0.5, 0, 0), (0, 0.5, 0)],
        [(2, 0, 0), (3, 0, 0), (2, 1, 0)],
    ]
    p = _table(t, [[1.0, 2, 3], [4.0, 5, 6], [7.0, 8, 9], [10.0, 10, 10]], source=[0, 0, 0, 1])
    assert np.allclose(p.area[:3], [0.5, 0.25, 0.125])
    write_radiosity_npz(tmp_path / "r.npz", p, 3, {"iterations": np.arange(3), "E": np.ones(2)})
    z = np.load(tmp_path / "r.npz")
    w = p.area[:3]
    expect0 = (w[:, None] * p.radiosity[:3]).sum(0) / w.sum()
    assert np.allclose(z["B"][0], expect0)
    assert np.allclose(z["B"][1], 10.0) and np.all(z["B"][2] == 0)
    assert z["valid"].tolist() == [True, True, False]
    for k in ("patch_B", "patch_unshot", "patch_area", "patch_source", "patch_rho", "patch_emission"):
        assert len(z[k]) == 4
    assert np.array_equal(z["iterations"], np.arange(3))
    bad = _table(t[:1], [[np.nan, 0, 0]], source=[0])
    with pytest.raises(Exception, match="non-finite"):
        write_radiosity_npz(tmp_path / "bad.npz", bad, 1, {})
    assert not (tmp_path / "bad.npz").exists()
    with pytest.raises(ValueError):
        write_radiosity_npz(tmp_path / "c.npz", p, 3, {"B": np.zeros(1)})
    b, valid = input_triangle_radiosity(p, 3)
    assert np.allclose(b, z["B"]) and np.array_equal(valid, z["valid"])


def test_corner_radiosity_matches_brute_force():
    rng = np.random.default_rng(3)
    # a bumpy height field on a 6x6 grid (shared vertices), some faces flipped
    g = np.stack(np.meshgrid(np.arange(6.0), np.arange(6.0), indexing="ij"), -1).reshape(-1, 2)
    verts = np.column_stack([g[:, 0], rng.random(len(g)) * 1.5, g[:, 1]])
    faces = []
    for i in range(5):
        for j in range(5):
            a, b, c, d = i * 6 + j, i * 6 + j + 1, (i + 1) * 6 + j + 1, (i + 1) * 6 + j
            faces += [[a, b, c], [a, c, d]]
    faces = np.array(faces)
    flip = rng.random(len(faces)) < 0.2
    faces[flip] = faces[flip][:, ::-1]
    n = len(faces)
    p = Patches(verts, faces, 0.5, 0.0, np.arange(n), np.zeros(n, np.int32), radiosity=rng.random((n, 3)))
    cv = corner_radiosity(p, crease_angle_deg=25.0)
    cos_t = math.cos(math.radians(25.0))
    tri, nrm, area = p.triangles, p.normal, p.area
    for q in range(n):  # reference: plain loops
        for k in range(3):
            num, den = np.zeros(3), 0.0
            for r in range(n):
                touches = np.any(np.all(np.isclose(tri[r], tri[q, k]), axis=1))
                d = nrm[q] @ nrm[r]
                if touches and d >= cos_t - 1e-9 and d > 0:
                    num += area[r] * p.radiosity[r]
                    den += area[r]
            assert np.allclose(cv[q, k], num / den)


# -- photometry (issue 15) --------------------------------------------------------------------
def test_lux_of_one_patch_is_the_hand_computation():
    """One patch, rho 0.5 grey, B = 10 W/m^2, E = 0: H = (B - E) / rho = 20 W/m^2, and with
    179 lm/W and Y weights summing to 1 for grey, E_v = 3580 lux; L = 179 * 10 / pi cd/m^2."""
    from dcrad.outputs import photometry

    p = Patches(vertices=[[0, 0, 0], [2, 0, 0], [0, 0, -1]], faces=[[0, 1, 2]], rho=np.full((1, 3), 0.5),
                emission=np.zeros((1, 3)), source=[0], obj=[0], names=["desk/oak"],
                radiosity=np.full((1, 3), 10.0))
    h, gathered = photometry.irradiance(p)
    np.testing.assert_allclose(h, [[20.0, 20.0, 20.0]])
    assert not gathered.any()
    lux = photometry.to_lux(h)
    np.testing.assert_allclose(lux, [3580.0])
    (entry,) = photometry.surface_stats(p, lux)
    assert entry["name"] == "desk" and entry["area_m2"] == pytest.approx(1.0)
    assert entry["E_avg_lux"] == pytest.approx(3580.0) and entry["E_min_lux"] == pytest.approx(3580.0)
    assert entry["E_max_lux"] == pytest.approx(3580.0) and entry["uniformity"] == pytest.approx(1.0)
    assert entry["L_avg_cd_m2"] == pytest.approx(179.0 * 10.0 / math.pi)
    # coloured: E_v weighs the channels by CIE Y
    p.radiosity = np.array([[2.0, 4.0, 8.0]])
    np.testing.assert_allclose(photometry.to_lux(photometry.irradiance(p)[0]),
                               [179.0 * (0.2126 * 4 + 0.7152 * 8 + 0.0722 * 16)])


def test_black_patch_and_work_plane_are_gathered_from_the_solution():
    """Closed box whose every wall has B = 3 W/m^2: whatever direction a gather ray takes it
    sees B = 3, so a black floor (rho 0: B says nothing) and a work plane get H = 3 exactly."""
    from dcrad.outputs import photometry

    p = _box(open_front=False)
    rho = np.full((12, 3), 0.5)
    rho[:2] = 0.0  # the floor
    p = Patches(vertices=p.vertices, faces=p.faces[:-2], rho=rho, emission=np.zeros((12, 3)),
                source=np.arange(12), obj=np.repeat(np.arange(6), 2), names=[f"default/w{i}" for i in range(6)],
                radiosity=np.full((12, 3), 3.0))
    h, gathered = photometry.irradiance(p)
    assert gathered.tolist() == [True, True] + [False] * 10
    np.testing.assert_allclose(h[:2], 3.0, rtol=1e-12)
    np.testing.assert_allclose(h[2:], 6.0)  # (B - E) / rho
    wp = photometry.workplane(p, 0.5, spacing=0.25)
    assert wp["n_points"] == 16
    np.testing.assert_allclose(wp["lux"], 179.0 * 3.0, rtol=1e-12)
    assert wp["uniformity"] == pytest.approx(1.0)
    names = [e["name"] for e in photometry.surface_stats(p, photometry.to_lux(h))]
    assert names == [f"w{i}" for i in range(6)]  # unnamed objects: by material


def test_false_colour_image_has_its_legend():
    from dcrad.outputs import photometry
    from dcrad.outputs.render import tonemap

    h, w = 120, 160
    value = np.full((h, w), 250.0)
    front = np.ones((h, w))
    front[:, :20] = 0.0  # nothing there: black
    img = photometry.false_colour(value, front, np.zeros((h, w)), top=500.0, legend_width=110)
    assert img.shape == (h, w + 110, 3) and img.dtype == np.uint8
    enc = lambda c: tonemap(np.asarray(c, np.float64)[None], exposure=1.0)[0]  # noqa: E731
    assert np.all(img[60, 80] == enc(photometry.colour_map(0.5)))
    assert np.all(img[60, 5] == 0)
    bar = img[:, w + 10 : w + 34]
    assert np.abs(bar[20, 12].astype(int) - enc(photometry.colour_map(1.0))).max() <= 3  # top: 500
    assert np.abs(bar[h - 21, 12].astype(int) - enc(photometry.colour_map(0.0))).max() <= 3  # bottom: 0
    labels = img[:, w + 40 :]
    bright = labels.min(axis=2) > 200  # white text
    rows = np.flatnonzero(bright.any(axis=1))
    assert len(rows) > 20 and rows.min() < 30 and rows.max() > h - 30  # labels at top and bottom ticks
    assert photometry.legend_scale(np.array([10.0, 420.0]), np.ones(2)) == 500.0


def test_tonemap_shoulder_rolls_highlights_off():
    from dcrad.outputs.render import SHOULDER

    lum = np.array([0.1, 0.5, 0.79, 0.9, 1.0, 2.0, 8.0])
    img = np.repeat(lum[:, None], 3, axis=1)
    hard = tonemap(img, exposure=1.0, srgb=False)[:, 0]
    soft = tonemap(img, exposure=1.0, srgb=False, shoulder=SHOULDER)[:, 0]
    assert np.all(soft[:3] == hard[:3])  # below the knee: unchanged
    assert np.all(np.diff(soft.astype(int)) > 0)  # still increasing past white: no clipping plateau
    assert hard[4] == hard[5] == hard[6] == 255 and soft[5] < 255
    # colour ratios are kept on the shoulder
    c = tonemap(np.array([[2.0, 1.0, 0.5]]), exposure=1.0, srgb=False, shoulder=SHOULDER)[0].astype(float)
    assert c[0] == 255 or abs(c[1] / c[2] - 2.0) < 0.05


def test_two_sided_statistics_count_the_lit_side_whatever_the_winding():
    from dcrad.outputs import photometry

    # two floor triangles, the second wound downward; each has a back twin (after the fronts)
    v = [[0, 0, 0], [0, 0, 1], [1, 0, 1], [1, 0, 0]]
    f = [[0, 1, 2], [0, 3, 2], [0, 2, 1], [0, 2, 3]]  # up, down, then their reversed twins
    p = Patches(vertices=v, faces=f, rho=np.full((4, 3), 0.5), emission=np.zeros((4, 3)), source=[0, 1, 0, 1],
                obj=[0, 0, 0, 0], names=["floor/grey"], twin=[2, 3, 0, 1])
    assert p.normal[0, 1] > 0 and p.normal[1, 1] < 0 and p.is_back.tolist() == [False, False, True, True]
    lux = np.array([300.0, 0.0, 0.0, 300.0])  # lit from above: the up-facing side of each
    entries = {e["name"]: e for e in photometry.surface_stats(p, lux)}
    assert entries["floor"]["E_min_lux"] == 300.0 and entries["floor"]["uniformity"] == 1.0
    assert entries["floor (other side)"]["E_max_lux"] == 0.0


def test_corner_smoother_kept_pairs_equal_pairs_formed_per_call():
    """The smoother's pairs kept (in chunks of any size) or formed again at each apply give the same
    corners, for any channels; corner_radiosity (checked against plain loops above) is its apply."""
    rng = np.random.default_rng(5)
    box = _box(open_front=False)
    values = rng.random((len(box), 6))
    kept = CornerSmoother(box, max_pairs=7)
    formed = CornerSmoother(box, keep_pairs=0)
    assert kept._chunks is not None and formed._chunks is None
    a, b = kept.apply(values), formed.apply(values)
    assert np.allclose(a, b, rtol=1e-13, atol=0)
    assert np.allclose(a[..., :3], corner_radiosity(box, values=values[:, :3]), rtol=1e-13, atol=0)
    assert kept.apply(values[:, 0], dtype=np.float32).shape == (len(box), 3, 1)
    partly = CornerSmoother(box, max_pairs=7, keep_pairs=0)  # a views process keeping its pairs
    stop = threading.Event()
    stop.set()
    partly.keep(stop)
    assert partly._chunks == []  # stopped before the first chunk
    partly._chunks = kept._chunks[:3]  # stopped after three: apply forms the rest, the same numbers
    assert partly.apply(values).tobytes() == kept.apply(values).tobytes()
    partly.keep()
    assert len(partly._chunks) == len(kept._chunks) == len(partly.bounds) - 1
    assert partly.apply(values).tobytes() == kept.apply(values).tobytes()
    # the false colour's coverage channels (means of ones and zeros) without summing them: the same bits
    appended = kept.apply(np.column_stack([values[:, :4], np.ones(len(box)), np.zeros(len(box))]), np.float32)
    assert kept.apply(values[:, :4], np.float32, coverage=True).tobytes() == appended.tobytes()
    assert formed.apply(values[:, :4], np.float32, coverage=True).tobytes() == appended.tobytes()
    rows = np.arange(0, len(box), 3)  # some patches' corners only (a live preview's visible ones)
    some = CornerSmoother(box, rows=rows).apply(values)
    assert np.allclose(some[rows], a[rows], rtol=1e-13, atol=0)
    rest = np.setdiff1d(np.arange(len(box)), rows)
    assert np.array_equal(some[rest], np.broadcast_to(values[rest, None, :], some[rest].shape))


def test_a_traced_view_shades_any_values_like_a_render():
    """A view traced once (trace_view) and shaded many times (shade_view) gives each time what a
    render of those values gives; shading is linear in the corner values."""
    rng = np.random.default_rng(6)
    box = _box(open_front=False)
    cam = auto_camera(box, 32, 24)
    mask = cutaway_mask(box)
    top = topdown_camera(box, 32, 32)
    front = trace_view(box, cam, samples=4)
    above = trace_view(box, top, mask=mask, samples=4)
    black = np.zeros(3)
    for _ in range(2):
        v1, v2 = rng.random((len(box), 3)), rng.random((len(box), 3))
        c1, c2 = corner_radiosity(box, values=v1), corner_radiosity(box, values=v2)
        assert np.allclose(shade_view(front, c1), render(box, cam, corner_values=c1, samples=4), atol=1e-6)
        assert np.allclose(shade_view(above, c2), render(box, top, mask=mask, corner_values=c2, samples=4), atol=1e-6)
        parts = shade_view(front, c1, backface_color=black) + shade_view(front, c2, backface_color=black)
        assert np.allclose(shade_view(front, c1 + c2, backface_color=black), parts, rtol=1e-5, atol=1e-6)
