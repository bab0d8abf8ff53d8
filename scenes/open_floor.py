"""An open floor under a light, nothing else, and its closed form.

A 1 x 1 m floor (rho 0.7, n x n squares of two triangles, facing +z) under a 1 x 1 m light
(E = 10 W/m^2, 4 x 4 squares, facing -z) 1 m above it: every boundary of a partition crosses
open space.  Built as a patch table directly (no file): tests and bench/bench_open_floor.py
compare divided runs with the unsplit one and with ``point_to_square``.
"""

from __future__ import annotations

import numpy as np

from dcrad.meshing.patches import Patches

__all__ = ["open_floor", "point_to_square", "FLOOR_RHO", "LIGHT_E"]

FLOOR_RHO, LIGHT_E = 0.7, 10.0


def _square(z: float, cells: int, flip: bool) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of [0,1]^2 at height z, cells x cells squares; faces +z (flip: -z)."""
    g = np.linspace(0.0, 1.0, cells + 1)
    x, y = np.meshgrid(g, g, indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)
    i, j = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    a = (i * (cells + 1) + j).ravel()
    b, c, d = a + cells + 1, a + cells + 2, a + 1
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return v, (f[:, [0, 2, 1]] if flip else f)


def open_floor(n: int = 20) -> tuple[Patches, np.ndarray]:
    """(patches, floor mask (m,) bool): the floor's n x n squares, then the light's."""
    vf, ff = _square(0.0, n, False)  # faces up
    vl, fl = _square(1.0, 4, True)  # faces down
    faces = np.concatenate([ff, fl + len(vf)])
    floor = np.arange(len(faces)) < len(ff)
    rho = np.where(floor[:, None], FLOOR_RHO, 0.0) * np.ones(3)
    emission = np.where(floor[:, None], 0.0, LIGHT_E) * np.ones(3)
    return Patches(np.concatenate([vf, vl]), faces, rho, emission, np.arange(len(faces)),
                   (~floor).astype(np.int32), ["floor", "light"]), floor


def point_to_square(x, y, h: float = 1.0):
    """Closed-form form factor from a point (x, y) on the floor, facing up, to the unit square
    [0,1]^2 at height h facing down: the sum of four corner rectangles (Howell's catalogue, B-3)."""
    def corner(a, b):
        X, Y = a / h, b / h
        sx, sy = np.sqrt(1 + X * X), np.sqrt(1 + Y * Y)
        return (X / sx * np.arctan(Y / sx) + Y / sy * np.arctan(X / sy)) / (2 * np.pi)
    return sum(corner(a, b) for a in (x, 1 - x) for b in (y, 1 - y))
