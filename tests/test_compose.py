"""The containers, for real: build the image, `compose up`, solve from the host, lose a worker.

For each compose tool on the machine (Debian's `docker-compose` 1.29 and the `docker
compose` v2 plugin), with the same docker-compose.yml:

- the base image (deploy/bootstrap-base.sh, offline, kept between runs) and the wheels
  (deploy/build-wheels.sh, kept while the dependencies do not change) are made, and the
  tool builds the image with no network (the layer cache makes a rebuild take seconds);
- `up` starts the coordinator and two workers, which register by service name; every
  container's gRPC health check turns healthy;
- the host's `dcrad submit --wait` solves a two-subscene job in the containers: the result
  equals the embedded mode's (`dcrad solve --workers 2`, same scene, settings and seed) to
  1e-12, the ledger closes, `dcrad fetch` gets the same files, and they are in the results
  volume; the web page answers on its published port;
- a second, longer job loses the worker holding subscene 0 (`docker stop`, a graceful
  SIGTERM) after the first barrier: the other worker takes the subscene over from the last
  checkpoint and the job ends done, with the undisturbed run's result;
- `up --scale worker=3` gives three registered workers;
- a third job (the second's settings) has its coordinator restarted under it (`compose
  restart coordinator`) after its second barrier: it resumes from the checkpoints in the
  volume and ends done, bit for bit the second job's result; the first job, finished
  before the restart, is still listed and fetchable;
- `down -v` removes everything, whatever happened.

Docker Engine is required: without `docker` or a running daemon these tests fail, they do
not skip. It takes a few minutes the first time (debootstrap, wheels, image build), then
about a minute per compose tool. Test-side helpers for deploy/healthcheck.py run without
Docker.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
import uuid
from pathlib import Path

import grpc
import numpy as np
import pytest

from coordinator import client
from coordinator.embedded import LocalCluster
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.v1 import dcrad_pb2_grpc as pb_grpc

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
COMPOSE_FILE = ROOT / "docker-compose.yml"
ARTIFACTS = ROOT / "test-artifacts"
DCRAD = [sys.executable, "-m", "dcrad.cli"]  # the host's CLI

SCENE = "office:rows=2,cols=3,seed=0"
# job 1: two subscenes, a few seconds; job 2: ten times the rays per shot, so it runs long
# enough (about 1 s per barrier) for a worker to be stopped in the middle
JOB1 = ["--subscenes", "2", "--tol", "0.005", "--seed", "3", "--iterations", "4"]
JOB2 = ["--subscenes", "2", "--tol", "0.002", "--seed", "3", "--iterations", "4", "--rays-per-power", "2e6"]

TOOLS = {"docker-compose": ["docker-compose"], "docker compose": ["docker", "compose"]}


# -- helpers -------------------------------------------------------------------------------
def run(cmd, timeout=600, check=True, **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout,
                          stdin=subprocess.DEVNULL, **kw)
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(map(str, cmd))} exited {proc.returncode}\n"
                             f"--- stdout\n{proc.stdout[-4000:]}\n--- stderr\n{proc.stderr[-4000:]}")
    return proc


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def tool_available(name: str) -> bool:
    try:
        return run([*TOOLS[name], "version"], timeout=60, check=False).returncode == 0
    except FileNotFoundError:
        return False


def require_tool(name: str) -> list[str]:
    """The tool's command; a missing one fails under CI (which installs both), else skips."""
    if tool_available(name):
        return TOOLS[name]
    how = ("apt-get install docker-compose" if name == "docker-compose"
           else "see .ci/install-docker-prereqs.sh, which installs the plugin from Debian's package")
    msg = f"`{name}` is not installed ({how})"
    if os.environ.get("CI"):
        pytest.fail(msg, pytrace=False)
    pytest.skip(msg)


def patch_b(folder: Path) -> np.ndarray:
    return np.load(folder / "radiosity.npz")["patch_B"]


def live_workers(address: str) -> list[pb.WorkerInfo]:
    with grpc.insecure_channel(address) as ch:
        reply = pb_grpc.CoordinatorStub(ch).ListWorkers(pb.ListWorkersRequest(), timeout=5)
    return [w for w in reply.workers if w.alive]


def list_jobs(address: str) -> dict[str, str]:
    with grpc.insecure_channel(address) as ch:
        reply = pb_grpc.CoordinatorStub(ch).ListJobs(pb.ListJobsRequest(), timeout=5)
    return {j.job_id: j.state for j in reply.jobs}


def wait_for(what: str, predicate, timeout: float, interval: float = 0.5):
    deadline = time.monotonic() + timeout
    last_error = None
    while time.monotonic() < deadline:
        try:
            value = predicate()
            if value:
                return value
        except Exception as exc:  # not up yet
            last_error = exc
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}"
                         + (f" (last error: {last_error})" if last_error else ""))


class Stack:
    """One `compose -p NAME` project on free loopback ports."""

    def __init__(self, tool: list[str]):
        self.tool = tool
        self.project = f"dcrad-test-{uuid.uuid4().hex[:8]}"
        self.grpc_port, self.web_port = free_port(), free_port()
        self.address = f"127.0.0.1:{self.grpc_port}"
        self.env = dict(os.environ, DCRAD_GRPC_PUBLISH=str(self.grpc_port), DCRAD_WEB_PUBLISH=str(self.web_port))
        for var in ("COMPOSE_FILE", "COMPOSE_PROJECT_NAME", "DCRAD_BASE", "DCRAD_BUILD_NETWORK"):
            self.env.pop(var, None)

    def __call__(self, *args, timeout=600, check=True) -> subprocess.CompletedProcess:
        return run([*self.tool, "-f", str(COMPOSE_FILE), "-p", self.project, *args],
                   timeout=timeout, check=check, env=self.env)

    def containers(self, service: str | None = None) -> list[str]:
        return self("ps", "-q", *([service] if service else [])).stdout.split()

    def inspect(self, cid: str, template: str) -> str:
        return run(["docker", "inspect", "-f", template, cid], timeout=60).stdout.strip()

    def ip(self, cid: str) -> str:
        return self.inspect(cid, "{{range .NetworkSettings.Networks}}{{.IPAddress}} {{end}}").split()[0]

    def save_logs(self, name: str) -> Path:
        ARTIFACTS.mkdir(exist_ok=True)
        path = ARTIFACTS / f"compose-{name.replace(' ', '-')}.log"
        logs = self("logs", "--no-color", "--timestamps", timeout=120, check=False)
        path.write_text(logs.stdout + logs.stderr)
        return path

    def down(self) -> None:
        self("down", "-v", "--remove-orphans", "--timeout", "5", timeout=300, check=False)


# -- fixtures ------------------------------------------------------------------------------
@pytest.fixture(scope="session")
def docker_engine() -> str:
    """Docker Engine's version; fails (never skips) when the engine cannot be used."""
    if shutil.which("docker") is None:
        pytest.fail("tests/test_compose.py needs Docker Engine, and `docker` is not installed "
                    "(Debian: apt-get install docker.io docker-compose)", pytrace=False)
    info = run(["docker", "info", "--format", "{{.ServerVersion}}"], timeout=120, check=False)
    if info.returncode != 0 or not info.stdout.strip():
        pytest.fail("tests/test_compose.py needs Docker Engine, and its daemon does not answer "
                    f"(`docker info`: {(info.stderr or info.stdout).strip()[:500]})", pytrace=False)
    return info.stdout.strip()


@pytest.fixture(scope="session")
def build_inputs(docker_engine) -> None:
    """The base image (offline, once) and the wheels (the dependencies once, dcrad each run)."""
    run(["bash", str(DEPLOY / "bootstrap-base.sh")], timeout=1800)
    run(["bash", str(DEPLOY / "build-wheels.sh")], timeout=1800, env=dict(os.environ, PYTHON=sys.executable))


@pytest.fixture(scope="module")
def embedded(tmp_path_factory) -> dict[str, Path]:
    """Both jobs solved by `dcrad solve --workers 2` (embedded mode) on the host."""
    out = {}
    for name, job in (("job1", JOB1), ("job2", JOB2)):
        folder = tmp_path_factory.mktemp(f"embedded-{name}")
        run([*DCRAD, "solve", SCENE, "--workers", "2", *job, "--out", str(folder)], timeout=600)
        out[name] = folder
    return out


# -- without Docker: the health check script -------------------------------------------------
def test_healthcheck_script_finds_the_port_of_process_1(tmp_path):
    sys.path.insert(0, str(DEPLOY))
    try:
        import healthcheck
    finally:
        sys.path.remove(str(DEPLOY))
    cmdline = tmp_path / "cmdline"
    for args, expected in (
        (["/opt/dcrad/venv/bin/python", "/opt/dcrad/lib/bin/dcrad", "worker", "--host", "0.0.0.0", "--port", "6000"],
         "127.0.0.1:6000"),
        (["python", "dcrad", "-v", "coordinator", "--port=7000"], "127.0.0.1:7000"),
        (["python", "dcrad", "coordinator"], "127.0.0.1:50051"),
        (["python", "dcrad", "worker"], "127.0.0.1:50052"),
    ):
        cmdline.write_bytes(b"\0".join(a.encode() for a in args) + b"\0")
        assert healthcheck.local_address(str(cmdline)) == expected


def test_healthcheck_script_against_real_services(tmp_path):
    script = [sys.executable, str(DEPLOY / "healthcheck.py")]
    with LocalCluster(workers=1, data=tmp_path) as cluster:
        assert run([*script, cluster.address], check=False).returncode == 0
        assert run([*script, cluster.address, "--service", "dcrad.v1.Coordinator"], check=False).returncode == 0
        worker = f"127.0.0.1:{cluster.worker_ports[0]}"
        assert run([*script, worker, "--service", "dcrad.v1.Worker"], check=False).returncode == 0
    closed = run([*script, f"127.0.0.1:{free_port()}", "--timeout", "1"], check=False)
    assert closed.returncode == 1 and "UNAVAILABLE" in closed.stderr


# -- with Docker ---------------------------------------------------------------------------
@pytest.mark.docker
@pytest.mark.parametrize("name", list(TOOLS))
def test_compose_file_is_valid(docker_engine, name):
    """Each tool reads the file the same way: two services, two workers, loopback ports."""
    import yaml

    tool = require_tool(name)
    config = yaml.safe_load(run([*tool, "-f", str(COMPOSE_FILE), "config"], timeout=120,
                                env={k: v for k, v in os.environ.items() if not k.startswith("DCRAD_")}).stdout)
    services = config["services"]
    assert set(services) == {"coordinator", "worker"}
    assert services["worker"]["scale"] == 2
    assert services["coordinator"]["image"] == services["worker"]["image"] == "dcrad:latest"
    assert services["coordinator"]["build"]["network"] == "none"
    ports = services["coordinator"]["ports"]
    # v1 writes "127.0.0.1:50051:50051/tcp", v2 a mapping
    as_text = sorted(p if isinstance(p, str) else f"{p['host_ip']}:{p['published']}:{p['target']}/tcp" for p in ports)
    assert as_text == ["127.0.0.1:50051:50051/tcp", "127.0.0.1:8080:8080/tcp"]


@pytest.mark.docker
@pytest.mark.timeout(1800)
@pytest.mark.parametrize("name", list(TOOLS))
def test_compose_stack(docker_engine, build_inputs, embedded, name, tmp_path):
    tool = require_tool(name)
    stack = Stack(tool)
    started = time.monotonic()
    ok = False
    try:
        # the user's guide's build command: wheels, compose build, and no dangling dcrad image left
        # (every rebuild moves dcrad:latest to a new image; the old one used to stay as <none>)
        run(["bash", str(DEPLOY / "build-image.sh"), *tool], timeout=1800,
            env=dict(stack.env, PYTHON=sys.executable))
        dangling = run(["docker", "images", "-q", "--filter", "dangling=true",
                        "--filter", "label=org.opencontainers.image.title=dcrad"]).stdout.split()
        assert not dangling, f"dangling dcrad images after the build: {dangling}"
        build_s = time.monotonic() - started
        stack("up", "-d", timeout=600)

        # -- two workers register by service name, each with its own container address
        workers = wait_for("two registered workers", lambda: len(ws := live_workers(stack.address)) == 2 and ws, 120)
        ips = {stack.ip(cid): cid for cid in stack.containers("worker")}
        assert len(ips) == 2
        assert {w.address for w in workers} == {f"{ip}:50052" for ip in ips}
        # every container's gRPC health check (Dockerfile / compose) turns healthy
        wait_for("healthy containers", lambda: all(
            stack.inspect(c, "{{.State.Health.Status}}") == "healthy" for c in stack.containers()), 120, 1.0)
        assert stack.inspect(stack.containers("coordinator")[0], "{{.Config.User}}") == "10001:10001"

        # -- job 1 from the host's CLI, as a user would
        out1 = tmp_path / "job1"
        sub = run([*DCRAD, "submit", SCENE, *JOB1, "--wait", "--out", str(out1), "--coordinator", stack.address])
        job1 = sub.stdout.split()[0]
        assert "done" in sub.stdout
        # the embedded mode's result: same scene, settings and seed give the same numbers
        assert np.allclose(patch_b(out1), patch_b(embedded["job1"]), rtol=1e-12, atol=1e-15)
        report = json.loads((out1 / "report.json").read_text())
        assert report["ledger"]["closure"] < 1e-12
        assert report["divided"]["subscenes"] == 2
        # fetch again: the same files
        out1b = tmp_path / "job1-fetch"
        run([*DCRAD, "fetch", job1, "--out", str(out1b), "--coordinator", stack.address])
        assert {p.name for p in out1b.iterdir()} == {p.name for p in out1.iterdir()}
        assert (out1b / "radiosity.npz").read_bytes() == (out1 / "radiosity.npz").read_bytes()
        # and they are in the results volume
        listing = stack("exec", "-T", "coordinator", "ls", f"/data/jobs/{job1}/out").stdout.split()
        assert {"radiosity.npz", "report.json"} <= set(listing)
        # the web page on its published port, where this dcrad has one
        if "--web-port" in run([*DCRAD, "coordinator", "--help"]).stdout:
            page = wait_for("the web page", lambda: urllib.request.urlopen(
                f"http://127.0.0.1:{stack.web_port}/api/jobs", timeout=10).read(), 60)
            assert job1 in page.decode()

        # -- job 2: stop the worker holding subscene 0 after the first barrier
        job2 = run([*DCRAD, "submit", SCENE, *JOB2, "--coordinator", stack.address]).stdout.split()[0]
        stopped = []

        def on_progress(p: pb.Progress) -> None:
            if p.barrier >= 1 and p.job.state == "running" and not stopped:
                victim = next(s.worker for s in p.subscenes if s.cell == 0)
                run(["docker", "stop", "--time", "10", ips[victim.rsplit(":", 1)[0]]], timeout=120)
                stopped.append((victim, p.barrier))

        final = client.watch(stack.address, job2, on_progress)
        assert stopped, "the job ended before its first barrier"
        victim, at_barrier = stopped[0]
        assert final.job.state == "done", final.job.error
        assert final.barrier > at_barrier, "the worker was stopped only after the last barrier"
        cell0 = next(s for s in final.subscenes if s.cell == 0)
        assert cell0.reassigned >= 1 and cell0.worker != victim
        # one worker left, and it holds both subscenes now
        assert {s.worker for s in final.subscenes} == {w.address for w in live_workers(stack.address)}
        assert len(live_workers(stack.address)) == 1
        assert final.ledger.closure < 1e-12  # nothing lost in the move
        out2 = tmp_path / "job2"
        client.fetch(stack.address, job2, out2)
        # resumed from the checkpoint, bit for bit the undisturbed run
        assert np.allclose(patch_b(out2), patch_b(embedded["job2"]), rtol=1e-12, atol=1e-15)
        assert json.loads((out2 / "report.json").read_text())["ledger"]["closure"] < 1e-12

        # -- scaling: the stopped worker comes back and a third one joins
        stack("up", "-d", "--scale", "worker=3", timeout=600)
        wait_for("three registered workers", lambda: len(live_workers(stack.address)) == 3, 120)

        # -- job 3 (job 2's settings): restart the coordinator container after its second barrier
        job3 = run([*DCRAD, "submit", SCENE, *JOB2, "--coordinator", stack.address]).stdout.split()[0]
        with grpc.insecure_channel(stack.address) as ch:
            for p in pb_grpc.CoordinatorStub(ch).Watch(pb.JobRef(job_id=job3), timeout=600):
                if p.job.state == "running" and p.barrier >= 2:
                    break
        assert p.job.state == "running", "job 3 ended before its second barrier"
        stack("restart", "coordinator", timeout=300)
        listed = wait_for("the restarted coordinator", lambda: list_jobs(stack.address), 120)
        assert listed[job1] == "done" and job3 in listed  # both jobs came back from the volume
        final3 = client.watch(stack.address, job3)
        assert final3.job.state == "done", final3.job.error
        assert final3.ledger.closure < 1e-12
        out3 = tmp_path / "job3"
        client.fetch(stack.address, job3, out3)
        report3 = json.loads((out3 / "report.json").read_text())
        assert any(c["code"] == "resumed" and c["text"].startswith("resumed from barrier")
                   for c in report3["choices"]), report3["choices"]
        assert np.array_equal(patch_b(out3), patch_b(out2))  # resumed: the same numbers, bit for bit
        out1c = tmp_path / "job1-after-restart"
        client.fetch(stack.address, job1, out1c)
        assert (out1c / "radiosity.npz").read_bytes() == (out1 / "radiosity.npz").read_bytes()
        ok = True
        print(f"\n{name}: build {build_s:.1f} s, whole test {time.monotonic() - started:.1f} s; "
              f"job 2 reassigned {cell0.reassigned}, closure {final.ledger.closure:.1e}")
    finally:
        if not ok:
            print(f"compose logs: {stack.save_logs(name)}")
        stack.down()
        leftover = run(["docker", "ps", "-aq", "--filter", f"label=com.docker.compose.project={stack.project}"],
                       check=False).stdout.split()
        assert not leftover, f"containers left after down: {leftover}"
