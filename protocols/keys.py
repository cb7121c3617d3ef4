"""Key expressions of the service (SPEC.md, "Key expressions"); map and instance names are one chunk."""

from __future__ import annotations

import re

PREFIX = "linereg"
_CHUNK = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")


def check_chunk(name: str, what: str = "name") -> str:
    """Returns ``name`` if it is a valid single key chunk (letters, digits, ``_ . -``), else ValueError."""
    if not isinstance(name, str) or not _CHUNK.match(name):
        raise ValueError(f"{what} {name!r} must be 1-64 characters of [A-Za-z0-9_.-]")
    return name


def localize_key(map_name: str) -> str:
    """Returns the shared localize key of a map (any instance serving it answers)."""
    return f"{PREFIX}/{check_chunk(map_name, 'map name')}/localize"


def instance_localize_key(map_name: str, instance: str) -> str:
    """Returns the localize key of one instance (replicas: the client picks one via liveliness)."""
    return (
        f"{PREFIX}/{check_chunk(map_name, 'map name')}/instance/{check_chunk(instance, 'instance')}/localize"
    )


def tile_localize_key(map_name: str, tile: str) -> str:
    """Returns the localize key of one map tile (``tile`` = ``*``: the selector reaching every tile)."""
    tile = tile if tile == "*" else check_chunk(tile, "tile")
    return f"{PREFIX}/{check_chunk(map_name, 'map name')}/tile/{tile}/localize"


def session_key(map_name: str) -> str:
    """Returns the key opening a tracking session on any instance serving the map."""
    return f"{PREFIX}/{check_chunk(map_name, 'map name')}/session"


def instance_session_key(map_name: str, instance: str) -> str:
    """Returns the tracking-session key of one instance (a session's frames all go to its instance)."""
    return (
        f"{PREFIX}/{check_chunk(map_name, 'map name')}/instance/{check_chunk(instance, 'instance')}/session"
    )


def info_key(map_name: str) -> str:
    """Returns the key answering the map's metadata."""
    return f"{PREFIX}/{check_chunk(map_name, 'map name')}/info"


def stats_key(map_name: str) -> str:
    """Returns the key answering service counters (operators only)."""
    return f"{PREFIX}/{check_chunk(map_name, 'map name')}/stats"


def alive_key(map_name: str, instance: str) -> str:
    """Returns the liveliness token key of one instance."""
    return f"{PREFIX}/{check_chunk(map_name, 'map name')}/alive/{check_chunk(instance, 'instance')}"


def alive_selector(map_name: str = "*") -> str:
    """Returns the liveliness selector listing the instances of a map (``*``: of every map)."""
    return f"{PREFIX}/{map_name}/alive/*"


def instance_of_alive_key(key: str) -> tuple[str, str]:
    """Returns (map name, instance) of a liveliness key; ValueError if it is not one."""
    parts = str(key).split("/")
    if len(parts) != 4 or parts[0] != PREFIX or parts[2] != "alive":
        raise ValueError(f"{key!r} is not a linereg liveliness key")
    return parts[1], parts[3]
