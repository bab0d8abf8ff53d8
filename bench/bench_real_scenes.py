"""Costs of the real-scene features (issue 15): texture means, two-sided patches, output writing.

Prints figures; no assertions.  Run: .venv/bin/python bench/bench_real_scenes.py [triangles]
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import scenes  # noqa: E402
from dcrad.config import SolverConfig  # noqa: E402
from dcrad.io.texture import uv_means  # noqa: E402
from dcrad.pipeline import prepare, write_outputs  # noqa: E402
from dcrad.solving.solver import Solver  # noqa: E402
from scenes.variants import variant  # noqa: E402


def texture_means(n: int) -> None:
    """uv_means over n small UV triangles (about 0.3 texel each, the common case) of a 1024^2 image."""
    rng = np.random.default_rng(0)
    image = rng.random((1024, 1024, 3))
    a = rng.random((n, 1, 2))
    uv = a + rng.normal(scale=1.0 / 1024, size=(n, 3, 2))
    t0 = time.perf_counter()
    uv_means(image, uv)
    dt = time.perf_counter() - t0
    print(f"uv_means: {n:,} triangles in {dt:.2f} s ({n / dt / 1e6:.2f} M triangles/s)")


def office(tmp: Path) -> None:
    """Load, solve and write outputs of a 2x2 office: as built, and Z-up/textured/mixed two-sided."""
    src = scenes.write_builtin("office", tmp / "y", rows=2, cols=2, seed=2)
    model = variant(src, tmp / "z", up="z", flip=0.35, texture=True, seed=7)
    for label, path, two in (("office 2x2", src, False), ("Z-up textured mixed, --two-sided", model, True)):
        t0 = time.perf_counter()
        scene, p, _ = prepare(path, None, 1.0, None, two)
        t_load = time.perf_counter() - t0
        s = Solver(p, SolverConfig(tol=0.05, seed=1))
        s.run()
        t0 = time.perf_counter()
        write_outputs(tmp / "out", scene, p, sections={}, workplane=0.8)
        t_out = time.perf_counter() - t0
        print(f"{label}: {len(p):,} patches; load+mesh {t_load:.2f} s, solve {s.stats.wall_seconds:.2f} s "
              f"({s.stats.rays:,} rays), outputs {t_out:.2f} s")


if __name__ == "__main__":
    texture_means(int(sys.argv[1]) if len(sys.argv) > 1 else 200_000)
    with tempfile.TemporaryDirectory() as tmp:
        office(Path(tmp))
