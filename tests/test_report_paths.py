"""One report document on every path: in process, in process divided, and the service.

A room whose east and west walls face outward (flipped normals) is solved three
ways; the reports must carry the same sections, stats and timings keys, the same
warnings naming the flipped walls, and the settings that were asked for.  The
service run (a real coordinator and two worker processes over gRPC) uses the same
seed and partition as the in-process divided run, so its ledger, choices and
warnings must be the same to round-off.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from coordinator import client
from coordinator.embedded import LocalCluster
from dcrad.config import DivideConfig, SolverConfig
from dcrad.outputs.report import TIMINGS
from dcrad.pipeline import solve_to
from scenes.objwriter import ObjWriter

FLIPPED = {"wall_east", "wall_west"}
CONFIG = SolverConfig(tol=0.02, seed=5, min_rays=16, snapshot_factor=1.5, adaptive_bins=False)
DIVIDE = DivideConfig(subscenes=2, iterations=3)


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """A 6 x 2.5 x 3 m room, a ceiling light across the middle; two walls face outward."""
    w = ObjWriter()
    w.material("white", kd=0.6)
    w.material("lamp", kd=0.2, ke=20.0)
    size = (6.0, 2.5, 3.0)
    walls = {"floor": (1, 0.0, 1), "ceiling": (1, size[1], -1), "wall_north": (2, 0.0, 1),
             "wall_south": (2, size[2], -1),
             "wall_west": (0, 0.0, -1), "wall_east": (0, size[0], 1)}  # these two face out
    for name, (axis, value, facing) in walls.items():
        u, v = [k for k in range(3) if k != axis]
        w.begin(name, "white")
        w.add_rect(axis, value, (0.0, 0.0), (size[u], size[v]), facing)
    w.begin("light", "lamp")
    w.add_rect(1, 2.45, (1.5, 1.0), (4.5, 2.0), -1)
    return w.write(tmp_path_factory.mktemp("room"), "room")


@pytest.fixture(scope="module")
def reports(room, tmp_path_factory):
    out = tmp_path_factory.mktemp("reports")
    single = solve_to(room, out / "single", CONFIG, width=64, height=48)
    divided = solve_to(room, out / "divided", CONFIG, width=64, height=48, divide=DIVIDE)
    with LocalCluster(workers=2, web=False, data=out / "cluster") as cluster:
        job = client.submit(cluster.address, room, CONFIG.as_dict() | {"patch_size": 0.0, "scale": 1.0},
                            DIVIDE.as_dict(), (64, 48))
        last = client.watch(cluster.address, job.job_id)
        assert last is not None and last.job.state == "done", last
        client.fetch(cluster.address, job.job_id, out / "service")
    service = json.loads((out / "service" / "report.json").read_text())
    return {"single": single, "divided": divided, "service": service}


def _named(warnings: list[str]) -> list[str]:
    """The objects a flipped-normals warning names, worst first ("name/material" -> "name")."""
    for w in warnings:
        m = re.search(r"flipped on: (.*)$", w)
        if m:
            return [n.strip().split("/")[0] for n in m.group(1).split(",")]
    return []


def test_every_path_warns_and_names_the_flipped_walls(reports):
    for path, r in reports.items():
        # the lamp's unlit back takes some light from the ceiling too, far less than the walls
        assert set(_named(r["warnings"])[:2]) == FLIPPED, (path, r["warnings"])


def test_the_three_reports_are_one_document(reports):
    single, divided, service = reports["single"], reports["divided"], reports["service"]
    assert set(single) == set(divided) == set(service) - {"error_curve"}
    assert set(single["stats"]) == set(divided["stats"]) == set(service["stats"])
    assert set(single["timings"]) == set(divided["timings"]) == set(service["timings"])
    for r in reports.values():
        assert list(r["timings"])[: len(TIMINGS)] == list(TIMINGS)
        assert all(r["timings"][k] > 0 for k in TIMINGS), r["timings"]
        # a real trace time, within the wall time of the workers' share (not the 0.0 it was)
        assert 0 < r["stats"]["trace_seconds"]
        assert r["ledger"]["closure"] < 1e-9
        assert set(r["ledger"]) == set(single["ledger"])
        # the settings asked for are the ones used (accuracy/rays_per_power as the stop rule resolved them)
        assert set(CONFIG.as_dict()) <= set(r["settings"])
        assert {k: r["settings"][k] for k in ("tol", "seed", "min_rays", "snapshot_factor", "adaptive_bins")} == \
            {"tol": 0.02, "seed": 5, "min_rays": 16, "snapshot_factor": 1.5, "adaptive_bins": False}
    # and the same on every path: they travelled to the coordinator and its workers
    assert single["settings"] == divided["settings"] == service["settings"]
    assert single["stats"]["barriers"] == 0 and single["divided"] is None
    assert divided["stats"]["barriers"] == service["stats"]["barriers"] == divided["divided"]["barriers"] > 0
    assert divided["stats"]["batches"] > divided["stats"]["barriers"]  # Embree calls, not barriers


def test_the_service_reproduces_the_in_process_divided_report(reports):
    divided, service = reports["divided"], reports["service"]
    # same seed, same partition, same numerics: the same books
    assert service["warnings"] == divided["warnings"]
    # the service says in addition how it chose to run the job (strategy.on_workers)
    strategy = [c for c in service["choices"] if c["code"] == "strategy"]
    assert len(strategy) == 1 and strategy[0]["text"].startswith("divided into the")
    assert [c for c in service["choices"] if c["code"] != "strategy"] == divided["choices"]
    for account, value in divided["ledger"].items():
        assert np.allclose(service["ledger"][account], value, rtol=1e-12, atol=1e-15), account
    for key in ("shots", "rays", "batches", "barriers", "stopped_by"):
        assert service["stats"][key] == divided["stats"][key], key
    same = json.loads(json.dumps(divided["divided"]))  # as the service's arrived: through JSON
    assert same == {k: service["divided"][k] for k in same}
    assert divided["divided"]["iterations"] == 3
