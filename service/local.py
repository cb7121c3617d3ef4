"""A service on a free loopback port for the lifetime of a ``with`` block (``linereg demo``, notebooks)."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from contextlib import contextmanager

from .client import Client
from .server import Service, ServiceConfig


def free_loopback_endpoint() -> str:
    """Returns ``tcp/127.0.0.1:<port>`` with a port free right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


@contextmanager
def local_service(
    map_path: str,
    workers: int = 1,
    loader: str = "service.engine:load_map_engine",
    config_path: str | None = None,
) -> Iterator[Client]:
    """Yields a Client of a service (worker processes, zenoh router on loopback) serving ``map_path``."""
    config = ServiceConfig(loader=loader, loader_args=(str(map_path), None, config_path), workers=workers,
                           listen=(free_loopback_endpoint(),))  # fmt: skip
    with Service(config) as service, Client(config.listen[0], map_name=service.map_name) as client:
        yield client
