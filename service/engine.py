"""What a worker localizes with: the map, loaded once, and the two library entry points."""

from __future__ import annotations

import importlib
import logging
from collections.abc import Callable
from dataclasses import dataclass, field

log = logging.getLogger(__name__)


@dataclass
class Engine:
    """A loaded map and the functions that localize against it (the real library or a stand-in).

    localize(image (H, W) uint8, line_map, camera, config=None, prior=None) -> Registration
    localize_segments(lines2d (N, 4) float64, line_map, camera, config=None, prior=None) -> Registration
    tracker(line_map, camera) -> an object with ``step(frame, relative_pose=None, timestamp=None) ->
        Registration``, ``start_at(cam_from_world, sigma_rot_deg, sigma_pos_m)`` and ``event`` (as
        ``linereg.Tracker``); None: this engine serves no tracking sessions
    """

    line_map: object
    localize: Callable
    localize_segments: Callable
    map_name: str
    map_version: str = ""
    info: dict = field(default_factory=dict)
    config: object = None
    map_id: str = ""  # unique id of the map's content (LineMap.info()["map_id"])
    tracker: Callable | None = None
    warm_up_s: float | None = None  # how long the compiled kernels took to be ready (None: no warm-up)


def load_engine(spec: str, args: tuple) -> Engine:
    """Returns the Engine built by ``spec`` = "module:function" called with ``args`` (runs in each worker)."""
    module_name, _, func_name = spec.partition(":")
    return getattr(importlib.import_module(module_name), func_name)(*args)


def load_map_engine(map_path: str, map_name: str | None = None, config_path: str | None = None) -> Engine:
    """Returns the Engine of the real library over the LineMap file ``map_path`` (config: the defaults, or
    the JSON overrides at ``config_path``), its compiled kernels and what every query of the map needs
    ready (``linereg.warm_up``: the worker announces itself after it, so that no query waits for numba to
    compile them on a fresh install, nor for the map's corner points and occlusion scene)."""
    import linereg

    line_map = linereg.LineMap.load(map_path)
    info = dict(line_map.info())
    name = map_name or str(getattr(line_map, "name", "") or info.get("name") or "map")
    engine = _engine(line_map, name, info)
    engine.config = _config(config_path)
    try:
        engine.warm_up_s = linereg.warm_up(line_map, engine.config)
    except Exception as e:  # an optimisation: the first query compiles what it did not
        log.warning("warm-up failed", extra={"fields": {"error": f"{type(e).__name__}: {e}"}})
    return engine


def load_segments_engine(lines3d_path: str, map_name: str, config_path: str | None = None) -> Engine:
    """Returns the Engine over a LineMap built from an (M, 6) ``.npy`` of 3D segments (tests, benchmarks)."""
    import numpy as np

    import linereg

    line_map = linereg.LineMap.from_segments(np.load(lines3d_path), name=map_name)
    engine = _engine(line_map, map_name, dict(line_map.info()))
    engine.config = _config(config_path)
    return engine


def _config(config_path: str | None):
    import linereg
    from linereg import io

    return io.read_config(config_path) if config_path else linereg.RegisterConfig()


def _engine(line_map, name: str, info: dict) -> Engine:
    """Returns the Engine of the real library over a loaded map with its ``info()`` metadata."""
    import linereg

    version = str(info.get("version", info.get("format_version", "")))
    engine = Engine(line_map, linereg.localize, linereg.localize_segments, name, version, info)
    engine.map_id = str(info.get("map_id", ""))
    engine.tracker = linereg.Tracker
    return engine
