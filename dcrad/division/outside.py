"""The light from outside the model (the sky and the sun, sky.py) in a divided run.

A subscene holds its cell's patches only: a ray that leaves the cell through the scene's box has
left the model, but a gather ray that crosses a boundary cannot learn at once whether its line of
sight goes on out of the model through the next cell.  So the sky and the sun are gathered once,
on the whole scene, before it is cut (``gather_outside``: the same ``DirectPhase`` a run in one
process spends them with, so the gather is the one that run would make, its two independent
halves included), and each subscene is handed what landed on its patches (``OutsideLight.for_cell``,
an ``emitters.Gathered``): its pieces take their parent's irradiance times their area, which the
clipping conserves.  The subscene books it as emitted and lays it down at its first iterate
(``DirectPhase.deposit``); from there it is reflected and crosses the boundaries like any light.
The books hold what lands, as a run in one process books the sky's and the sun's light: what met
the envelope's outside or passed the model by never entered it.  The gather's rays go with the
first cell's share.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from dcrad.choices import Choices
from dcrad.config import SolverConfig
from dcrad.meshing.patches import Patches
from dcrad.solving.accuracy import resolve
from dcrad.solving.passes import PASS_SEED
from dcrad.solving.solver import Solver
from dcrad.transport.emitters import Gathered, sources_power

__all__ = ["OutsideLight", "gather_outside", "split_outside"]


def split_outside(sources) -> tuple[tuple, tuple]:
    """(the light sources among ``sources`` that shine from outside the model (``outside``: sky.py),
    the others)."""
    inside = tuple(s for s in sources if not getattr(s, "outside", False))
    return tuple(s for s in sources if getattr(s, "outside", False)), inside


@dataclass
class OutsideLight:
    """What the sky and the sun put on the whole scene (``gather_outside``)."""

    name: str
    irradiance: np.ndarray  #: (n,3) W/m^2 on each patch of the whole table
    irradiance_a: np.ndarray  #: (n,3) W/m^2 of it from half A's samples
    rays: int  #: rays the gather traced
    choices: Choices  #: what the gather chose (the report's lines)

    def noise(self, patches: Patches) -> float:
        """RMS of the noise of the direct light it reflects over RMS of that light (area-weighted, all
        channels): half the difference of its two halves' estimates, rho (E_A - E_B) / 2."""
        rho, a = patches.rho, patches.area[:, None]
        half = rho * (2.0 * self.irradiance_a - self.irradiance)
        light = float((a * (rho * self.irradiance) ** 2).sum())
        return math.sqrt(float((a * half ** 2).sum()) / light) if light > 0 else 0.0

    def combine(self, other: "OutsideLight") -> "OutsideLight":
        """Two independent gathers as one, each in proportion to its rays (their halves stay halves)."""
        w = self.rays / max(self.rays + other.rays, 1)
        return OutsideLight(self.name, w * self.irradiance + (1 - w) * other.irradiance,
                            w * self.irradiance_a + (1 - w) * other.irradiance_a,
                            self.rays + other.rays, Choices([*self.choices, *(c for c in other.choices
                                                                              if c not in self.choices)]))

    def for_cell(self, sub: Patches, parent: np.ndarray, first: bool) -> Gathered | None:
        """The light that landed on a cell's pieces (``sub``, their ``parent`` rows of the whole table);
        the gather's rays with the ``first`` cell's.  None when nothing landed there and it is not the
        first."""
        got = self.irradiance[parent]
        rows = np.flatnonzero(got.any(axis=1))
        if not len(rows) and not first:
            return None
        area = sub.area[rows, None]
        return Gathered(self.name, rows, got[rows] * area, self.irradiance_a[parent[rows]] * area,
                        rays=self.rays if first else 0)


#: the gather's own noise (of the direct light it reflects: the final light's is lower) may be this
#: share of the accuracy target; above it the gather runs again, denser, and the two are combined
#: (a divided run has no accuracy passes to lower it later: it ends on its noise floor)
NOISE_SHARE = 0.5
#: gathers at most, and the most a further one may grow the density by (passes.PASS_GROWTH's reasons)
MAX_GATHERS, GROWTH = 3, 4.0


def gather_outside(patches: Patches, config: SolverConfig) -> OutsideLight | None:
    """The sky's and the sun's light on every patch of ``patches``, gathered as a run in one process
    gathers it (``DirectPhase.shoot_sources`` on a Solver of the whole scene, its light kept, not the
    Solver); None when no source shines from outside.  ``patches`` is not changed.

    In accuracy mode (no ray budget) the gather's noise, in proportion to its share of the run's
    light, is held to NOISE_SHARE of the target: a run in one process lowers it by further passes, a
    divided one cannot.  A denser gather is combined
    with the ones before it in proportion to their rays (each is unbiased; its halves stay
    independent)."""
    outside, inside = split_outside(patches.sources)
    if not outside:
        return None
    config = resolve(config, patches.read_units)
    light = _gather(patches, config, outside)
    goal = NOISE_SHARE * config.accuracy
    density = config.rays_per_power
    # the rest of the run's light dilutes the gather's noise: office3's lamps emit 4x what the sky lands
    # there, and held to the sky's own light its gather went on to 30M rays (the run ends on the
    # shooting's noise floor all the same)
    others = float(patches.emitted_power.sum()) + float(sources_power(inside).sum())
    for k in range(1, MAX_GATHERS):
        landed = float((light.irradiance * patches.area[:, None]).sum())
        noise = light.noise(patches) * (landed / (landed + others) if landed > 0 else 1.0)
        if not (goal > 0 and not config.max_rays and noise > goal):
            break
        density *= min(GROWTH, 1.1 * (noise / goal) ** 2)
        more = _gather(patches, config.replace(rays_per_power=density, seed=config.seed + k * PASS_SEED), outside)
        light = light.combine(more)
        light.choices.add("direct", f"{light.name}: gathered again at {density:.3g} rays per emitted power: the "
                                    f"gather before read {noise:.4f} of the run's light (its noise on the light it "
                                    f"reflects, times its share of the light), above {NOISE_SHARE:g} of the target "
                                    f"(a divided run has no further passes)")
    return light


def _gather(patches: Patches, config: SolverConfig, outside: tuple) -> OutsideLight:
    work = dataclasses.replace(patches, radiosity=patches.radiosity.copy(), unshot=patches.unshot.copy(),
                               sources=outside)
    solver = Solver(work, config)
    solver.direct.kept = []
    solver.direct.shoot_sources()
    n = len(patches)
    got, got_a = np.zeros((n, 3)), np.zeros((n, 3))
    for t in solver.direct.kept:
        np.add.at(got, t.hit, t.received)
        np.add.at(got_a, t.hit, t.received_a if t.received_a is not None else 0.5 * t.received)
    area = np.maximum(patches.area, 1e-300)[:, None]
    names = " and ".join(s.name for s in outside)
    return OutsideLight(names, got / area, got_a / area, solver.stats.rays, solver.choices)
