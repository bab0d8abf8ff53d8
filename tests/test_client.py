"""The coordinator client against a fake coordinator: scene files, chunked upload, watch, fetch, CLI errors."""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from concurrent import futures
from pathlib import Path

import grpc
import pytest

from coordinator import client
from dcrad.errors import DcradError, ExchangeError
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.v1 import dcrad_pb2_grpc as pb_grpc
from dcrad.wire import CHUNK_BYTES, FileAssembler

RESULTS = {"radiosity.npz": b"\x93NUMPY" + bytes(range(256)) * 9000, "previews/top.png": b"\x89PNG fake"}


class FakeCoordinator(pb_grpc.CoordinatorServicer):
    """Records uploads; knows jobs 'job-1' (done), 'job-bad' (failed) and 'job-slow' (never ends)."""

    def __init__(self):
        self.limit = 64 << 20
        self.specs: list[pb.JobSpec] = []
        self.files: dict[str, bytes] = {}
        self.order: list[tuple[str, int]] = []  # (kind, offset) in arrival order
        self.watching = threading.Event()
        self.cancelled = []

    def _known(self, job_id, context):
        if job_id not in ("job-1", "job-bad", "job-slow"):
            context.abort(grpc.StatusCode.NOT_FOUND, f"job '{job_id}' not found")

    def Submit(self, request_iterator, context):
        asm = FileAssembler(self.limit)
        spec = None
        for req in request_iterator:
            if req.HasField("spec"):
                assert spec is None and not self.order
                spec = req.spec
                self.order.append(("spec", 0))
                continue
            self.order.append((req.file.path, req.file.offset))
            try:
                asm.add(req.file)
            except ExchangeError as exc:
                context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, str(exc))
        self.specs.append(spec)
        self.files = {k: bytes(v) for k, v in asm.files.items()}
        job_id = "job-bad" if spec.solver.seed == 13 else "job-1"
        return pb.JobSummary(job_id=job_id, state="queued", scene=spec.scene, subscenes=spec.divide.subscenes)

    def Watch(self, request, context):
        self._known(request.job_id, context)
        self.watching.set()
        if request.job_id == "job-slow":
            while context.is_active():
                time.sleep(0.05)
            return
        final = "failed" if request.job_id == "job-bad" else "done"
        for i, residual in enumerate((0.2, 0.05, 0.008), 1):
            state = final if i == 3 else "running"
            job = pb.JobSummary(job_id=request.job_id, state=state, scene="scene.obj", subscenes=2,
                                elapsed_s=1.5 * i, residual=residual, workers=["w1:1", "w2:2"],
                                error="worker w2:2 lost" if state == "failed" else "")
            yield pb.Progress(job=job, barrier=i, shots=10 * i, rays=100_000 * i,
                              ledger=pb.Ledger(residual=residual, closure=1e-15 * i))

    def Fetch(self, request, context):
        self._known(request.job_id, context)
        for path, data in RESULTS.items():
            for off in range(0, len(data), CHUNK_BYTES):
                yield pb.FileChunk(path=path, offset=off, total_bytes=len(data), data=data[off:off + CHUNK_BYTES])

    def Cancel(self, request, context):
        self._known(request.job_id, context)
        self.cancelled.append(request.job_id)
        return pb.JobSummary(job_id=request.job_id, state="cancelled")

    def ListJobs(self, request, context):
        return pb.JobList(jobs=[
            pb.JobSummary(job_id="job-1", state="running", scene="office.obj", subscenes=4, elapsed_s=12.25,
                          residual=0.031, workers=["a:1", "b:2"]),
            pb.JobSummary(job_id="job-2", state="queued", scene="cornell.gltf")])


@pytest.fixture
def fake():
    servicer = FakeCoordinator()
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=8),
                         options=[("grpc.max_receive_message_length", 8 << 20)])
    pb_grpc.add_CoordinatorServicer_to_server(servicer, server)
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    servicer.address = f"127.0.0.1:{port}"
    yield servicer
    server.stop(grace=None)


@pytest.fixture
def closed_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_scene(folder: Path, obj_extra: bytes = b"", mtllib: str = "scene.mtl") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "scene.mtl").write_text("newmtl white\nKd 0.5 0.5 0.5\n")
    obj = folder / "scene.obj"
    obj.write_bytes(f"mtllib {mtllib}\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl white\nf 1 2 3\n".encode() + obj_extra)
    return obj


def cli(argv) -> int:
    ap = argparse.ArgumentParser(prog="dcrad")
    client.add_client_commands(ap.add_subparsers(dest="command", required=True))
    args = ap.parse_args([str(a) for a in argv])
    return args.func(args)


# -- scene files ------------------------------------------------------------------------------
def test_scene_files_obj_with_mtl(tmp_path):
    obj = write_scene(tmp_path / "s")
    files = client.scene_files(obj)
    assert list(files) == ["scene.obj", "scene.mtl"]
    assert files["scene.mtl"] == (tmp_path / "s" / "scene.mtl").read_bytes()
    assert files["scene.obj"] == obj.read_bytes()


def test_scene_files_obj_subfolder_mtl(tmp_path):
    folder = tmp_path / "s"
    (folder / "mats").mkdir(parents=True)
    (folder / "mats" / "a.mtl").write_text("newmtl a\nKd 0.1 0.2 0.3\n")
    obj = write_scene(folder, mtllib="mats/a.mtl  # materials")
    assert list(client.scene_files(obj)) == ["scene.obj", "mats/a.mtl"]


def test_scene_files_refuses_escaping_mtllib(tmp_path):
    (tmp_path / "x.mtl").write_text("newmtl x\n")
    obj = write_scene(tmp_path / "s", mtllib="../x.mtl")
    with pytest.raises(DcradError, match=r"\.\./x\.mtl"):
        client.scene_files(obj)


def test_scene_files_gltf_and_glb(tmp_path):
    (tmp_path / "tex").mkdir()
    (tmp_path / "mesh.bin").write_bytes(b"\0" * 36)
    (tmp_path / "tex" / "a.png").write_bytes(b"png")
    header = {"asset": {"version": "2.0"}, "buffers": [{"uri": "mesh.bin", "byteLength": 36}],
              "images": [{"uri": "data:image/png;base64,AAAA"}, {"uri": "tex/a.png"}]}
    gltf = tmp_path / "scene.gltf"
    gltf.write_text(json.dumps(header))
    assert list(client.scene_files(gltf)) == ["scene.gltf", "mesh.bin", "tex/a.png"]
    header["buffers"][0]["uri"] = "../outside.bin"
    gltf.write_text(json.dumps(header))
    with pytest.raises(DcradError, match="outside.bin"):
        client.scene_files(gltf)
    glb = tmp_path / "scene.glb"
    glb.write_bytes(b"glTF binary")
    assert list(client.scene_files(glb)) == ["scene.glb"]
    with pytest.raises(DcradError, match="unsupported scene format"):
        client.scene_files(tmp_path / "scene.ply")


# -- API -----------------------------------------------------------------------------------
def test_submit_streams_spec_then_exact_chunked_bytes(fake, tmp_path):
    obj = write_scene(tmp_path / "s", obj_extra=b"# padding to make several chunks\n" * 80_000)
    assert obj.stat().st_size > 2 * CHUNK_BYTES
    job = client.submit(fake.address, obj, {"tol": 0.02, "seed": 7, "rays_per_power": 1e4},
                        {"subscenes": 3, "mode": "exact"})
    assert job.job_id == "job-1" and job.scene == "scene.obj" and job.subscenes == 3
    spec = fake.specs[0]
    assert spec.scene == "scene.obj"
    assert spec.solver.tol == 0.02 and spec.solver.seed == 7 and spec.solver.rays_per_power == 1e4
    assert spec.divide.subscenes == 3 and spec.divide.mode == "exact"
    assert fake.files == {"scene.obj": obj.read_bytes(), "scene.mtl": (tmp_path / "s" / "scene.mtl").read_bytes()}
    obj_chunks = [off for path, off in fake.order if path == "scene.obj"]
    assert fake.order[0] == ("spec", 0)
    assert len(obj_chunks) >= 3 and obj_chunks == sorted(obj_chunks) and obj_chunks[0] == 0
    assert fake.order[1:] == [("scene.obj", o) for o in obj_chunks] + [("scene.mtl", 0)]


def test_watch_returns_last_progress(fake):
    seen = []
    last = client.watch(fake.address, "job-1", seen.append)
    assert [p.barrier for p in seen] == [1, 2, 3]
    assert last.barrier == 3 and last.job.state == "done" and last.ledger.residual == 0.008


def test_fetch_writes_files(fake, tmp_path):
    written = client.fetch(fake.address, "job-1", tmp_path / "res")
    assert sorted(p.relative_to(tmp_path / "res").as_posix() for p in written) == sorted(RESULTS)
    for rel, data in RESULTS.items():
        assert (tmp_path / "res" / rel).read_bytes() == data


def test_cancel_and_list_jobs(fake):
    assert client.cancel(fake.address, "job-1").state == "cancelled"
    assert [j.job_id for j in client.list_jobs(fake.address)] == ["job-1", "job-2"]


def test_unknown_job_is_not_found(fake):
    with pytest.raises(grpc.RpcError) as info:
        client.watch(fake.address, "nope")
    assert info.value.code() == grpc.StatusCode.NOT_FOUND


# -- command line ------------------------------------------------------------------------------
@pytest.mark.parametrize("command", ["watch", "fetch", "cancel"])
def test_cli_not_found_is_one_line(fake, capsys, command):
    assert cli([command, "nope", "--coordinator", fake.address]) == 2
    out, err = capsys.readouterr()
    assert err == "dcrad: error: job 'nope' not found\n" and out == ""


def test_cli_unreachable_coordinator(monkeypatch, capsys, closed_port):
    monkeypatch.setattr(client, "RETRY_ATTEMPTS", 2)
    monkeypatch.setenv("DCRAD_COORDINATOR", f"127.0.0.1:{closed_port}")
    t0 = time.monotonic()
    assert cli(["jobs"]) == 2
    assert time.monotonic() - t0 < 15
    _, err = capsys.readouterr()
    assert err == f"dcrad: error: cannot reach coordinator at 127.0.0.1:{closed_port}\n"


def test_cli_unreachable_subprocess(closed_port, tmp_path):
    """A real process: one line, exit 2, no traceback."""
    code = ("import argparse, sys; from coordinator import client; client.RETRY_ATTEMPTS = 2\n"
            "ap = argparse.ArgumentParser(prog='dcrad'); client.add_client_commands(ap.add_subparsers())\n"
            "a = ap.parse_args(sys.argv[1:]); sys.exit(a.func(a))")
    r = subprocess.run([sys.executable, "-c", code, "watch", "abc", "--coordinator", f"127.0.0.1:{closed_port}"],
                       capture_output=True, text=True, timeout=60, cwd=Path(__file__).parents[1])
    assert r.returncode == 2
    assert r.stderr == f"dcrad: error: cannot reach coordinator at 127.0.0.1:{closed_port}\n"


def test_cli_submit_prints_job_id(fake, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("DCRAD_COORDINATOR", fake.address)
    obj = write_scene(tmp_path / "s")
    assert cli(["submit", obj, "--subscenes", "2", "--boundary", "exact", "--tol", "0.03", "--seed", "5",
                "--time-limit", "9", "--max-rays", "1000000", "--patch-size", "0.25", "--rays-per-power", "5e4"]) == 0
    out, err = capsys.readouterr()
    assert out == "job-1\n" and err == ""
    s = fake.specs[0]
    assert (s.divide.subscenes, s.divide.mode, s.solver.tol, s.solver.seed) == (2, "exact", 0.03, 5)
    assert (s.solver.time_limit, s.solver.max_rays, s.solver.patch_size, s.solver.rays_per_power) == \
        (9.0, 1_000_000, 0.25, 5e4)


def test_cli_submit_wait_fetches(fake, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    obj = write_scene(tmp_path / "s")
    assert cli(["submit", obj, "--wait", "--coordinator", fake.address]) == 0
    out, _ = capsys.readouterr()
    lines = out.splitlines()
    assert lines[0] == "job-1"
    assert "done" in lines[1] and "8.00e-03" in lines[1] and "closure" in lines[1]
    assert str(Path("out") / "job-1") in lines[-1]
    assert (tmp_path / "out" / "job-1" / "radiosity.npz").read_bytes() == RESULTS["radiosity.npz"]


def test_cli_submit_wait_failed_job(fake, tmp_path, capsys):
    obj = write_scene(tmp_path / "s")
    code = cli(["submit", obj, "--wait", "--seed", "13", "--out", tmp_path / "r", "--coordinator", fake.address])
    assert code == 1
    out, err = capsys.readouterr()
    assert out.splitlines()[0] == "job-bad"
    assert "worker w2:2 lost" in err and not (tmp_path / "r").exists()


def test_cli_upload_too_large(fake, tmp_path, capsys):
    fake.limit = 1000
    obj = write_scene(tmp_path / "s", obj_extra=b"# pad\n" * 1000)
    assert cli(["submit", obj, "--coordinator", fake.address]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("dcrad: error: upload too large") and err.count("\n") == 1


def test_cli_escaping_scene_is_one_line(fake, tmp_path, capsys):
    obj = write_scene(tmp_path / "s", mtllib="../x.mtl")
    assert cli(["submit", obj, "--coordinator", fake.address]) == 2
    _, err = capsys.readouterr()
    assert err.startswith("dcrad: error: ") and "../x.mtl" in err and err.count("\n") == 1
    assert not fake.specs


def test_cli_watch_bar_and_final_line(fake, capsys):
    assert cli(["watch", "job-1", "--progress", "--coordinator", fake.address]) == 0
    out, err = capsys.readouterr()
    assert "barrier 3" in err and "Mrays/s" in err and "0.07 Mrays/s" in err  # 100k rays per 1.5 s
    assert out.startswith("dcrad: job job-1 done: residual 8.00e-03, ledger closure 3.0e-15")
    assert cli(["watch", "job-bad", "--coordinator", fake.address]) == 1


def test_cli_fetch_cancel_jobs(fake, tmp_path, capsys):
    assert cli(["fetch", "job-1", "--out", tmp_path / "f", "--coordinator", fake.address]) == 0
    assert (tmp_path / "f" / "previews" / "top.png").read_bytes() == RESULTS["previews/top.png"]
    assert cli(["cancel", "job-slow", "--coordinator", fake.address]) == 0
    assert fake.cancelled == ["job-slow"]
    capsys.readouterr()
    assert cli(["jobs", "--coordinator", fake.address]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["ID", "STATE", "SCENE", "SUBSCENES", "WORKERS", "ELAPSED", "RESIDUAL"]
    assert lines[1].split() == ["job-1", "running", "office.obj", "4", "2", "12.2s", "3.10e-02"]
    # a queued job has no subscenes or workers yet: "-", not a misleading 0
    assert lines[2].split()[:5] == ["job-2", "queued", "cornell.gltf", "-", "-"]


@pytest.mark.skipif(os.name != "posix", reason="SIGINT")
def test_cli_watch_ctrl_c(fake):
    code = ("import argparse, sys; from coordinator import client\n"
            "ap = argparse.ArgumentParser(prog='dcrad'); client.add_client_commands(ap.add_subparsers())\n"
            "a = ap.parse_args(sys.argv[1:]); sys.exit(a.func(a))")
    proc = subprocess.Popen([sys.executable, "-c", code, "watch", "job-slow", "--coordinator", fake.address],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=Path(__file__).parents[1])
    try:
        assert fake.watching.wait(30)
        time.sleep(0.3)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 130
    assert "Traceback" not in err and "stopped watching job job-slow" in err
