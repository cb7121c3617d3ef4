"""The service's handlers: pure ``bytes -> bytes`` functions, their dependencies passed in, no network."""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

import protocols
from linereg.camera import Camera
from linereg.errors import InvalidInputError
from protocols import Error, Limits, LocalizeReply, LocalizeRequest, ProtocolError

from .engine import Engine

log = logging.getLogger(__name__)


def error_bytes(code: str, message: str, request_id: str = "") -> bytes:
    """Returns the wire bytes of an Error."""
    return protocols.encode_error(Error(code=code, message=message, id=request_id))


def handle_localize(payload: bytes, engine: Engine, limits: Limits) -> bytes:
    """Returns the LocalizeReply bytes for a LocalizeRequest payload, or Error bytes (never raises)."""
    try:
        req = protocols.decode_request(payload, limits)
    except ProtocolError as e:
        return error_bytes(e.code, e.message, protocols.request_id(payload))

    def answer() -> bytes:
        reg = _localize(req, engine)
        return protocols.encode_reply(reply_of(req.id, reg, engine, req.return_matches))

    return guarded(req.id, answer)


def guarded(request_id: str, compute: Callable[[], bytes]) -> bytes:
    """Returns ``compute()``, or the Error bytes of what it raised: a ProtocolError's code, bad input
    ``bad_request``, anything else ``internal`` (a bug or a library failure must not kill the worker)."""
    try:
        return compute()
    except ProtocolError as e:
        return error_bytes(e.code, e.message, request_id)
    except InvalidInputError as e:
        return error_bytes("bad_request", str(e), request_id)
    except Exception as e:
        log.exception("request %s failed", request_id)
        return error_bytes("internal", f"{type(e).__name__}: {e}", request_id)


def reply_of(request_id: str, reg, engine: Engine, return_matches: bool) -> LocalizeReply:
    """Returns the LocalizeReply carrying Registration ``reg`` and the engine's map."""
    return LocalizeReply.from_registration(
        request_id, reg, engine.map_name, engine.map_version, return_matches, engine.map_id
    )


def _localize(req: LocalizeRequest, engine: Engine):
    """Returns the Registration of a decoded request."""
    prior = to_library_prior(req.prior)
    if req.segments is not None:
        return engine.localize_segments(req.segments, engine.line_map, req.camera, engine.config, prior)
    image = decode_pixels(req.image, req.image_format, req.camera)
    return engine.localize(image, engine.line_map, req.camera, engine.config, prior)


def decode_pixels(image: bytes | np.ndarray | None, image_format: str, camera: Camera) -> np.ndarray:
    """Returns a decoded message's image as the library reads it: raw pixels as (H, W) uint8 grey, an
    encoded image as decoded ((H, W[, C]) uint8 or uint16, BGR), for ``localize`` to make grey."""
    import cv2

    if image_format == "raw":
        pixels = np.asarray(image)
        if pixels.dtype == np.uint16:
            pixels = (pixels // 257).astype(np.uint8)  # 16-bit full range onto 8-bit
        if pixels.ndim == 3:
            code = {1: None, 3: cv2.COLOR_BGR2GRAY, 4: cv2.COLOR_BGRA2GRAY}[pixels.shape[2]]
            pixels = pixels[:, :, 0] if code is None else cv2.cvtColor(pixels, code)
        return np.ascontiguousarray(pixels)
    buffer = np.frombuffer(image, dtype=np.uint8)  # type: ignore[arg-type]
    # as stored, grey made by the library (``lines2d.to_gray8``): libpng's own grey conversion
    # (IMREAD_GRAYSCALE) differs by a grey level here and there, enough to move a borderline photo's pose
    decoded = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED) if len(buffer) else None
    if decoded is None:
        raise ProtocolError("bad_request", f"image does not decode as {image_format}")
    if decoded.shape[:2] != (camera.height, camera.width):
        raise ProtocolError(
            "bad_request", f"decoded image is {decoded.shape[1]}x{decoded.shape[0]}, not the camera's size"
        )
    return decoded


def to_library_prior(prior: protocols.Prior | None):
    """Returns the library's Prior for a wire prior."""
    if prior is None:
        return None
    from linereg import Prior as library_prior

    gravity = {"gravity": prior.gravity, "gravity_sigma_deg": prior.gravity_sigma_deg}
    if prior.position is not None:
        return library_prior(position=prior.position, radius_m=prior.radius_m, **gravity)
    if prior.cam_from_world is not None:
        return library_prior(
            cam_from_world=prior.cam_from_world,
            sigma_rot_deg=prior.sigma_rot_deg,
            sigma_pos_m=prior.sigma_pos_m,
            **gravity,
        )
    return library_prior(**gravity)


def handle_info(payload: bytes, info: dict) -> bytes:
    """Returns the ``info`` document (map metadata, bounds, protocol version); the payload is ignored."""
    return protocols.pack("info", {"map": info, "protocol_version": protocols.PROTOCOL_VERSION})


def handle_stats(payload: bytes, snapshot: dict) -> bytes:
    """Returns the ``stats`` document (counters, latency percentiles, queue depth); payload ignored."""
    return protocols.pack("stats", snapshot)
