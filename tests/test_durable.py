"""Durable jobs: a coordinator killed with SIGKILL and restarted on its data folder loses nothing.

Real processes (coordinator.embedded.LocalCluster): a job that finished before the
restart is still listed and fetchable; a job running at the kill resumes from its
last checkpointed barrier on the workers that re-register, and ends bit-identical to
an undisturbed run of the same job with a closed ledger.  A damaged job record is
skipped with a warning.  Checkpoint files give back their arrays bit for bit.
"""

from __future__ import annotations

import json
import logging
import time
import urllib.request

import grpc
import numpy as np
import pytest
from test_service import fetch, npz, submit, watch

import scenes
from coordinator.embedded import LocalCluster
from coordinator.jobs import JobManager
from coordinator.remote import WorkerPool
from coordinator.store import CheckpointWriter, ChunkFile, JobRecord, JobStore, cell_file
from dcrad.config import SolverConfig
from dcrad.division.divide import DivideConfig, assemble, build_subscenes, run_divided
from dcrad.division.subscene import build_subscene, checkpoint_arrays, subscene_arrays
from dcrad.pipeline import prepare
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.v1 import dcrad_pb2_grpc as pb_grpc
from dcrad.wire import arrays_to_chunks

SOLVER = {"tol": 0.002, "seed": 5}
DIVIDE = {"subscenes": 2}


def _manifest_barrier(cluster: LocalCluster, job_id: str) -> int:
    path = cluster.data / "coordinator" / "jobs" / job_id / "checkpoints" / "manifest.json"
    try:
        return int(json.loads(path.read_text())["barrier"])
    except (OSError, ValueError, KeyError):
        return 0


def test_coordinator_sigkill_mid_job_resumes_bit_identical(tmp_path):
    folder = tmp_path / "office"
    scenes.write_builtin("office", folder, rows=2, cols=3, seed=0)
    with LocalCluster(workers=2, data=tmp_path / "data") as cluster:
        # an undisturbed run of the job, finished before the restart
        ref = submit(cluster.address, folder, "office.obj", SOLVER, DIVIDE)
        ref_final = watch(cluster.address, ref.job_id)[-1]
        assert ref_final.job.state == "done", ref_final.job.error
        assert ref_final.barrier >= 4  # enough barriers to kill one in the middle
        ref_files = fetch(cluster.address, ref.job_id)

        job = submit(cluster.address, folder, "office.obj", SOLVER, DIVIDE)
        with grpc.insecure_channel(cluster.address) as ch:
            for p in pb_grpc.CoordinatorStub(ch).Watch(pb.JobRef(job_id=job.job_id), timeout=600):
                if p.job.state == "running" and p.barrier >= 2:
                    break
        deadline = time.monotonic() + 30
        while _manifest_barrier(cluster, job.job_id) < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        cluster.kill_coordinator()
        at_kill = _manifest_barrier(cluster, job.job_id)
        assert 1 <= at_kill < ref_final.barrier  # killed in the middle, with a checkpoint on disk

        cluster.restart_coordinator()
        with grpc.insecure_channel(cluster.address) as ch:
            listed = {j.job_id: j for j in pb_grpc.CoordinatorStub(ch).ListJobs(pb.ListJobsRequest()).jobs}
        assert listed[ref.job_id].state == "done" and job.job_id in listed
        assert listed[ref.job_id].workers == ref_final.job.workers  # kept in its record
        again = fetch(cluster.address, ref.job_id)  # the finished job survived the restart
        assert bytes(again["radiosity.npz"]) == bytes(ref_files["radiosity.npz"])
        with urllib.request.urlopen(f"{cluster.web_url}/jobs/{ref.job_id}/preview.png", timeout=30) as r:
            assert r.status == 200 and r.read(8) == b"\x89PNG\r\n\x1a\n"  # its page keeps its preview

        final = watch(cluster.address, job.job_id)[-1]  # the workers re-register; it resumes
        assert final.job.state == "done", final.job.error
        files = fetch(cluster.address, job.job_id)
    log = "".join(p.read_text() for p in cluster.data.glob("coordinator-*.log"))
    report = json.loads(bytes(files["report.json"]))
    resumed = [c["text"] for c in report["choices"] if c["code"] == "resumed"]
    assert resumed and f"barrier {at_kill}" in resumed[0], report["choices"]
    assert f"resumes from barrier {at_kill}" in log
    assert final.barrier == ref_final.barrier
    assert report["ledger"]["closure"] < 1e-10 and final.ledger.closure < 1e-10
    assert np.array_equal(npz(files)["patch_B"], npz(ref_files)["patch_B"])  # bit-identical
    assert np.array_equal(npz(files)["B"], npz(ref_files)["B"])
    # a finished job keeps no checkpoints
    assert not (cluster.data / "coordinator" / "jobs" / job.job_id / "checkpoints").exists()


def test_damaged_records_are_skipped_with_a_warning(tmp_path, caplog):
    store = JobStore(tmp_path / "jobs")
    spec = pb.JobSpec(scene="office.obj")
    store.save(JobRecord(id="finished1", spec=spec, state="done", created=1.0, started=2.0, finished=5.0,
                         residual=0.004))
    (store.folder("finished1") / "out").mkdir()
    (store.folder("finished1") / "out" / "report.json").write_text(json.dumps({"ledger": {"closure": 1e-15}}))
    store.save(JobRecord(id="truncated", spec=spec, state="done"))
    blob = (store.folder("truncated") / "job.json").read_bytes()
    (store.folder("truncated") / "job.json").write_bytes(blob[: len(blob) // 2])
    store.save(JobRecord(id="garbled", spec=spec, state="done"))
    (store.folder("garbled") / "job.json").write_bytes(b"\x00\xff" * 40)
    # a running job whose checkpoint files are half-written: it starts over, no crash
    store.save(JobRecord(id="running1", spec=pb.JobSpec(scene="furnace.obj"), state="running",
                         divide={"subscenes": 2}))
    scenes.write_builtin("furnace", store.folder("running1") / "scene")
    ck = store.folder("running1") / "checkpoints"
    ck.mkdir()
    (ck / "manifest.json").write_text(json.dumps({"format": 2, "barrier": 3, "cells": {"0": "cell-0-000003.ck"}}))
    (ck / "cell-0-000003.ck").write_bytes(ChunkFile.MAGIC + b"\x10\x00 half")
    with caplog.at_level(logging.WARNING, logger="dcrad.coordinator"):
        manager = JobManager(tmp_path, WorkerPool(), worker_wait=0.01)
    assert set(manager.jobs) == {"finished1", "running1"}
    done = manager.jobs["finished1"]
    assert done.state == "done" and done.summary().elapsed_s == 3.0 and done.report is not None
    text = caplog.text
    assert "truncated" in text and "garbled" in text and "unreadable" in text
    assert "running1" in text and "starts over" in text
    # the running job starts over and, with no worker, fails with a readable reason
    deadline = time.monotonic() + 30
    while manager.jobs["running1"].state not in ("failed", "done") and time.monotonic() < deadline:
        time.sleep(0.02)
    assert manager.jobs["running1"].state == "failed"
    assert "no worker registered" in manager.jobs["running1"].error


def _arrays(rng, n):
    return {"radiosity": rng.random((n, 3)), "unshot": rng.random((n, 3)), "ledger": rng.random((10, 3)),
            "stats": np.arange(5, dtype=np.int64), "rng_state": np.frombuffer(b'{"state": 1}', np.uint8),
            "empty": np.zeros((0, 3), np.float32)}


def test_chunk_files_give_back_their_arrays_and_refuse_a_cut_one(tmp_path):
    arrays = _arrays(np.random.default_rng(1), 300_000)  # several chunks per array
    path = tmp_path / "a.ck"
    nbytes, kept = ChunkFile.write(path, arrays_to_chunks(arrays), keep={"radiosity"})
    assert nbytes == sum(a.nbytes for a in arrays.values())
    assert set(kept) == {"radiosity"} and np.array_equal(kept["radiosity"], arrays["radiosity"])
    back = ChunkFile.read(path)
    assert set(back) == set(arrays)
    for k, a in arrays.items():
        assert back[k].dtype == a.dtype and back[k].shape == a.shape and np.array_equal(back[k], a), k
    assert {c.name for c in ChunkFile.chunks(path, skip={"radiosity"})} == set(arrays) - {"radiosity"}
    blob = path.read_bytes()
    for cut in (len(blob) - 8, len(blob) // 2, 5):
        (tmp_path / "cut.ck").write_bytes(blob[:cut])
        with pytest.raises(ValueError, match="cut short|not a dcrad"):
            ChunkFile.read(tmp_path / "cut.ck")
    assert not list(tmp_path.glob(".*.tmp"))


def test_checkpoint_writer_manifest_reloads_exactly(tmp_path):
    rng = np.random.default_rng(2)
    store = JobStore(tmp_path / "jobs")
    folder = store.folder("j") / "checkpoints"
    folder.mkdir(parents=True)
    writer = CheckpointWriter(folder)
    for barrier in range(1, 8):
        state = {c: _arrays(rng, n) for c, n in ((0, 300), (1, 200))}
        files = {}
        for c, arrays in state.items():
            files[c] = folder / cell_file(c, barrier)
            ChunkFile.write(files[c], arrays_to_chunks(arrays))
        writer.submit(barrier, files, float(barrier), barrier / 100)
        writer.flush()  # every barrier on disk, none skipped
    writer.close()
    res = store.resume("j")
    assert res is not None and res.barrier == 7 and res.elapsed == 7.0 and res.crossing == 0.07
    for c in state:
        back = ChunkFile.read(res.cells[c])
        for k in state[c]:
            assert np.array_equal(back[k], state[c][k])
    # only the last barrier's files are left
    assert sorted(p.name for p in folder.glob("cell-*")) == [cell_file(0, 7), cell_file(1, 7)]
    assert writer.stats["barriers"] == 7 and writer.stats["bytes"] > 0


def test_checkpoint_arrays_resume_a_subscene_exactly(tmp_path):
    """The checkpoint is the whole state: subscenes rebuilt from it at barrier 2 (as a worker
    or a restarted coordinator does) finish bit-identical to the undisturbed run."""
    path = scenes.write_builtin("office", tmp_path, rows=2, cols=3, seed=0)
    _, p, _ = prepare(path)
    config, divide = SolverConfig(tol=0.002, seed=5), DivideConfig(subscenes=2)
    subs, bnds, parents, _ = build_subscenes(p, config, divide)
    ref_run = run_divided(subs, bnds, config, divide.batches_per_barrier)
    ref = assemble(len(p), p.area, parents, [s.patches for s in subs])

    subs, *_ = build_subscenes(p, config, divide)
    done = {"barriers": 0}
    run_divided(subs, bnds, config, divide.batches_per_barrier,
                on_barrier=lambda r: done.update(barriers=r.barriers), should_stop=lambda: done["barriers"] >= 2)
    assert done["barriers"] == 2 < ref_run.barriers
    fresh, *_ = build_subscenes(p, config, divide)
    resumed = [build_subscene(f.cell, f.config, f.power_per_ray, f.mode, list(f.patches.names),
                              subscene_arrays(f) | checkpoint_arrays(s), f.local_target)
               for f, s in zip(fresh, subs)]
    run = run_divided(resumed, bnds, config, divide.batches_per_barrier, first_barrier=2)
    assert run.barriers == ref_run.barriers and run.ledger.closure() < 1e-10
    assert np.array_equal(assemble(len(p), p.area, parents, [s.patches for s in resumed]), ref)
