"""The wire protocol: golden vectors, round trips, limits, and a decoder that never crashes (hypothesis)."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import protocols
from linereg import Camera
from protocols import Limits, LocalizeRequest, ProtocolError, keys, session
from protocols.golden_vectors import GOLDEN_DIR, bad_vectors, encode, messages, tiny_png

CAMERA = Camera(fx=8.0, fy=8.0, cx=3.5, cy=2.5, width=8, height=6)


def _decode(data: bytes):
    kind = protocols.unpack(data)["type"]
    golden_camera = messages()["session_open"].camera  # the session of the track_request vectors
    return {"localize_request": protocols.decode_request, "localize_reply": protocols.decode_reply,
            "error": lambda b: protocols.decode_error(b), "session_open": session.decode_session_open,
            "session_opened": session.decode_session_opened,
            "track_request": lambda b: session.decode_track_request(b, golden_camera),
            "track_reply": session.decode_track_reply, "session_close": session.decode_session_close,
            "session_closed": session.decode_session_closed}[kind](data)  # fmt: skip


def _same(a: object, b: object) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a):
        return math.isnan(b)
    if hasattr(a, "__dataclass_fields__"):
        return type(a) is type(b) and all(_same(getattr(a, f), getattr(b, f)) for f in a.__dataclass_fields__)
    return a == b


@pytest.mark.parametrize("name", sorted(messages()))
def test_golden_vectors_decode_to_their_message_and_reencode_to_the_same_bytes(name):
    stored = (GOLDEN_DIR / f"{name}.msgpack").read_bytes()
    decoded = _decode(stored)
    assert _same(decoded, messages()[name])
    assert encode(decoded) == stored


@pytest.mark.parametrize("name", sorted(bad_vectors()))
def test_golden_bad_vectors_get_their_error_code(name):
    stored = (GOLDEN_DIR / f"{name}.msgpack").read_bytes()
    with pytest.raises(ProtocolError) as e:
        protocols.decode_request(stored)
    assert e.value.code == bad_vectors()[name][1]


def test_arrays_travel_as_dtype_shape_bytes_little_endian():
    a = np.arange(6, dtype=">f8").reshape(2, 3)  # big-endian in memory, little-endian on the wire
    wire = protocols.encode_array(a)
    assert (
        wire["dtype"] == "float64" and wire["shape"] == [2, 3] and wire["data"] == a.astype("<f8").tobytes()
    )
    back = protocols.decode_array(wire, "a", ("float64",), (2,), 100)
    assert np.array_equal(back, a)
    with pytest.raises(ProtocolError, match="bytes"):
        protocols.decode_array(wire | {"shape": [3, 3]}, "a", ("float64",), (2,), 100)
    with pytest.raises(ProtocolError) as e:
        protocols.decode_array(wire | {"shape": [2**40, 2**40]}, "a", ("float64",), (2,), 100)
    assert e.value.code == "too_large"
    with pytest.raises(ProtocolError):
        protocols.encode_array(np.array(["text"]))


def _request(**overrides) -> dict:
    doc = msgpack.unpackb(encode(messages()["request_segments_position_prior"]), raw=False)
    doc.update(overrides)
    return doc


@pytest.mark.parametrize(
    ("overrides", "code"),
    [
        ({"v": 1}, "unsupported_version"),
        ({"v": "1"}, "bad_request"),
        ({"type": "localize_reply"}, "bad_request"),
        ({"id": 5}, "bad_request"),
        ({"id": "x" * 1000}, "too_large"),
        ({"camera": {"fx": "800", "fy": 8.0, "cx": 1.0, "cy": 1.0, "width": 8, "height": 6}}, "bad_request"),
        (
            {"camera": {"fx": float("nan"), "fy": 8.0, "cx": 1.0, "cy": 1.0, "width": 8, "height": 6}},
            "bad_request",
        ),
        ({"camera": {"fx": -1.0, "fy": 8.0, "cx": 1.0, "cy": 1.0, "width": 8, "height": 6}}, "bad_request"),
        ({"camera": {"fx": 8.0, "fy": 8.0, "cx": 1.0, "cy": 1.0, "width": 0, "height": 6}}, "bad_request"),
        (
            {"camera": {"fx": 8.0, "fy": 8.0, "cx": 1.0, "cy": 1.0, "width": 60000, "height": 60000}},
            "too_large",
        ),
        (
            {"segments": {"dtype": "float64", "shape": [1, 4], "data": np.full(4, np.nan).tobytes()}},
            "bad_request",
        ),
        ({"segments": {"dtype": "float64", "shape": [1, 4], "data": np.zeros(4).tobytes()}}, "bad_request"),
        (
            {"segments": {"dtype": "float64", "shape": [1, 4], "data": np.array([0, 0, 1e200, 1]).tobytes()}},
            "bad_request",
        ),
        ({"prior": {"gravity": [0.0, 0.0, 0.0], "gravity_sigma_deg": 3.0}}, "bad_request"),
        ({"segments": {"dtype": "float64", "shape": [10**9, 4], "data": b""}}, "too_large"),
        ({"segments": {"dtype": "int8", "shape": [1, 4], "data": b"1234"}}, "bad_request"),
        ({"image": {"format": "png", "data": b"\x89PNG"}}, "bad_request"),  # both image and segments
        ({"prior": {"position": [1.0, 2.0], "radius_m": 1.0}}, "bad_request"),
        ({"prior": {"position": [1.0, 2.0, 3.0], "radius_m": -1.0}}, "bad_request"),
        ({"options": {"deadline_ms": 0}}, "bad_request"),
        ({"options": {"return_matches": 1}}, "bad_request"),
    ],
)
def test_decoder_answers_the_right_code_for_bad_fields(overrides, code):
    with pytest.raises(ProtocolError) as e:
        protocols.decode_request(msgpack.packb(_request(**overrides), use_bin_type=True))
    assert e.value.code == code, e.value.message


def test_image_size_is_checked_from_the_header_before_decoding():
    big = tiny_png(np.zeros((6, 8), np.uint8)).replace(
        b"\x00\x00\x00\x08\x00\x00\x00\x06", b"\x00\x01\x00\x00\x00\x01\x00\x00", 1
    )
    doc = _request(segments=None, image={"format": "png", "data": big})
    with pytest.raises(ProtocolError, match="65536x65536"):
        protocols.decode_request(msgpack.packb(doc, use_bin_type=True))
    req = LocalizeRequest("j", CAMERA, _jpeg_header(8, 6), "jpeg")
    assert protocols.decode_request(protocols.encode_request(req)).image_format == "jpeg"


def _jpeg_header(width: int, height: int) -> bytes:
    app0 = b"\xff\xe0\x00\x10JFIF\x00\x01\x01\x00\x00\x01\x00\x01\x00\x00"
    sof = b"\xff\xc0\x00\x0b\x08" + height.to_bytes(2, "big") + width.to_bytes(2, "big") + b"\x01\x01\x11\x00"
    return b"\xff\xd8" + app0 + sof + b"\xff\xd9"


def test_payload_over_the_limit_is_too_large():
    data = encode(messages()["request_png"])
    with pytest.raises(ProtocolError) as e:
        protocols.decode_request(data, Limits(max_payload_bytes=len(data) - 1))
    assert e.value.code == "too_large"


def test_reply_round_trip_gives_back_the_registration():
    reply = messages()["reply_ok"]
    reg = protocols.decode_reply(encode(reply)).to_registration()
    assert reg.success and reg.num_inliers == 42 and reg.matches.shape == (2, 2)
    assert np.array_equal(reg.cam_from_world, reply.cam_from_world)
    assert reg.ambiguity == pytest.approx(0.25)  # runner-up score / score, as in-process
    assert reg.alternatives.shape == (1, 4, 4) and reg.alternative_scores.tolist() == [1280.25]


def test_every_registration_field_crosses_the_wire():
    """The reply carries all a Registration holds: a field added to one and not the other fails here."""
    import dataclasses

    from linereg.registration import Registration

    reg = Registration(
        success=True,
        reason="",
        cam_from_world=messages()["reply_ok"].cam_from_world,
        matches=np.array([[0, 10], [1, 11], [3, 2]], dtype=np.int64),
        num_inliers=3,
        covariance=np.diag(np.arange(1.0, 7.0)) * 1e-4,
        rms_px=0.5,
        score=812.5,
        explained_fraction=0.5,
        log10_nfa=-12.5,
        runner_up_score=120.0,
        alternatives=np.stack([np.eye(4), 2 * np.eye(4)]),
        alternative_scores=np.array([120.0, 60.0]),
        timings={"refine": 0.01},
    )
    names = {f.name for f in dataclasses.fields(Registration)}
    defaults = Registration(success=False)
    assert all(not _equal(getattr(reg, n), getattr(defaults, n)) for n in names - {"reason"}), (
        "set every field"
    )
    reply = protocols.LocalizeReply.from_registration("r", reg, "m", "1", return_matches=True)
    back = protocols.decode_reply(encode(reply)).to_registration()
    for name in names:
        assert _equal(getattr(back, name), getattr(reg, name)), name


def _equal(a, b) -> bool:
    if isinstance(a, np.ndarray):
        return a.shape == np.shape(b) and bool(np.array_equal(a, b, equal_nan=True))
    return bool(a == b)


def _track_request(**overrides) -> bytes:
    doc = msgpack.unpackb(encode(messages()["track_request_segments_odometry"]), raw=False)
    return msgpack.packb({k: v for k, v in (doc | overrides).items() if v is not None}, use_bin_type=True)


@pytest.mark.parametrize(
    ("overrides", "code"),
    [
        ({"session": None}, "bad_request"),
        ({"session": "s" * 65}, "too_large"),
        ({"relative_pose": protocols.encode_array(np.full((4, 4), np.nan))}, "bad_request"),
        ({"relative_pose": protocols.encode_array(np.eye(3))}, "bad_request"),
        ({"timestamp": float("nan")}, "bad_request"),
        ({"timestamp": "0.5"}, "bad_request"),
        ({"segments": None}, "bad_request"),  # no frame
        ({"image": {"format": "raw", "pixels": protocols.encode_array(np.zeros((6, 9), np.uint8))}}, "bad_request"),
        ({"segments": None, "image": {"format": "raw", "pixels": protocols.encode_array(np.zeros((5, 8), np.uint8))}},
         "bad_request"),  # the session camera's size is 8 x 6
    ],
)  # fmt: skip
def test_track_request_decoder_answers_the_right_code(overrides, code):
    camera = messages()["session_open"].camera
    with pytest.raises(ProtocolError) as e:
        session.decode_track_request(_track_request(**overrides), camera)
    assert e.value.code == code, e.value.message


def test_session_messages_name_their_session_and_a_start_must_be_a_pose():
    assert session.session_of(encode(messages()["track_request_png"])) == (
        "track_request",
        "0123456789abcdef",
    )
    assert session.session_of(encode(messages()["session_open"])) == ("session_open", "")
    with pytest.raises(ProtocolError):
        session.session_of(encode(messages()["request_png"]))
    position_start = protocols.SessionOpen("o", CAMERA, protocols.Prior(position=np.zeros(3), radius_m=1.0))
    with pytest.raises(ProtocolError, match="pose"):
        session.decode_session_open(session.encode_session_open(position_start))


def test_keys_are_single_chunks():
    assert keys.localize_key("campus") == "linereg/campus/localize"
    assert keys.instance_of_alive_key(keys.alive_key("campus", "a1")) == ("campus", "a1")
    assert keys.instance_session_key("campus", "a1") == "linereg/campus/instance/a1/session"
    for bad in ("a/b", "*", "", "x" * 65, "a b"):
        with pytest.raises(ValueError):
            keys.localize_key(bad)


def test_every_error_code_is_documented_in_the_spec():
    spec = (GOLDEN_DIR.parent / "SPEC.md").read_text()
    for code in protocols.ERROR_CODES:
        assert f"`{code}`" in spec


_msgpack_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=20)
    | st.binary(max_size=40),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=12), inner, max_size=6),
    max_leaves=20,
)  # fmt: skip


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=300))
def test_decoder_never_crashes_on_random_bytes(data):
    for decode in (protocols.decode_request, protocols.decode_reply, protocols.decode_error):
        try:
            decode(data)
        except ProtocolError as e:
            assert e.code in protocols.ERROR_CODES


@settings(max_examples=60, deadline=None)
@given(st.dictionaries(st.sampled_from(["v", "type", "id", "camera", "image", "segments", "prior", "options"]),
                       _msgpack_values, max_size=8))  # fmt: skip
def test_decoder_never_crashes_on_wrong_types(fields):
    data = msgpack.packb({"v": 2, "type": "localize_request"} | fields, use_bin_type=True)
    try:
        protocols.decode_request(data)
    except ProtocolError as e:
        assert e.code in protocols.ERROR_CODES


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_decoder_never_crashes_on_mutated_golden_requests(data):
    name = data.draw(
        st.sampled_from(["request_png", "request_raw_pose_prior", "request_segments_position_prior"])
    )
    good = bytearray((GOLDEN_DIR / f"{name}.msgpack").read_bytes())
    for _ in range(data.draw(st.integers(1, 4))):
        good[data.draw(st.integers(0, len(good) - 1))] = data.draw(st.integers(0, 255))
    try:
        protocols.decode_request(bytes(good))
    except ProtocolError as e:
        assert e.code in protocols.ERROR_CODES
