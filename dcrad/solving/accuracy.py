"""The accuracy target as the main knob: ray density, stop rule and passes.

``SolverConfig.accuracy`` (``--accuracy``, default 0.02) is a target for the
estimated RMS error over the RMS of the reflected light B - E (noise.py).  While
``tol`` is 0 (its default) a run

* chooses the power per ray from the patch count and the target
  (``rays_for``; ``rays_per_power`` overrides it);
* stops when the estimate meets the target (``stopped_by: accuracy``), or at
  ``time_limit`` / ``max_rays``;
* when its light is all but shot (bias below a quarter of the target) and the
  noise is still above the target, the ray density was too low for this scene:
  the pass stops (``noise_floor``).  ``passes.solve_to_accuracy`` (single-subscene
  runs) then runs an independent pass at the density that brings the blend
  under the target and blends the passes by inverse variance, B = sum w_k B_k /
  sum w_k with w_k = 1 / (estimated error of pass k)^2 (the half-solution
  differences and the ledger blend alike, so the estimate and the books stay
  exact), at most ``MAX_PASSES`` passes.  A divided run stops on the floor and
  says so.

A single-subscene run whose direct light is gathered from exact form factors
follows a ``FinalPlan`` instead: it shoots the reflected light at a small share of
the density, stops shooting once the bias is below FINAL_BIAS_SHARE of the target
(``final_gather``), gathers the reflected light again with many rays per receiver
(final.py) and tops that gather up while the estimate is above the target
(final_phase.FinalPhase.finish); ``noise_floor`` then means the gather could not get there.

With ``tol`` > 0 a run stops at that residual instead and ``accuracy`` is not
used (it reads 0 in the resolved settings); ``rays_per_power`` is then 2e5
unless given, as before the target existed.
"""

from __future__ import annotations

import math

import numpy as np

from dcrad.config import MAX_RAYS_PER_POWER, SolverConfig
from dcrad.errors import ConfigError

__all__ = ["by_accuracy", "resolve", "rays_for", "LEGACY_TOL", "LEGACY_RAYS_PER_POWER", "MAX_PASSES",
           "noise_floor", "residual_goal", "pass_target", "describe", "noise_floor_note", "FinalPlan",
           "final_plan", "SHOOT_SHARE", "FINAL_SHARE", "SHADOW_SHARE", "FINAL_MIN_RAYS", "SHOOT_FLOOR",
           "SHADOW_FLOOR", "FINAL_BIAS_SHARE"]

LEGACY_TOL = 0.01  #: residual tolerance when neither tol nor accuracy is set
LEGACY_RAYS_PER_POWER = 2e5  #: ray density of runs that stop by tol
#: rays_per_power = RAYS_PER_PATCH * patches / accuracy^2.  Measured noise^2 * rays_per_power
#: / patches on converged runs: Cornell 0.32 (shooting), 0.22 (direct gather), office 0.16.
#: Rays to reach 3%: 0.4 -> Cornell 11.9M, office 21.5M; 0.25 -> 8.3M, 13.8M; 0.18 -> 13.7M
#: (Cornell needed a second pass), 10.7M (bench/RESULTS.md)
RAYS_PER_PATCH = 0.25
MAX_PASSES = 3  #: passes of one single-subscene run at most (the first one included)
#: a pass is done when its bias is below this share of the target (the rest is noise)
BIAS_SHARE = 0.25
#: a later pass aims the blend at this share of the target
MARGIN = 0.9


#: A single-subscene run in accuracy mode whose direct light is gathered from exact form
#: factors (direct.gather_analytic) spends the density d = rays_per_power differently: it
#: shoots the reflected light at SHOOT_SHARE * d (coarse: the shot solution is only read),
#: then gathers it again with FINAL_SHARE * d / patches rays per receiver (final.py), and
#: gathers the direct light with SHADOW_SHARE * d / patches shadow rays per receiver.
#: Measured on Cornell (23680 patches) and the office 3x3 (19884) at 1.3-1.4% of the
#: reflected light: 3e5 rays per power shot with an 8-ray floor, 16-32 shadow rays and 256
#: gather rays per patch were the cheapest mix (bench/RESULTS.md).
SHOOT_SHARE = 0.02
FINAL_SHARE = 0.2
SHADOW_SHARE = 0.03
#: floors: rays per emitted power per patch of the shooting, shadow rays per receiver (at 2% the
#: shares alone left the office's shot solution and direct light too noisy for more gather rays
#: to help: 6.3M rays for 1.99%, against 1.35% for 6.2M at 1.5%).  With the Korobov gather the
#: shot solution's noise (read by every gather ray) weighed more: Cornell, error (%) x sqrt(M rays)
#: at ~6M rays: floor 30 2.44, 40 2.35, 45 2.32, 50 2.29, 60 2.30, 75 2.31 (office 3x3 at 0.0125:
#: 30 2.73, 50 2.66); shadow rays 24 2.35, 32 2.29, 44 2.38
SHOOT_FLOOR = 50.0
SHADOW_FLOOR = 32
#: fewest rays per patch shot in such a run (the shot solution is read by many gather rays,
#: so a weak shot needs no 32 rays of its own: 8 cut Cornell's shooting rays 2x; 4 cut them
#: from 1.01M to 0.76M at --accuracy 0.0175 for the same error, 1.04%)
FINAL_MIN_RAYS = 4
#: such a run stops shooting (and gathers) once the unshot light's bias is below this share of
#: the target: the final gather keeps the shot total, so the bias stays in B.  Cornell at
#: --accuracy 0.0175: 0.25 left a bias of 0.40% of the reflected light (15% of the error's
#: square) and took 6.02M rays for 1.04%; 0.1 left 0.17% and took 6.15M for 0.99%
FINAL_BIAS_SHARE = 0.1


class FinalPlan:
    """How a final-gather run spends its density: power per ray of the shooting, rays per
    receiver of the final gather and of the direct gather, the floor per shot."""

    def __init__(self, config: SolverConfig, patches: int):
        per_patch = config.rays_per_power / max(patches, 1)
        self.shoot_rays_per_power = max(config.rays_per_power * SHOOT_SHARE, SHOOT_FLOOR * max(patches, 1), 1e3)
        self.final_rays = int(min(max(2 * round(FINAL_SHARE * per_patch / 2), 16), 4096))
        self.shadow_rays = config.shadow_rays or int(min(max(2 * round(SHADOW_SHARE * per_patch / 2),
                                                             SHADOW_FLOOR), 512))
        self.min_rays = min(config.min_rays, FINAL_MIN_RAYS)


def final_plan(config: SolverConfig, patches: int) -> FinalPlan | None:
    """The plan of a run that will gather its reflected light at the end, or None (tol mode,
    no direct gather, or no final gather: ``direct`` off)."""
    if not by_accuracy(config) or not config.direct:
        return None
    return FinalPlan(config, patches)


def by_accuracy(config: SolverConfig) -> bool:
    """True when the run stops by its error estimate (tol 0 and an accuracy target)."""
    return config.tol == 0.0 and config.accuracy > 0.0


def rays_for(patches: int, accuracy: float) -> float:
    """Default ray density (rays for shooting the emitted power once) for a target.

    Noise per patch falls as 1/sqrt(hits): the rays needed grow with the number
    of patches and as 1/accuracy^2.
    """
    return max(RAYS_PER_PATCH * max(patches, 1) / (accuracy * accuracy), 1e3)


def resolve(config: SolverConfig, patches: int | None = None) -> SolverConfig:
    """The concrete settings of a run over ``patches`` patches (idempotent).

    Accuracy mode keeps tol = 0 and fills in rays_per_power (when ``patches`` is
    known); otherwise tol defaults to 0.01, rays_per_power to 2e5 and accuracy reads 0.
    """
    if by_accuracy(config):
        if config.rays_per_power > 0 or patches is None:
            return config
        rays = rays_for(patches, config.accuracy)
        if rays > MAX_RAYS_PER_POWER:
            least = math.sqrt(RAYS_PER_PATCH * max(patches, 1) / MAX_RAYS_PER_POWER)
            raise ConfigError(f"--accuracy {config.accuracy:g} for {patches} patches needs about {rays:.2g} rays "
                              f"per emitted power, more than {MAX_RAYS_PER_POWER:.0e} (months of tracing); "
                              f"ask for {least:.2g} or more")
        return config.replace(rays_per_power=rays)
    return config.replace(tol=config.tol or LEGACY_TOL, accuracy=0.0,
                          rays_per_power=config.rays_per_power or LEGACY_RAYS_PER_POWER)


def residual_goal(config: SolverConfig) -> float:
    """The residual a run works towards: ``tol``, or in accuracy mode half the target.

    A subscene's adaptive doIterations stop at its share of it (divide.py); in
    accuracy mode the run itself stops by the estimate.  The unshot light a
    residual r leaves is about r of the reflected light (Cornell divided at
    r = 0.028: bias 2.9%), so half the target leaves the noise most of it.
    """
    return config.tol if config.tol > 0 else 0.5 * config.accuracy


def noise_floor(estimate, accuracy: float) -> bool:
    """A pass can do no better: its light is nearly all shot and the noise is above target."""
    return estimate.bias_refl <= BIAS_SHARE * accuracy and estimate.noise_refl > accuracy


def pass_target(so_far: float, accuracy: float, bias: float = 0.0) -> float:
    """The noise a new independent pass must reach for the blend with passes of noise ``so_far``
    (relative) to come to MARGIN * accuracy with ``bias`` beside it: 1/t^2 = 1/n^2 - 1/so_far^2,
    n^2 = (m a)^2 - bias^2 (the passes' noise averages down in the blend, their bias does not; n at
    least half of m a: a bias near the target would otherwise ask for any density at all)."""
    goal = max(math.sqrt(max((MARGIN * accuracy) ** 2 - bias ** 2, 0.0)), 0.5 * MARGIN * accuracy)
    room = 1.0 / goal ** 2 - 1.0 / max(so_far, goal * 1.0001) ** 2
    return 1.0 / np.sqrt(room)


def describe(config: SolverConfig) -> str:
    """One line on how the run chose its density and stop rule (for the report's choices)."""
    if by_accuracy(config):
        return (f"accuracy target {config.accuracy:g} of the reflected light: {config.rays_per_power:.3g} rays "
                f"per emitted power, stop when the error estimate meets it")
    return f"stop at residual {config.tol:g} with {config.rays_per_power:.3g} rays per emitted power (expert settings)"


def noise_floor_note(estimate, accuracy: float) -> str:
    """The report's line when a run ended on its noise floor, above the target."""
    noise = estimate.noise_refl if estimate is not None else float("nan")
    return (f"stopped on the noise floor: all light shot but the estimated noise {noise:.4f} of the reflected "
            f"light is above the target {accuracy:g}; more rays per emitted power (--rays-per-power) or "
            f"more passes would lower it")
