"""White-furnace test scene: a closed cube, uniform reflectance, one emitter.

The cube spans [0, size]^3 (m), +Y up, every face pointing INTO the cube, and
the mesh is watertight (no T-junctions).  The ceiling (y = size) is tiled as a
centred light square plus a ring of four trapezoids joining the light's
corners to the cube's top corners; all are coplanar, with no gap or overlap.

Light definition: ``light_fraction`` is the fraction of the CEILING AREA that
emits, i.e. the light square has side ``size * sqrt(light_fraction)`` and area
``light_fraction * size**2``.  It emits ``emission`` W/m^2; every surface,
the light included, has reflectance ``rho``.

For a closed enclosure the total power leaving all surfaces is
``sum(B A) = Phi / (1 - rho)``, so the area-weighted mean of the reflected
radiosity is exactly ``rho * Phi / ((1 - rho) * A_total)`` whatever the
geometry: see :func:`furnace_expected`.
"""

from __future__ import annotations

import math
import pathlib

import numpy as np

from .objwriter import ObjWriter, rgb

__all__ = ["furnace_box", "furnace_expected"]


def _check(rho, size, emission, light_fraction, grey):
    if grey and (np.ndim(rho) or np.ndim(emission)):
        raise ValueError("grey=True needs scalar rho and emission (use grey=False for RGB)")
    rho3 = np.asarray(rgb(rho))
    em3 = np.asarray(rgb(emission))
    if np.any(rho3 < 0) or np.any(rho3 >= 1):
        raise ValueError(f"rho {rho} must be in [0, 1)")
    if np.any(em3 < 0):
        raise ValueError(f"emission {emission} must be >= 0")
    if not size > 0:
        raise ValueError(f"size {size} must be > 0")
    if not 0 < light_fraction <= 1:
        raise ValueError(f"light_fraction {light_fraction} must be in (0, 1]")
    return rho3, em3


def furnace_box(
    folder,
    rho=0.5,
    size: float = 1.0,
    emission=1.0,
    light_fraction: float = 0.2,
    grey: bool = True,
    stem: str = "furnace",
) -> pathlib.Path:
    """Write the furnace cube as ``<folder>/<stem>.obj`` + ``.mtl``; return the OBJ path.

    Parameters
    ----------
    rho : float, or (3,) floats if ``grey`` is False
        Diffuse reflectance of every surface, in [0, 1).
    size : float
        Cube edge length, m.
    emission : float, or (3,) floats if ``grey`` is False
        Exitance of the light square, W/m^2.
    light_fraction : float in (0, 1]
        Emitting fraction of the ceiling area (see the module docstring).
    grey : bool
        If True, ``rho`` and ``emission`` must be scalars and are written to
        all three channels.  If False they may be RGB triples (each channel is
        then an independent furnace).

    Objects: ``floor``, ``wall_x0``, ``wall_x1``, ``wall_z0``, ``wall_z1``,
    ``ceiling`` (the ring; absent when ``light_fraction == 1``) and ``light``.
    """
    rho3, em3 = _check(rho, size, emission, light_fraction, grey)
    s = float(size)
    w = ObjWriter()
    w.material("furnace_white", rho3)
    w.material("furnace_light", rho3, ke=em3)

    for name, axis, value, facing in (
        ("floor", 1, 0.0, 1),
        ("wall_x0", 0, 0.0, 1),
        ("wall_x1", 0, s, -1),
        ("wall_z0", 2, 0.0, 1),
        ("wall_z1", 2, s, -1),
    ):
        w.begin(name, "furnace_white")
        w.add_rect(axis, value, (0.0, 0.0), (s, s), facing)

    half = 0.5 * s * math.sqrt(light_fraction)
    c = 0.5 * s
    down = (0.0, -1.0, 0.0)
    # corners, going round the ceiling in the same order: outer and inner (light)
    outer = [np.array([x, s, z]) for x, z in ((0, 0), (s, 0), (s, s), (0, s))]
    inner = [np.array([c + dx, s, c + dz]) for dx, dz in ((-half, -half), (half, -half), (half, half), (-half, half))]
    if light_fraction < 1.0:
        w.begin("ceiling", "furnace_white")
        for k in range(4):
            j = (k + 1) % 4
            w.add_quad(outer[k], outer[j], inner[j], inner[k], facing=down)
    w.begin("light", "furnace_light")
    w.add_quad(*(outer if light_fraction >= 1.0 else inner), facing=down)
    return w.write(folder, stem)


def furnace_expected(rho=0.5, size: float = 1.0, emission=1.0, light_fraction: float = 0.2) -> dict:
    """Exact energy balance of :func:`furnace_box` with the same arguments.

    Returns a dict (floats, or (3,) arrays for RGB ``rho``/``emission``):

    ``total_area``      A_total = 6 size^2, m^2
    ``light_area``      light_fraction * size^2, m^2
    ``emitted_power``   Phi = emission * light_area, W
    ``mean_b``          area-weighted mean radiosity Phi / ((1 - rho) A_total), W/m^2
    ``mean_b_minus_e``  area-weighted mean of B - E = rho Phi / ((1 - rho) A_total), W/m^2
    """
    grey = not (np.ndim(rho) or np.ndim(emission))
    rho3, em3 = _check(rho, size, emission, light_fraction, False)
    area = 6.0 * size * size
    light_area = light_fraction * size * size
    power = em3 * light_area
    mean_b = power / ((1.0 - rho3) * area)
    out = {
        "total_area": area,
        "light_area": light_area,
        "emitted_power": power,
        "mean_b": mean_b,
        "mean_b_minus_e": rho3 * mean_b,
    }
    if grey:
        for k in ("emitted_power", "mean_b", "mean_b_minus_e"):
            out[k] = float(out[k][0])
    return out
