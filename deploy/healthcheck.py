#!/opt/dcrad/venv/bin/python
"""Health check of a dcrad container: is the gRPC service SERVING?

    python healthcheck.py [ADDRESS] [--service NAME] [--timeout SECONDS]

Asks the standard gRPC health service (grpc.health.v1.Health/Check), which both the
coordinator and the worker serve, and exits 0 when the answer is SERVING and 1
otherwise, with one line on stderr saying why. The Dockerfile's HEALTHCHECK, the
compose healthchecks and the Kubernetes probes all run it.

ADDRESS defaults to the dcrad service of this container: the role and port come from the
command line of process 1 (``dcrad coordinator --port N`` / ``dcrad worker --port N``),
else DCRAD_PORT (coordinator) or DCRAD_WORKER_PORT (worker); the host is 127.0.0.1.
NAME defaults to "" (the server as a whole); "dcrad.v1.Coordinator" and
"dcrad.v1.Worker" ask for one service.
"""

from __future__ import annotations

import argparse
import os
import sys

DEFAULT_PORTS = {"coordinator": ("DCRAD_PORT", "50051"), "worker": ("DCRAD_WORKER_PORT", "50052")}


def _port_of(args: list[str]) -> str | None:
    for i, arg in enumerate(args):
        if arg == "--port" and i + 1 < len(args):
            return args[i + 1]
        if arg.startswith("--port="):
            return arg.split("=", 1)[1]
    return None


def local_address(cmdline_path: str = "/proc/1/cmdline") -> str:
    """127.0.0.1:PORT of the dcrad service that process 1 of this container runs."""
    try:
        with open(cmdline_path, "rb") as f:
            args = [a.decode(errors="replace") for a in f.read().split(b"\0") if a]
    except OSError:
        args = []
    role = next((a for a in args if a in DEFAULT_PORTS), "coordinator")
    tail = args[args.index(role) + 1:] if role in args else []
    env, default = DEFAULT_PORTS[role]
    return f"127.0.0.1:{_port_of(tail) or os.environ.get(env) or default}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="healthcheck.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("address", nargs="?", help="host:port (default: the service of this container)")
    ap.add_argument("--service", default="", help="service name to check (default '': the whole server)")
    ap.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for the answer (default 3)")
    args = ap.parse_args(argv)
    address = args.address or local_address()

    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    try:
        with grpc.insecure_channel(address) as channel:
            reply = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(service=args.service), timeout=args.timeout)
    except grpc.RpcError as exc:
        print(f"healthcheck: {address}: {exc.code().name}: {exc.details() or ''}".rstrip(), file=sys.stderr)
        return 1
    status = health_pb2.HealthCheckResponse.ServingStatus.Name(reply.status)
    if reply.status != health_pb2.HealthCheckResponse.SERVING:
        print(f"healthcheck: {address}: {status}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
