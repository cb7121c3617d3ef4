"""The golden test vectors: example messages whose exact bytes are stored in ``protocols/golden/``.

``python -m protocols.golden_vectors`` rewrites the files (only when the protocol changes on purpose);
tests check that today's encoder produces the stored bytes and that the decoder reads them back.
"""

from __future__ import annotations

import sys
import zlib
from pathlib import Path

import numpy as np

from linereg.camera import Camera

from .codec import encode_error, encode_reply, encode_request, pack
from .messages import Error, LocalizeReply, LocalizeRequest, Prior
from .session import (
    ENCODERS,
    SessionClose,
    SessionClosed,
    SessionOpen,
    SessionOpened,
    TrackReply,
    TrackRequest,
    encode_session_message,
)

GOLDEN_DIR = Path(__file__).parent / "golden"
_CAMERA = Camera(fx=8.0, fy=8.0, cx=3.5, cy=2.5, width=8, height=6, dist=(-0.1, 0.01, 0.0, 0.0))


def tiny_png(pixels: np.ndarray) -> bytes:
    """Returns a grey 8-bit PNG of (H, W) uint8 ``pixels`` built by hand (deterministic bytes, no OpenCV)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return len(data).to_bytes(4, "big") + body + zlib.crc32(body).to_bytes(4, "big")

    h, w = pixels.shape
    ihdr = w.to_bytes(4, "big") + h.to_bytes(4, "big") + bytes([8, 0, 0, 0, 0])
    raw = b"".join(b"\x00" + pixels[r].tobytes() for r in range(h))  # filter type 0 per row
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(raw, 9))
        + chunk(b"IEND", b"")
    )


def _pixels() -> np.ndarray:
    return (np.arange(48, dtype=np.uint8) * 5).reshape(6, 8)


def messages() -> dict[str, object]:
    """Returns name -> message of every golden vector."""
    pose = np.array([[0.0, -1, 0, 1.5], [0, 0, -1, 0.25], [1, 0, 0, -2.0], [0, 0, 0, 1]])
    segments = np.array([[0.5, 1.0, 6.5, 1.0], [1.0, 0.5, 1.0, 4.5]])
    cov = np.diag([1e-4, 1e-4, 4e-4, 1e-2, 1e-2, 4e-2])
    cov[5, 5] = np.nan  # NaN travels as IEEE-754 NaN: "unknown"
    return {
        "request_png": LocalizeRequest("req-1", _CAMERA, tiny_png(_pixels()), "png", deadline_ms=2000),
        "request_raw_pose_prior": LocalizeRequest(
            "req-2",
            _CAMERA,
            _pixels(),
            "raw",
            prior=Prior(
                cam_from_world=pose, sigma_rot_deg=5.0, sigma_pos_m=0.5, gravity=np.array([0.0, 1.0, 0.0])
            ),
        ),
        "request_segments_position_prior": LocalizeRequest(
            "req-3",
            _CAMERA,
            None,
            "",
            segments,
            Prior(position=np.array([1.0, 2.0, 0.5]), radius_m=10.0),
            return_matches=True,
        ),
        "reply_ok": LocalizeReply(
            "req-3",
            True,
            "",
            pose,
            cov,
            num_inliers=42,
            score=5121.0,
            explained_fraction=0.625,
            log10_nfa=-42.5,
            runner_up_score=1280.25,
            ambiguity=0.25,
            rms_px=0.61,
            alternatives=pose[None].copy(),
            alternative_scores=np.array([1280.25]),
            matches=np.array([[0, 10], [1, 11]], dtype=np.int64),
            timings={"vanishing": 0.004, "refine": 0.012},
            map_name="campus",
            map_version="3",
            map_id="5f0c2a9e",
        ),
        "reply_not_localized": LocalizeReply(
            "req-1", False, "too few segments", map_name="campus", map_version="3"
        ),
        "error_busy": Error("busy", "queue full (8 waiting)", "req-2"),
    } | session_messages(pose, segments, cov)


def session_messages(pose: np.ndarray, segments: np.ndarray, cov: np.ndarray) -> dict[str, object]:
    """Returns name -> message of the tracking-session vectors."""
    step = np.array([[1.0, 0, 0, 0.0], [0, 0, -1, 0.0], [0, 1, 0, 0.5], [0, 0, 0, 1]])  # 90 deg, 0.5 m
    tracked = LocalizeReply(
        "trk-2", True, "", pose, cov, num_inliers=40, score=5000.0, explained_fraction=0.75,
        rms_px=0.5, timings={"step": 0.009}, map_name="campus", map_version="3", map_id="5f0c2a9e",
    )  # fmt: skip
    predicted = LocalizeReply("trk-3", False, "from neighbours: 1 frame(s) predicted", pose, cov)
    session = "0123456789abcdef"
    return {
        "session_open": SessionOpen(
            "open-1", _CAMERA, Prior(cam_from_world=pose, sigma_rot_deg=2.0, sigma_pos_m=0.25)
        ),
        "session_opened": SessionOpened("open-1", session, "host-1a2b", 60.0, "campus", "3", "5f0c2a9e"),
        "track_request_png": TrackRequest("trk-1", session, tiny_png(_pixels()), "png", timestamp=0.0),
        "track_request_segments_odometry": TrackRequest(
            "trk-2", session, segments=segments, relative_pose=step, timestamp=0.1, deadline_ms=500
        ),
        "track_reply_tracked": TrackReply(tracked, session, 1, "tracked"),
        "track_reply_predicted_restarted": TrackReply(predicted, session, 2, "predicted", restarted=True),
        "session_close": SessionClose("close-1", session),
        "session_closed": SessionClosed("close-1", session, 3),
        "error_unknown_session": Error("unknown_session", "no session 0123456789abcdef here", "trk-4"),
    }


def encode(message: object) -> bytes:
    """Returns the wire bytes of any golden message."""
    if isinstance(message, LocalizeRequest):
        return encode_request(message)
    if isinstance(message, LocalizeReply):
        return encode_reply(message)
    if type(message) in ENCODERS:
        return encode_session_message(message)
    return encode_error(message)  # type: ignore[arg-type]


def bad_vectors() -> dict[str, tuple[bytes, str]]:
    """Returns name -> (bytes, expected error code) of messages a decoder must refuse."""
    good = encode(messages()["request_png"])
    return {
        "bad_version": (
            pack("localize_request", {"id": "x"}).replace(b"\xa1v\x02", b"\xa1v\x01"),  # v1: no longer served
            "unsupported_version",
        ),
        "bad_truncated": (good[: len(good) // 2], "bad_request"),
        "bad_not_a_map": (b"\x93\x01\x02\x03", "bad_request"),
    }


def write(directory: Path = GOLDEN_DIR) -> None:
    """Writes every vector as ``<name>.msgpack``."""
    directory.mkdir(exist_ok=True)
    for name, message in messages().items():
        (directory / f"{name}.msgpack").write_bytes(encode(message))
    for name, (data, _) in bad_vectors().items():
        (directory / f"{name}.msgpack").write_bytes(data)


if __name__ == "__main__":
    write(Path(sys.argv[1]) if len(sys.argv) > 1 else GOLDEN_DIR)
