"""The real models of ../shared/models (issue 26) solve at defaults: regression guards, not truths.

Each is meshed by its light (no refusal, no more elements than about 3x the larger of its input
triangles and area / size^2), solved in this process to the default accuracy target, its books
closed.  Marked ``corpus`` (`-m "not corpus"` skips them); skipped where ../shared is absent.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dcrad.config import SolverConfig
from dcrad.pipeline import solve_to

MODELS = Path(__file__).resolve().parents[2] / "shared" / "models"
NAMES = ["office2", "classroom", "office3", "icecream_store"]

pytestmark = pytest.mark.corpus


@pytest.mark.parametrize("name", NAMES)
def test_a_real_model_solves_at_defaults(tmp_path, name):
    model = MODELS / name / "scene.obj"
    if not model.exists():
        pytest.skip(f"{model} is not here")
    report = solve_to(model, tmp_path, SolverConfig(), width=64, height=48)
    scene, settings = report["scene"], report["settings"]
    size = settings["patch_size_m"]
    assert 0.05 < size < 1.0  # a room's scale, whatever the triangles' (office3's median edge is 6 mm)
    bound = 3 * max(scene["valid_triangles"], scene["total_area_m2"] / size ** 2)
    assert scene["patches"] <= 1.3 * bound
    assert report["ledger"]["closure"] < 1e-9
    assert report["stats"]["stopped_by"] == "accuracy"
    assert report["error"]["rms_refl"] <= SolverConfig().accuracy
    b = np.load(tmp_path / "radiosity.npz")["B"]
    assert np.isfinite(b).all() and b.max() > 0
    assert any(c["code"] == "mesh" and c["text"].startswith("mesh: element size") for c in report["choices"])
