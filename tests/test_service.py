"""The distributed service with real processes talking gRPC on loopback.

A real coordinator and real worker processes (coordinator.embedded.LocalCluster):
results equal the in-process divided solution, a killed worker's subscene resumes
elsewhere from the last checkpoint, a worker started first registers later, and
bad requests get their documented status codes.
"""

from __future__ import annotations

import io
import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import grpc
import numpy as np
import pytest

import scenes
from coordinator.embedded import LocalCluster
from dcrad.config import SolverConfig
from dcrad.division.divide import DivideConfig, solve_divided, subscene_specs
from dcrad.division.placement import expected_work, placement
from dcrad.pipeline import prepare
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.v1 import dcrad_pb2_grpc as pb_grpc
from dcrad.wire import file_chunks


def submit(address, folder: Path, main: str, solver: dict, divide: dict, files=None):
    files = files or [p.name for p in folder.iterdir() if p.is_file()]

    def requests():
        yield pb.SubmitRequest(spec=pb.JobSpec(scene=main, solver=pb.SolverSettings(**solver),
                                               divide=pb.DivideSettings(**divide)))
        for name in files:
            for c in file_chunks((folder / name).read_bytes(), name):
                yield pb.SubmitRequest(file=c)

    with grpc.insecure_channel(address) as ch:
        return pb_grpc.CoordinatorStub(ch).Submit(requests(), timeout=60)


def watch(address, job_id, on_progress=None):
    out = []
    with grpc.insecure_channel(address) as ch:
        for p in pb_grpc.CoordinatorStub(ch).Watch(pb.JobRef(job_id=job_id), timeout=600):
            out.append(p)
            if on_progress:
                on_progress(p)
    return out


def fetch(address, job_id) -> dict:
    files: dict[str, bytearray] = {}
    with grpc.insecure_channel(address) as ch:
        for c in pb_grpc.CoordinatorStub(ch).Fetch(pb.JobRef(job_id=job_id), timeout=120):
            files.setdefault(c.path, bytearray()).extend(c.data)
    return files


def npz(files: dict, name="radiosity.npz"):
    return np.load(io.BytesIO(bytes(files[name])))


@pytest.fixture(scope="module")
def office(tmp_path_factory):
    folder = tmp_path_factory.mktemp("office")
    scenes.write_builtin("office", folder, rows=2, cols=3, seed=0)
    return folder


@pytest.fixture(scope="module")
def in_process(office):
    """The in-process divided solution the service must reproduce."""
    _, p, _ = prepare(office / "office.obj")
    run, *_ = solve_divided(p, SolverConfig(tol=0.005, seed=3), DivideConfig(subscenes=2))
    p.pool()  # what the service writes: clustered patches share one B
    return p.radiosity.copy(), run


def test_two_workers_reproduce_the_in_process_solution(office, in_process, tmp_path):
    with LocalCluster(workers=2, data=tmp_path) as cluster:
        job = submit(cluster.address, office, "office.obj", {"tol": 0.005, "seed": 3}, {"subscenes": 2})
        assert job.state in ("queued", "running")
        progress = watch(cluster.address, job.job_id)
        files = fetch(cluster.address, job.job_id)
    final = progress[-1]
    assert final.job.state == "done", final.job.error
    assert len({s.worker for s in final.subscenes}) == 2  # both workers served a subscene
    barriers = [p for p in progress if p.job.state == "running"]
    assert len(barriers) >= 3 and all(p.ledger.closure < 1e-10 for p in progress)
    assert final.bytes_relayed > 0  # twin buffers crossed the wire
    b_ref, run = in_process
    got = npz(files)["patch_B"]
    # same seed, same partition, same numerics: the same result to round-off
    assert np.allclose(got, b_ref, rtol=1e-12, atol=1e-15)
    assert final.barrier == run.barriers
    report = json.loads(bytes(files["report.json"]))
    assert report["ledger"]["closure"] < 1e-10 and report["divided"]["subscenes"] == 2
    assert {"preview.png", "preview.exr", "scene.glb", "patches.ply"} <= set(files)


def run_killing_at_first_barrier(cluster, folder, name, solver, divide, cell=0):
    """Submit a job, kill the worker that holds ``cell`` once the first barrier is reported,
    and watch it to the end: (the last progress, the fetched files, [killed worker],
    {cell: its worker at barrier 1})."""
    job = submit(cluster.address, folder, name, solver, divide)
    killed, placed = [], {}

    def on_progress(pr):
        if pr.barrier == 1 and not killed and pr.job.state == "running":
            placed.update({s.cell: s.worker for s in pr.subscenes})
            victim = next(s.worker for s in pr.subscenes if s.cell == cell)
            cluster.kill_worker(cluster.worker_ports.index(int(victim.rsplit(":", 1)[1])))
            killed.append(victim)

    progress = watch(cluster.address, job.job_id, on_progress)
    return progress[-1], fetch(cluster.address, job.job_id), killed, placed


def test_killed_worker_resumes_from_the_last_checkpoint(office, in_process, tmp_path):
    with LocalCluster(workers=3, data=tmp_path) as cluster:
        # after the first barrier, kill the worker that holds cell 0
        final, files, killed, _ = run_killing_at_first_barrier(
            cluster, office, "office.obj", {"tol": 0.005, "seed": 3}, {"subscenes": 2})
    assert killed and final.job.state == "done", final.job.error
    cell0 = next(s for s in final.subscenes if s.cell == 0)
    assert cell0.reassigned >= 1 and cell0.worker != killed[0]
    assert final.ledger.closure < 1e-10  # nothing lost
    # deterministic resume: the result equals the undisturbed run
    b_ref, _ = in_process
    assert np.allclose(npz(files)["patch_B"], b_ref, rtol=1e-12, atol=1e-15)


def test_over_decomposed_job_survives_a_killed_worker(office, tmp_path):
    """More subscenes than workers (4 on 2): each worker holds two; one is killed after the
    first barrier, the survivor takes all four and the result equals the undisturbed
    in-process run with 4 subscenes."""
    _, p, _ = prepare(office / "office.obj")
    run, *_ = solve_divided(p, SolverConfig(tol=0.005, seed=3), DivideConfig(subscenes=4))
    p.pool()  # what the service writes: clustered patches share one B
    with LocalCluster(workers=2, data=tmp_path) as cluster:
        final, files, killed, placed = run_killing_at_first_barrier(
            cluster, office, "office.obj", {"tol": 0.005, "seed": 3}, {"subscenes": 4})
    assert killed and final.job.state == "done", final.job.error
    assert len(placed) == 4 and len(set(placed.values())) == 2  # over-decomposed: both workers hold some
    # placed by expected work (placement.placement of the cells' lamps and patches), as in process
    subs, *_ = subscene_specs(p, SolverConfig(tol=0.005, seed=3), DivideConfig(subscenes=4))
    slots = placement([expected_work(s.patches) for s in subs], 2)
    assert len({(slots[c], w) for c, w in placed.items()}) == 2  # same grouping of cells
    assert {s.worker for s in final.subscenes} == set(placed.values()) - set(killed)  # one survivor holds all
    assert sum(s.reassigned for s in final.subscenes) == list(placed.values()).count(killed[0])
    assert final.ledger.closure < 1e-10 and final.barrier == run.barriers
    assert np.allclose(npz(files)["patch_B"], p.radiosity, rtol=1e-12, atol=1e-15)


def test_stiff_job_overshoots_across_workers_and_survives_a_kill(tmp_path):
    """rho = 0.99 furnace cut in two: the barrier plan (the job's ambient overshoot and ray
    factor) travels to the workers, a worker killed after the first barrier is replaced, and
    the result equals the in-process divided solution to round-off."""
    folder = tmp_path / "furnace"
    scenes.write_builtin("furnace", folder, rho=0.99)
    _, p, _ = prepare(folder / "furnace.obj")
    run, subs, *_ = solve_divided(p, SolverConfig(tol=0.01, seed=4), DivideConfig(subscenes=2), record=False)
    assert run.stopped_by == "tolerance" and all(s.plan is not None and s.plan.stiffness.scale.any() for s in subs)
    with LocalCluster(workers=3, data=tmp_path / "data") as cluster:
        final, files, killed, _ = run_killing_at_first_barrier(
            cluster, folder, "furnace.obj", {"tol": 0.01, "seed": 4}, {"subscenes": 2}, cell=1)
    assert killed and final.job.state == "done", final.job.error
    assert next(s for s in final.subscenes if s.cell == 1).reassigned >= 1
    assert final.barrier == run.barriers and final.ledger.closure < 1e-10
    assert np.allclose(npz(files)["patch_B"], p.radiosity, rtol=1e-12, atol=1e-15)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_worker_started_before_the_coordinator_registers(tmp_path):
    port = free_port()
    worker = subprocess.Popen([sys.executable, "-m", "dcrad.cli", "worker", "--port", "0",
                               "--coordinator", f"127.0.0.1:{port}"],
                              stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert "listening" in worker.stdout.readline()
        time.sleep(1.0)  # the worker is retrying against nothing
        with LocalCluster(workers=0, data=tmp_path, port=port) as cluster:
            cluster.wait_registered(1)
            with grpc.insecure_channel(cluster.address) as ch:
                workers = pb_grpc.CoordinatorStub(ch).ListWorkers(pb.ListWorkersRequest()).workers
            assert len(workers) == 1 and workers[0].alive
    finally:
        worker.terminate()
        worker.wait(10)


def test_documented_errors(office, tmp_path):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "s.mtl").write_text("newmtl white\nKd 1.0 0.5 0.5\n")
    (bad / "s.obj").write_text("mtllib s.mtl\no floor\nusemtl white\nv 0 0 0\nv 1 0 0\nv 0 0 1\nf 1 3 2\n")
    with LocalCluster(workers=1, data=tmp_path / "c", coordinator_args=("--max-upload", "4000")) as cluster:
        with pytest.raises(grpc.RpcError) as e:
            submit(cluster.address, bad, "s.obj", {}, {})
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "white" in e.value.details()

        with pytest.raises(grpc.RpcError) as e:
            submit(cluster.address, office, "office.obj", {}, {})  # ~15 kB > 4 kB limit
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "too large" in e.value.details()

        with grpc.insecure_channel(cluster.address) as ch:
            stub = pb_grpc.CoordinatorStub(ch)
            for call in (lambda: list(stub.Watch(pb.JobRef(job_id="nope"))),
                         lambda: list(stub.Fetch(pb.JobRef(job_id="nope"))),
                         lambda: stub.Cancel(pb.JobRef(job_id="nope"))):
                with pytest.raises(grpc.RpcError) as e:
                    call()
                assert e.value.code() == grpc.StatusCode.NOT_FOUND and "nope" in e.value.details()

    # no results while running; a cancelled job ends cancelled with the results so far
    furnace = tmp_path / "furnace"
    scenes.write_builtin("furnace", furnace, rho=0.99)
    with LocalCluster(workers=1, data=tmp_path / "c2") as cluster:
        job = submit(cluster.address, furnace, "furnace.obj", {"tol": 1e-9}, {"subscenes": 1})
        with grpc.insecure_channel(cluster.address) as ch:
            stub = pb_grpc.CoordinatorStub(ch)
            with pytest.raises(grpc.RpcError) as e:
                list(stub.Fetch(pb.JobRef(job_id=job.job_id)))
            assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION
            assert "running" in e.value.details() or "queued" in e.value.details()
            for p in stub.Watch(pb.JobRef(job_id=job.job_id)):
                if p.barrier >= 1 and p.job.state == "running":
                    stub.Cancel(pb.JobRef(job_id=job.job_id))
                final = p
            assert final.job.state == "cancelled"
        files = fetch(cluster.address, job.job_id)
    report = json.loads(bytes(files["report.json"]))
    assert report["stats"]["stopped_by"] == "stopped" and report["ledger"]["closure"] < 1e-10


def test_a_cancel_does_not_wait_for_the_barrier_in_flight(office, tmp_path):
    """Cancelled a while into barrier 2: the coordinator interrupts the workers' doIterations (the
    Interrupt call), so barrier 2 ends after the batches in flight, not after its 100 batches,
    and the job ends cancelled with closed books and results."""
    with LocalCluster(workers=2, data=tmp_path / "c") as cluster:
        job = submit(cluster.address, office, "office.obj", {"tol": 1e-30, "rays_per_power": 1e10, "time_limit": 300},
                     {"subscenes": 2, "iterations": 100})
        seen, timers = [], []

        def cancel():
            with grpc.insecure_channel(cluster.address) as ch:
                pb_grpc.CoordinatorStub(ch).Cancel(pb.JobRef(job_id=job.job_id))

        def cancel_in_the_second_barrier(p):
            seen.append(p)
            if p.barrier == 1 and p.job.state == "running":
                # a quarter of the job's time so far on: barrier 2 (as long as barrier 1) is in
                # flight, not about to start (a cancel before it starts stops the run at barrier 1)
                timers.append(threading.Timer(0.25 * p.job.elapsed_s, cancel))
                timers[-1].start()

        watch(cluster.address, job.job_id, cancel_in_the_second_barrier)
        for t in timers:
            t.join()
        files = fetch(cluster.address, job.job_id)
    first = next(p for p in seen if p.barrier == 1)
    assert seen[-1].job.state == "cancelled" and seen[-1].barrier == 2
    report = json.loads(bytes(files["report.json"]))
    assert report["stats"]["stopped_by"] == "stopped" and report["ledger"]["closure"] < 1e-10
    # barrier 1 shot 100 batches a subscene; barrier 2 only what was in flight when the cancel came
    assert first.rays > 0 and report["stats"]["rays"] - first.rays < 0.5 * first.rays


def test_health_service_on_both(tmp_path):
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    with LocalCluster(workers=1, data=tmp_path) as cluster:
        targets = {cluster.address: "dcrad.v1.Coordinator",
                   f"127.0.0.1:{cluster.worker_ports[0]}": "dcrad.v1.Worker"}
        for address, service in targets.items():
            with grpc.insecure_channel(address) as ch:
                stub = health_pb2_grpc.HealthStub(ch)
                for name in ("", service):
                    reply = stub.Check(health_pb2.HealthCheckRequest(service=name), timeout=10)
                    assert reply.status == health_pb2.HealthCheckResponse.SERVING, (address, name)
