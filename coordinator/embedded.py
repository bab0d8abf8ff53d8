"""A coordinator and N worker processes on loopback, for `dcrad solve` and tests.

``LocalCluster`` starts real processes (``python -m dcrad.cli coordinator`` and
``worker``) on free ports, waits until every worker has registered, and stops
them all (SIGTERM, then SIGKILL after a grace period) when the ``with`` block
ends.  ``kill_worker(i)`` is there for the worker-loss tests.  The coordinator's
web status pages listen on a free loopback port (``web_url``) unless
``web=False``.

The cluster ends with its parent however the parent ends (SIGTERM, SIGHUP,
SIGKILL): each child learns its parent's pid from ``DCRAD_PARENT_PID`` and calls
``die_with_parent`` at start, which asks Linux for a parent-death signal (when
the parent spawned it from its main thread: the signal follows the spawning
thread) and starts a watchdog thread that stops the child once its parent pid
changes (re-parented to init or a subreaper).
"""

from __future__ import annotations

import ctypes
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import grpc

from dcrad.errors import ConfigError, DcradError
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.v1 import dcrad_pb2_grpc as pb_grpc

#: environment of a child of LocalCluster: the parent's pid, and "1" when the parent-death
#: signal may be used (the child was spawned from the parent's main thread)
PARENT_ENV, DEATHSIG_ENV = "DCRAD_PARENT_PID", "DCRAD_PARENT_DEATHSIG"
_PR_SET_PDEATHSIG = 1
#: s between the watchdog's looks at the parent pid, and s a stopping child gets before it is ended
WATCH_PERIOD, GRACE = 0.5, 10.0


def max_local_workers() -> int:
    """The most worker processes ``dcrad solve`` starts on this machine: 4 per CPU, and at most
    one per 256 MiB of memory (each worker holds its subscenes and an Embree scene)."""
    cpus = os.cpu_count() or 1
    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        memory = 1 << 40
    return max(1, min(4 * cpus, memory // (256 << 20)))


def check_workers(n: int) -> None:
    """ConfigError unless 0 <= n <= max_local_workers() (0: solve in this process)."""
    if n < 0:
        raise ConfigError(f"--workers must be >= 0 (0: solve in this process), not {n}")
    limit = max_local_workers()
    if n > limit:
        raise ConfigError(f"--workers {n}: at most {limit} local worker processes on this machine "
                          f"({os.cpu_count() or 1} CPUs; more only compete for them); for more, run "
                          f"`dcrad coordinator` and workers on other machines")


def die_with_parent(environ=os.environ) -> bool:
    """In a child of LocalCluster: end this process when its parent ends; False when not such a child.

    The parent-death signal (SIGTERM, so the services stop as on ``docker stop``)
    covers a parent killed by any signal, SIGKILL included; the watchdog covers the
    rest (a parent that died before the signal was armed, or a non-Linux kernel).
    A child still alive ``GRACE`` s after its parent is gone exits at once.
    """
    try:
        parent = int(environ.get(PARENT_ENV, ""))
    except ValueError:
        return False
    if environ.get(DEATHSIG_ENV) == "1" and sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
        except (OSError, AttributeError):
            pass

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(WATCH_PERIOD)
        os.kill(os.getpid(), signal.SIGTERM)  # the services' own clean stop
        time.sleep(GRACE)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()
    return True


def _read_port(proc: subprocess.Popen, role: str, timeout: float, on_line=None) -> int:
    """The gRPC port from the 'listening on host:port' line; earlier lines go to ``on_line``."""
    if proc.stdout is None:
        raise DcradError(f"the {role} process was started without a stdout pipe")
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            if proc.poll() is not None:
                raise DcradError(f"the {role} process exited with code {proc.returncode} before listening")
            continue
        if on_line is not None:
            on_line(line)
        if "listening on" in line:
            return int(line.strip().rsplit(":", 1)[1])
    raise DcradError(f"the {role} did not start listening within {timeout:.0f} s")


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port on ``host`` that nothing listens on now (the kernel's choice)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


class LocalCluster:
    """``with LocalCluster(workers=2) as c: c.address`` -> "127.0.0.1:PORT".

    ``with LocalCluster(workers=2, wait=False) as c: ...; c.wait()`` starts the processes and
    lets the caller work while they import."""

    def __init__(self, workers: int = 2, data: str | Path | None = None, python: str = sys.executable,
                 log_dir: str | Path | None = None, start_timeout: float = 60.0,
                 coordinator_args: tuple[str, ...] = (), port: int = 0, web: bool = True, wait: bool = True):
        self.n_workers = workers
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        if not data:
            self._tmp = tempfile.TemporaryDirectory(prefix="dcrad-cluster-")
            data = self._tmp.name
        self.data = Path(data)
        self.python = python
        self.log_dir = Path(log_dir) if log_dir else self.data
        self.start_timeout = start_timeout
        self.coordinator_args = tuple(coordinator_args)
        self.port = port
        self.web = web
        self.wait_ready = wait  #: ``with`` waits for the processes (False: the caller calls ``wait()``)
        self.web_url = ""  #: "http://127.0.0.1:PORT" of the status pages ("" when off)
        self.coordinator: subprocess.Popen | None = None
        self.workers: list[subprocess.Popen] = []
        self.worker_ports: list[int] = []
        self.address = ""

    def _spawn(self, *args: str, index: int | None = None) -> subprocess.Popen:
        main = threading.current_thread() is threading.main_thread()
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        env.update({PARENT_ENV: str(os.getpid()), DEATHSIG_ENV: "1" if main else "0"})
        self.log_dir.mkdir(parents=True, exist_ok=True)
        with open(self.log_dir / f"{args[0]}-{len(self.workers) if index is None else index}.log", "ab") as err:
            return subprocess.Popen([self.python, "-m", "dcrad.cli", *args], stdout=subprocess.PIPE, stderr=err,
                                    text=True, env=env, stdin=subprocess.DEVNULL,
                                    # a process group of its own, so a terminal Ctrl-C reaches only the parent;
                                    # the parent's session, so its scheduler autogroup: the coordinator's
                                    # background threads (nice 10, display.background) yield to the workers
                                    process_group=0)

    def start_worker(self) -> int:
        """Start one more worker; returns its index."""
        proc = self._spawn("worker", "--port", "0", "--coordinator", self.address)
        self.workers.append(proc)
        self.worker_ports.append(_read_port(proc, "worker", self.start_timeout))
        return len(self.workers) - 1

    def kill_coordinator(self) -> None:
        """SIGKILL the coordinator: no goodbye, as a crash would be (the workers keep running)."""
        if self.coordinator is None:
            raise DcradError("kill_coordinator: the coordinator was never started")
        self.coordinator.kill()
        self.coordinator.wait(10)
        if self.coordinator.stdout:
            self.coordinator.stdout.close()

    def restart_coordinator(self) -> None:
        """Start the coordinator again on the same port and data folder (after ``kill_coordinator``)."""
        self.port = int(self.address.rsplit(":", 1)[1])
        self._start_coordinator()

    def kill_worker(self, i: int) -> None:
        """SIGKILL worker i: no goodbye, as a crash would be."""
        self.workers[i].kill()
        self.workers[i].wait(10)

    def wait_registered(self, n: int) -> None:
        """Wait until the coordinator lists n live workers."""
        deadline = time.monotonic() + self.start_timeout
        with grpc.insecure_channel(self.address) as ch:
            stub = pb_grpc.CoordinatorStub(ch)
            while time.monotonic() < deadline:
                try:
                    live = [w for w in stub.ListWorkers(pb.ListWorkersRequest(), timeout=5).workers if w.alive]
                    if len(live) >= n:
                        return
                except grpc.RpcError:
                    pass
                time.sleep(0.05)
        raise DcradError(f"fewer than {n} workers registered within {self.start_timeout:.0f} s")

    def _spawn_coordinator(self) -> subprocess.Popen:
        web: tuple[str, ...] = ("--web-port", "0", "--web-host", "127.0.0.1") if self.web else ("--web-port", "-1")
        if "--web-port" in self.coordinator_args:
            web = ()
        self.coordinator = self._spawn("coordinator", "--port", str(self.port), "--data",
                                       str(self.data / "coordinator"), *web, *self.coordinator_args)
        return self.coordinator

    def _coordinator_listening(self) -> None:
        def on_line(line: str) -> None:
            if " web on " in line:
                self.web_url = line.strip().rsplit(" ", 1)[1]

        assert self.coordinator is not None
        port = _read_port(self.coordinator, "coordinator", self.start_timeout, on_line)
        self.address = f"127.0.0.1:{port}"

    def _start_coordinator(self) -> None:
        self._spawn_coordinator()
        self._coordinator_listening()

    def start(self) -> "LocalCluster":
        """Start the coordinator and the workers at once and return (``wait`` waits for them): each
        imports numpy, Embree and gRPC, about 0.5 s of CPU, which a caller can overlap with its
        own work (``dcrad solve`` validates the scene meanwhile).  The coordinator's port is chosen
        here (``port`` 0: a free one) so that the workers are told it before it listens."""
        try:
            if not self.port:
                self.port = free_port()
            self.address = f"127.0.0.1:{self.port}"
            self._spawn_coordinator()
            self.workers.extend(self._spawn("worker", "--port", "0", "--coordinator", self.address, index=i)
                                for i in range(self.n_workers))
        except BaseException:
            self.close()
            raise
        return self

    def wait(self) -> "LocalCluster":
        """Wait until the coordinator listens and every worker has registered."""
        try:
            self._coordinator_listening()
            for proc in self.workers[len(self.worker_ports):]:
                self.worker_ports.append(_read_port(proc, "worker", self.start_timeout))
            self.wait_registered(self.n_workers)
        except BaseException:
            self.close()
            raise
        return self

    def __enter__(self) -> "LocalCluster":
        self.start()
        return self.wait() if self.wait_ready else self

    def close(self) -> None:
        procs = [p for p in self.workers + [self.coordinator] if p is not None]
        for p in procs:
            if p.poll() is None:
                p.terminate()
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(10)
            if p.stdout:
                p.stdout.close()
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def __exit__(self, *exc) -> None:
        self.close()
