"""msgpack encoding and strict, size-limited decoding of the protocol's messages (SPEC.md).

Every decode either returns a valid message or raises ``ProtocolError`` with the code to answer; it never
raises anything else, whatever the bytes.
"""

from __future__ import annotations

import math

import msgpack
import numpy as np

from linereg.camera import Camera
from linereg.errors import MAX_COORDINATE, beyond_bound
from linereg.geometry import unit_vector

from .arrays import decode_array, encode_array
from .errors import ProtocolError
from .fields import number, optional, require, text
from .images import encoded_image_size
from .messages import IMAGE_FORMATS, PROTOCOL_VERSION, Error, Limits, LocalizeReply, LocalizeRequest, Prior

_DEFAULT_LIMITS = Limits()


def _default(obj: object) -> object:
    """Returns a msgpack-native stand-in for numpy scalars/arrays (or a string) met in info/stats documents."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, tuple | set):
        return list(obj)
    return str(obj)  # paths, enums, ... in map metadata: readable beats refusing the whole document


def pack(kind: str, body: dict) -> bytes:
    """Returns the msgpack bytes of a message of type ``kind`` whose other fields are ``body``."""
    return msgpack.packb({"v": PROTOCOL_VERSION, "type": kind, **body}, use_bin_type=True, default=_default)


def unpack(payload: bytes, limits: Limits = _DEFAULT_LIMITS) -> dict:
    """Returns the top-level map of ``payload`` after size and version checks; ProtocolError otherwise."""
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise ProtocolError("bad_request", "payload must be bytes")
    if len(payload) > limits.max_payload_bytes:
        raise ProtocolError(
            "too_large", f"payload is {len(payload)} bytes; the limit is {limits.max_payload_bytes}"
        )
    try:
        doc = msgpack.unpackb(
            payload, raw=False, strict_map_key=True, max_bin_len=limits.max_payload_bytes,
            max_str_len=limits.max_payload_bytes, max_array_len=1_000_000, max_map_len=10_000,
        )  # fmt: skip
    except Exception as e:  # msgpack raises many types (ValueError, ExtraData, StackError, ...)
        raise ProtocolError("bad_request", f"payload is not valid msgpack: {type(e).__name__}") from None
    if not isinstance(doc, dict):
        raise ProtocolError("bad_request", "payload must be a msgpack map")
    version = doc.get("v")
    if not isinstance(version, int) or isinstance(version, bool):
        raise ProtocolError("bad_request", "field 'v' (protocol version) must be an integer")
    if version != PROTOCOL_VERSION:
        raise ProtocolError(
            "unsupported_version", f"protocol version {version} is not served; use {PROTOCOL_VERSION}"
        )
    if not isinstance(doc.get("type"), str):
        raise ProtocolError("bad_request", "field 'type' must be a string")
    return doc


def message_type(payload: bytes) -> str:
    """Returns the ``type`` field of a message ("" if it is not a valid message)."""
    try:
        return unpack(payload)["type"]
    except ProtocolError:
        return ""


def request_id(payload: bytes) -> str:
    """Returns the ``id`` of a message if it has a readable one, else "" (for error replies to garbage)."""
    try:
        value = unpack(payload).get("id")
    except ProtocolError:
        return ""
    return value if isinstance(value, str) and len(value) <= _DEFAULT_LIMITS.max_id_chars else ""


# --- LocalizeRequest ----------------------------------------------------------------------------------


def encode_request(req: LocalizeRequest) -> bytes:
    """Returns the wire bytes of a LocalizeRequest."""
    body: dict = {"id": req.id, "camera": req.camera.to_dict()}
    body |= frame_fields(req.image, req.image_format, req.segments)
    if req.prior is not None:
        body["prior"] = encode_prior(req.prior)
    body["options"] = options_fields(req.deadline_ms, req.return_matches)
    return pack("localize_request", body)


def frame_fields(image: bytes | np.ndarray | None, image_format: str, segments: np.ndarray | None) -> dict:
    """Returns the ``image`` and/or ``segments`` fields of a frame (a request's or a tracking step's)."""
    body: dict = {}
    if image is not None:
        if image_format == "raw":
            body["image"] = {"format": "raw", "pixels": encode_array(np.asarray(image))}
        else:
            body["image"] = {"format": image_format, "data": bytes(image)}  # type: ignore[arg-type]
    if segments is not None:
        body["segments"] = encode_array(np.asarray(segments, dtype=np.float64))
    return body


def options_fields(deadline_ms: int | None, return_matches: bool) -> dict:
    """Returns the ``options`` map: ``return_matches`` always, ``deadline_ms`` when set."""
    options: dict = {"return_matches": bool(return_matches)}
    if deadline_ms is not None:
        options["deadline_ms"] = int(deadline_ms)
    return options


def encode_prior(prior: Prior) -> dict:
    """Returns the wire ``prior`` map of a Prior."""
    out: dict = {}
    if prior.position is not None:
        out |= {"position": [float(x) for x in prior.position], "radius_m": float(prior.radius_m)}
    elif prior.cam_from_world is not None:
        out |= {
            "cam_from_world": encode_array(np.asarray(prior.cam_from_world, dtype=np.float64)),
            "sigma_rot_deg": float(prior.sigma_rot_deg),
            "sigma_pos_m": float(prior.sigma_pos_m),
        }
    if prior.gravity is not None:
        out |= {
            "gravity": [float(x) for x in prior.gravity],
            "gravity_sigma_deg": float(prior.gravity_sigma_deg),
        }
    return out


def decode_request(payload: bytes, limits: Limits = _DEFAULT_LIMITS) -> LocalizeRequest:
    """Returns the validated LocalizeRequest in ``payload``; ProtocolError with the code to answer otherwise."""
    doc = expect(payload, "localize_request", limits)
    req_id = text(doc, "id", limits.max_id_chars)
    camera = decode_camera(require(doc, "camera", dict), limits)
    image, image_format, segments = decode_frame(doc, camera, limits)
    prior = decode_prior(optional(doc, "prior", dict))
    deadline, return_matches = decode_options(doc, limits)
    return LocalizeRequest(req_id, camera, image, image_format, segments, prior, deadline, return_matches)


def decode_frame(
    doc: dict, camera: Camera, limits: Limits
) -> tuple[bytes | np.ndarray | None, str, np.ndarray | None]:
    """Returns (image, image format, segments) of a message holding exactly one of ``image``, ``segments``."""
    image, image_format = _decode_image(optional(doc, "image", dict), camera, limits)
    segments = _decode_segments(doc.get("segments"), camera, limits)
    if (image is None) == (segments is None):
        raise ProtocolError("bad_request", "exactly one of 'image' and 'segments' must be given")
    return image, image_format, segments


def decode_options(doc: dict, limits: Limits) -> tuple[int | None, bool]:
    """Returns (deadline_ms or None, return_matches) of a message's ``options`` map."""
    options = optional(doc, "options", dict) or {}
    deadline = optional(options, "deadline_ms", int)
    if deadline is not None and not 0 < deadline <= limits.max_deadline_ms:
        raise ProtocolError("bad_request", f"options.deadline_ms must be in (0, {limits.max_deadline_ms}]")
    return deadline, optional(options, "return_matches", bool) or False


def decode_camera(d: dict, limits: Limits) -> Camera:
    """Returns the Camera of a wire camera map (strict: numbers must be numbers, not strings)."""
    values: dict = {k: number(d, k, f"camera.{k}") for k in ("fx", "fy", "cx", "cy")}
    size: dict = {k: require(d, k, int, f"camera.{k}") for k in ("width", "height")}
    if not all(0 < n <= 65535 for n in size.values()):
        raise ProtocolError("bad_request", "camera width and height must be in [1, 65535]")
    if size["width"] * size["height"] > limits.max_image_pixels:
        raise ProtocolError("too_large", f"camera has more than {limits.max_image_pixels} pixels")
    dist = optional(d, "dist", list, "camera.dist") or []
    if len(dist) > 8 or not all(isinstance(x, int | float) and not isinstance(x, bool) for x in dist):
        raise ProtocolError("bad_request", "camera.dist must be a list of at most 8 numbers")
    try:
        return Camera(**values, **size, dist=tuple(float(x) for x in dist))
    except ValueError as e:  # InvalidInputError: NaN, negative focal length, bad distortion count
        raise ProtocolError("bad_request", str(e)) from None


def _decode_image(d: dict | None, camera: Camera, limits: Limits) -> tuple[bytes | np.ndarray | None, str]:
    """Returns (encoded bytes or (H, W[, C]) pixels, format) checked against the camera's size."""
    if d is None:
        return None, ""
    fmt = require(d, "format", str, "image.format")
    if fmt not in IMAGE_FORMATS:
        raise ProtocolError("bad_request", f"image.format must be one of {', '.join(IMAGE_FORMATS)}")
    if fmt == "raw":
        pixels = decode_array(
            d.get("pixels"), "image.pixels", ("uint8", "uint16"), (2, 3), limits.max_image_pixels * 4
        )
        if pixels.ndim == 3 and pixels.shape[2] not in (1, 3, 4):
            raise ProtocolError("bad_request", "image.pixels must have 1, 3 or 4 channels")
        width, height, image = pixels.shape[1], pixels.shape[0], pixels
    else:
        image = require(d, "data", bytes, "image.data")
        width, height = encoded_image_size(image, fmt)
    if (width, height) != (camera.width, camera.height):
        raise ProtocolError(
            "bad_request", f"image is {width}x{height}, camera is {camera.width}x{camera.height}"
        )
    return image, fmt


def _decode_segments(obj: object, camera: Camera, limits: Limits) -> np.ndarray | None:
    """Returns (N, 4) float64 finite, non-degenerate segments, or None when absent."""
    if obj is None:
        return None
    lines = decode_array(obj, "segments", ("float32", "float64"), (2,), limits.max_segments * 4)
    if lines.shape[1:] != (4,):
        raise ProtocolError("bad_request", f"segments must have shape (N, 4), got {tuple(lines.shape)}")
    lines = lines.astype(np.float64)
    if not np.isfinite(lines).all():
        raise ProtocolError("bad_request", "segments contain NaN or inf")
    if beyond_bound(lines) is not None:
        raise ProtocolError("bad_request", f"segments hold a coordinate beyond +-{MAX_COORDINATE:g} px")
    if (np.linalg.norm(lines[:, 2:] - lines[:, :2], axis=1) == 0).any():
        raise ProtocolError("bad_request", "segments contain zero-length segments")
    return lines


def decode_prior(d: dict | None) -> Prior | None:
    """Returns the Prior of a wire prior map: a position with radius, or a pose with sigmas (or neither),
    and optionally gravity (a unit vector in the camera frame) with its sigma."""
    if d is None:
        return None
    gravity, gravity_sigma = None, 5.0
    if "gravity" in d:
        gravity = _three(d, "gravity", "prior.gravity (camera frame)")
        if not np.abs(gravity).max() > 0:
            raise ProtocolError("bad_request", "prior.gravity must not be zero")
        gravity = unit_vector(gravity)
        gravity_sigma = number(d, "gravity_sigma_deg", "prior.gravity_sigma_deg", positive=True)
    if "position" in d:
        pos = _three(d, "position", "prior.position (world metres)")
        radius = number(d, "radius_m", "prior.radius_m", positive=True)
        return Prior(position=pos, radius_m=radius, gravity=gravity, gravity_sigma_deg=gravity_sigma)
    if "cam_from_world" not in d:
        if gravity is None:
            raise ProtocolError("bad_request", "prior needs position, cam_from_world or gravity")
        return Prior(gravity=gravity, gravity_sigma_deg=gravity_sigma)
    pose = decode_array(d.get("cam_from_world"), "prior.cam_from_world", ("float64",), (2,), 16)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise ProtocolError("bad_request", "prior.cam_from_world must be a finite (4, 4) float64 array")
    sigma_rot = number(d, "sigma_rot_deg", "prior.sigma_rot_deg", positive=True)
    sigma_pos = number(d, "sigma_pos_m", "prior.sigma_pos_m", positive=True)
    return Prior(
        cam_from_world=pose.copy(),
        sigma_rot_deg=sigma_rot,
        sigma_pos_m=sigma_pos,
        gravity=gravity,
        gravity_sigma_deg=gravity_sigma,
    )


def _three(d: dict, key: str, name: str) -> np.ndarray:
    """Returns ``d[key]`` as 3 finite float64 numbers; ProtocolError naming ``name`` otherwise."""
    value = require(d, key, list, name)
    if len(value) != 3 or not all(isinstance(x, int | float) and not isinstance(x, bool) for x in value):
        raise ProtocolError("bad_request", f"{name} must be 3 numbers")
    out = np.array(value, dtype=np.float64)
    if not np.isfinite(out).all():
        raise ProtocolError("bad_request", f"{name} must be finite")
    return out


# --- LocalizeReply and Error --------------------------------------------------------------------------


def encode_reply(rep: LocalizeReply) -> bytes:
    """Returns the wire bytes of a LocalizeReply."""
    return pack("localize_reply", reply_fields(rep))


def reply_fields(rep: LocalizeReply) -> dict:
    """Returns the fields of a LocalizeReply's message (a ``track_reply`` has them too)."""
    return {
        "id": rep.id,
        "status": "ok" if rep.success else "not_localized",
        "reason": rep.reason,
        "cam_from_world": encode_array(np.asarray(rep.cam_from_world, dtype=np.float64)),
        "covariance": encode_array(np.asarray(rep.covariance, dtype=np.float64)),
        "num_inliers": int(rep.num_inliers),
        "score": float(rep.score),
        "explained_fraction": float(rep.explained_fraction),
        "log10_nfa": float(rep.log10_nfa),
        "runner_up_score": float(rep.runner_up_score),
        "ambiguity": float(rep.ambiguity),
        "rms_px": float(rep.rms_px),
        "alternatives": encode_array(np.asarray(rep.alternatives, dtype=np.float64).reshape(-1, 4, 4)),
        "alternative_scores": encode_array(np.asarray(rep.alternative_scores, dtype=np.float64).reshape(-1)),
        "matches": None if rep.matches is None else encode_array(np.asarray(rep.matches, dtype=np.int64)),
        "timings": {str(k): float(v) for k, v in rep.timings.items()},
        "map": {"name": rep.map_name, "id": rep.map_id, "version": rep.map_version},
    }


def decode_reply(payload: bytes, limits: Limits = _DEFAULT_LIMITS) -> LocalizeReply:
    """Returns the validated LocalizeReply in ``payload``; ProtocolError otherwise."""
    return reply_of(expect(payload, "localize_reply", limits), limits)


def expect(payload: bytes, kind: str, limits: Limits = _DEFAULT_LIMITS) -> dict:
    """Returns the top-level map of a message of type ``kind``; ProtocolError otherwise."""
    doc = unpack(payload, limits)
    if doc["type"] != kind:
        raise ProtocolError("bad_request", f"expected a {kind}, got {doc['type'][:40]!r}")
    return doc


def reply_of(doc: dict, limits: Limits) -> LocalizeReply:
    """Returns the LocalizeReply of a decoded reply map (``localize_reply`` or ``track_reply``)."""
    status = require(doc, "status", str)
    if status not in ("ok", "not_localized"):
        raise ProtocolError("bad_request", f"status must be 'ok' or 'not_localized', got {status[:40]!r}")
    pose = decode_array(doc.get("cam_from_world"), "cam_from_world", ("float64",), (2,), 16)
    cov = decode_array(doc.get("covariance"), "covariance", ("float64",), (2,), 36)
    if pose.shape != (4, 4) or cov.shape != (6, 6):
        raise ProtocolError("bad_request", "cam_from_world must be (4, 4) and covariance (6, 6)")
    matches = None
    if doc.get("matches") is not None:
        matches = decode_array(doc["matches"], "matches", ("int64",), (2,), limits.max_matches * 2)
        if matches.shape[1:] != (2,):
            raise ProtocolError("bad_request", "matches must have shape (K, 2)")
    timings = optional(doc, "timings", dict) or {}
    if not all(isinstance(k, str) and isinstance(v, float) for k, v in timings.items()):
        raise ProtocolError("bad_request", "timings must map stage names to seconds (floats)")
    alternatives = decode_array(doc.get("alternatives"), "alternatives", ("float64",), (3,), 16 * 64)
    alternative_scores = decode_array(
        doc.get("alternative_scores"), "alternative_scores", ("float64",), (1,), 64
    )
    if alternatives.shape[1:] != (4, 4) or alternative_scores.shape != (len(alternatives),):
        raise ProtocolError("bad_request", "alternatives must be (A, 4, 4) with alternative_scores (A,)")
    map_doc = optional(doc, "map", dict) or {}
    return LocalizeReply(
        id=text(doc, "id", limits.max_id_chars),
        success=status == "ok",
        reason=optional(doc, "reason", str) or "",
        cam_from_world=pose.copy(),
        covariance=cov.copy(),
        num_inliers=require(doc, "num_inliers", int),
        score=number(doc, "score"),
        explained_fraction=number(doc, "explained_fraction"),
        # added in 2026-11 without a version change: a reply without it says unknown
        log10_nfa=number(doc, "log10_nfa", allow_nan=True) if doc.get("log10_nfa") is not None else math.nan,
        runner_up_score=number(doc, "runner_up_score"),
        ambiguity=number(doc, "ambiguity", allow_nan=True),
        rms_px=number(doc, "rms_px", allow_nan=True) if doc.get("rms_px") is not None else math.nan,
        alternatives=alternatives.copy(),
        alternative_scores=alternative_scores.copy(),
        matches=None if matches is None else matches.copy(),
        timings=timings,
        map_name=optional(map_doc, "name", str) or "",
        map_version=str(map_doc.get("version", "")),
        map_id=str(map_doc.get("id", "")),
    )


def encode_error(err: Error) -> bytes:
    """Returns the wire bytes of an Error."""
    return pack("error", {"id": err.id, "code": err.code, "message": err.message})


def decode_error(payload: bytes) -> Error:
    """Returns the Error in ``payload``; ProtocolError if it is not one."""
    doc = expect(payload, "error")
    return Error(
        code=require(doc, "code", str), message=optional(doc, "message", str) or "", id=doc.get("id") or ""
    )
