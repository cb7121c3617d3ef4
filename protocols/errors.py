"""The protocol's error codes and the exception that carries one."""

from __future__ import annotations

from linereg.errors import LineregError

# code -> meaning; the wire carries the code string (SPEC.md, "Error codes")
ERROR_CODES = {
    "bad_request": "the payload is not a valid message (msgpack, fields, types, values, image)",
    "unsupported_version": "the message's major protocol version is not served here",
    "too_large": "the payload or a declared size exceeds the service's limits",
    "busy": "the queue or the tracking sessions are full (or it is shutting down); retry later or elsewhere",
    "unknown_session": "the tracking session is not open here (never opened, closed or expired); open another",
    "timeout": "the request's deadline passed before it was answered",
    "not_found": "the map or key asked for is not served here",
    "internal": "the service failed (a worker crashed, a bug); the request may be retried",
}


class ProtocolError(LineregError):
    """A message that cannot be served; ``code`` is one of ERROR_CODES."""

    def __init__(self, code: str, message: str):
        if code not in ERROR_CODES:
            raise ValueError(f"unknown error code {code!r}")
        super().__init__(message)
        self.code = code
        self.message = message
