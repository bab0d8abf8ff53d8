"""The final gather's rounds: one driver for a run in one process and a shared run.

``gather_rounds`` traces a first round of rays per receiver within the run's limits, then, in
accuracy mode, top-up rounds while the estimate is above the target; ``fit_round`` cuts a round to
what ``--max-rays`` or ``--time-limit`` leaves, and ``budget_cut_note`` says so in ``choices``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from dcrad.config import SolverConfig
from dcrad.solving.accuracy import by_accuracy
from dcrad.transport.final import BRIGHT_SHARE

__all__ = [
    "FINAL_MARGIN", "FINAL_ROUNDS", "Rounds", "budget_cut_note", "fit_round", "gather_rounds", "top_up",
    "within_budget"
]


#: rounds of the final gather at most (the first included; final.FinalGather)
FINAL_ROUNDS = 3
#: a top-up round aims at the target with this margin on the rays: part of the noise is what
#: the gather reads, which more rays do not lower (1.1 left the office at 2.07% for 2%;
#: 1.4 overshot: 7.3M rays for 1.87%)
FINAL_MARGIN = 1.25


def budget_cut_note(cut: int, planned: int, limit: str, config: SolverConfig, used: int) -> str:
    """The report's line on a final gather cut by ``fit_round`` to what ``limit`` ("ray_budget" or
    "time_limit") of ``config`` left (in process and shared runs)."""
    kind, flag = (("time limit", f"--time-limit {config.time_limit:g}") if limit == "time_limit" else
                  ("ray budget", f"--max-rays {config.max_rays}"))
    return (f"{kind}: the final gather cut to {cut} rays per receiving patch (planned {planned}), what "
            f"{flag} leaves after {used} rays" + ("; not gathered: B is the shot solution"
                                                  if cut < 2 else ""))


def fit_round(rays: int, config: SolverConfig, used: int, elapsed: float, receivers: int) -> tuple[int, str]:
    """A final-gather round of ``rays`` a receiver cut to what --max-rays leaves after ``used`` rays
    and what --time-limit leaves after ``elapsed`` s at the run's rate so far (``used / elapsed``
    rays a second), and the limit that cut it: "ray_budget", "time_limit" or "" (none did)."""
    got, by = within_budget(rays, config.max_rays, used, receivers), "ray_budget"
    if config.time_limit and used and elapsed > 0:
        left = used / elapsed * (config.time_limit - elapsed)
        timed = within_budget(rays, used + int(max(left, 0.0)), used, receivers)
        if timed < got:
            got, by = timed, "time_limit"
    return got, by if got < rays else ""


@dataclass
class Rounds:
    """The final gather's rounds as ``gather_rounds`` ran them: rays a receiver of each, and the limit
    that cut one ("ray_budget", "time_limit" or "": none did)."""

    traced: list[int]
    by: str


def gather_rounds(first: int, config: SolverConfig, receivers: int, spent, trace, error, halted,
                  on_first=None) -> Rounds:
    """The final gather's rounds, one driver for a run in one process (FinalPhase.finish) and a shared
    run (share.run_shared): a first round of ``first`` rays a receiver cut to what the limits leave
    (fit_round; ``on_first(rays, limit)`` is told before it is traced); then, in accuracy mode, while
    ``error()`` is above the target, a top-up round (top_up: (error / target)^2 x FINAL_MARGIN rays a
    receiver in all, at most 8x the first), at most FINAL_ROUNDS rounds in all, none once
    ``halted()`` (a stop was asked, or a round stopped before it reached every receiver) and none the
    limits leave no two rays for (a passed time limit leaves none).  ``spent()`` -> (rays traced so
    far, seconds so far); ``trace(rays)`` traces a round of that many (even) rays a receiver."""
    rays, elapsed = spent()
    more, by = fit_round(first + first % 2, config, rays, elapsed, receivers)
    if on_first is not None:
        on_first(more, by)
    done: list[int] = []
    while more >= 2:
        trace(more)
        done.append(more)
        if len(done) >= FINAL_ROUNDS or not by_accuracy(config) or halted():
            break
        err = error()
        if err <= config.accuracy:
            break
        want = top_up(sum(done), first, err, config.accuracy)
        rays, elapsed = spent()
        more, cut = fit_round(want + want % 2, config, rays, elapsed, receivers)
        by = by or cut
    return Rounds(done, by)


def within_budget(rays: int, max_rays: int, used: int, receivers: int) -> int:
    """Gather rays per receiver of a final round (``rays``) cut to what ``max_rays`` leaves after
    ``used``, even (0: not two fit).  A round of r rays traces r cosine rays a receiver and at
    most BRIGHT_SHARE x r area samples of the bright set (final.FinalGather)."""
    fit = int((max_rays - used) / (max(receivers, 1) * (1.0 + BRIGHT_SHARE))) if max_rays else rays
    return rays if fit >= rays else max(fit - fit % 2, 0)


def top_up(done: int, first: int, err: float, target: float) -> int:
    """Gather rays per receiver of the next top-up round of a final gather that has ``done`` of them
    (``first`` in its first round) and reads ``err`` for ``target``: (err / target)^2 x FINAL_MARGIN
    of them in all, as if the noise were all the gather's sampling, at most 8x the first round's."""
    more = int(math.ceil(done * ((err / target) ** 2 * FINAL_MARGIN - 1.0)))
    return min(more, 8 * first - done)
