"""The public API (``dcrad/__init__.py``): its docstring's example runs, its results meet an
independent truth, and ``import dcrad`` stays cheap.

The truth: in the closed white furnace every watt emitted is absorbed in the end, so the
area-weighted mean radiosity is exactly Phi / ((1 - rho) A) (``scenes.furnace.furnace_expected``),
whatever the geometry; the solve's mean misses it by no more than its estimated RMS error (a
mean's error is at most the RMS of the errors it averages).  And a patch keeps rho of the light
that lands on it and absorbs 1 - rho, so sum A (B - E) (1 - rho) / rho read from the returned B
is the power the solver's ledger booked as absorbed.
"""

from __future__ import annotations

import doctest
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import dcrad
from dcrad.pipeline import resolve_scene
from scenes.furnace import furnace_expected


def test_the_docstring_example_runs():
    result = doctest.testmod(dcrad, optionflags=doctest.ELLIPSIS)
    assert result.attempted >= 8 and result.failed == 0, result


@pytest.mark.parametrize("rho", [0.5, 0.8])
def test_the_furnace_meets_its_closed_form_within_the_estimate(tmp_path, rho):
    result = dcrad.solve(resolve_scene(f"furnace:rho={rho}", tmp_path), accuracy=0.05, patch_size=0.25)
    p, est = result.patches, result.estimate
    assert isinstance(est, dcrad.Estimate) and est.rms_refl <= 0.05
    exact = furnace_expected(rho=rho)["mean_b"]
    mean_b = (result.radiosity * p.area[:, None]).sum(axis=0) / p.area.sum()
    assert np.all(np.abs(mean_b - exact) <= est.rms), (mean_b, exact, est)
    assert np.all(np.abs(mean_b - exact) > 0)  # (the run is not converged: the check has teeth)
    # the energy the returned B holds is what the ledger booked as absorbed
    absorbed = ((result.radiosity - p.emission) * p.area[:, None] * (1 - p.rho) / p.rho).sum(axis=0)
    assert np.allclose(absorbed, result.report["ledger"]["absorbed"], rtol=1e-9, atol=0)
    # B per input triangle is the area-weighted mean of its patches: the same power
    scene = result.scene
    tri = scene.vertices[scene.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    assert result.triangle_valid.all() and result.triangle_radiosity.shape == (len(scene.faces), 3)
    assert np.allclose((result.triangle_radiosity * area[:, None]).sum(axis=0),
                       (result.radiosity * p.area[:, None]).sum(axis=0), rtol=1e-12)
    assert result.out is None and result.report["outputs"] == {}


def test_solve_writes_the_outputs_only_when_asked(tmp_path):
    scene = dcrad.load(resolve_scene("cornell", tmp_path))
    before = sorted(tmp_path.rglob("*"))
    quiet = dcrad.solve(scene, accuracy=0.1, patch_size=0.2)
    assert sorted(tmp_path.rglob("*")) == before and "photometry" not in quiet.report

    out = tmp_path / "out"
    written = dcrad.solve(scene, out, accuracy=0.1, patch_size=0.2, width=80, height=60)
    assert written.out == out and (out / "report.json").is_file() and "photometry" in written.report
    assert json.loads((out / "report.json").read_text())["ledger"] == written.report["ledger"]
    npz = np.load(out / "radiosity.npz")
    assert np.array_equal(npz["B"], written.triangle_radiosity) and np.array_equal(npz["patch_B"], written.radiosity)
    # the same seed, the same solve: writing the outputs does not change B
    assert np.array_equal(quiet.radiosity, written.radiosity)


def test_bad_input_raises_the_api_errors(tmp_path):
    path = resolve_scene("cornell", tmp_path)
    with pytest.raises(dcrad.ConfigError, match="sedd"):
        dcrad.solve(path, sedd=3)
    with pytest.raises(dcrad.ConfigError):
        dcrad.load(path, scale=-1.0)
    with pytest.raises(dcrad.SceneError):
        dcrad.load(tmp_path / "missing.obj")
    assert issubclass(dcrad.SceneError, dcrad.DcradError) and issubclass(dcrad.ConfigError, dcrad.DcradError)
    assert dcrad.SolverConfig().accuracy == 0.02  # solve's default is the settings' default


def test_import_dcrad_is_cheap_and_solve_stays_the_function():
    """``import dcrad`` (the command and the workers do it at start) loads no numpy, Embree, trimesh,
    OpenImageIO or gRPC; the API's names come when used; importing the solver's module
    (``dcrad/solving/solver.py``) leaves the function ``dcrad.solve`` as it is."""
    code = """if True:
        import sys
        import dcrad
        heavy = ("numpy", "embreex", "trimesh", "OpenImageIO", "grpc", "google.protobuf", "scipy", "matplotlib")
        loaded = sorted(m for m in sys.modules if m.startswith(heavy))
        assert not loaded, loaded
        assert sorted(m for m in sys.modules if m.startswith("dcrad")) == ["dcrad", "dcrad.errors"]
        from dcrad.solving.solver import Solver
        assert callable(dcrad.solve) and dcrad.solve.__module__ == "dcrad.api", dcrad.solve
        assert sys.modules["dcrad.solving.solver"].Solver is Solver
        for name in dcrad.__all__:
            assert getattr(dcrad, name) is not None, name
        try:
            dcrad.no_such_name
        except AttributeError:
            pass
        else:
            raise AssertionError("dcrad.no_such_name did not raise AttributeError")
        print("ok")
    """
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1])
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr


def test_all_lists_the_api():
    assert set(dcrad.__all__) == {"load", "solve", "Result", "Scene", "Patches", "Estimate", "SolverConfig",
                                  "PointSource", "DaylightSpec", "DcradError", "SceneError", "ConfigError"}
    from dcrad.estimate.noise import Estimate
    from dcrad.io.scene import Scene
    from dcrad.meshing.patches import Patches
    from dcrad.transport.emitters import PointSource

    assert (dcrad.Scene, dcrad.Patches, dcrad.Estimate, dcrad.PointSource) == (Scene, Patches, Estimate, PointSource)
