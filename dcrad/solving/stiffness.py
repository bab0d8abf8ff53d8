"""Stiff scenes: where the light returns to where it came from (closed bright rooms, lamp cavities).

``stiffness`` reads a run's return tallies: when most of the shot power comes back, plain shooting
converges slowly, and the solver overshoots (shoots an ambient estimate of the light still to come
ahead of time) and spends more rays a shot; ``Stiffness`` holds how, ``stiff_choice`` says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dcrad.config import SolverConfig

__all__ = [
    "Stiffness", "stiff_choice", "stiffness"
]


@dataclass(frozen=True)
class Stiffness:
    """How a (sub)scene shoots now: the ambient scale and the ray budget factor.

    scale      : (3,) 1/m^2, F with ambient irradiance g = F * U (U: signed
                 unshot power, W); zeros: no overshooting
    ray_factor : the power per ray is multiplied by this (>= 1; 1 unless stiff)
    ret        : the return ratio it was estimated from
    """

    scale: np.ndarray
    ray_factor: float = 1.0
    ret: float = 0.0  #: the measured return ratio lambda (largest channel)

    @staticmethod
    def none() -> "Stiffness":
        return Stiffness(np.zeros(3), 1.0)

    @property
    def active(self) -> bool:
        """True when it changes how the scene shoots (overshoot or a larger power per ray)."""
        return bool(self.scale.any()) or self.ray_factor != 1.0

    def min_rays(self, config: SolverConfig) -> int:
        """Fewest rays per patch shot: the floor shrinks with the ray factor.

        The floor spreads a weak shot over the hemisphere; in a stiff scene every
        patch is shot many times (overshoot, then corrections), each with a new
        lattice, so its directions add up over the run.  A full floor there made
        each sweep cost 32 rays per patch for power worth one.
        """
        return max(1, int(math.ceil(config.min_rays / self.ray_factor)))


def stiff_choice(st: Stiffness, config: SolverConfig) -> str:
    """The report's line on what a stiff scene changed."""
    what = []
    if st.scale.any():
        what.append("ambient overshooting")
    if st.ray_factor != 1.0:
        what.append(f"power per ray x{st.ray_factor:.3g} and at least {st.min_rays(config)} rays a patch shot")
    return f"stiff scene (return ratio {st.ret:.4f}): " + ", ".join(what)


def stiffness(tallies: np.ndarray, area: float, config: SolverConfig, mean_rho: np.ndarray | None = None) -> Stiffness:
    """Estimate how stiff a scene is from its return tallies and choose how to shoot.

    tallies: (4,3) W (magnitudes) shot by patches, lost (escaped or back faces),
    landed and kept (``Solver.tallies``, summed over subscenes for a divided
    job); area: m^2 of all patches.  The share of shot power that lands is
    q = 1 - lost / shot (light crossing a boundary is still on its way), and the
    return ratio lambda = q * kept / landed (q times the mean rho where light
    lands).  Before the first shot ``mean_rho`` stands in for lambda (a closed
    scene); without it, nothing is assumed.

    Stiff (lambda >= overshoot_min_return): F = overshoot * q / ((1-lambda) * A),
    and with ``stiff_rays`` the power per ray grows by sqrt((1-min_return)/(1-lambda)).
    """
    shot, lost, landed, kept = np.asarray(tallies, np.float64)
    if area <= 0:
        return Stiffness.none()
    if shot.sum() > 0 and landed.sum() > 0:
        q = np.clip(1.0 - lost / np.maximum(shot, 1e-300), 0.0, 1.0)
        lam = q * kept / np.maximum(landed, 1e-300)
    elif shot.sum() > 0:
        return Stiffness.none()  # nothing has landed: an open scene
    elif mean_rho is not None:
        q, lam = np.ones(3), np.asarray(mean_rho, np.float64)
    else:
        return Stiffness.none()
    lam = np.clip(lam, 0.0, 1.0 - 1e-6)
    if lam.max() < config.overshoot_min_return:
        return Stiffness.none()  # not stiff: the tail is short, plain shooting keeps B >= 0
    factor = math.sqrt((1.0 - config.overshoot_min_return) / (1.0 - float(lam.max()))) if config.stiff_rays else 1.0
    return Stiffness(config.overshoot * q / ((1.0 - lam) * area), max(1.0, factor), float(lam.max()))
