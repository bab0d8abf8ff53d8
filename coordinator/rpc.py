"""gRPC plumbing the coordinator, its workers and the client share.

One message size limit both ways (:data:`MAX_MESSAGE`), and one way to run a
``grpc.aio`` server: with the standard health service reporting SERVING for ""
and for the dcrad service, stopped by SIGTERM/SIGINT, shut down gracefully
(health NOT_SERVING first, then the server with a grace period).
"""

from __future__ import annotations

import asyncio
import signal
from collections.abc import Callable, Iterable

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc

__all__ = ["MAX_MESSAGE", "start_server", "stop_on_signals", "shutdown"]

#: gRPC message size limit (bytes) of every channel and server: array and file chunks are 1 MB
MAX_MESSAGE = 8 * 1024 * 1024


async def start_server(add_servicer: Callable[[grpc.aio.Server], None], service: str, host: str, port: int,
                       options: Iterable[tuple[str, object]] = ()
                       ) -> tuple[grpc.aio.Server, health.aio.HealthServicer, int]:
    """Start a server with ``add_servicer(server)`` and the health service on ``host:port``.

    service: the full name health checks may ask for ("dcrad.v1.Worker"); options: more
    channel arguments.  Returns (server, health servicer, bound port).
    """
    server = grpc.aio.server(options=[("grpc.max_receive_message_length", MAX_MESSAGE),
                                      ("grpc.max_send_message_length", MAX_MESSAGE), *options])
    add_servicer(server)
    health_servicer = health.aio.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    bound = server.add_insecure_port(f"{host}:{port}")
    await server.start()
    for name in ("", service):
        await health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    return server, health_servicer, bound


def stop_on_signals(stop: asyncio.Event | None = None) -> asyncio.Event:
    """An event that SIGTERM and SIGINT set (where the loop can take signal handlers)."""
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        try:
            loop.add_signal_handler(sig, stop.set)
        except (NotImplementedError, RuntimeError):
            pass
    return stop


async def shutdown(server: grpc.aio.Server, health_servicer: health.aio.HealthServicer,
                   tasks: Iterable[asyncio.Task] = (), grace: float = 2.0) -> None:
    """Health NOT_SERVING, wait for ``tasks``, then stop the server after ``grace`` s."""
    await health_servicer.enter_graceful_shutdown()
    for t in tasks:
        await t
    await server.stop(grace=grace)
