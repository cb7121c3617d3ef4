"""The zenoh session configuration shared by the service and the client (one place for zenoh flags)."""

from __future__ import annotations

import json
from collections.abc import Sequence

import zenoh

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


def session_config(
    mode: str | None,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    config_file: str | None = None,
    multicast: bool = False,
) -> zenoh.Config:
    """Returns a zenoh Config: ``config_file`` (json5) if given, then mode/endpoints/scouting on top.

    ``mode`` None keeps the file's mode; empty endpoint lists keep the file's endpoints.

    Multicast scouting is off unless asked for: on loopback and in tests, discovery is by endpoint.
    """
    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    if mode is not None:
        conf.insert_json5("mode", json.dumps(mode))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if not config_file or not multicast:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast)))
    return conf
