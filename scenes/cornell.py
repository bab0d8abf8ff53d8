"""The Cornell box, from the Cornell Program of Computer Graphics measured data.

Geometry is the published measured data (``cornell-box`` page, millimetres)
converted to metres, unchanged except for:

* the light quad is moved 1 mm below the ceiling (the original is coplanar
  with it) and faces down (-Y);
* the blocks have no bottom faces (they stand on the floor: invisible and
  coplanar with it); their top and four sides face outward.

Orientation: +Y up, the box spans x in [0, 0.556], y in [0, 0.5488],
z in [0, 0.5592].  The back wall is at z = 0.5592 and the FRONT IS OPEN at
z = 0: the camera stands outside, on the -Z side, looking along +Z.  The
original camera (:data:`CAMERA`) is at (0.278, 0.273, -0.800) looking +Z,
up +Y, vertical field of view 39.3 deg (35 mm lens, 25 mm film).  Seen from
there +X points to the viewer's LEFT, so the red wall (x ~ 0.55) is on the
left and the green wall (x = 0) is on the right, as in the photographs.
"""

from __future__ import annotations

import pathlib

import numpy as np

from .objwriter import ObjWriter

__all__ = ["cornell_box", "CAMERA", "WHITE", "RED", "GREEN", "LIGHT_KD", "LIGHT_EXITANCE"]

WHITE = (0.73, 0.73, 0.73)
RED = (0.63, 0.065, 0.05)
GREEN = (0.14, 0.45, 0.09)
LIGHT_KD = (0.78, 0.78, 0.78)
#: Default light exitance (W/m^2): a warm white, red > green > blue.
LIGHT_EXITANCE = (40.0, 30.0, 20.0)
#: Original camera: position, look-at target, up vector (m) and vertical fov (deg).
CAMERA = {
    "position": (0.278, 0.273, -0.800),
    "target": (0.278, 0.273, 0.0),
    "up": (0.0, 1.0, 0.0),
    "fov_deg": 39.3,
}

_MM = 1e-3
# measured data, millimetres; each quad in the order given by Cornell
_FLOOR = [(552.8, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 559.2), (549.6, 0.0, 559.2)]
_CEILING = [(556.0, 548.8, 0.0), (556.0, 548.8, 559.2), (0.0, 548.8, 559.2), (0.0, 548.8, 0.0)]
_BACK = [(549.6, 0.0, 559.2), (0.0, 0.0, 559.2), (0.0, 548.8, 559.2), (556.0, 548.8, 559.2)]
_RIGHT_GREEN = [(0.0, 0.0, 559.2), (0.0, 0.0, 0.0), (0.0, 548.8, 0.0), (0.0, 548.8, 559.2)]
_LEFT_RED = [(552.8, 0.0, 0.0), (549.6, 0.0, 559.2), (556.0, 548.8, 559.2), (556.0, 548.8, 0.0)]
_LIGHT = [(343.0, 227.0), (343.0, 332.0), (213.0, 332.0), (213.0, 227.0)]  # (x, z)
_LIGHT_Y = 548.8 - 1.0  # 1 mm below the ceiling
# block top outlines (x, z) and heights (mm)
_SHORT_TOP = [(130.0, 65.0), (82.0, 225.0), (240.0, 272.0), (290.0, 114.0)]
_SHORT_H = 165.0
_TALL_TOP = [(423.0, 247.0), (265.0, 296.0), (314.0, 456.0), (472.0, 406.0)]
_TALL_H = 330.0


def _m(points) -> list[np.ndarray]:
    return [np.asarray(p, np.float64) * _MM for p in points]


def _add_block(w: ObjWriter, top_xz, height_mm: float) -> None:
    """A rotated block standing on the floor: top (+Y) and 4 outward sides."""
    top = [np.array([x, height_mm, z]) * _MM for x, z in top_xz]
    bot = [np.array([x, 0.0, z]) * _MM for x, z in top_xz]
    centre = np.mean(top + bot, axis=0)
    w.add_quad(*top, facing=(0.0, 1.0, 0.0))
    for k in range(4):
        a, b = k, (k + 1) % 4
        quad = [bot[a], bot[b], top[b], top[a]]
        out = np.mean(quad, axis=0) - centre
        out[1] = 0.0
        w.add_quad(*quad, facing=out)


def cornell_box(
    folder,
    light_exitance=LIGHT_EXITANCE,
    stem: str = "cornell",
) -> pathlib.Path:
    """Write the Cornell box as ``<folder>/<stem>.obj`` + ``.mtl``; return the OBJ path.

    Parameters
    ----------
    folder : path-like
        Output folder (created if missing).
    light_exitance : float or (3,) floats
        Emitted exitance of the light quad, W/m^2 (scalar = grey).  The light
        is 0.130 m x 0.105 m, so the default (40, 30, 20) emits about
        (0.55, 0.41, 0.27) W.

    Objects: ``floor``, ``ceiling``, ``back_wall``, ``left_wall`` (red),
    ``right_wall`` (green), ``short_block``, ``tall_block``, ``light``.
    Walls, floor and ceiling face into the box; the light faces down; the
    blocks face outward.  The front (z = 0) is open; see the module docstring.
    """
    w = ObjWriter()
    w.material("white", WHITE)
    w.material("red", RED)
    w.material("green", GREEN)
    w.material("light", LIGHT_KD, ke=light_exitance)

    inside = np.array([278.0, 274.4, 279.6]) * _MM  # centre of the box
    for name, quad, mat in (
        ("floor", _FLOOR, "white"),
        ("ceiling", _CEILING, "white"),
        ("back_wall", _BACK, "white"),
        ("left_wall", _LEFT_RED, "red"),
        ("right_wall", _RIGHT_GREEN, "green"),
    ):
        pts = _m(quad)
        w.begin(name, mat)
        w.add_quad(*pts, facing=inside - np.mean(pts, axis=0))

    w.begin("short_block", "white")
    _add_block(w, _SHORT_TOP, _SHORT_H)
    w.begin("tall_block", "white")
    _add_block(w, _TALL_TOP, _TALL_H)

    w.begin("light", "light")
    w.add_quad(*_m([(x, _LIGHT_Y, z) for x, z in _LIGHT]), facing=(0.0, -1.0, 0.0))
    return w.write(folder, stem)
