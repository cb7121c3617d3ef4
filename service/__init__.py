"""linereg's network service over zenoh: ``Service`` (queryables + worker pool) and ``Client``.

Run it with ``linereg serve --map MAP`` or ``python -m service --map MAP``.
"""

from .client import Client, ServiceError
from .server import Service, ServiceConfig, run

__all__ = ["Client", "Service", "ServiceConfig", "ServiceError", "run"]
