"""The final gather of a run's reflected light, composed by the ``Solver`` (``solver.final``).

Planned by the direct phase (``rays`` a receiver: accuracy.FinalPlan), run once the shooting
has shot nearly all the light: a first round and, in accuracy mode, top-up rounds while the
settled estimate is above the target (``rounds.gather_rounds``, the driver a shared run uses
too).  B is replaced by the gathered solution; the ledger stays the shooting's.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from dcrad.solving.rounds import budget_cut_note, gather_rounds
from dcrad.transport.final import FinalGather

if TYPE_CHECKING:
    from dcrad.solving.solver import Solver

__all__ = ["FinalPhase"]


class FinalPhase:
    """``rays``: gather rays per receiver planned (0: none); ``done``: a round has run; ``gather``:
    the FinalGather so far (None: none yet); ``cut``: the limit that cut the first round
    ("ray_budget", "time_limit" or "")."""

    def __init__(self, solver: "Solver"):
        self.solver = solver
        self.rays = 0
        self.done = False
        self.gather: FinalGather | None = None
        self.cut = ""

    def pending(self) -> bool:
        """True while a final gather is planned and has not run."""
        s = self.solver
        return bool(self.rays) and s.direct.light is not None and not self.done

    def round(self, rays: int, should_stop=None) -> int:
        """A round of the final gather of the indirect light, ``rays`` rays per receiver (final.py);
        return the rays traced (0: not done: the direct light was shot, or nothing to gather).
        The first round reads the shot solution; later rounds add rays reading the same one.
        ``should_stop()`` True ends the round between two batches (FinalGather._trace)."""
        s = self.solver
        if s.direct.light is None or rays < 2 or not s.patches.rho.any():
            return 0
        self.done = True
        t0 = time.perf_counter()
        if self.gather is None:
            self.gather = FinalGather(s.patches, s.tracer, s.noise.diff, *s.direct.light,
                                      batch_rays=s.config.batch_rays)
        b, d, traced, mismatch = self.gather.round(rays + rays % 2, s.rng, should_stop)
        s.stats.trace_seconds += time.perf_counter() - t0
        s.patches.radiosity, s.noise.diff = b, d
        s.noise.resync(s.patches)
        absorbed = float(s.ledger.absorbed.sum())
        s.choices.set(
            "final_gather", f"final gather of the indirect light: {2 * self.gather.per_half} rays per receiving "
                            f"patch read the shot solution's reflected light (final.py): the ledger is the "
                            f"shooting's and B keeps its reflected total; the indirect light landed differs from "
                            f"the shot by {float(mismatch.sum()) / max(absorbed, 1e-300):.2%} of the absorbed power"
                            + ("; stopped before its last round reached every receiver (those keep fewer "
                               "rays, or the shot solution)" if self.gather.stopped else ""))
        return s.counted(0, traced)

    def finish(self, should_stop=None) -> None:
        """The final gather and its top-up rounds (``gather_rounds``, the driver a shared run uses
        too): a first round of ``final_rays`` a receiver within the limits, then in accuracy mode more
        while the settled estimate is above the target."""
        s = self.solver
        receivers = int(s.patches.rho.any(axis=1).sum())

        def first_cut(cut: int, by: str) -> None:
            if by:
                self.cut = by
                s.choices.add("budget", budget_cut_note(cut, self.rays, by, s.config, s.stats.rays))

        rounds = gather_rounds(self.rays, s.config, receivers,
                               spent=lambda: (s.stats.rays, s.elapsed()),
                               trace=lambda rays: self.round(rays, should_stop),
                               error=s.settled_target_error,
                               halted=lambda: self.gather is None or self.gather.stopped, on_first=first_cut)
        self.cut = rounds.by or self.cut
