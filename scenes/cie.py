"""CIE 171:2006 test room layouts: a 4 x 4 x 3 m room, one 1 x 1 m Lambertian ceiling panel.

Case 5.3's layout (the room black, so the illuminance is the panel's direct light alone, and the
closed form E = L x integral of cos cos / d^2 over the panel is the truth at every point): the
floor (y = 0) and the wall x = 0 are gridded at ``grid`` m, as validation files are (17,280
triangles at 0.1 m), the other walls and the ceiling are two triangles each.  ``rho`` > 0 makes
the walls reflect (case 5.8's uniform-reflectance enclosure with an area source).  The panel is
centred in the ceiling, 1 cm below it, facing down, exitance ``emission`` W/m^2 (luminance
179 x emission / pi cd/m^2 for a grey panel: photometry.EFFICACY).
"""

from __future__ import annotations

import math
import pathlib

import numpy as np

from .objwriter import ObjWriter

__all__ = ["cie_room", "ROOM"]

#: the room's extent (x, y up, z), m
ROOM = (4.0, 3.0, 4.0)


def cie_room(folder, stem: str = "cie_room", grid: float = 0.1, rho: float = 0.0, emission: float = 100.0,
             panel: float = 1.0) -> pathlib.Path:
    if not (0.0 <= rho < 1.0 and emission > 0 and 0 < panel < min(ROOM[0], ROOM[2]) and grid > 0):
        raise ValueError(f"cie_room: rho {rho} in [0, 1), emission {emission} > 0, panel {panel} m inside the "
                         f"ceiling, grid {grid} > 0")
    x, h, z = ROOM
    w = ObjWriter()
    w.material("surface", rho)
    w.material("panel", 0.0, emission)
    cells_x, cells_z, cells_y = (max(1, math.ceil(v / grid - 1e-9)) for v in (x, z, h))
    w.begin("floor", "surface")
    xs, zs = np.linspace(0.0, x, cells_x + 1), np.linspace(0.0, z, cells_z + 1)
    for i in range(cells_x):
        for k in range(cells_z):
            w.add_rect(1, 0.0, (xs[i], zs[k]), (xs[i + 1], zs[k + 1]), +1)
    w.begin("wall_x0", "surface")
    ys = np.linspace(0.0, h, cells_y + 1)
    for j in range(cells_y):
        for k in range(cells_z):
            w.add_rect(0, 0.0, (ys[j], zs[k]), (ys[j + 1], zs[k + 1]), +1)
    w.begin("walls", "surface")
    w.add_rect(0, x, (0.0, 0.0), (h, z), -1)
    w.add_rect(2, 0.0, (0.0, 0.0), (x, h), +1)
    w.add_rect(2, z, (0.0, 0.0), (x, h), -1)
    w.begin("ceiling", "surface")
    w.add_rect(1, h, (0.0, 0.0), (x, z), -1)
    w.begin("panel", "panel")
    a = 0.5 * panel
    w.add_rect(1, h - 0.01, (x / 2 - a, z / 2 - a), (x / 2 + a, z / 2 + a), -1)
    return w.write(folder, stem)
