"""Strict field readers for decoded msgpack maps: a wrong type is ``bad_request``, never a crash."""

from __future__ import annotations

import math

from .errors import ProtocolError


def _type_ok(value: object, kind: type) -> bool:
    # bool is an int in Python but not on the wire
    return isinstance(value, kind) and (kind is bool or not isinstance(value, bool))


def require(doc: dict, key: str, kind: type, name: str | None = None):
    """Returns ``doc[key]`` if present and of type ``kind``; ProtocolError(bad_request) otherwise."""
    if key not in doc:
        raise ProtocolError("bad_request", f"field {name or key!r} is missing")
    value = doc[key]
    if not _type_ok(value, kind):
        raise ProtocolError(
            "bad_request", f"field {name or key!r} must be {kind.__name__}, got {type(value).__name__}"
        )
    return value


def optional(doc: dict, key: str, kind: type, name: str | None = None):
    """Returns ``doc[key]`` checked as in ``require``, or None when absent or nil."""
    return None if doc.get(key) is None else require(doc, key, kind, name)


def number(
    doc: dict, key: str, name: str | None = None, positive: bool = False, allow_nan: bool = False
) -> float:
    """Returns ``doc[key]`` (an int or float; finite unless allowed, > 0 if ``positive``) as a float."""
    value = doc.get(key)
    if not (isinstance(value, int | float) and not isinstance(value, bool)):
        raise ProtocolError("bad_request", f"field {name or key!r} must be a number")
    value = float(value)
    if (math.isnan(value) and not allow_nan) or (positive and not value > 0):
        raise ProtocolError(
            "bad_request", f"field {name or key!r} must be {'positive' if positive else 'finite'}"
        )
    return value


def text(doc: dict, key: str, max_chars: int) -> str:
    """Returns the string ``doc[key]`` of at most ``max_chars`` characters."""
    value = require(doc, key, str)
    if len(value) > max_chars:
        raise ProtocolError("too_large", f"field {key!r} is longer than {max_chars} characters")
    return value
