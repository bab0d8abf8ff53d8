"""The books of a divided run (in process or on workers) for its report: ``divided_books``."""

from __future__ import annotations

import numpy as np

from dcrad.choices import Choices
from dcrad.config import SolverConfig
from dcrad.meshing.patches import Patches
from dcrad.outputs.report import RunBooks
from dcrad.solving.accuracy import describe, noise_floor_note, resolve
from dcrad.solving.solver import GREY_CHOICE, Stats
from dcrad.solving.stiffness import stiff_choice

__all__ = ["divided_books", "dense_twin_bytes"]


def dense_twin_bytes(boundaries) -> int:
    """Bytes dense twin buffers would hold: a sent and a pending buffer (RGB float64) for each
    crossing of every portal cell and direction bin."""
    return sum(2 * b.n_cells * b.n_bins * 2 * 3 * 8 for b in boundaries)


def divided_books(run, patches: Patches, config: SolverConfig, boundaries, part, divide,
                  timings: dict[str, float] | None = None) -> RunBooks:
    """The books of a divided run (in process or on workers) from its last barrier's states.

    ``patches`` holds the assembled B.  The report's ``divided`` section is in
    ``books.divided``; the coordinator adds its service figures to it.
    """
    config = resolve(config, patches.read_units)  # the settings the run used (ray density, stop rule)
    states = run.states
    last = run.snapshots[-1]
    stats = Stats(shots=last.shots, rays=last.rays, batches=sum(s.batches for s in states),
                  barriers=run.barriers, trace_seconds=float(sum(s.trace_seconds for s in states)),
                  wall_seconds=run.wall_seconds, stopped_by=run.stopped_by)
    back = np.zeros(max(len(patches.names), 1))
    for s in states:
        back[: len(s.back_by_obj)] += s.back_by_obj[: len(back)]
    choices = Choices()
    if patches.is_grey and len(patches):
        choices.add("grey", GREY_CHOICE)
    delivered = sum(s.twins_delivered for s in states)
    blocks = sum(s.twin_blocks for s in states)
    # dense: a sent and a pending buffer for each crossing of every portal cell and bin
    dense = dense_twin_bytes(boundaries) if divide.mode == "binned" else None
    if divide.mode == "binned":
        choices.add("subscenes", f"twin buffers are sparse: at most {run.max_twin_bytes} bytes held, "
                       f"against {dense} bytes dense (sent and pending, every portal cell, bin "
                       f"and crossing)")
        if config.adaptive_bins and delivered:
            choices.add("subscenes", f"directional resolution where the energy is: {delivered} twin entries "
                           f"arrived, kept as {blocks} direction blocks (light weaker than one ray "
                           f"shares coarser bins)")
    else:
        choices.add("subscenes", f"boundaries forward each crossing ray exactly (no direction bins, which blur light "
                       f"where a boundary crosses open space): at most {run.max_twin_bytes} bytes of rays "
                       f"held at a barrier")
    if run.stiff is not None:
        choices.add("stiff", stiff_choice(run.stiff, config) + " (for the whole divided job)")
    divided = {"subscenes": len(states), "boundaries": len(boundaries), "barriers": run.barriers,
               "mode": divide.mode, "iterations": divide.iterations,
               "barrier_batches": f"adaptive, at most {divide.max_iterations}" if divide.adaptive
               else divide.iterations, "solid": divide.solid,
               "max_twin_bytes": run.max_twin_bytes, "max_barrier_closure": max(run.barrier_closures),
               "twins_delivered": delivered, "twin_blocks": blocks, "dense_twin_bytes": dense,
               "partition": part.as_dict(), "barrier_goals": [round(g, 4) for g in run.goals]}
    landed = [g for g in run.goals if g > 0]
    if landed:
        choices.add("barriers",
                    f"{len(landed)} barrier(s) aimed at the target: each subscene left {landed[-1]:.2f} of its "
                       f"residual, not a quarter, for the estimate to land just below it (divide.landing_goal)")
    choices.add("accuracy", describe(config))
    if run.stopped_by == "noise_floor":
        choices.add("noise_floor",
                    noise_floor_note(run.estimate, config.accuracy) + "; a divided run shoots its direct "
                       "light, where one process (--workers 0) or a shared run gathers it")
    return RunBooks(patches, config, run.ledger, stats, list(run.snapshots), run.snapshot_B, back,
                    choices, dict(timings or {}), divided, estimate=run.estimate,
                    channels=1 if patches.is_grey and len(patches) else 3, stiff=run.stiff)
