"""The embedded cluster of `dcrad solve` ends with it, however it ends.

`dcrad solve --workers 2` is a real process with a real coordinator and two worker
processes.  It is stopped with SIGTERM, SIGHUP (both handled like Ctrl-C: the job is
cancelled and the results so far written) and SIGKILL (no chance to clean up: the
children's parent-death signal and watchdog end them).  Afterwards none of its
children is alive.  Processes are identified by pid and start time, never by name:
other dcrad processes may run on the same machine.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest


def _stat(pid: int) -> list[str] | None:
    """Fields of /proc/PID/stat after the command name, or None when the pid is gone."""
    return _stat_of(f"/proc/{pid}/stat")


def _stat_of(path: str) -> list[str] | None:
    """Fields of a /proc stat file after the command name, or None when it is gone."""
    try:
        text = Path(path).read_text()
    except OSError:
        return None
    return text.rsplit(")", 1)[1].split()


def children_of(pid: int) -> dict[int, str]:
    """{child pid: start time} of the live children of ``pid``."""
    out = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            st = _stat(int(entry.name))
            if st is not None and int(st[1]) == pid and st[0] != "Z":
                out[int(entry.name)] = st[19]
    return out


def _nices(pid: int) -> list[str]:
    """The nice of each thread of ``pid``, the main thread's first ([] when it is gone)."""
    try:
        tasks = sorted(int(t.name) for t in Path(f"/proc/{pid}/task").iterdir())
    except OSError:
        return []
    return [st[16] for st in (_stat_of(f"/proc/{pid}/task/{t}/stat") for t in tasks) if st is not None]


def alive(pid: int, start: str) -> bool:
    st = _stat(pid)
    return st is not None and st[19] == start and st[0] != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGKILL], ids=lambda s: s.name)
def test_killed_solve_leaves_no_process(tmp_path, sig):
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "dcrad.cli", "solve", "furnace:rho=0.99", "--tol", "1e-9",
                             "--workers", "2", "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                            start_new_session=True)  # its own group: the signal reaches it alone
    kids: dict[int, str] = {}
    try:
        lines = []
        for line in proc.stderr:
            lines.append(line)
            if "status page" in line:  # the cluster is up and the job submitted
                break
        assert proc.poll() is None, "".join(lines)
        kids = children_of(proc.pid)
        assert len(kids) == 3, kids  # the coordinator and two workers
        time.sleep(1.0)  # let the job run a little
        os.kill(proc.pid, sig)
        rest = proc.communicate(timeout=120)[1]
        deadline = time.monotonic() + 60
        while any(alive(p, s) for p, s in kids.items()) and time.monotonic() < deadline:
            time.sleep(0.1)
        left = [p for p, s in kids.items() if alive(p, s)]
        assert not left, f"still running after {sig.name}: {left}"
        if sig != signal.SIGKILL:  # handled like Ctrl-C: cancelled, results so far written
            assert proc.returncode == 0, rest
            report = json.loads((out / "report.json").read_text())
            assert report["stats"]["stopped_by"] == "stopped"
        else:
            assert proc.returncode == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        for p, s in kids.items():  # never leave them to the machine, even when the test fails
            if alive(p, s):
                os.kill(p, signal.SIGKILL)


def test_cluster_started_without_waiting_registers_or_stops_with_the_callers_error(tmp_path):
    """LocalCluster(wait=False) returns while its processes import (dcrad solve validates the scene
    meanwhile): wait() then sees the coordinator listen and every worker register; an error in the
    caller's block (a bad scene) stops every process it started."""
    import grpc

    from coordinator.embedded import LocalCluster
    from dcrad.v1 import dcrad_pb2 as pb
    from dcrad.v1 import dcrad_pb2_grpc as pb_grpc

    with LocalCluster(workers=2, data=tmp_path / "a", web=False, wait=False) as cluster:
        assert cluster.coordinator is not None and len(cluster.workers) == 2
        assert cluster.address.endswith(f":{cluster.port}") and cluster.port > 0
        cluster.wait()
        with grpc.insecure_channel(cluster.address) as ch:
            listed = pb_grpc.CoordinatorStub(ch).ListWorkers(pb.ListWorkersRequest(), timeout=10).workers
        assert sum(w.alive for w in listed) == 2
    procs = []
    with pytest.raises(RuntimeError, match="bad scene"):
        with LocalCluster(workers=2, data=tmp_path / "b", web=False, wait=False) as cluster:
            procs = [cluster.coordinator, *cluster.workers]
            raise RuntimeError("bad scene")
    assert len(procs) == 3 and all(p is not None and p.poll() is not None for p in procs)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_killed_coordinator_leaves_no_views_process(tmp_path):
    """The outputs' views are made in a child of the coordinator (coordinator/ahead.py); SIGKILL the
    coordinator mid-job and that child ends too."""
    from coordinator import client
    from coordinator.embedded import LocalCluster
    from dcrad.pipeline import resolve_scene

    path = resolve_scene("office", tmp_path)
    with LocalCluster(workers=2, data=tmp_path / "data", web=False) as cluster:
        assert cluster.coordinator is not None
        client.submit(cluster.address, path, {"accuracy": 0.005}, {"subscenes": None}, (64, 48))
        deadline = time.monotonic() + 60
        kids: dict[int, str] = {}
        while not kids and time.monotonic() < deadline:
            kids = children_of(cluster.coordinator.pid)
            time.sleep(0.05)
        assert kids, "the job started no views process"
        cluster.kill_coordinator()
        deadline = time.monotonic() + 30
        while any(alive(p, s) for p, s in kids.items()) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not [p for p, s in kids.items() if alive(p, s)]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_job_takes_the_views_process_started_ahead(tmp_path):
    """coordinator/ahead.py keeps one views process started ahead: a job's ViewsAhead takes it (the
    same pid), starts the next at nice 19, and gets the views the coordinator would make itself."""
    import numpy as np

    from coordinator import ahead
    from dcrad.pipeline import output_views, prepare, resolve_scene

    scene, patches, _ = prepare(resolve_scene("office", tmp_path))
    ahead.prestart()
    spare = ahead._spare
    assert spare is not None and spare.poll() is None
    job = ahead.ViewsAhead(patches, None, 64, 48, (32, 24))
    assert job._proc.pid == spare.pid  # taken, not started anew
    following = ahead._spare
    assert following is not None and following.pid != spare.pid
    got = job.future.result(timeout=120)
    want = output_views(scene, patches, 64, 48, ahead=True)
    for name in ("pixel", "patch", "bc", "back"):
        np.testing.assert_array_equal(getattr(got.hits, name), getattr(want.hits, name))
    assert got.live is not None and got.live.width == 32
    assert job._proc.poll() is None  # it waits for B, to write the pictures (test_pictures.py)
    job.close()
    assert job._proc.poll() is not None
    # the next one's views thread lowers itself before it imports anything; its main thread keeps
    # the coordinator's priority, for the pictures
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and "19" not in _nices(following.pid):
        time.sleep(0.05)
    assert "19" in _nices(following.pid) and _nices(following.pid)[0] == "0"
    following.stdin.close()  # as the coordinator's exit would: it ends without a job
    assert following.wait(30) == 0
    following.stdout.close()
    ahead._spare = None
