"""Error against run time: sequential vs divided curves, the paper's claims, the files and the CLI."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

import scenes
from dcrad.config import SolverConfig
from dcrad.errors import DcradError
from dcrad.estimate.compare import compare, loglog_interp, write_compare
from dcrad.pipeline import prepare

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def office(tmp_path_factory):
    return scenes.write_builtin("office", tmp_path_factory.mktemp("office"), rows=1, cols=2)


@pytest.fixture(scope="module")
def result(office):
    return compare(office, subscenes=(1, 2), config=SolverConfig(tol=0.05))


@pytest.fixture(scope="module")
def written(result, tmp_path_factory):
    out = tmp_path_factory.mktemp("compare")
    return out, write_compare(result, out)


def test_loglog_interp():
    xs, ys = [0, 10, 100, 1000], [5.0, 1.0, 0.1, 0.01]
    assert loglog_interp(xs, ys, 100) == pytest.approx(0.1)
    assert loglog_interp(xs, ys, 10 ** 1.5) == pytest.approx(10 ** -0.5)  # straight in log-log
    assert loglog_interp(xs, ys, 5) is None and loglog_interp(xs, ys, 2000) is None


def test_runs_and_curves(result):
    assert [r["k"] for r in result["runs"]] == [1, 2]
    assert result["reference"]["source"] == "sequential run"
    assert result["reference"]["seed"] != result["settings"]["solver"]["seed"]
    assert result["reference"]["tol"] == pytest.approx(1e-3)
    assert result["reference"]["rms_W_m2"] > 0
    for r in result["runs"]:
        pts = r["points"]
        assert len(pts) >= 3, r["label"]
        for key in ("time_s", "shots", "rays"):  # measured in order
            vals = [p[key] for p in pts]
            assert vals == sorted(vals) and vals[-1] > 0
        assert pts[-1]["rms"] < pts[0]["rms"]  # the error decreases overall
        assert pts[-1]["rms_norm"] < 0.5 * pts[0]["rms_norm"]
        assert pts[-1]["residual"] <= 0.05
        for p in pts:
            assert p["rms_norm"] == pytest.approx(p["rms"] / result["reference"]["rms_W_m2"])
    # the divided run really was divided, and measured at its barriers
    div = result["runs"][1]
    assert div["subscenes"] == 2 and div["barriers"] == len(div["points"]) - 1
    # same limit: final normalised errors within 2x of each other
    finals = [r["final_rms_norm"] for r in result["runs"]]
    assert max(finals) < 2 * min(finals), finals
    assert max(finals) < 0.1  # and both close to B*


def _loglog(xs, ys, x):
    """S at x, straight in log-log between the measured points (numpy, not compare.py)."""
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    keep = (xs > 0) & (ys > 0)
    lx, ly = np.log(xs[keep]), np.log(ys[keep])
    assert lx[0] <= np.log(x) <= lx[-1], "n outside the sequential curve"
    return float(np.exp(np.interp(np.log(x), lx, ly)))


def test_claims_agree_with_an_independent_reading_of_the_curves(result):
    claims = result["claims"]
    assert set(claims) == {"claim1", "claim2", "claim3"}
    for c in claims.values():
        assert isinstance(c["holds"], bool) and c["statement"] and c["method"]
    seq, div = result["runs"]
    sx, sy = [p["shots"] for p in seq["points"]], [p["rms_norm"] for p in seq["points"]]
    first = next(p for p in div["points"] if p["shots"] > 0)  # P is first measured at the first barrier
    n, k = first["shots"], div["k"]
    s_n, s_small = _loglog(sx, sy, n), _loglog(sx, sy, n / k)
    (c1,), (c3,) = claims["claim1"]["per_k"], claims["claim3"]["per_k"]
    assert c1["n"] == n and c1["S(n)"] == pytest.approx(s_n, rel=1e-9) and c1["P(n)"] == first["rms_norm"]
    assert claims["claim1"]["holds"] == (s_n < first["rms_norm"])
    assert c3["kn"] == n and c3["S(n)"] == pytest.approx(s_small, rel=1e-9)
    assert claims["claim3"]["holds"] == (s_small > first["rms_norm"])
    finals = [r["points"][-1]["rms_norm"] for r in result["runs"]]
    c2 = claims["claim2"]
    assert c2["spread"] == pytest.approx(max(finals) / min(finals))
    assert c2["holds"] == (max(finals) / min(finals) <= c2["tolerance_factor"])


def _run(k, points):
    return {"k": k, "points": [{"shots": n, "rms_norm": e, "residual": 0.0} for n, e in points]}


@pytest.mark.parametrize("divided,expect", [
    # sequential S(n) = 1/n; the divided run worse early (P(100) = 0.015 > S(100) = 0.01) but better
    # than S(50) = 0.02: claims 1 and 3 hold; it ends at the same error: claim 2 holds
    ([(0, 1.0), (100, 0.015), (1000, 0.001)], (True, True, True)),
    # better than the sequential at once (no start-up cost) and at k n: claim 1 fails, 3 holds
    ([(0, 1.0), (100, 0.005), (1000, 0.001)], (False, True, True)),
    # far worse early and at the end (5x): claim 1 holds, claim 3 fails, claim 2 fails
    ([(0, 1.0), (100, 0.5), (1000, 0.005)], (True, False, False)),
])
def test_claims_on_curves_with_a_known_answer(divided, expect):
    from dcrad.estimate.compare import _claims

    seq = _run(1, [(0, 1.0), (10, 0.1), (100, 0.01), (1000, 0.001)])
    got = _claims([seq, _run(2, divided)])
    assert (got["claim1"]["holds"], got["claim3"]["holds"], got["claim2"]["holds"]) == expect, got


def test_files(written, result):
    out, files = written
    for kind in ("json", "csv", "png", "svg"):
        assert files[kind].is_file() and files[kind].stat().st_size > 0
    data = json.loads(files["json"].read_text())
    with open(files["csv"]) as fh:
        rows = list(csv.DictReader(fh))
    assert set(rows[0]) == {"run", "k", "time_s", "shots", "rays", "residual", "rms", "rms_norm"}
    assert len(rows) == sum(len(r["points"]) for r in data["runs"])
    for k in (1, 2):
        n_csv = sum(1 for r in rows if int(r["k"]) == k)
        n_json = len(next(r for r in data["runs"] if r["k"] == k)["points"])
        assert n_csv == n_json
    last = [r for r in rows if int(r["k"]) == 2][-1]
    assert float(last["rms_norm"]) == pytest.approx(data["runs"][1]["final_rms_norm"])
    assert data["claims"]["claim2"]["holds"] == result["claims"]["claim2"]["holds"]

    import OpenImageIO as oiio

    img = oiio.ImageInput.open(str(files["png"]))
    assert img is not None
    spec = img.spec()
    assert spec.width > 400 and spec.height > 200
    pixels = img.read_image()
    img.close()
    assert np.ptp(pixels) > 0  # not a blank image

    root = ET.parse(files["svg"]).getroot()
    assert root.tag.endswith("svg")
    assert "office" in files["svg"].read_text()  # title names the scene


def test_reference_file_wrong_patch_count(office, tmp_path):
    bad = tmp_path / "radiosity.npz"
    np.savez(bad, patch_B=np.ones((5, 3)))
    _, patches, _ = prepare(office)
    with pytest.raises(DcradError, match=rf"5 patches.*{len(patches)} patches"):
        compare(office, subscenes=(1,), config=SolverConfig(tol=0.05), reference=bad)
    with pytest.raises(DcradError, match="patch_B"):
        np.savez(bad, B=np.ones((5, 3)))
        compare(office, subscenes=(1,), config=SolverConfig(tol=0.05), reference=bad)


def test_reference_file_is_used(office, tmp_path):
    _, patches, _ = prepare(office)
    ref = np.full((len(patches), 3), 2.0)
    np.savez(tmp_path / "ref.npz", patch_B=ref, patch_area=patches.area)
    res = compare(office, subscenes=(1,), config=SolverConfig(tol=0.2), reference=tmp_path / "ref.npz")
    assert res["reference"]["source"] == "file"
    assert res["reference"]["rms_W_m2"] == pytest.approx(2.0)
    assert res["claims"]["claim1"]["holds"] is None  # nothing divided to compare with


def test_cli_compare(tmp_path):
    out = tmp_path / "cmp"
    proc = subprocess.run(
        [sys.executable, "-m", "dcrad.cli", "compare", "office:rows=1,cols=2", "--subscenes", "1,2",
         "--tol", "0.05", "--out", str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    for name in ("compare.json", "compare.csv", "compare.png", "compare.svg"):
        assert (out / name).stat().st_size > 0
    assert "claim1" in proc.stdout and "claim3" in proc.stdout
    assert (out / "scene" / "office.obj").is_file()
    data = json.loads((out / "compare.json").read_text())
    assert [r["k"] for r in data["runs"]] == [1, 2]


def test_cli_bad_subscenes(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "dcrad.cli", "compare", "office", "--subscenes", "1,x",
                           "--out", str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "subscenes" in proc.stderr
