"""Shared runs (dcrad.solving.share): k workers share one solve of the whole scene.

Checked against independent truths: a converged solution with other seeds (the shared run's
error is what its estimate says, and what a one-process run at the same target reaches), the
books (the ledger closes), the wire forms (round trips), and real worker processes talking
gRPC (bit-identical to the in-process shares, also with a worker killed mid-run).
"""

from __future__ import annotations

import io
import json

import grpc
import numpy as np
import pytest
from test_service import fetch, watch
from test_service import submit as submit_job

import scenes
from coordinator.embedded import LocalCluster
from dcrad.config import SolverConfig
from dcrad.pipeline import prepare
from dcrad.settings import to_pb
from dcrad.solving.energy import read_error, rms_error
from dcrad.solving.passes import solve_to_accuracy
from dcrad.solving.share import (
    LocalShares,
    Replica,
    Shot,
    receiver_shares,
    run_shared,
    shared_books,
    tally_from_arrays,
    tally_to_arrays,
    work_shares,
)
from dcrad.transport.rays import Tracer
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.v1 import dcrad_pb2_grpc as pb_grpc
from dcrad.wire import arrays_to_chunks

ACCURACY = 0.05


@pytest.fixture(scope="module")
def office(tmp_path_factory):
    folder = tmp_path_factory.mktemp("office")
    scenes.write_builtin("office", folder, rows=1, cols=2, seed=0)
    return folder


@pytest.fixture(scope="module")
def table(office):
    _, patches, _ = prepare(office / "office.obj")
    return patches, Tracer(patches.triangles)


@pytest.fixture(scope="module")
def reference(table):
    """A converged solution with its own seed (0.5% of the reflected light)."""
    patches, tracer = table
    patches.reset()
    solve_to_accuracy(patches, SolverConfig(accuracy=0.005, seed=999), tracer)
    return patches.radiosity.copy()


def refl_rms(patches, b):
    return float(np.sqrt(((b - patches.emission) ** 2).mean(axis=1) @ patches.area / patches.area.sum()))


@pytest.fixture(scope="module")
def shared_two(table):
    patches, tracer = table
    patches.reset()
    cfg = SolverConfig(accuracy=ACCURACY, seed=5)
    run = run_shared(patches, cfg, 2, LocalShares(patches, cfg, tracer))
    return run, patches.radiosity.copy()


def test_receiver_shares_split_every_receiver_once(table):
    patches, _ = table
    parts = receiver_shares(patches, 3)
    every = np.concatenate(parts)
    assert np.array_equal(np.sort(every), np.flatnonzero(patches.rho.any(axis=1)))
    assert max(map(len, parts)) - min(map(len, parts)) <= 1
    assert all(np.all(np.diff(p) > 0) for p in parts)


def test_work_shares_split_every_receiver_once_big_ones_first(table, monkeypatch):
    """A worker's shares halve in size from one round of k to the next (the queue hands out the big
    ones first), and together they are every receiver once, in sorted runs."""
    import dcrad.solving.share as share

    patches, _ = table
    rec = np.flatnonzero(patches.rho.any(axis=1))
    assert [len(p) for p in work_shares(patches, 1)] == [len(rec)]
    for per in (1, 4):
        monkeypatch.setattr(share, "SHARES_PER_WORKER", per)
        for k in (2, 3):
            parts = work_shares(patches, k)
            assert len(parts) == per * k
            assert np.array_equal(np.sort(np.concatenate(parts)), rec)
            assert all(np.all(np.diff(p) > 0) for p in parts)
            sizes = np.array([len(p) for p in parts], float).reshape(per, k)
            assert np.all(np.abs(sizes[1:] / sizes[:-1] - 0.5) < 0.01)  # each round half the one before
            assert np.ptp(sizes, axis=1).max() <= 1


def test_shared_run_meets_its_target_as_its_estimate_says(table, reference, shared_two):
    """Against the converged reference: the shared run's measured error, per element and per input
    triangle, is within 1.5x of its estimate in each reading, near the target, and like a
    one-process run's at the same target; the books close."""
    patches, tracer = table
    run, b = shared_two
    measured = rms_error(b, reference, patches.area) / refl_rms(patches, reference)
    est = run.estimate
    assert run.stats.stopped_by == "accuracy" and est.rms_refl <= ACCURACY
    for per_triangle, figure in ((False, est.elements_refl), (True, est.triangles_refl)):
        got = read_error(patches, b, reference, per_triangle)
        assert figure is not None and figure / 1.5 <= got <= figure * 1.5, (per_triangle, figure, got)
    assert run.ledger.closure() < 1e-10
    assert run.stats.rays == run.direct_rays + sum(r.rays for r in run.replicas) + run.gather_rays
    assert run.rounds and run.rounds[0] >= 16  # the gather ran, with the job's rays per receiver
    patches.reset()
    solver = solve_to_accuracy(patches, SolverConfig(accuracy=ACCURACY, seed=5), tracer)
    one = rms_error(patches.radiosity, reference, patches.area) / refl_rms(patches, reference)
    assert solver.stats.stopped_by == "accuracy"
    assert measured <= 1.5 * max(one, 0.5 * ACCURACY), (measured, one)
    # the replicas are independent: their shot solutions differ
    a, c = run.replicas
    assert not np.array_equal(a.radiosity, c.radiosity)


def test_wire_forms_round_trip(table, shared_two):
    patches, tracer = table
    run, _ = shared_two
    rep = run.replicas[0]
    back = Replica.from_arrays(rep.to_arrays(), len(patches))
    for name in Replica._STATE + ("tallies", "back_by_obj"):
        assert np.array_equal(getattr(back, name), getattr(rep, name)), name
    assert back.ledger.as_dict() == rep.ledger.as_dict() and back.stopped_by == rep.stopped_by
    assert back.choices == rep.choices and back.rays == rep.rays
    with pytest.raises(ValueError, match="radiosity"):
        Replica.from_arrays(rep.to_arrays() | {"radiosity": rep.radiosity[:-1]}, len(patches))
    patches.reset()
    shares = LocalShares(patches, SolverConfig(accuracy=ACCURACY), tracer)
    tally = shares.direct([np.flatnonzero(patches.rho.any(axis=1))[:50]])[0]
    again = tally_from_arrays(tally_to_arrays(tally), len(patches))
    assert np.array_equal(again.received, tally.received) and np.array_equal(again.hit, tally.hit)
    assert again.rays == tally.rays
    with pytest.raises(ValueError, match="outside"):
        tally_from_arrays(tally_to_arrays(tally) | {"hit": tally.hit + len(patches)}, len(patches))
    with pytest.raises(ValueError, match="shape"):
        Shot.from_arrays({"radiosity": np.zeros((3, 3)), "diff": np.zeros((3, 3)),
                          "direct": np.zeros((3, 3)), "direct_a": np.zeros((2, 3))}, 3)


def submit(address, folder, solver: dict, divide: dict | None = None):
    return submit_job(address, folder, "office.obj", solver, divide or {})


def in_process(table, k: int, seed: int):
    patches, tracer = table
    patches.reset()  # B = E and the clusters as meshed, as the service meshes it
    cfg = SolverConfig(accuracy=ACCURACY, seed=seed)
    run = run_shared(patches, cfg, k, LocalShares(patches, cfg, tracer))
    patches.pool()  # what the service writes: clustered patches share one B
    return run, patches.radiosity.copy()


def test_two_workers_share_a_job_bit_identically(office, table, tmp_path):
    """An accuracy job with the subscenes left to the coordinator runs shared on both workers:
    the same B as the in-process shares, to the bit; the report says how it ran, and that the
    divided-run flag it was given did not apply."""
    run, b_ref = in_process(table, 2, seed=3)
    with LocalCluster(workers=2, data=tmp_path) as cluster:
        job = submit(cluster.address, office, {"accuracy": ACCURACY, "seed": 3}, {"iterations": 8})
        progress = watch(cluster.address, job.job_id)
        files = fetch(cluster.address, job.job_id)
    final = progress[-1]
    assert final.job.state == "done", final.job.error
    assert len(set(final.job.workers)) == 2
    b = np.load(io.BytesIO(bytes(files["radiosity.npz"])))["patch_B"]
    assert np.array_equal(b, b_ref)
    report = json.loads(bytes(files["report.json"]))
    assert report["shared"]["workers"] == 2 and report["divided"] is None
    assert report["stats"]["rays"] == run.stats.rays
    assert report["ledger"]["closure"] < 1e-10
    assert any(c["code"] == "shared" and c["text"].startswith("shared run on 2 workers") for c in report["choices"])
    assert any(c["code"] == "strategy" and c["text"].startswith("shared by the 2 worker(s)") for c in report["choices"])
    assert any(c["code"] == "unused_flags" and c["text"].startswith("--iterations 8: for divided runs only")
               for c in report["choices"])
    # the status page's barriers: direct, shoot, each gather round
    assert [p.barrier for p in progress if p.job.state == "running"][-1] == 2 + len(run.rounds)


def test_a_killed_worker_s_share_runs_elsewhere_with_the_same_result(office, table, tmp_path):
    """Three workers registered, one killed before the job: the coordinator still counts it, gives it a
    share of every phase, finds it gone at the first call and runs that share on a survivor (with
    the patch table sent again where needed).  The result is the undisturbed 3-share run's, to the bit."""
    _, b_ref = in_process(table, 3, seed=4)
    with LocalCluster(workers=3, data=tmp_path) as cluster:
        cluster.kill_worker(0)
        job = submit(cluster.address, office, {"accuracy": ACCURACY, "seed": 4})
        progress = watch(cluster.address, job.job_id)
        files = fetch(cluster.address, job.job_id)
    final = progress[-1]
    assert final.job.state == "done", final.job.error
    report = json.loads(bytes(files["report.json"]))
    assert report["shared"]["workers"] == 3 and report["shared"]["reassigned"] >= 1
    assert len(report["shared"]["workers_used"]) == 2
    b = np.load(io.BytesIO(bytes(files["radiosity.npz"])))["patch_B"]
    assert np.array_equal(b, b_ref)


def test_a_cancelled_shared_job_ends_with_what_it_has(office, tmp_path):
    """Cancelled once the direct light is in: the replicas stop cleanly, the job ends cancelled
    with its results written (the books closed), as a divided job does."""
    with LocalCluster(workers=2, data=tmp_path) as cluster:
        job = submit(cluster.address, office, {"accuracy": 0.003, "seed": 4})
        sent: list[bool] = []

        def on_progress(pr):
            if pr.barrier == 1 and not sent:
                with grpc.insecure_channel(cluster.address) as ch:
                    pb_grpc.CoordinatorStub(ch).Cancel(pb.JobRef(job_id=job.job_id), timeout=10)
                sent.append(True)

        progress = watch(cluster.address, job.job_id, on_progress)
        files = fetch(cluster.address, job.job_id)
    assert sent and progress[-1].job.state == "cancelled", progress[-1].job.error
    report = json.loads(bytes(files["report.json"]))
    assert report["stats"]["stopped_by"] == "stopped" and report["shared"]["gather_rounds"] == []
    assert report["ledger"]["closure"] < 1e-10


def test_a_shared_job_cancelled_before_its_direct_light_ends_with_b_equal_e(office, tmp_path):
    """Cancelled before its direct shares begin (while it waits for a worker: no race with a small
    scene's quick direct phase): the job ends cancelled, not divided, with its outputs written:
    B = E, all the light unshot, the books closed, and the report says the direct gather was stopped."""
    with LocalCluster(workers=0, data=tmp_path) as cluster:
        job = submit(cluster.address, office, {"accuracy": 0.003, "seed": 4})
        with grpc.insecure_channel(cluster.address) as ch:
            pb_grpc.CoordinatorStub(ch).Cancel(pb.JobRef(job_id=job.job_id), timeout=10)
        cluster.start_worker()
        progress = watch(cluster.address, job.job_id)
        assert progress[-1].job.state == "cancelled", progress[-1].job.error
        files = fetch(cluster.address, job.job_id)
    report = json.loads(bytes(files["report.json"]))
    assert report["stats"]["stopped_by"] == "stopped" and report["stats"]["shots"] == 0
    assert report["shared"]["replica_rays"] == [] and report["divided"] is None
    assert report["ledger"]["closure"] < 1e-10
    assert any(c["code"] == "direct" and c["text"].startswith("direct gather stopped") for c in report["choices"])
    npz = np.load(io.BytesIO(bytes(files["radiosity.npz"])))
    assert np.array_equal(npz["patch_B"], npz["patch_emission"])
    assert np.array_equal(npz["patch_unshot"], npz["patch_emission"])


def test_a_stop_in_a_shared_run_s_direct_or_gather_phase_ends_it_there(table, monkeypatch):
    """In process (LocalShares, the workers' reference): a stop during the direct shares leaves
    B = E with every watt unshot and booked so; a stop during a gather round loses that round
    only: B is the shot solution's, the run says it stopped, and its books close."""
    from dcrad.transport import direct as direct_mod

    patches, tracer = table
    monkeypatch.setattr(direct_mod, "CHUNK_PAIRS", 2000)  # several runs of cells: a stop lands between
    cfg = SolverConfig(accuracy=ACCURACY, seed=5)
    calls = [0]

    def after(n):
        def should_stop() -> bool:
            calls[0] += 1
            return calls[0] > n
        return should_stop

    patches.reset()
    run = run_shared(patches, cfg, 2, LocalShares(patches, cfg, tracer), should_stop=after(1))
    assert run is not None and run.stats.stopped_by == "stopped" and run.replicas == [] and run.rounds == []
    assert np.array_equal(patches.radiosity, patches.emission)
    assert np.allclose(run.ledger.unshot, run.ledger.emitted, rtol=1e-12) and run.ledger.closure() < 1e-12
    books, shared = shared_books(run, patches, cfg)
    assert shared["replica_rays"] == [] and books.stats.stopped_by == "stopped"

    class StopInGather(LocalShares):
        def gather(self, shot, shares, rounds, should_stop=None):
            self.shot_b = shot.radiosity.copy()
            return super().gather(shot, shares, rounds, lambda: True)

    patches.reset()
    cfg = cfg.replace(batch_rays=1024, max_rays_per_shot=1024)  # a round of several batches: the stop lands between two
    shares = StopInGather(patches, cfg, tracer)
    run = run_shared(patches, cfg, 2, shares)
    assert run.stats.stopped_by == "stopped" and run.rounds == [] and run.gather_rays == 0
    assert len(run.replicas) == 2 and np.array_equal(patches.radiosity, shares.shot_b)
    assert run.ledger.closure() < 1e-10


def test_explicit_subscenes_divide_instead(office, tmp_path):
    """--subscenes given: the job divides space as asked, no shared run."""
    with LocalCluster(workers=2, data=tmp_path) as cluster:
        job = submit(cluster.address, office, {"accuracy": 0.1, "seed": 3}, {"subscenes": 2})
        progress = watch(cluster.address, job.job_id)
        files = fetch(cluster.address, job.job_id)
    assert progress[-1].job.state == "done", progress[-1].job.error
    report = json.loads(bytes(files["report.json"]))
    assert report.get("shared") is None and report["divided"]["subscenes"] == 2


def test_more_shares_than_receivers_still_solve(tmp_path):
    """A scene with fewer receivers than shares: the empty shares gather nothing, the run meets
    its target and its books close (one shared run's shares may outnumber a small scene's patches)."""
    from dcrad.meshing.patches import Patches

    # a 1 m floor (2 triangles) under a 0.5 m emitter facing it
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1],
                  [0.25, 1, 0.25], [0.75, 1, 0.25], [0.75, 1, 0.75], [0.25, 1, 0.75]], float)
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7]])
    rho = np.array([[0.5] * 3, [0.5] * 3, [0] * 3, [0] * 3])
    e = np.array([[0] * 3, [0] * 3, [10] * 3, [10] * 3])
    p = Patches(v, f, rho, e, np.arange(4), np.zeros(4, np.int32), ["floor"])
    cfg = SolverConfig(accuracy=0.05, seed=2)
    run = run_shared(p, cfg, 5, LocalShares(p, cfg))
    assert run is not None and run.ledger.closure() < 1e-10
    assert run.stats.stopped_by in ("accuracy", "noise_floor", "tolerance")
    assert np.all(p.radiosity[:2] > 0)  # the floor is lit


def test_a_worker_refuses_bad_shares_by_name(table):
    """Malformed shares get INVALID_ARGUMENT naming the problem; a share of a job whose patch table
    the worker never got, NOT_FOUND."""
    patches, _ = table
    with LocalCluster(workers=1, web=False) as cluster:
        with grpc.insecure_channel(f"127.0.0.1:{cluster.worker_ports[0]}") as ch:
            stub = pb_grpc.WorkerStub(ch)

            def share(header, arrays=None, **groups):
                """The Share call with the phase's own arrays and other groups (scene, shot, tally)."""
                def requests():
                    yield pb.ShareRequest(header=header)
                    for group, given in {"array": arrays or {}, **groups}.items():
                        for chunk in arrays_to_chunks(given):
                            yield pb.ShareRequest(**{group: chunk})
                return list(stub.Share(requests(), timeout=60))

            settings = to_pb(SolverConfig(accuracy=0.05), pb.SolverSettings)
            with pytest.raises(grpc.RpcError) as err:
                share(pb.ShareHeader(job_id="j", phase=pb.SHARE_PHASE_PILOT, index=0, count=1, solver=settings))
            assert err.value.code() == grpc.StatusCode.NOT_FOUND and "patch table" in err.value.details()
            for phase in (pb.SHARE_PHASE_UNSPECIFIED, 99):  # unset, or a phase this worker does not know
                with pytest.raises(grpc.RpcError) as err:
                    share(pb.ShareHeader(job_id="j", phase=phase, index=0, count=1, solver=settings))
                assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT, err.value.details()
                assert f"phase {phase} (unset or unknown)" in err.value.details()
            with pytest.raises(grpc.RpcError) as err:
                share(pb.ShareHeader(job_id="j", phase=pb.SHARE_PHASE_PILOT, index=0, count=1, solver=settings,
                                     names=list(patches.names), scene=True),
                      {"rows": np.array([len(patches) + 7])}, scene=patches.table_arrays())
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "outside" in err.value.details()
            with pytest.raises(grpc.RpcError) as err:  # the table is held now; a gather without its shot
                share(pb.ShareHeader(job_id="j", phase=pb.SHARE_PHASE_GATHER, index=0, count=1, solver=settings),
                      {"rows": np.array([0, 1]), "rounds": np.array([4])})
            assert err.value.code() == grpc.StatusCode.NOT_FOUND and "shot solution" in err.value.details()
            n = len(patches)
            shot = {"radiosity": np.zeros((n, 3)), "diff": np.zeros((n, 3)),
                    "direct": np.zeros((n, 2)), "direct_a": np.zeros((n, 3))}
            with pytest.raises(grpc.RpcError) as err:
                share(pb.ShareHeader(job_id="j", phase=pb.SHARE_PHASE_GATHER, index=0, count=1, solver=settings),
                      {"rows": np.array([0, 1]), "rounds": np.array([4])}, shot=shot)
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "direct has shape" in err.value.details()


def test_a_shared_run_keeps_to_its_time_limit(table):
    """A time limit the run cannot meet its target in: it stops at the limit (the replicas get what
    the direct shares left of it, the gather is skipped), says so, and its books close."""
    patches, tracer = table
    patches.reset()
    cfg = SolverConfig(accuracy=0.001, seed=6, time_limit=0.5)
    run = run_shared(patches, cfg, 2, LocalShares(patches, cfg, tracer))
    assert run.stats.stopped_by == "time_limit" and run.rounds == []
    assert run.ledger.closure() < 1e-10
    assert all(r.stopped_by == "time_limit" for r in run.replicas)


def test_a_worker_s_direct_and_gather_shares_stop_when_asked(table, monkeypatch):
    """A cancelled job's shares on a worker stop at their next batch (the worker answers CANCELLED):
    the direct share between runs of cells, the gather share between batches of receivers, each
    raising GatherStopped rather than returning partial sums a shared run would read as whole;
    not asked, they run as before."""
    from dcrad.solving.share import direct_share, gather_share
    from dcrad.transport import direct as direct_mod
    from dcrad.transport.direct import GatherStopped

    patches, tracer = table
    patches.reset()
    cfg = SolverConfig(accuracy=ACCURACY, seed=5, batch_rays=4096, max_rays_per_shot=4096)
    rows = receiver_shares(patches, 2)[0]
    monkeypatch.setattr(direct_mod, "CHUNK_PAIRS", 2000)  # several runs of cells
    with pytest.raises(GatherStopped):
        direct_share(patches, cfg, tracer, rows, 0, 1.0, None, lambda: True)
    tally = direct_share(patches, cfg, tracer, rows, 0, 1.0, None, lambda: False)
    assert tally is not None and len(tally.hit) > 0
    n = len(patches)
    shot = Shot(patches.radiosity.copy(), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), None, None)
    with pytest.raises(GatherStopped):
        gather_share(patches, cfg, tracer, shot, rows, 0, [8], None, lambda: True)
    fg, traced = gather_share(patches, cfg, tracer, shot, rows, 0, [8], None, lambda: False)
    assert traced > 0 and not fg.stopped and (fg.counts == 4).all()
