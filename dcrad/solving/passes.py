"""Accuracy passes: run a Solver to its target; blend independent passes by inverse variance.

``solve_to_accuracy`` runs one Solver (single-subscene runs).  When a pass ends
on its noise floor (accuracy.py: its light all but shot, its noise above the
target), an independent pass runs at the density that brings the blend to the
target, and the two are blended: B = sum w_k B_k / sum w_k with w_k = 1 /
(estimated error of pass k)^2.  B, dB, the half-solution differences, the
ledger and the return tallies are all linear in the rays' outcomes, so the
blend is a solution whose books close and whose estimate is that of the blend.
"""

from __future__ import annotations

from dcrad.choices import Choice, Choices
from dcrad.config import SolverConfig
from dcrad.estimate.noise import finite
from dcrad.solving.accuracy import BIAS_SHARE, MAX_PASSES, pass_target
from dcrad.solving.energy import ACCOUNTS, MAGNITUDES
from dcrad.solving.solver import Solver

__all__ = ["blend", "solve_to_accuracy", "settle", "PASS_SEED", "PASS_GROWTH", "CALIBRATION", "SPARSER"]

#: each further pass seeds its random streams this much after the pass before
PASS_SEED = 7919
#: a further pass is at most this many times denser than the pass before
PASS_GROWTH = 4.0
#: a first pass that shoots its light spends this share of the density (Budget.calibrate)
CALIBRATION = 0.25
#: the sparsest a pass after a calibrated one may be, against it
SPARSER = 0.5


def blend(solver, saved: dict, weight_saved: float, weight_now: float) -> None:
    """Blend ``solver``'s state with ``saved`` (``_save``) in proportion to the weights.

    B, dB, the half-solution differences, the ledger and the return tallies are all
    linear in the rays' outcomes, so the blend is a solution whose books close.
    """
    total = weight_saved + weight_now
    a, b = weight_saved / total, weight_now / total
    p, led = solver.patches, solver.ledger
    p.radiosity = a * saved["radiosity"] + b * p.radiosity
    p.unshot = a * saved["unshot"] + b * p.unshot
    solver.noise.diff = a * saved["diff"] + b * solver.noise.diff
    solver.noise.unshot = a * saved["diff_unshot"] + b * solver.noise.unshot
    for name in ACCOUNTS + MAGNITUDES:
        setattr(led, name, a * getattr(saved["ledger"], name) + b * getattr(led, name))
    solver.tallies = a * saved["tallies"] + b * solver.tallies
    solver.recount()  # |dB| sums are not linear: recount them from the blended table
    solver.noise.resync(p)
    solver.pool.invalidate()


def _save(solver) -> dict:
    p = solver.patches
    return {"radiosity": p.radiosity.copy(), "unshot": p.unshot.copy(), "diff": solver.noise.diff.copy(),
            "diff_unshot": solver.noise.unshot.copy(), "tallies": solver.tallies.copy(),
            "ledger": solver.ledger.copy()}


def solve_to_accuracy(patches, config: SolverConfig, tracer=None, on_progress=None, should_stop=None):
    """Run a Solver; in accuracy mode, while a pass ends on its noise floor, run another
    independent pass and blend (module doc).  Returns the last Solver, holding the blend;
    its stats, time limit and ray budget count every pass.
    """
    solver = Solver(patches, config, tracer=tracer)
    if not config.rays_per_power:  # the density is the run's own choice: measure the scene's noise first
        solver.budget.calibration = CALIBRATION
    solver.run(on_progress=on_progress, should_stop=should_stop)
    goal = solver.config.accuracy
    passes = 1
    while solver.stats.stopped_by == "noise_floor" and passes < MAX_PASSES:
        est, cfg, done = solver.estimate(), solver.config, solver.stats
        saved, weight = _save(solver), 1.0 / max(est.rms, 1e-300) ** 2
        # the pass's direct-light entries become "pass" entries (labelled already after the first pass)
        earlier = Choices(c if c.code in ("pass", "density") else
                          Choice("pass", c.text if passes > 1 else f"pass {passes}: {c.text}")
                          for c in solver.choices.of("direct", "pass", "density"))
        # a pass that ended just above the target needs little from the next: its own target can come
        # out above 1 (a closed cube: 1.27), which is no accuracy at all; half the light is plenty
        # (the bias the blend will carry: at least what a later pass leaves, its cap below)
        target = min(pass_target(est.noise_refl, goal, max(est.bias_refl, BIAS_SHARE * goal)), 0.5)
        # never sparser than the pass before: at low densities the 32-ray floors and the gather's
        # tails make a pass's noise hard to predict
        # and never more than PASS_GROWTH times denser: a pass's own noise can be far above what its
        # density predicts (a lamp in a fixture), and escalating by the ratio can ask for 4e9 rays per
        # emitted power, which no run can pay
        # ... except after a calibrated first pass (Budget.calibrate), which shot at a share of the
        # density: the next one starts from what it spent, may be sparser (its noise follows its
        # density: the ice-cream store's first pass read 2.18% at 3.9e6 rays per emitted power, and a
        # second pass as dense would pay twice for 1.8%) and may grow to PASS_GROWTH times the whole
        # density (a uniform furnace needed 6.7x its first pass, and at 4x ended on its noise floor)
        calibrated = passes == 1 and bool(solver.choices.of("density"))
        density = solver.budget.density() if calibrated else cfg.rays_per_power
        growth = PASS_GROWTH / solver.budget.calibration if calibrated else PASS_GROWTH
        # (10% more than the noise asks, but after a calibrated pass, whose noise was measured at a
        # density like the next one's: MARGIN is margin enough)
        want = max((est.noise_refl / target) ** 2 * (1.0 if calibrated else 1.1), SPARSER if calibrated else 1.0)
        rpp = density * min(want, growth)
        shot = solver.direct.tried and solver.direct.light is None and not solver.final.rays
        if want > growth:
            earlier.add("pass", f"pass {passes + 1}: the target would want {want:.3g}x the density of pass {passes}; "
                           f"held to {growth:g}x (passes.PASS_GROWTH)")
        patches.reset()
        # its own random streams: a pass with the same seed would repeat the first one's rays
        # (passes * PASS_SEED: the seed of the run is put back after each blend, and a third pass seeded
        # like the second repeated its rays, which the blend took for independent ones)
        solver = Solver(patches, cfg.replace(rays_per_power=rpp, accuracy=target,
                                             seed=config.seed + passes * PASS_SEED), tracer=solver.tracer)
        # the pass before decided to shoot its direct light after a gather on every receiver (its
        # pilot): the decision stands, and its shadow rays are not paid twice
        solver.direct.tried = shot
        solver.bias_cap = BIAS_SHARE * goal
        solver.settled = True  # the clusters settle on the blend, whose noise is lower (below)
        solver.stats.rays, solver.stats.shots, solver.stats.batches = done.rays, done.shots, done.batches
        solver.stats.wall_seconds, solver.stats.trace_seconds = done.wall_seconds, done.trace_seconds
        solver.run(on_progress=on_progress, should_stop=should_stop)
        now = solver.estimate()
        blend(solver, saved, weight, 1.0 / max(now.rms, 1e-300) ** 2)
        passes += 1
        solver.config = solver.config.replace(accuracy=goal, seed=config.seed)
        solver.choices = Choices(earlier + [c if c.code != "direct" else Choice("direct", f"pass {passes}: {c.text}")
                                            for c in solver.choices])
        solver.choices.add("passes",
            f"accuracy pass {passes}: the passes before ended on their noise floor ({est.rms_refl:.4f} of the "
            f"reflected light at {density:.3g} rays per emitted power); an independent pass at "
            f"{rpp:.3g} reached {now.rms_refl:.4f} and the two were blended by inverse variance")
        reason = solver.stats.stopped_by
        # the clusters settle on the blend before it is judged (the report's estimate): on either pass
        # alone their noise hides the spread of clusters whose light varies (the ice-cream store's
        # second pass undid 21 of 6,162)
        solver.settled = False
        solver.settled_target_error()
        blended = solver.estimate()
        if reason in ("accuracy", "noise_floor", "tolerance"):
            solver.stats.stopped_by = "accuracy" if blended.rms_refl <= goal else "noise_floor"
        if solver.snapshots:  # the last snapshot's estimate is the blend's (its B stays the last pass's)
            last = solver.snapshots[-1]
            last.error_rms, last.error_refl = finite(blended.rms), finite(blended.rms_refl)
    settle(solver)
    return solver


def settle(solver) -> None:
    """Clusters whose patches' light differs beyond their noise are undone, the rest keep one B
    (NoiseTally.settle); the report says how many, and the estimate counts the kept ones' bias."""
    if not solver.noise.pooled:
        return
    kept, undone = solver.settle()
    solver.choices.add("clusters", f"clusters: {kept} keep one B (their patches agree within four times their noise's "
                          f"spread; the rest of their spread is in the estimate's bias), {undone} undone (their "
                          f"patches' light differs beyond their noise: each keeps its own B)")
