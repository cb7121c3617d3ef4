"""The service's pure handlers, without a network: right replies, right error codes, never an exception."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import protocols
from protocols import Limits, LocalizeRequest
from protocols.golden_vectors import GOLDEN_DIR, tiny_png
from service.fake import expected_pose, load_fake_engine
from service.handlers import handle_info, handle_localize, handle_stats
from service.loadgen import CAMERA, garbage_request, valid_request

ENGINE = load_fake_engine()
LIMITS = Limits()


def _answer(payload: bytes):
    """Returns the decoded reply or error of ``handle_localize``."""
    reply = handle_localize(payload, ENGINE, LIMITS)
    kind = protocols.unpack(reply)["type"]
    return protocols.decode_reply(reply) if kind == "localize_reply" else protocols.decode_error(reply)


def test_valid_requests_get_the_engine_answer(rng):
    for i in range(20):
        payload, pose = valid_request(rng, f"r{i}")
        reply = _answer(payload)
        assert isinstance(reply, protocols.LocalizeReply) and reply.id == f"r{i}"
        assert np.allclose(reply.cam_from_world, pose) and reply.map_name == "fake"


def test_png_image_is_decoded_to_grey_pixels():
    pixels = (np.arange(48, dtype=np.uint8) * 5).reshape(6, 8)
    camera = protocols.decode_request((GOLDEN_DIR / "request_png.msgpack").read_bytes()).camera
    payload = protocols.encode_request(
        LocalizeRequest("p", camera, tiny_png(pixels), "png", return_matches=True)
    )
    reply = _answer(payload)
    assert np.allclose(reply.cam_from_world, expected_pose(pixels)) and reply.matches is not None


def test_matches_only_when_asked():
    lines = np.array([[1.0, 2.0, 3.0, 4.0]])
    for wanted in (False, True):
        reply = _answer(
            protocols.encode_request(LocalizeRequest("m", CAMERA, segments=lines, return_matches=wanted))
        )
        assert (reply.matches is not None) == wanted


def test_engine_failures_become_error_codes_not_exceptions():
    def ask(first_segment):
        lines = np.array([first_segment, [1.0, 2.0, 3.0, 4.0]])
        return _answer(protocols.encode_request(LocalizeRequest("f", CAMERA, segments=lines)))

    assert ask([-3.0, 0.0, 1.0, 1.0]).code == "internal"  # the engine raised
    not_localized = ask([-4.0, 0.0, 1.0, 1.0])
    assert isinstance(not_localized, protocols.LocalizeReply) and not not_localized.success


def test_garbage_gets_its_error_code(rng):
    for i in range(60):
        payload, code = garbage_request(rng, f"g{i}")
        assert _answer(payload).code == code


def test_info_and_stats_documents():
    info = protocols.unpack(handle_info(b"anything", {"name": "m", "bounds": np.zeros((2, 3))}))
    assert info["map"]["name"] == "m" and info["map"]["bounds"] == [[0.0] * 3] * 2
    assert protocols.unpack(handle_stats(b"", {"requests": 3}))["requests"] == 3


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=400))
def test_handler_never_raises_on_random_bytes(data):
    err = protocols.decode_error(handle_localize(data, ENGINE, LIMITS))
    assert err.code in ("bad_request", "unsupported_version", "too_large")


@pytest.mark.parametrize("size", [(0, 0), (240, 321), (240, 320, 2)])
def test_raw_images_of_the_wrong_size_are_refused(size):
    body = {"format": "raw", "pixels": protocols.encode_array(np.zeros(size, np.uint8))}
    doc = protocols.unpack(
        protocols.encode_request(LocalizeRequest("z", CAMERA, segments=np.ones((1, 4)) * [1, 1, 2, 2]))
    )
    doc.pop("segments")
    payload = protocols.pack(
        "localize_request", {k: v for k, v in doc.items() if k not in ("v", "type")} | {"image": body}
    )
    assert _answer(payload).code == "bad_request"
