"""Load generation against a service running the fake engine: valid queries with known answers mixed
with garbage that must be refused with a known code (tests and ``linereg bench service``)."""

from __future__ import annotations

import time
from collections import Counter

import msgpack
import numpy as np

import protocols
from linereg.camera import Camera
from protocols import LocalizeRequest, keys

from .fake import expected_pose

CAMERA = Camera(fx=400.0, fy=400.0, cx=159.5, cy=119.5, width=320, height=240)


def valid_request(rng: np.random.Generator, request_id: str) -> tuple[bytes, np.ndarray]:
    """Returns (payload, expected (4, 4) pose) of a valid request (segments, or a raw image 1 in 8)."""
    if rng.random() < 0.125:
        pixels = rng.integers(0, 256, size=(CAMERA.height, CAMERA.width), dtype=np.uint8)
        return protocols.encode_request(LocalizeRequest(request_id, CAMERA, pixels, "raw")), expected_pose(
            pixels
        )
    lines = rng.uniform(0, 300, size=(int(rng.integers(1, 50)), 4))
    lines[:, 2] += 1.0  # never zero length
    return protocols.encode_request(LocalizeRequest(request_id, CAMERA, segments=lines)), expected_pose(lines)


def garbage_request(rng: np.random.Generator, request_id: str) -> tuple[bytes, str]:
    """Returns (payload, expected error code) of one of several kinds of bad request."""
    lines = np.array([[1.0, 2.0, 3.0, 4.0]])
    good = msgpack.unpackb(
        protocols.encode_request(LocalizeRequest(request_id, CAMERA, segments=lines)), raw=False
    )
    kind = int(rng.integers(0, 8))
    if kind == 0:
        return rng.bytes(int(rng.integers(0, 200))), "bad_request"
    if kind == 1:
        data = protocols.encode_request(LocalizeRequest(request_id, CAMERA, segments=lines))
        return data[: int(rng.integers(1, len(data) - 1))], "bad_request"
    if kind == 2:
        return msgpack.packb(good | {"v": 7}), "unsupported_version"
    if kind == 3:
        return msgpack.packb(good | {"camera": CAMERA.to_dict() | {"fx": float("nan")}}), "bad_request"
    if kind == 4:
        huge = {"dtype": "float64", "shape": [2**31, 4], "data": b""}
        return msgpack.packb(good | {"segments": huge}), "too_large"
    if kind == 5:  # a PNG header with the right size and a body that does not decode
        header = (
            protocols.images.PNG_MAGIC
            + b"\x00\x00\x00\x0dIHDR"
            + (320).to_bytes(4, "big")
            + (240).to_bytes(4, "big")
        )
        body = good | {"image": {"format": "png", "data": header + rng.bytes(64)}}
        body.pop("segments")
        return msgpack.packb(body), "bad_request"
    if kind == 6:
        return msgpack.packb(good | {"camera": "camera"}), "bad_request"
    body = good | {"image": {"format": "raw", "pixels": protocols.encode_array(np.zeros((0, 0), np.uint8))}}
    body.pop("segments")
    return msgpack.packb(body), "bad_request"


def run_client(connect: str, map_name: str, num_queries: int, garbage_fraction: float, seed: int,
               timeout_s: float = 10.0) -> dict:  # fmt: skip
    """Returns counts of one client's run: right, wrong, errors as expected, unexpected, lost; latencies."""
    from .client import Client

    rng = np.random.default_rng(seed)
    counts: Counter[str] = Counter()
    latencies = []
    key = keys.localize_key(map_name)
    with Client(connect, map_name=map_name) as client:
        for i in range(num_queries):
            rid = f"s{seed}-{i}"
            bad = rng.random() < garbage_fraction
            payload, expected = garbage_request(rng, rid) if bad else valid_request(rng, rid)
            start = time.perf_counter()
            try:
                ok, reply = client.request(key, payload, timeout_s)
            except Exception:
                counts["lost"] += 1
                continue
            latencies.append(time.perf_counter() - start)
            counts[_judge(ok, reply, expected, bad)] += 1
    return {"counts": dict(counts), "latencies_s": latencies}


def _judge(ok: bool, reply: bytes, expected, bad: bool) -> str:
    if bad:
        if ok or reply == b"Timeout":
            return "garbage_accepted"
        code = protocols.decode_error(reply).code
        return "garbage_refused" if code == expected else f"garbage_wrong_code:{expected}->{code}"
    if not ok:
        return "valid_refused:" + (protocols.decode_error(reply).code if reply != b"Timeout" else "timeout")
    pose = protocols.decode_reply(reply).cam_from_world
    return "valid_right" if np.allclose(pose, expected) else "valid_wrong"
