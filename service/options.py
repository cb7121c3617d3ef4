"""The flags of the service (``python -m service`` and ``linereg serve`` share them) and the ServiceConfig
they describe. Imports neither zenoh nor the rest of the service, so that ``linereg``'s command line can
list them without starting the network stack."""

from __future__ import annotations

import argparse

DEFAULT_ENGINE = "service.engine:load_map_engine"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Adds the service's flags to ``parser`` (shared with ``python -m service``)."""
    parser.add_argument("--map", required=True, help="line map file to serve (from `linereg map build`)")
    parser.add_argument("--name", help="map name on the network (default: the map's own name)")
    parser.add_argument("--instance", help="instance id in keys and liveliness (default: random)")
    parser.add_argument(
        "--tile",
        help="also serve linereg/<map>/tile/<TILE>/localize (map split over instances; default: none)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=2,
        help="worker processes, each with the map loaded (default %(default)s)",
    )
    parser.add_argument(
        "--threads-per-worker", type=int, help="BLAS/OpenMP threads per worker (default: cores // workers)"
    )
    parser.add_argument(
        "--queue",
        type=int,
        default=8,
        help="requests waiting beyond the workers before 'busy' (default %(default)s)",
    )
    parser.add_argument(
        "--mode",
        choices=("router", "peer", "client"),
        help="zenoh mode (default: the config file's, else router)",
    )
    parser.add_argument(
        "--listen", action="append", help="endpoint to listen on (repeatable; default tcp/127.0.0.1:7447)"
    )
    parser.add_argument(
        "--connect", action="append", default=[], help="endpoint to connect to (repeatable; default: none)"
    )
    parser.add_argument(
        "--zenoh-config", help="zenoh json5 config file; the mode/endpoint flags override it (default: none)"
    )
    parser.add_argument(
        "--deadline-ms",
        type=int,
        default=10_000,
        help="deadline of requests that set none (default %(default)s)",
    )
    parser.add_argument(
        "--max-payload-mb",
        type=float,
        default=16.0,
        help="largest accepted request in MiB (default %(default)s)",
    )
    parser.add_argument(
        "--config", help="JSON file of registration overrides, nested per section (default: none)"
    )
    parser.add_argument(
        "--session-idle-s",
        type=float,
        default=60.0,
        help="a tracking session without a message for this long expires (default %(default)s)",
    )
    parser.add_argument(
        "--max-sessions",
        type=int,
        default=64,
        help="tracking sessions open at once on this instance (default %(default)s)",
    )
    parser.add_argument(
        "--sessions-per-worker",
        type=int,
        default=32,
        help="tracking sessions held by one worker process (default %(default)s)",
    )
    parser.add_argument("--engine", default=DEFAULT_ENGINE, help=argparse.SUPPRESS)
    parser.add_argument(
        "--plain-logs", action="store_true", help="text logs instead of JSON lines (default: JSON lines)"
    )


def config_from_args(args: argparse.Namespace):
    """Returns the ServiceConfig the flags describe."""
    from protocols import Limits

    from .server import ServiceConfig
    from .sessions import SessionLimits
    from .zconfig import DEFAULT_ENDPOINT

    limits = Limits(
        max_payload_bytes=int(args.max_payload_mb * 1024 * 1024), default_deadline_ms=args.deadline_ms
    )
    mode = args.mode or (None if args.zenoh_config else "router")
    default_listen = () if args.zenoh_config or mode == "client" else (DEFAULT_ENDPOINT,)
    listen = tuple(args.listen) if args.listen else default_listen
    return ServiceConfig(
        loader=args.engine, loader_args=(args.map, args.name, args.config), map_name=args.name,
        instance=args.instance, tile=args.tile, workers=args.workers, queue_size=args.queue, mode=mode,
        threads_per_worker=args.threads_per_worker, listen=listen,
        connect=tuple(args.connect), zenoh_config=args.zenoh_config, limits=limits,
        sessions=SessionLimits(args.session_idle_s, args.max_sessions, args.sessions_per_worker),
    )  # fmt: skip
