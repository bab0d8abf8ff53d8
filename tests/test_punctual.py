"""glTF KHR_lights_punctual point and spot lights (punctual.py), against closed forms.

The scenes are closed boxes written here as glTF by hand (json + base64 buffers), the lights placed
by nodes.  The truths: E = I cos / d^2 under a point light of I candela (every lumen of its 4 pi I
absorbed by a black box), a spot's E equal to the point's inside its inner cone and zero outside its
outer one, its direction the node's -Z turned by the node's (and its parent's) rotation, its flux the
integral of its falloff over the sphere, a red light lighting the red channel only at the lux of its
candela, a Z-up millimetre file against the same room Y-up in metres; the false-colour image marks
the light where a camera looking straight at it puts it, the image's centre.  Directional lights and
``range`` leave warnings; bad lights are one error naming the file and the light.
"""

from __future__ import annotations

import base64
import json
import math
from pathlib import Path

import numpy as np
import pytest

import dcrad
from dcrad.cli import main
from dcrad.errors import SceneFormatError, SceneValueError
from dcrad.io.scene import NO_EMITTERS
from dcrad.outputs.photometry import EFFICACY, Y_WEIGHTS, direct_irradiance, to_lux, workplane
from dcrad.outputs.render import Camera, draw_marks, marks_in_view
from dcrad.transport.punctual import PunctualLight, SpotLight
from dcrad.transport.rays import Tracer

I0 = 1000.0  # cd
LAMP = (2.0, 3.0, 2.0)  # 3 m above the floor of a 4 x 3.2 x 4 m room
INNER, OUTER = math.radians(20), math.radians(30)  # a spot's cone angles
DOWN = [-math.sin(math.pi / 4), 0.0, 0.0, math.cos(math.pi / 4)]  # -90 deg about X: the node's -Z to -Y


def identity(p):
    return tuple(float(c) for c in p)


def box_gltf(path: Path, lights=(), light_nodes=(), *, size=(4.0, 3.2, 4.0), rho=0.0, floor_rho=None,
             frame=identity, extra: dict | None = None) -> Path:
    """A closed box, its six faces facing in (one node and mesh each), reflectance ``rho`` (the floor
    ``floor_rho`` if given), and ``light_nodes`` placing ``lights``; ``frame`` maps the Y-up metre
    coordinates of the box to the file's (a proper rotation and a scale, so the winding holds)."""
    x, y, z = size
    quads = {
        "floor": [(0, 0, 0), (0, 0, z), (x, 0, z), (x, 0, 0)],
        "ceiling": [(0, y, 0), (x, y, 0), (x, y, z), (0, y, z)],
        "wall_x0": [(0, 0, 0), (0, y, 0), (0, y, z), (0, 0, z)],
        "wall_x1": [(x, 0, 0), (x, 0, z), (x, y, z), (x, y, 0)],
        "wall_z0": [(0, 0, 0), (x, 0, 0), (x, y, 0), (0, y, 0)],
        "wall_z1": [(0, 0, z), (0, y, z), (x, y, z), (x, 0, z)],
    }
    blob, views, accessors, meshes, nodes = b"", [], [], [], []
    for i, (name, quad) in enumerate(quads.items()):
        v = np.array([frame(p) for p in quad], np.float32)
        f = np.array([0, 1, 2, 0, 2, 3, 0, 0], np.uint16)  # two triangles, padded to 4 bytes
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": v.nbytes})
        blob += v.tobytes()
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": 12})
        blob += f.tobytes()
        accessors += [{"bufferView": 2 * i, "componentType": 5126, "count": 4, "type": "VEC3",
                       "min": v.min(axis=0).tolist(), "max": v.max(axis=0).tolist()},
                      {"bufferView": 2 * i + 1, "componentType": 5123, "count": 6, "type": "SCALAR"}]
        material = 1 if name == "floor" and floor_rho is not None else 0
        meshes.append({"name": name, "primitives": [{"attributes": {"POSITION": 2 * i}, "indices": 2 * i + 1,
                                                     "material": material}]})
        nodes.append({"name": name, "mesh": i})
    f_rho = rho if floor_rho is None else floor_rho
    materials = [{"name": "surface", "pbrMetallicRoughness": {"baseColorFactor": [rho, rho, rho, 1.0]}},
                 {"name": "floor", "pbrMetallicRoughness": {"baseColorFactor": [f_rho, f_rho, f_rho, 1.0]}}]
    nodes += [dict(n) for n in light_nodes]
    held = {c for n in nodes for c in n.get("children", [])}
    g = {"asset": {"version": "2.0"}, "scene": 0,
         "scenes": [{"nodes": [i for i in range(len(nodes)) if i not in held]}],
         "nodes": nodes, "meshes": meshes, "materials": materials,
         "buffers": [{"byteLength": len(blob),
                      "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode()}],
         "bufferViews": views, "accessors": accessors}
    if lights:
        g["extensionsUsed"] = ["KHR_lights_punctual"]
        g["extensions"] = {"KHR_lights_punctual": {"lights": list(lights)}}
    g.update(extra or {})
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(g))
    return path


def placed(light: int, translation=LAMP, rotation=None, name="lamp", **more) -> dict:
    node = {"name": name, "translation": list(translation), "extensions": {"KHR_lights_punctual": {"light": light}}}
    if rotation is not None:
        node["rotation"] = list(rotation)
    return node | more


def floor_grid(patches, height=1e-4):
    """The work plane just above the floor (every point: no border), its exact direct light."""
    return workplane(patches, height, spacing=0.37, tracer=Tracer.mesh(patches), border=0.0)


def point_lux(points, at=LAMP, candela=I0, normal=(0.0, 1.0, 0.0)):
    """I cos / d^2 at ``points`` facing ``normal`` from a point of ``candela`` cd at ``at``."""
    d = np.asarray(at) - points
    r = np.linalg.norm(d, axis=1)
    return candela * np.maximum(d @ np.asarray(normal), 0.0) / r ** 3


def spot(inner=INNER, outer=OUTER, **more) -> dict:
    return {"type": "spot", "intensity": I0, "spot": {"innerConeAngle": inner, "outerConeAngle": outer}} | more


def test_a_point_light_3_m_above_a_black_floor_gives_i_cos_over_d2_and_the_ledger_closes(tmp_path):
    """CIE 171:2006 case 5.2's layout with an isotropic source: E = I cos / d^2 at every floor point
    (one shadow ray a point: exact), all of its 4 pi I lumens absorbed by the black box."""
    path = box_gltf(tmp_path / "room.gltf", [{"type": "point", "intensity": I0, "name": "bulb"}], [placed(0)])
    scene = dcrad.load(path)
    assert NO_EMITTERS not in scene.warnings and not scene.warnings, scene.warnings
    (light,) = scene.sources
    assert isinstance(light, PunctualLight) and light.name == "glTF point light 'bulb'"
    result = dcrad.solve(path, accuracy=0.05, patch_size=0.5, seed=1)
    assert [s.name for s in result.patches.sources] == [light.name]
    wp = floor_grid(result.patches)
    assert len(wp["lux"]) > 80
    np.testing.assert_allclose(wp["lux"], point_lux(wp["points"]), rtol=1e-9)
    led = result.report["ledger"]
    watts = 4 * math.pi * I0 / EFFICACY
    assert led["emitted"] == pytest.approx([watts] * 3, rel=1e-12)
    assert sum(led["absorbed"]) == pytest.approx(3 * watts, rel=1e-9)
    assert sum(led["escaped"]) == 0.0 and led["closure"] < 1e-9
    section = result.report["gltf_lights"]
    assert section["count"] == 1 and section["lumens"] == pytest.approx(4 * math.pi * I0, rel=1e-12)
    (entry,) = section["lights"]
    assert entry["name"] == "bulb" and entry["node"] == "lamp" and entry["position"] == list(LAMP)
    assert not any("no emitters" in w for w in result.report["warnings"])


def test_a_spot_is_the_point_inside_its_inner_cone_and_dark_outside_its_outer_cone(tmp_path):
    """A spot aimed down by its node's rotation: inside the inner cone the point light's I cos / d^2,
    beyond the outer cone nothing, between them less than the point and more than nothing; its lumens
    the integral of its falloff over the sphere, all absorbed."""
    inner, outer = INNER, OUTER
    path = box_gltf(tmp_path / "room.gltf", [spot(inner, outer, name="beam")], [placed(0, rotation=DOWN)])
    result = dcrad.solve(path, accuracy=0.05, patch_size=0.5, seed=2)
    (light,) = result.patches.sources
    assert isinstance(light, SpotLight)
    np.testing.assert_allclose(light.axis, [0.0, -1.0, 0.0], atol=1e-12)
    wp = floor_grid(result.patches)
    d = np.asarray(LAMP) - wp["points"]
    angle = np.arccos(d[:, 1] / np.linalg.norm(d, axis=1))  # from straight down
    full, dark = angle < inner - 1e-6, angle > outer + math.radians(2)
    between = (angle > inner + math.radians(1)) & (angle < outer - math.radians(1))
    assert full.sum() > 10 and dark.sum() > 30 and between.sum() > 5
    expected = point_lux(wp["points"])
    np.testing.assert_allclose(wp["lux"][full], expected[full], rtol=1e-9)
    assert (wp["lux"][dark] == 0).all()
    assert (wp["lux"][between] > 0).all() and (wp["lux"][between] < expected[between]).all()
    # its flux: the falloff integrated over the sphere by a fine midpoint rule in the polar angle
    theta = (np.arange(200_000) + 0.5) * (math.pi / 2) / 200_000
    relative = light.falloff(np.cos(theta)) * np.sin(theta) * 2 * math.pi * (math.pi / 2) / 200_000
    lumens = I0 * relative.sum()
    assert light.lumens == pytest.approx(lumens, rel=1e-8)
    assert result.report["gltf_lights"]["lumens"] == pytest.approx(lumens, rel=1e-8)
    led = result.report["ledger"]
    assert led["emitted"] == pytest.approx([lumens / EFFICACY] * 3, rel=1e-8)
    assert sum(led["absorbed"]) == pytest.approx(3 * lumens / EFFICACY, rel=1e-8) and led["closure"] < 1e-9


def test_the_spot_follows_its_node_and_its_parent(tmp_path):
    """A spot on a child node (its parent moved to the room's middle, the child turned -90 degrees
    about Y so its -Z points along +X) lights the x = 4 wall ahead as a point would inside its inner
    cone, and not the floor below it."""
    turn = [0.0, -math.sin(math.pi / 4), 0.0, math.cos(math.pi / 4)]
    nodes = [{"name": "rig", "translation": [2.0, 0.0, 2.0], "children": [7]},
             placed(0, translation=(0.0, 1.5, 0.0), rotation=turn, name="head")]
    path = box_gltf(tmp_path / "room.gltf", [spot()], nodes)
    scene = dcrad.load(path)
    (light,) = scene.sources
    np.testing.assert_allclose(light.position, [2.0, 1.5, 2.0], atol=1e-12)
    np.testing.assert_allclose(light.axis, [1.0, 0.0, 0.0], atol=1e-12)
    patches = scene.patches(0.5)
    tracer = Tracer.mesh(patches)
    yy, zz = np.meshgrid(np.linspace(0.9, 2.1, 7), np.linspace(1.4, 2.6, 7))
    wall = np.column_stack([np.full(yy.size, 4.0 - 1e-4), yy.ravel(), zz.ravel()])
    toward = np.tile([-1.0, 0.0, 0.0], (len(wall), 1))
    lux = to_lux(direct_irradiance(patches, tracer, wall, toward)[0])
    d = wall - light.position
    inside = np.arccos(d[:, 0] / np.linalg.norm(d, axis=1)) < math.radians(20)
    assert inside.sum() > 20
    np.testing.assert_allclose(lux[inside], point_lux(wall, light.position, normal=(-1, 0, 0))[inside], rtol=1e-9)
    assert lux[len(wall) // 2] == pytest.approx(I0 / (2.0 - 1e-4) ** 2, rel=1e-9)  # straight ahead: I / d^2
    floor = np.array([[x, 1e-4, z] for x in (1.0, 2.0, 3.0, 3.9) for z in (1.0, 2.0, 3.0)])
    assert (to_lux(direct_irradiance(patches, tracer, floor, np.tile([0.0, 1.0, 0.0], (len(floor), 1)))[0]) == 0).all()


def test_a_red_light_lights_the_red_channel_at_the_lux_of_its_candela(tmp_path):
    """color [1, 0, 0]: W/sr in the red channel only, I / 179 / 0.2126, so 179 lm/W x Y(H) gives back
    I cos / d^2 lux; the grey walls reflect red light only."""
    path = box_gltf(tmp_path / "room.gltf", [{"type": "point", "intensity": I0, "color": [1.0, 0.0, 0.0]}],
                    [placed(0)], rho=0.5, floor_rho=0.0)
    result = dcrad.solve(path, accuracy=0.05, patch_size=0.5, seed=3)
    (light,) = result.patches.sources
    np.testing.assert_allclose(light.power(), [4 * math.pi * I0 / EFFICACY / Y_WEIGHTS[0], 0.0, 0.0], rtol=1e-12)
    b = result.patches.radiosity
    assert (b[:, 1:] == 0).all() and b[:, 0].max() > 0
    patches = result.patches
    pts = np.array([[x, 1e-4, z] for x in (0.5, 1.3, 2.0, 3.1) for z in (0.7, 2.0, 3.5)])
    h = direct_irradiance(patches, Tracer.mesh(patches), pts, np.tile([0.0, 1.0, 0.0], (len(pts), 1)))[0]
    assert (h[:, 1:] == 0).all()
    np.testing.assert_allclose(to_lux(h), point_lux(pts), rtol=1e-9)
    assert result.report["gltf_lights"]["lights"][0]["color"] == [1.0, 0.0, 0.0]


def test_a_z_up_millimetre_file_lights_as_the_y_up_metre_one(tmp_path):
    """The same room and spot written Z up in millimetres (the spot's node unturned: its -Z is the
    file's down) and loaded with --up z --scale 0.001: the light lands where the Y-up one does, aimed
    down, and lights the floor alike; the report gives the file's own coordinates."""
    def z_up_mm(p):
        return (1000.0 * p[0], -1000.0 * p[2], 1000.0 * p[1])

    y_up = box_gltf(tmp_path / "y.gltf", [spot(name="s")], [placed(0, rotation=DOWN)])
    z_up = box_gltf(tmp_path / "z.gltf", [spot(name="s")], [placed(0, translation=z_up_mm(LAMP))], frame=z_up_mm)
    a, b = dcrad.load(y_up), dcrad.load(z_up, scale=0.001, up="z")
    np.testing.assert_allclose(b.sources[0].position, LAMP, atol=1e-9)
    np.testing.assert_allclose(b.sources[0].axis, [0.0, -1.0, 0.0], atol=1e-12)
    ra = dcrad.solve(a, accuracy=0.05, patch_size=0.5, seed=4)
    rb = dcrad.solve(b, accuracy=0.05, patch_size=0.5, scale=0.001, seed=4)
    np.testing.assert_allclose(floor_grid(rb.patches)["lux"], floor_grid(ra.patches)["lux"], rtol=1e-6, atol=1e-9)
    assert rb.report["gltf_lights"]["lights"][0]["position"] == pytest.approx(list(z_up_mm(LAMP)), rel=1e-12)


def test_directional_lights_and_range_are_said_to_be_left_out(tmp_path):
    lights = [{"type": "directional", "intensity": 5.0, "name": "Sun"},
              {"type": "point", "intensity": 10.0, "range": 5.0, "name": "bulb"}]
    path = box_gltf(tmp_path / "room.gltf", lights, [placed(0, name="sun"), placed(1)],
                    extra={"extensionsRequired": ["KHR_lights_punctual"]})
    scene = dcrad.load(path)
    assert [s.name for s in scene.sources] == ["glTF point light 'bulb'"]
    sun = [w for w in scene.warnings if "'Sun'" in w]
    assert len(sun) == 1 and "room.gltf" in sun[0] and "directional" in sun[0] and "lights nothing" in sun[0], sun
    assert any("'bulb'" in w and "range 5.0 ignored" in w for w in scene.warnings), scene.warnings
    only_sun = box_gltf(tmp_path / "sun.gltf", lights[:1], [placed(0, name="sun")])
    scene = dcrad.load(only_sun)
    assert scene.sources == () and NO_EMITTERS in scene.warnings
    assert any("directional" in w for w in scene.warnings)
    dark = box_gltf(tmp_path / "dark.gltf", [{"type": "point", "intensity": 0.0}], [placed(0)])
    scene = dcrad.load(dark)
    assert scene.sources == () and any("emits nothing" in w for w in scene.warnings)


BAD = [  # (light, node patch, error type, what the message says)
    ({"type": "point", "intensity": -5.0}, {}, SceneValueError, r"intensity -5\.0 cd must be finite and >= 0"),
    ({"type": "point", "intensity": float("nan")}, {}, SceneValueError, r"intensity nan cd must be finite"),
    ({"type": "point", "intensity": "bright"}, {}, SceneValueError, r"intensity 'bright' is not a number"),
    ({"type": "point", "color": [1.0, -1.0, 0.0]}, {}, SceneValueError, r"color \[1\.0, -1\.0, 0\.0\] must be finite"),
    ({"type": "point", "color": [1.0, float("inf"), 0.0]}, {}, SceneValueError, r"color .* must be finite"),
    ({"type": "point", "color": [1.0, 1.0]}, {}, SceneValueError, r"color \[1\.0, 1\.0\] is not three numbers"),
    (spot(0.6, 0.5), {}, SceneValueError, r"innerConeAngle 0\.6 and outerConeAngle 0\.5 must satisfy"),
    (spot(0.1, 2.0), {}, SceneValueError, r"outerConeAngle 2\.0 must satisfy 0 <= inner < outer <= pi/2"),
    (spot(-0.1, 0.5), {}, SceneValueError, r"innerConeAngle -0\.1 .* must satisfy"),
    (spot(0.2, 0.2), {}, SceneValueError, r"must satisfy 0 <= inner < outer"),
    ({"type": "area"}, {}, SceneFormatError, r"type 'area' is not one of point, spot, directional"),
    ({"intensity": 3.0}, {}, SceneFormatError, r"type None is not one of"),
    ({"type": "point"}, {"extensions": {"KHR_lights_punctual": {"light": 3}}}, SceneFormatError,
     r"node 'lamp' refers to KHR_lights_punctual light 3, but the file has 1 light"),
]


@pytest.mark.parametrize("light, node, kind, says", BAD, ids=[b[3][:30] for b in BAD])
def test_a_bad_light_is_one_error_naming_the_file_and_the_light(tmp_path, light, node, kind, says):
    path = box_gltf(tmp_path / "bad.gltf", [light | {"name": "L1"}], [placed(0) | node])
    with pytest.raises(kind, match=says) as info:
        dcrad.load(path)
    message = str(info.value)
    assert "\n" not in message and "bad.gltf" in message, message
    if "refers to" not in message:
        assert "KHR_lights_punctual light 0 ('L1', node 'lamp')" in message, message


def test_the_command_refuses_a_bad_light_and_the_service_takes_good_ones(tmp_path, capsys):
    """Exit 2 and one line naming the file and the light for a bad light; the service's upload (a
    coordinator's job manager) takes a file with good ones, its lights on the job's patches."""
    bad = box_gltf(tmp_path / "bad.gltf", [{"type": "point", "intensity": -1.0}], [placed(0)])
    assert main(["solve", str(bad), "--out", str(tmp_path / "o1"), "--workers", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bad.gltf" in err and "intensity -1.0 cd" in err, err
    good = box_gltf(tmp_path / "good.gltf", [{"type": "point", "intensity": 100.0, "name": "bulb"}], [placed(0)])

    from coordinator.jobs import JobManager
    from coordinator.remote import WorkerPool
    from dcrad.v1 import dcrad_pb2 as pb

    jobs = JobManager(tmp_path / "coordinator", WorkerPool())
    job = jobs.create(pb.JobSpec(scene="good.gltf"), {"good.gltf": good.read_bytes()})
    assert job.prepared is not None and len(job.prepared[1].sources) == 1


def test_the_false_colour_image_marks_the_light_where_the_camera_sees_it(tmp_path):
    """The file's camera sits under the light looking straight up at it: the light is at the image's
    centre, where illuminance.png has the mark's white centre inside a black ring, and no other pixel
    of the picture is pure white or black (a closed box fills the view)."""
    up = [math.sin(math.pi / 4), 0.0, 0.0, math.cos(math.pi / 4)]  # +90 deg about X: the camera's -Z to +Y
    camera = {"name": "eye", "camera": 0, "translation": [2.0, 1.0, 2.0], "rotation": up}
    path = box_gltf(tmp_path / "room.gltf", [{"type": "point", "intensity": I0}], [placed(0), camera], rho=0.5,
                    extra={"cameras": [{"type": "perspective", "perspective": {"yfov": 1.2, "znear": 0.01}}]})
    out = tmp_path / "out"
    dcrad.solve(path, out, accuracy=0.05, patch_size=0.5, width=64, height=48, seed=5)
    import OpenImageIO as oiio

    img = np.asarray(oiio.ImageBuf(str(out / "illuminance.png")).get_pixels(oiio.UINT8)).reshape(48, -1, 3)[:, :64]
    assert img[24, 32].tolist() == [255, 255, 255]  # the light projects to (32, 24): pixel (24, 32)'s corner
    ring = [img[24, 33], img[22, 32], img[25, 30]]  # 1.6 to 2.1 pixels from it: the black ring
    assert all(p.tolist() == [0, 0, 0] for p in ring), ring
    rows, cols = np.nonzero((img == 255).all(axis=2) | (img == 0).all(axis=2))
    assert len(rows) and np.hypot(cols + 0.5 - 32, rows + 0.5 - 24).max() <= 7.0 + 1e-9


def test_marks_land_where_the_camera_casts_its_rays_and_hide_behind_surfaces():
    """``Camera.project`` puts a point on a pixel's ray back on that pixel (perspective and
    orthographic); ``marks_in_view`` drops points behind the camera, outside the image and behind a
    surface; ``draw_marks`` paints only the picture's columns."""
    for cam in (Camera((0.0, 1.0, 5.0), (0.3, 1.2, 0.0), fov_y=50.0, width=40, height=30),
                Camera((0.0, 5.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, -1.0), width=40, height=30,
                       orthographic_height=4.0)):
        origins, dirs = cam.rays()
        points = origins + dirs * np.linspace(0.5, 3.0, len(dirs))[:, None]
        xy, depth = cam.project(points)
        j, i = np.meshgrid(np.arange(40), np.arange(30))
        np.testing.assert_allclose(xy, np.column_stack([j.ravel(), i.ravel()]) + 0.5, atol=1e-9)
        assert (depth > 0).all()
    cam = Camera((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), width=40, height=30)
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 9.0], [50.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
    np.testing.assert_allclose(marks_in_view(cam, pts), cam.project(pts[[0, 3]])[0])
    # a quad at z = 1 in front of the first point (not the last): it hides the first
    from dcrad.meshing.patches import Patches

    quad = Patches(np.array([[-0.2, -0.2, 1.0], [0.2, -0.2, 1.0], [0.2, 0.2, 1.0], [-0.2, 0.2, 1.0]]),
                   np.array([[0, 1, 2], [0, 2, 3]]), 0.5, 0.0, np.arange(2), np.zeros(2))
    np.testing.assert_allclose(marks_in_view(cam, pts, Tracer.mesh(quad)), cam.project(pts[[3]])[0])
    img = np.full((30, 50, 3), 128, np.uint8)
    draw_marks(img, np.array([[39.5, 15.5]]), width=40)
    assert img[15, 39].tolist() == [255, 255, 255] and (img[:, 40:] == 128).all()
