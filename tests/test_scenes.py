"""Tests for the built-in scene generators in the ``scenes`` package."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh
from trimesh.exchange.obj import parse_mtl

import scenes
from scenes.cornell import cornell_box
from scenes.furnace import furnace_box, furnace_expected
from scenes.objwriter import ObjWriter
from scenes.office import office_floor, room_rect

UP = np.array([0.0, 1.0, 0.0])


# -- helpers -------------------------------------------------------------------------
def read_obj(path):
    """Tiny OBJ reader: {object name: (material, (n, 3, 3) triangles)} in file order."""
    verts, objs, name, libs = [], {}, None, []
    for line in path.read_text().splitlines():
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        if parts[0] == "mtllib":
            libs.append(parts[1])
        elif parts[0] == "v":
            verts.append([float(x) for x in parts[1:4]])
        elif parts[0] == "o":
            name = parts[1]
            assert name not in objs, f"duplicate object {name}"
            objs[name] = [None, []]
        elif parts[0] == "usemtl":
            objs[name][0] = parts[1]
        elif parts[0] == "f":
            assert len(parts) == 4, "triangles only"
            assert name is not None and objs[name][0] is not None, "face before o/usemtl"
            objs[name][1].append([int(k) - 1 for k in parts[1:]])
    assert libs == [path.stem + ".mtl"]
    v = np.array(verts)
    return {k: (m, v[np.array(f, dtype=np.int64)]) for k, (m, f) in objs.items()}


def normals(tri):
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def all_tris(objs):
    return np.concatenate([t for _, t in objs.values()])


def load_mtl(path):
    mats = parse_mtl(path.with_suffix(".mtl").read_text())
    for name, m in mats.items():
        kd = np.asarray(m["kd"], float)
        assert kd.shape == (3,) and np.all(kd >= 0) and np.all(kd < 1), (name, kd)
    return mats


def ke(mat):
    return np.array([float(x) for x in mat["ke"]]) if "ke" in mat else np.zeros(3)


def common_checks(path):
    """Geometry sanity shared by every scene; returns (objects, materials)."""
    objs = read_obj(path)
    mats = load_mtl(path)
    tri = all_tris(objs)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    assert area.min() > 1e-6, "degenerate triangle"
    unique = {tuple(sorted(map(tuple, t))) for t in np.round(tri, 6).tolist()}
    assert len(unique) == len(tri), "duplicate triangle"
    mesh = trimesh.load(path, force="mesh")
    assert len(mesh.faces) == len(tri)
    assert not np.any(mesh.area_faces <= 1e-9)
    assert {m for m, _ in objs.values()} <= set(mats)
    for name, (m, t) in objs.items():
        if name.startswith("light"):
            assert np.all(ke(mats[m]) > 0), name
            assert np.allclose(normals(t), -UP), f"{name} must face down"
        else:
            assert np.all(ke(mats[m]) == 0), name
    return objs, mats


def first_hits(tri, origins, dirs, eps=1e-9):
    """Brute-force Moeller-Trumbore: (t, face index) of the nearest hit, inf/-1 if none."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(dirs[:, None, :], e2[None])
    det = np.einsum("tj,rtj->rt", e1, p)
    det = np.where(np.abs(det) < 1e-14, np.nan, det)
    s = origins[:, None, :] - tri[None, :, 0]
    u = np.einsum("rtj,rtj->rt", s, p) / det
    q = np.cross(s, e1[None])
    v = np.einsum("rj,rtj->rt", dirs, q) / det
    t = np.einsum("tj,rtj->rt", e2, q) / det
    ok = (u >= -eps) & (v >= -eps) & (u + v <= 1 + eps) & (t > 1e-7)
    t = np.where(ok, t, np.inf)
    idx = np.argmin(t, axis=1)
    best = t[np.arange(len(t)), idx]
    return best, np.where(np.isfinite(best), idx, -1)


# -- registry ------------------------------------------------------------------------
def test_registry(tmp_path):
    assert scenes.names() == ["cie_room", "cornell", "furnace", "office"]
    for name in scenes.names():
        assert scenes.describe(name)
        path = scenes.write_builtin(name, tmp_path / "sub")
        assert path == tmp_path / "sub" / f"{name}.obj" and path.with_suffix(".mtl").exists()
    with pytest.raises(ValueError, match="cie_room, cornell, furnace, office"):
        scenes.write_builtin("nope", tmp_path)
    with pytest.raises(ValueError):
        scenes.describe("nope")


def test_writer_rejects_bad_input():
    w = ObjWriter()
    with pytest.raises(ValueError):
        w.material("bad", 1.0)
    w.material("m", 0.5)
    w.begin("a", "m")
    with pytest.raises(ValueError):
        w.add_tri((0, 0, 0), (1, 0, 0), (2, 0, 0))
    with pytest.raises(ValueError):
        w.begin("a", "m")
    w.add_box((0, 0, 0), (1, 2, 3), outward=False, skip_faces=("top",))
    assert w.triangle_count == 10


# -- Cornell box ---------------------------------------------------------------------
def test_cornell(tmp_path):
    path = cornell_box(tmp_path, light_exitance=(40, 30, 20))
    objs, mats = common_checks(path)
    assert set(objs) == {"floor", "ceiling", "back_wall", "left_wall", "right_wall",
                         "short_block", "tall_block", "light"}
    centre = np.array([0.278, 0.274, 0.280])
    for name in ("floor", "ceiling", "back_wall", "left_wall", "right_wall"):
        t = objs[name][1]
        assert np.all(np.einsum("ij,ij->i", normals(t), centre - t.mean(axis=1)) > 0), name
    assert np.all(normals(objs["floor"][1])[:, 1] > 0.999)
    assert np.all(normals(objs["ceiling"][1])[:, 1] < -0.999)
    for name in ("short_block", "tall_block"):
        t = objs[name][1]
        assert len(t) == 10  # top + 4 sides, no bottom
        mid = t.reshape(-1, 3).mean(axis=0)
        assert np.all(np.einsum("ij,ij->i", normals(t), t.mean(axis=1) - mid) > 0), name
    light = objs["light"][1]
    assert np.allclose(light[..., 1], 0.5478) and np.all(light[..., 1] < 0.5488)
    assert np.allclose(ke(mats[objs["light"][0]]), (40, 30, 20))
    assert np.allclose(mats[objs["light"][0]]["kd"], 0.78)
    assert np.allclose(mats[objs["left_wall"][0]]["kd"], (0.63, 0.065, 0.05))
    assert np.allclose(mats[objs["right_wall"][0]]["kd"], (0.14, 0.45, 0.09))
    # open front: nothing at z = 0 except the floor/ceiling/wall edges
    tri = all_tris(objs)
    assert not np.any(np.all(np.abs(tri[..., 2]) < 1e-9, axis=1))


# -- furnace -------------------------------------------------------------------------
@pytest.mark.parametrize("lf,size", [(0.2, 1.0), (0.5, 2.5), (1.0, 1.0)])
def test_furnace(tmp_path, lf, size):
    path = furnace_box(tmp_path, rho=0.6, size=size, emission=2.0, light_fraction=lf)
    objs, mats = common_checks(path)
    mesh = trimesh.load(path, force="mesh")
    mesh.merge_vertices()
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume < 0 and math.isclose(-mesh.volume, size**3, rel_tol=1e-9)
    tri = all_tris(objs)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    lt = objs["light"][1]
    light_area = 0.5 * np.linalg.norm(np.cross(lt[:, 1] - lt[:, 0], lt[:, 2] - lt[:, 0]), axis=1).sum()
    exp = furnace_expected(rho=0.6, size=size, emission=2.0, light_fraction=lf)
    assert math.isclose(area.sum(), exp["total_area"], rel_tol=1e-9)
    assert math.isclose(light_area, exp["light_area"], rel_tol=1e-9)
    assert math.isclose(exp["emitted_power"], 2.0 * lf * size**2)
    assert math.isclose(exp["mean_b_minus_e"], 0.6 * exp["emitted_power"] / (0.4 * 6 * size**2))
    for m in mats.values():
        assert np.allclose(m["kd"], 0.6)
    assert np.allclose(ke(mats[objs["light"][0]]), 2.0)


def test_furnace_rgb(tmp_path):
    path = furnace_box(tmp_path, rho=(0.2, 0.5, 0.8), emission=(1, 2, 3), grey=False)
    objs, mats = common_checks(path)
    assert np.allclose(mats[objs["floor"][0]]["kd"], (0.2, 0.5, 0.8))
    exp = furnace_expected(rho=(0.2, 0.5, 0.8), emission=(1, 2, 3))
    rho = np.array([0.2, 0.5, 0.8])
    assert np.allclose(exp["mean_b_minus_e"], rho * [1, 2, 3] * 0.2 / ((1 - rho) * 6))
    with pytest.raises(ValueError):
        furnace_box(tmp_path, rho=(0.2, 0.5, 0.8))
    with pytest.raises(ValueError):
        furnace_box(tmp_path, rho=1.0)


# -- office --------------------------------------------------------------------------
def furniture_boxes(objs):
    out = []
    for name, (_, t) in objs.items():
        if name.startswith(("desk_", "cabinet_")):
            pts = t.reshape(-1, 3)
            out.append((pts.min(axis=0), pts.max(axis=0)))
    return out


@pytest.mark.parametrize("rows,cols,seed", [(2, 3, 0), (3, 2, 7), (1, 1, 1)])
def test_office_closed(tmp_path, rows, cols, seed):
    path = office_floor(tmp_path, rows=rows, cols=cols, seed=seed)
    objs, mats = common_checks(path)
    tri = all_tris(objs)
    if (rows, cols) == (2, 3):
        assert 200 <= len(tri) <= 500
    n_walls = rows * (cols - 1) + (rows - 1) * cols
    assert sum(n.startswith("lintel_") for n in objs) == n_walls
    n_lit = max(1, math.ceil(0.5 * rows * cols))
    assert len({n.rsplit("_", 1)[0] for n in objs if n.startswith("light_")}) == n_lit
    boxes = furniture_boxes(objs)
    assert len(boxes) >= rows * cols
    for name, (_, t) in objs.items():
        if name.startswith(("desk_", "cabinet_")):
            assert len(t) == 10 and np.min(t[..., 1]) == 0.0  # on the floor, no bottom
            mid = t.reshape(-1, 3).mean(axis=0)
            assert np.all(np.einsum("ij,ij->i", normals(t), t.mean(axis=1) - mid) > 0), name
    # reflectances
    for name, (m, _) in objs.items():
        kd = np.asarray(mats[m]["kd"])
        if name.startswith(("desk_", "cabinet_")):
            assert np.all((kd >= 0.2) & (kd <= 0.6)), name
    # closedness: random rays from inside rooms all hit a front face
    rng = np.random.default_rng(123)
    n = 3000
    rooms = np.array([room_rect(i, j) for i in range(rows) for j in range(cols)])
    r = rooms[rng.integers(len(rooms), size=4 * n)]
    pts = np.column_stack([
        rng.uniform(r[:, 0] + 0.02, r[:, 2] - 0.02),
        rng.uniform(0.02, 2.8 - 0.05, 4 * n),
        rng.uniform(r[:, 1] + 0.02, r[:, 3] - 0.02),
    ])
    inside = np.zeros(len(pts), bool)
    for lo, hi in boxes:
        inside |= np.all((pts > lo - 0.01) & (pts < hi + 0.01), axis=1)
    pts = pts[~inside][:n]
    assert len(pts) == n
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for k in range(0, n, 500):
        t, idx = first_hits(tri, pts[k:k + 500], d[k:k + 500])
        assert np.all(idx >= 0), "ray escaped the office"
        assert np.all(np.einsum("ij,ij->i", d[k:k + 500], normals(tri[idx])) < 0), "hit a back face"
    # every door is open: a horizontal ray through each opening crosses the wall
    for name, (_, t) in objs.items():
        if name.startswith("lintel_"):
            lo, hi = t.reshape(-1, 3).min(axis=0), t.reshape(-1, 3).max(axis=0)
            assert math.isclose(lo[1], 2.1) and math.isclose(hi[1], 2.8)
            axis = 2 if name.startswith("lintel_h") else 0  # crossing direction
            o = (lo + hi) / 2
            o[1] = 1.0
            o[axis] = lo[axis] - 0.5
            dirn = np.zeros(3)
            dirn[axis] = 1.0
            dist, _ = first_hits(tri, o[None], dirn[None])
            assert dist[0] > 0.5 + 0.12 + 0.9, name


def footprint(t):
    """(x0, z0, x1, z1) bounding rectangle of triangles, seen from above."""
    pts = t.reshape(-1, 3)
    return (pts[:, 0].min(), pts[:, 2].min(), pts[:, 0].max(), pts[:, 2].max())


def tri_area(t):
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum()


def tri_enters_rect(tri, rect, eps=1e-9):
    """True if the triangle, seen from above, has a point strictly inside the open
    rectangle (x0, z0, x1, z1) (separating-axis test on the xz projection)."""
    poly = [np.array([x0, z0]) for x0, z0 in ((rect[0], rect[1]), (rect[2], rect[1]),
                                               (rect[2], rect[3]), (rect[0], rect[3]))]
    t2 = tri[:, [0, 2]]
    axes = [np.array([1.0, 0.0]), np.array([0.0, 1.0])]
    axes += [np.array([-e[1], e[0]]) for e in (t2[1] - t2[0], t2[2] - t2[1], t2[0] - t2[2])]
    for ax in axes:
        ax = ax / np.linalg.norm(ax)
        a, b = t2 @ ax, np.array(poly) @ ax
        if a.max() <= b.min() + eps or b.max() <= a.min() + eps:
            return False  # separated (touching edges do not count)
    return True


@pytest.mark.parametrize("kw", [dict(rows=2, cols=3, seed=0), dict(rows=3, cols=2, seed=7),
                                dict(rows=1, cols=1, seed=1),
                                dict(rows=3, cols=3, seed=4, room=3.3, wall=0.2, door_width=1.0)])
def test_office_floor_ceiling_split(tmp_path, kw):
    """Floors and ceilings are per room (+ doorway strips): nothing under/over a wall."""
    rows, cols = kw["rows"], kw["cols"]
    room, wall, dw = kw.get("room", 4.0), kw.get("wall", 0.12), kw.get("door_width", 0.9)
    height = 2.8
    path = office_floor(tmp_path, **kw)
    objs, _ = common_checks(path)
    flat = {n: t for n, (m, t) in objs.items() if m in ("floor", "ceiling")}
    assert "floor" not in objs and "ceiling" not in objs  # no building-wide quads any more
    walls = sorted(n[len("wall_"):] for n in objs if n.startswith("wall_"))
    rooms = [(i, j) for i in range(rows) for j in range(cols)]
    expected = {f"room_{i}_{j}_{s}" for i, j in rooms for s in ("floor", "ceiling")}
    expected |= {f"door_{w}_floor" for w in walls}
    assert set(flat) == expected
    assert len(walls) == rows * (cols - 1) + (rows - 1) * cols
    # each room: its own floor (+Y, y = 0) and ceiling (-Y, y = height) covering exactly its free area
    for i, j in rooms:
        rect = room_rect(i, j, room, wall)
        for s, y, up in (("floor", 0.0, 1), ("ceiling", height, -1)):
            t = flat[f"room_{i}_{j}_{s}"]
            assert objs[f"room_{i}_{j}_{s}"][0] == s
            assert np.allclose(t[..., 1], y) and np.allclose(normals(t), up * UP)
            assert np.allclose(footprint(t), rect, atol=1e-9)
            assert math.isclose(tri_area(t), room * room, rel_tol=1e-9)
    # each doorway: a floor strip (door width x wall thickness) exactly under the lintel,
    # whose underside is the doorway's ceiling; its long edges are the adjacent rooms' edges
    for wname in walls:
        kind, i, j = wname.split("_")
        i, j = int(i), int(j)
        t = flat[f"door_{wname}_floor"]
        assert objs[f"door_{wname}_floor"][0] == "floor"
        assert np.allclose(t[..., 1], 0.0) and np.allclose(normals(t), UP)
        assert math.isclose(tri_area(t), dw * wall, rel_tol=1e-9)
        fp = footprint(t)
        lintel = objs[f"lintel_{wname}"][1]
        under = lintel[np.all(np.isclose(lintel[..., 1], 2.1), axis=1)]
        assert np.allclose(normals(under), -UP) and np.allclose(footprint(under), fp, atol=1e-9)
        ra, rb = room_rect(i - (kind == "h"), j - (kind == "v"), room, wall), room_rect(i, j, room, wall)
        if kind == "h":  # between rooms (i-1, j) and (i, j), along X
            assert math.isclose(fp[1], ra[3], abs_tol=1e-9) and math.isclose(fp[3], rb[1], abs_tol=1e-9)
            assert rb[0] < fp[0] < fp[2] < rb[2] and math.isclose(fp[2] - fp[0], dw)
        else:
            assert math.isclose(fp[0], ra[2], abs_tol=1e-9) and math.isclose(fp[2], rb[0], abs_tol=1e-9)
            assert rb[1] < fp[1] < fp[3] < rb[3] and math.isclose(fp[3] - fp[1], dw)
    # no floor/ceiling triangle has a point strictly inside an interior wall's solid footprint
    # (wall box minus its door opening) or a wall junction, and the pieces do not overlap
    solid = []
    for wname in walls:
        wx0, wz0, wx1, wz1 = footprint(objs[f"wall_{wname}"][1])
        lx0, lz0, lx1, lz1 = footprint(objs[f"lintel_{wname}"][1])
        if wname.startswith("h"):
            solid += [(wx0, wz0, lx0, wz1), (lx1, wz0, wx1, wz1)]
        else:
            solid += [(wx0, wz0, wx1, lz0), (wx0, lz1, wx1, wz1)]
    p_ = room + wall
    solid += [(j * p_ - wall, i * p_ - wall, j * p_, i * p_) for i in range(1, rows) for j in range(1, cols)]
    pieces = {n: footprint(t) for n, t in flat.items() if not n.endswith("_ceiling")}
    for name, t in flat.items():
        for tri in t:
            for rect in solid:
                assert not tri_enters_rect(tri, rect), (name, rect)
            for other, rect in pieces.items():
                if other != name and other != name.replace("_ceiling", "_floor"):
                    assert not tri_enters_rect(tri, rect), (name, other)
    # rays from inside each doorway (between the jambs, under the lintel) all hit a front face
    if not walls:
        return
    tri = all_tris(objs)
    rng = np.random.default_rng(5)
    fps = np.array([footprint(flat[f"door_{w}_floor"]) for w in walls])
    f = fps[rng.integers(len(fps), size=400)]
    pts = np.column_stack([rng.uniform(f[:, 0] + 1e-3, f[:, 2] - 1e-3), rng.uniform(0.02, 2.08, 400),
                           rng.uniform(f[:, 1] + 1e-3, f[:, 3] - 1e-3)])
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    _, idx = first_hits(tri, pts, d)
    assert np.all(idx >= 0), "ray escaped through a doorway"
    assert np.all(np.einsum("ij,ij->i", d, normals(tri[idx])) < 0), "hit a back face"


def test_office_lit_fraction_and_validation(tmp_path):
    objs = read_obj(office_floor(tmp_path, lit_fraction=0.0))
    assert len({n.rsplit("_", 1)[0] for n in objs if n.startswith("light_")}) == 1
    objs = read_obj(office_floor(tmp_path, lit_fraction=1.0))
    assert len({n.rsplit("_", 1)[0] for n in objs if n.startswith("light_")}) == 6
    with pytest.raises(ValueError):
        office_floor(tmp_path, door_height=3.0)


def test_office_determinism(tmp_path):
    a = office_floor(tmp_path / "a", seed=5)
    b = office_floor(tmp_path / "b", seed=5)
    c = office_floor(tmp_path / "c", seed=6)
    assert a.read_bytes() == b.read_bytes()
    assert a.with_suffix(".mtl").read_bytes() == b.with_suffix(".mtl").read_bytes()
    assert a.read_bytes() != c.read_bytes()
    assert cornell_box(tmp_path / "d").read_bytes() == cornell_box(tmp_path / "e").read_bytes()


# -- real-scene variants: Z-up, mixed winding, two-sided (issue 15) ---------------------------
def test_z_up_copy_solves_to_the_same_radiosity_and_floor_plan(tmp_path):
    """A Z-up copy (exact rotation) is detected, rotated back at load, and gives the Y-up
    solution bit for bit; the office copy still gets its top-down floor plan."""
    from dcrad.config import SolverConfig
    from dcrad.pipeline import solve_to
    from scenes.variants import variant

    src = scenes.write_builtin("office", tmp_path / "y", rows=1, cols=2, seed=1)
    z = variant(src, tmp_path / "z", up="z")
    cfg = SolverConfig(tol=0.05, seed=3)
    ry = solve_to(src, tmp_path / "oy", cfg)
    rz = solve_to(z, tmp_path / "oz", cfg)
    assert rz["settings"]["up"] == "z" and ry["settings"]["up"] == "y"
    assert rz["settings"]["up_source"].startswith("detected")
    by = np.load(tmp_path / "oy" / "radiosity.npz")["B"]
    bz = np.load(tmp_path / "oz" / "radiosity.npz")["B"]
    np.testing.assert_array_equal(by, bz)
    assert "preview_top_png" in rz["outputs"] and "preview_top_png" in ry["outputs"]
    # meshes are written back in the input's (Z-up) frame
    import trimesh

    ply = trimesh.load(tmp_path / "oz" / "patches.ply", process=False)
    vz = np.array([[float(t) for t in ln.split()[1:4]] for ln in z.read_text().splitlines() if ln.startswith("v ")])
    assert np.allclose(ply.bounds, [vz.min(axis=0), vz.max(axis=0)], atol=1e-5)


def test_up_override_and_bad_up(tmp_path):
    from dcrad.errors import ConfigError
    from dcrad.io.scene import load_scene
    from scenes.variants import variant

    src = scenes.write_builtin("cornell", tmp_path)
    z = variant(src, tmp_path / "z", up="-x")
    assert load_scene(z).up == "-x"
    assert load_scene(z, up="y").up == "y" and load_scene(z, up="y").up_source == "given"
    with pytest.raises(ConfigError, match="up axis"):
        load_scene(z, up="w")


@pytest.mark.parametrize("rho", [0.5, 0.8])
def test_two_sided_mixed_winding_furnace_identity(tmp_path, rho):
    """Closed cube, uniform rho, 40% of the wall triangles wound the wrong way, two-sided:
    the light inside lands on whichever side faces in; the mean reflected radiosity over
    the inward sides meets rho Phi / ((1 - rho) A) within 1% and the ledger closes (no back
    faces).  One-sided, the same model loses light and warns about flipped normals."""
    from dcrad.config import SolverConfig
    from dcrad.io.scene import load_scene
    from dcrad.solving.solver import Solver
    from scenes.variants import variant

    src = scenes.write_builtin("furnace", tmp_path, rho=rho, emission=3.0)
    mixed = variant(src, tmp_path / "m", up="y", flip=0.4, seed=2)
    one = load_scene(mixed)
    p1 = one.patches(0.2)
    s1 = Solver(p1, SolverConfig(tol=0.02, seed=5))
    s1.run()
    lost = s1.ledger.back_faces.sum() + s1.ledger.escaped.sum()  # the direct gather books its share as escaped
    assert lost > 0.2 * s1.ledger.emitted.sum()  # one-sided: light lost
    assert s1.warnings() and "flipped" in s1.warnings()[0]

    scene = load_scene(mixed, two_sided=True)
    p = scene.patches(0.2)
    assert p.is_back.sum() == len(p) // 2
    s = Solver(p, SolverConfig(tol=2e-3, seed=5))
    s.run()
    assert s.ledger.closure() < 1e-10
    # nothing meets a back face; "escaped" holds only the direct gather's noise on the total
    assert s.ledger.back_faces.sum() == 0.0 and s.ledger.escaped.sum() < 0.01 * s.ledger.emitted.sum()
    assert s.warnings() == []
    inward = p.normal @ np.array([0.5, 0.5, 0.5]) - np.einsum("ij,ij->i", p.normal, p.centroid) > 0
    exp = furnace_expected(rho, 1.0, 3.0, 0.2)["mean_b_minus_e"]
    a = p.area[inward]
    mean = ((p.radiosity - p.emission)[inward] * a[:, None]).sum(axis=0) / a.sum()
    assert np.all(np.abs(mean - exp) <= 0.01 * exp), (mean, exp)
    assert abs(a.sum() - 6.0) < 1e-9  # one inward side per triangle
    assert np.all(p.radiosity[~inward] == 0)  # the outside sees nothing


def test_two_sided_mixed_winding_divided(tmp_path):
    """The same identity when the cube is cut in two: twins survive clipping and travel with
    their subscene (the back side of a clipped piece is the nearest piece of its twin)."""
    from dcrad.config import DivideConfig, SolverConfig
    from dcrad.pipeline import solve_to
    from scenes.variants import variant

    src = scenes.write_builtin("furnace", tmp_path, rho=0.5, emission=3.0)
    mixed = variant(src, tmp_path / "m", up="y", flip=0.4, seed=2)
    r = solve_to(mixed, tmp_path / "out", SolverConfig(tol=2e-3, seed=5), patch_size=0.2,
                 divide=DivideConfig(subscenes=2), two_sided=True)
    assert r["ledger"]["closure"] < 1e-10 and sum(r["ledger"]["back_faces"]) == 0.0
    assert not any("flipped" in w for w in r["warnings"])
    z = np.load(tmp_path / "out" / "radiosity.npz")
    reflected = ((z["patch_B"] - z["patch_emission"]) * z["patch_area"][:, None]).sum(axis=0) / 6.0
    exp = furnace_expected(0.5, 1.0, 3.0, 0.2)["mean_b_minus_e"]  # only inward sides receive light
    assert np.all(np.abs(reflected - exp) <= 0.01 * exp), reflected
    assert z["B_back"].shape == z["B"].shape


def test_furnace_illuminance_meets_the_identity(tmp_path):
    """Closed cube, uniform rho: the power incident on all surfaces is Phi / (1 - rho), so the
    area-mean illuminance is 179 Y(Phi) / ((1 - rho) A) lux; photometry.irradiance recovers it
    from B as (B - E) / rho, and black patches gathered from the solution agree."""
    from dcrad.config import SolverConfig
    from dcrad.io.scene import load_scene
    from dcrad.outputs import photometry
    from dcrad.solving.solver import Solver

    rho = 0.6
    p = load_scene(scenes.write_builtin("furnace", tmp_path, rho=rho, emission=3.0)).patches(0.15)
    Solver(p, SolverConfig(tol=2e-3, seed=2)).run()
    h, gathered = photometry.irradiance(p)
    exp = furnace_expected(rho, 1.0, 3.0, 0.2)
    lux = photometry.to_lux(h)
    mean = float((lux * p.area).sum() / p.area.sum())
    assert not gathered.any()
    assert mean == pytest.approx(179.0 * exp["mean_b"], rel=5e-3)  # grey: Y(H) = H
    # the same patches treated as black (gathered from the solved B) see the same mean
    black = p.subset(np.arange(len(p)))
    black.rho = np.zeros_like(black.rho)
    hb, gb = photometry.irradiance(black, rays=64)
    assert gb.all()
    assert float((photometry.to_lux(hb) * p.area).sum() / p.area.sum()) == pytest.approx(mean, rel=0.02)


def test_auto_camera_stands_in_the_lit_room(tmp_path):
    """Two rooms, one lit: the automatic camera of the closed floor looks at the lit one."""
    from dcrad.config import SolverConfig
    from dcrad.io.scene import load_scene
    from dcrad.outputs.render import auto_camera
    from dcrad.solving.solver import Solver

    for seed in range(20):  # a seed whose two rooms differ: one lit, one dark
        path = scenes.write_builtin("office", tmp_path / str(seed), rows=1, cols=2, lit_fraction=0.5, seed=seed)
        p = load_scene(path).patches(0.5)
        lamps = p.centroid[np.any(p.emission > 0, axis=1)]
        if len(lamps) and np.ptp(np.sign(lamps[:, 0] - p.centroid[:, 0].mean())) == 0:
            break
    Solver(p, SolverConfig(tol=0.05, seed=1)).run()
    mid = 0.5 * (p.bounds[0][0] + p.bounds[1][0])
    lit_side = np.sign(lamps[0, 0] - mid)
    cam = auto_camera(p, 64, 48)
    assert np.sign(cam.eye[0] - mid) == lit_side and np.sign(cam.target[0] - mid) == lit_side


def test_detect_up_cues():
    """Lamps hang high whatever their winding; floors facing ceilings give the axis; a lone
    plane gives no evidence (Y)."""
    from dcrad.io.scene import UP_AXES, detect_up

    quad = lambda y, up: [[0, y, 0], [0, y, 1], [1, y, 1]] if up else [[0, y, 0], [1, y, 1], [0, y, 1]]  # noqa: E731
    for lamp_up in (False, True):  # a lamp at the top, facing down or (wrongly) up
        tri = np.array([quad(0.0, True), quad(1.0, False), quad(0.9, lamp_up)], np.float64)
        em = np.array([[0, 0, 0], [0, 0, 0], [5, 5, 5]], np.float64)
        for name in ("y", "z", "-x"):
            rot = np.array(UP_AXES[name], float).T  # Y-up -> a frame whose up is ``name``
            v = tri.reshape(-1, 3) @ rot.T
            got, why = detect_up(v, np.arange(9).reshape(3, 3), em)
            assert got == name, (lamp_up, name, got, why)
    plane = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    assert detect_up(plane, np.array([[0, 1, 2]]))[0] == "y"
    room = np.array([quad(0.0, True), quad(1.0, False), quad(0.2, True)], np.float64)  # a table, low
    v = room.reshape(-1, 3) @ np.array(UP_AXES["z"], float)
    assert detect_up(v, np.arange(9).reshape(3, 3))[0] == "z"


def test_planes_are_given_in_the_files_frame(tmp_path):
    """--planes for a Z-up file name its own axes: z=4.06 in the Y-up office is y=-4.06 in the
    Z-up copy, and the two divided solves agree bit for bit."""
    from dcrad.config import DivideConfig, SolverConfig
    from dcrad.pipeline import solve_to
    from scenes.variants import variant

    src = scenes.write_builtin("office", tmp_path / "y", rows=2, cols=1, seed=1)
    z = variant(src, tmp_path / "z", up="z")
    cfg, div = SolverConfig(tol=0.05, seed=3), DivideConfig(subscenes=2, iterations=4)
    ry = solve_to(src, tmp_path / "oy", cfg, divide=div, planes=[(2, 4.06)])
    rz = solve_to(z, tmp_path / "oz", cfg, divide=div, planes=[(1, -4.06)])
    assert ry["divided"]["partition"]["planes"] == rz["divided"]["partition"]["planes"]
    np.testing.assert_array_equal(np.load(tmp_path / "oy" / "radiosity.npz")["B"],
                                  np.load(tmp_path / "oz" / "radiosity.npz")["B"])
