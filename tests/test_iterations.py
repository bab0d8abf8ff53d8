"""--iterations (DivideConfig.iterations): 0 is adaptive barriers, N > 0 is N batches per barrier.

It used to be ignored (1 and 16 gave bit-identical runs); now a fixed N switches the
adaptive target off, each subscene runs exactly N batches between barriers, and
the count is in the report.
"""

from __future__ import annotations

import numpy as np
import pytest

import scenes
from dcrad.config import DivideConfig, SolverConfig
from dcrad.division.divide import build_subscenes, run_subscenes
from dcrad.pipeline import prepare, solve_to

#: a ray budget, not a tolerance: every run does about the same work, in different barrier schedules
CONFIG = SolverConfig(tol=1e-6, seed=1, rays_per_power=2e4, max_rays=200_000, batch_rays=65536, max_shooters=256)
PATCH = 0.1  # m: 840 patches


@pytest.fixture(scope="module")
def cornell(tmp_path_factory):
    return scenes.write_builtin("cornell", tmp_path_factory.mktemp("cornell"))


def _run(path, iterations: int):
    _, p, _ = prepare(path, PATCH)
    divide = DivideConfig(subscenes=2, iterations=iterations)
    subs, boundaries, parents, _ = build_subscenes(p, CONFIG, divide)
    run = run_subscenes(p, subs, boundaries, parents, CONFIG, divide)
    return run, subs, p.radiosity.copy()


def test_fixed_iterations_are_n_batches_per_barrier_and_change_the_barrier_count(cornell):
    one, subs1, b1 = _run(cornell, 1)
    eight, subs8, b8 = _run(cornell, 8)
    for run, subs, n in ((one, subs1, 1), (eight, subs8, 8)):
        assert run.stopped_by == "ray_budget"
        assert all(s.local_target == 0.0 for s in subs)  # adaptive off
        # each subscene ran exactly n batches at every barrier (there was always light to shoot) but
        # the last, where its share of the ray budget ended it (divide.ray_shares), after at least one
        assert all(n * (run.barriers - 1) + 1 <= s.stats.batches <= n * run.barriers for s in subs), \
            [s.stats.batches for s in subs]
    # the same ray budget: eight batches a barrier need far fewer barriers than one
    assert eight.barriers * 4 <= one.barriers, (one.barriers, eight.barriers)
    assert not np.array_equal(b1, b8)  # the exchange schedule changed the run


def test_adaptive_is_the_default_and_differs_from_a_fixed_count(cornell):
    adaptive, subs, _ = _run(cornell, 0)
    four, _, _ = _run(cornell, 4)
    assert DivideConfig().iterations == 0 and DivideConfig().adaptive
    assert all(s.local_target > 0 for s in subs)
    assert adaptive.barriers != four.barriers


def test_the_report_says_which(cornell, tmp_path):
    fixed = solve_to(cornell, tmp_path / "fixed", CONFIG, patch_size=PATCH, width=32, height=24,
                     divide=DivideConfig(subscenes=2, iterations=1))
    auto = solve_to(cornell, tmp_path / "auto", CONFIG, patch_size=PATCH, width=32, height=24,
                    divide=DivideConfig(subscenes=2))
    assert fixed["divided"]["iterations"] == 1 and fixed["divided"]["barrier_batches"] == 1
    assert auto["divided"]["iterations"] == 0
    assert auto["divided"]["barrier_batches"] == f"adaptive, at most {DivideConfig().max_iterations}"
    assert fixed["stats"]["barriers"] != auto["stats"]["barriers"]
