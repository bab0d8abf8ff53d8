"""CIE 171:2006 case 5.3's layout end to end at defaults: the lux a user reads against the closed form.

A black 4 x 4 x 3 m room lit by one 1 x 1 m Lambertian ceiling panel: the illuminance at a floor
point is the panel's exitance times the configuration factor of a parallel rectangle, in closed
form (the four-rectangle superposition of the corner formula), computed here, not by dcrad.
"""

from __future__ import annotations

import math

import numpy as np

import scenes
from dcrad.config import SolverConfig
from dcrad.io.scene import load_scene
from dcrad.meshing.patches import triangle_areas
from dcrad.outputs.photometry import EFFICACY
from dcrad.pipeline import solve_to
from scenes.cie import ROOM


def corner_factor(a: np.ndarray, b: np.ndarray, h: float) -> np.ndarray:
    """Configuration factor from a differential area to a parallel a x b rectangle h above it with
    one corner straight above the point (signed a, b: the sign carries through)."""
    x, y = a / h, b / h
    sx, sy = np.sqrt(1 + x * x), np.sqrt(1 + y * y)
    return (x / sx * np.arctan(y / sx) + y / sy * np.arctan(x / sy)) / (2 * math.pi)


def panel_factor(px: np.ndarray, pz: np.ndarray, lo: tuple, hi: tuple, h: float) -> np.ndarray:
    f = np.zeros(len(px))
    for cx, sx in ((hi[0], 1), (lo[0], -1)):
        for cz, sz in ((hi[1], 1), (lo[1], -1)):
            f += sx * sz * corner_factor(cx - px, cz - pz, h)
    return f


def test_black_room_floor_lux_is_the_closed_form_everywhere(tmp_path):
    path = scenes.write_builtin("cie_room", tmp_path / "scene", grid=0.1, emission=100.0)
    report = solve_to(path, tmp_path / "out", SolverConfig(), width=64, height=48)
    z = np.load(tmp_path / "out" / "radiosity.npz")
    scene = load_scene(path)
    floor = scene.names.index(next(n for n in scene.names if n.startswith("floor")))
    rows = np.flatnonzero(scene.obj[z["patch_source"]] == floor)
    assert len(rows) == len(np.unique(z["patch_source"][rows]))  # the 0.1 m grid is kept whole ...
    tri = scene.vertices[scene.faces[z["patch_source"][rows]]]
    c = tri.mean(axis=1)
    x, h, zz = ROOM
    lo, hi = (x / 2 - 0.5, zz / 2 - 0.5), (x / 2 + 0.5, zz / 2 + 0.5)
    # the patch mean of the closed form (a 3-point rule over each 0.005 m^2 triangle: its curvature
    # is far below the tolerance, but the test should not lean on it)
    pts = (tri + c[:, None, :]) / 2
    exact = np.mean([panel_factor(pts[:, k, 0], pts[:, k, 2], lo, hi, h - 0.01) for k in range(3)], axis=0)
    want = EFFICACY * 100.0 * exact
    got = z["patch_E_lux"][rows]
    assert np.abs(got / want - 1).max() < 0.01, np.abs(got / want - 1).max()
    assert report["ledger"]["closure"] < 1e-9
    # ... and the light the floor receives adds up: sum E A over the floor against the closed form's
    a = triangle_areas(tri)
    assert abs((got * a).sum() / (want * a).sum() - 1) < 1e-3
