"""The ray plan of a run, composed by the ``Solver`` (``solver.budget``): how dense its shooting
is and how it keeps to --max-rays.

A first pass of a run that shoots all its light spends a share of the density
(``calibrate``, set by passes.solve_to_accuracy); under --max-rays the shooting and the final
gather are coarsened alike to fit what the budget leaves (``fit``), and the gather's rays are
kept for it (``gather_reserve``).  The power per ray and the ledger stay the solver's.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from dcrad.solving.accuracy import by_accuracy
from dcrad.transport.final import BRIGHT_SHARE

if TYPE_CHECKING:
    from dcrad.solving.solver import Solver

__all__ = ["Budget", "BUDGET_FIT"]

#: a run under --max-rays plans its shooting and gather to this share of what the budget leaves
#: (``Budget.fit``): the rest is for the shots' ray floors and the prediction's error
BUDGET_FIT = 0.85


class Budget:
    """``calibration``: share of the density a first accuracy pass shoots at when its light is all
    shot (no final plan; 1: the whole density); ``gather_reserve``: rays kept for the final gather
    under --max-rays (the shooting stops short of them); ``fitted``: ``fit`` has run."""

    def __init__(self, solver: "Solver"):
        self.solver = solver
        self.calibration = 1.0
        self.gather_reserve = 0
        self.fitted = False

    def with_reflections(self, power: np.ndarray) -> tuple[float, float]:
        """(W, W): the power (3,) and all its reflections, P / (1 - rho) for the scene's mean
        reflectance rho weighted by the power's channels, and P itself."""
        s = self.solver
        power = np.abs(power)
        total = float(power.sum())
        rho = float(np.dot(s.patches.mean_rho, power) / max(total, 1e-300))
        return total / (1.0 - min(rho, 0.95)), total

    def shoot_prediction(self) -> float:
        """Rays the shooting will take from here: the unshot power and its reflections, a ray per
        ``power_per_ray`` (the shots' floors come on top: ``BUDGET_FIT`` leaves them room)."""
        s = self.solver
        return self.with_reflections(s.ledger.unshot)[0] / max(s.power_per_ray, 1e-300)

    def plan_rays(self, plan, receivers: int) -> float:
        """Rays a final plan's shooting and gather would take from here (before the direct gather:
        the reflections of the emitted power are what will be shot)."""
        s = self.solver
        everything, emitted = self.with_reflections(s.ledger.emitted)
        ppr = emitted / (plan.shoot_rays_per_power * s.role.shoot_share)
        shoot = (everything - emitted) / max(ppr, 1e-300)
        return shoot + plan.final_rays * receivers * (1.0 + BRIGHT_SHARE) * s.role.shoot_share

    def left(self) -> int | None:
        """Rays --max-rays leaves this run (None: no budget; a shared run's replica: its 1/k of what
        the shared direct gather left).  The plan is fitted to the ray budget only (``Budget.fit``):
        a run's seconds are not in proportion to its rays (a coarser shooting makes more shots of
        fewer rays, each with its own cost: the office 3x3 fitted to 1 s traced 1.1M rays where the
        plan traced 2.1M), so a time limit only cuts the final gather (``fit_round``)."""
        s = self.solver
        cfg = s.config
        if not cfg.max_rays:
            return None
        preset = s.role.preset_direct
        spent = s.stats.rays + (preset.rays * s.role.shoot_share if preset is not None else 0)
        return int(cfg.max_rays - spent)

    @staticmethod
    def scale(left: float, need: float) -> float:
        """The share of the planned density that fits ``need`` rays in BUDGET_FIT of ``left`` (1: it fits)."""
        if need <= BUDGET_FIT * left:
            return 1.0
        return max(BUDGET_FIT * left, 0.0) / max(need, 1e-300)  # 0: nothing left (the run stops by the budget)

    def calibrate(self) -> None:
        """As the shooting starts: a first pass that shoots all its light (no final plan) spends
        ``calibration`` of the run's density.  The density comes from the unknowns' count and a
        constant (accuracy.rays_for), but the noise a ray leaves differs from scene to scene
        (noise^2 x density / unknowns: Cornell 0.32, the classroom 0.15, the ice-cream store 0.073):
        a sparse first pass measures it, and passes.solve_to_accuracy runs an independent second
        pass at the density that brings the blend to the target when it is needed.  The blend
        weighs the passes by inverse variance, so the first pass's rays are not lost."""
        s = self.solver
        share = self.calibration
        if not (0.0 < share < 1.0) or s.final.pending() or not by_accuracy(s.config):
            return
        s.power_per_ray /= share
        s.choices.add("density", f"first pass at {share:g} of the density ({self.density():.3g} rays per emitted "
                            f"power): its measured noise sets the density of a second pass if one is needed")

    def density(self) -> float:
        """Rays per emitted power this run's shooting spends."""
        s = self.solver
        return float(s.ledger.emitted.sum()) / max(s.power_per_ray, 1e-300)

    def fit(self) -> None:
        """Under --max-rays, in accuracy mode, as the shooting starts: when the shooting to its end and
        the final gather (if planned) would not fit in what the budget leaves, coarsen both alike
        (fewer rays a unit of power, fewer gather rays a receiver), so the light is all shot and
        gathered within the budget.  Without it a small budget stopped the shooting with most of the
        light unshot: the office 3x3 at 1e6 rays read 41% off (bench/RESULTS.md).  The gather's
        rays are then kept for it (``gather_reserve``): the shooting stops short of them."""
        s = self.solver
        self.fitted = True
        cfg = s.config
        left = self.left()
        if left is None or not by_accuracy(cfg):
            return
        receivers = int(s.patches.rho.any(axis=1).sum())
        per_ray = receivers * (1.0 + BRIGHT_SHARE) * s.role.shoot_share  # this run's share of a gather ray
        pending = s.final.pending()
        shoot, gather = self.shoot_prediction(), (s.final.rays * per_ray if pending else 0.0)
        f = self.scale(left, shoot + gather)
        if 0.0 < f < 1.0:
            s.power_per_ray /= f
            if pending:
                s.final.rays = max(2 * int(s.final.rays * f / 2), 2)
            share = f" (this replica's 1/{s.role.replicas} of them)" if s.role.replicas > 1 else ""
            takes = f"{shoot:.3g} shooting" + (f", {gather:.3g} in the final gather" if pending else "")
            gives = (f"shooting at {float(s.ledger.emitted.sum()) / s.power_per_ray:.3g} rays per emitted "
                     f"power" + (f", {s.final.rays} gather rays per receiving patch" if pending else ""))
            s.choices.add(
                "budget", f"ray budget: --max-rays {cfg.max_rays} leaves about {left} rays{share}, and the plan "
                                f"would take about {shoot + gather:.3g} ({takes}): its density is coarsened to "
                                f"{f:.2g}x ({gives}) to fit")
        if pending:
            self.gather_reserve = int(math.ceil(s.final.rays * per_ray))
