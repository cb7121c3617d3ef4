"""Tracking sessions in the service (fake engine, zenoh on loopback): one worker per session, expiry, caps,
a killed or crashed worker, bad frames; the session table and the worker's trackers without a network."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest
from test_service import fake_config, fake_service, free_endpoint

import protocols
from protocols import session as wire
from service import Client, Service, ServiceError
from service.fake import expected_pose, expected_track_pose, load_fake_engine
from service.loadgen import CAMERA
from service.sessions import SessionLimits, SessionTable
from service.trackers import Trackers, track_job


def frame(k: float, first: float = 1.0) -> np.ndarray:
    return np.array([[first, 2.0, 3.0 + k, 4.0], [1.0, 2.0, 3.0, 4.0 + k]])


def poll(condition, timeout_s: float = 10.0) -> bool:
    """Returns whether ``condition()`` came true within ``timeout_s`` (polled, no fixed sleep)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


@pytest.fixture(scope="module")
def service():
    with fake_service(workers=2, hard_grace_s=2.0) as svc:
        yield svc


@pytest.fixture
def client(service):
    with Client(service.endpoint, map_name="fake") as c:
        yield c


def test_every_frame_of_a_session_reaches_its_own_tracker(client, service):
    sessions = [client.open_session(CAMERA) for _ in range(4)]
    assert sorted(service.sessions.slot_of(s.id) for s in sessions) == [0, 0, 1, 1]  # spread over the workers
    for k in range(5):
        for s in sessions:  # interleaved, with ordinary queries on the shared queue between them
            lines = frame(k)
            reg = s.step(lines, timestamp=float(k))
            # the fake tracker counts its own steps: a frame reaching another worker would count from 1
            assert np.allclose(reg.cam_from_world, expected_track_pose(lines, k + 1))
            assert s.event == ("initialized" if k == 0 else "tracked") and not s.restarted
            assert s.frames == k + 1
        assert np.allclose(client.localize_segments(lines, CAMERA).cam_from_world, expected_pose(lines))
    assert [s.close() for s in sessions] == [5, 5, 5, 5]
    with pytest.raises(ServiceError) as e:
        sessions[0].step(frame(0))
    assert e.value.code == "unknown_session"
    assert client.stats()["sessions"]["open"] == 0


def test_client_track_streams_frames_with_odometry_and_a_start(client):
    frames = [frame(k) for k in range(3)]
    step = np.eye(4)
    step[:3, 3] = [0.1, 0.0, 0.0]
    start = protocols.Prior(cam_from_world=np.eye(4), sigma_rot_deg=1.0, sigma_pos_m=0.1)
    regs = list(client.track(frames, CAMERA, relative_poses=[step] * 2, start=start))
    assert [r.success for r in regs] == [True] * 3
    assert np.allclose(regs[2].cam_from_world, expected_track_pose(frames[2], 3))


def test_bad_frames_get_bad_request_and_the_session_goes_on(client):
    with client.open_session(CAMERA) as s:
        s.step(frame(0))
        not_rigid = np.eye(4)
        not_rigid[0, 1] = 0.3
        nan = frame(1)
        nan[0, 2] = np.nan
        bad = [
            lambda: s.step(np.zeros((CAMERA.height + 1, CAMERA.width), np.uint8)),  # wrong size
            lambda: s.step(frame(1), relative_pose=not_rigid),
            lambda: s.step(frame(1), relative_pose=np.eye(3)),
            lambda: s.step(nan),
        ]
        for send in bad:
            with pytest.raises(ServiceError) as e:
                send()
            assert e.value.code == "bad_request", e.value.message
        reg = s.step(frame(2))
        assert np.allclose(reg.cam_from_world, expected_track_pose(frame(2), 2)) and s.event == "tracked"
        assert s.frames == 2 and not s.restarted


def test_a_killed_worker_costs_its_sessions_a_global_relocalization_only(service):
    with Client(service.endpoint, map_name="fake", retries=1) as c, c.open_session(CAMERA) as s:
        s.step(frame(0))
        s.step(frame(1))
        slot = service.sessions.slot_of(s.id)
        os.kill(service.pool.pids()[slot], signal.SIGKILL)
        # answered by the replacement worker (a frame sent to the dead one is answered ``internal`` and
        # sent again: retries=1)
        reg = s.step(frame(2))
        assert s.restarted and s.event == "initialized" and s.frames == 3
        assert np.allclose(reg.cam_from_world, expected_track_pose(frame(2), 1))  # a new tracker
        s.step(frame(3))
        assert not s.restarted and s.event == "tracked"
    assert poll(lambda: service.pool.alive() == 2)


def test_a_frame_crashing_its_worker_answers_internal_and_the_next_relocalizes(client, service):
    with client.open_session(CAMERA) as s:
        s.step(frame(0))
        with pytest.raises(ServiceError) as e:
            s.step(frame(1, first=-1.0))  # the fake tracker's worker exits
        assert e.value.code == "internal"
        s.step(frame(2))
        assert s.restarted and s.event == "initialized" and s.frames == 2
    assert poll(lambda: service.pool.alive() == 2)


def test_sessions_are_capped_and_idle_ones_expire():
    limits = SessionLimits(idle_timeout_s=2.0, max_sessions=3, per_worker=2)
    with Service(fake_config(free_endpoint(), workers=1, sessions=limits)) as svc:
        with Client(svc.config.listen[0], map_name="fake") as c:
            first, second = c.open_session(CAMERA), c.open_session(CAMERA)
            with pytest.raises(ServiceError) as e:
                c.open_session(CAMERA)  # one worker holds at most 2
            assert e.value.code == "busy"
            assert second.close() == 0
            kept = c.open_session(CAMERA)
            first.step(frame(0))
            assert c.info()["sessions"]["idle_timeout_s"] == 2.0
            assert poll(lambda: c.stats()["sessions"]["expired"] == 2)  # nothing was sent for 2 s
            for gone in (first, kept):
                with pytest.raises(ServiceError) as e:
                    gone.step(frame(1))
                assert e.value.code == "unknown_session"
            assert first.close() == 0  # closing an expired session is no error for the client


def test_session_messages_that_name_no_open_session_or_are_garbage(client):
    key = protocols.keys.instance_session_key("fake", client.instances("fake")[0][1])
    step = wire.encode_track_request(wire.TrackRequest("x", "nosuchsession", segments=frame(0)))
    for payload, code in [(step, "unknown_session"), (b"\x93garbage", "bad_request"),
                          (protocols.encode_request(protocols.LocalizeRequest("l", CAMERA, segments=frame(0))),
                           "bad_request")]:  # fmt: skip
        ok, reply = client.request(key, payload, 5.0)
        assert not ok and protocols.decode_error(reply).code == code


# --- without a network ------------------------------------------------------------------------------


def test_session_table_spreads_caps_and_expires_only_idle_sessions():
    now = [0.0]
    table = SessionTable(2, SessionLimits(idle_timeout_s=10.0, max_sessions=3, per_worker=2), lambda: now[0])
    a, b, c = (table.open(CAMERA, b"") for _ in range(3))
    assert [a.slot, b.slot, c.slot] == [0, 1, 0]
    with pytest.raises(protocols.ProtocolError, match="cap"):
        table.open(CAMERA, b"")
    busy = table.begin(a.id)  # a frame in flight: never expires meanwhile
    now[0] = 11.0
    table.end(table.begin(b.id), answered=True)  # b was used just now
    assert {s.id for s in table.expire()} == {c.id}
    table.end(busy, answered=True)
    assert busy.frames == 1
    now[0] = 22.0
    assert {s.id for s in table.expire()} == {a.id, b.id} and table.snapshot()["open"] == 0
    with pytest.raises(protocols.ProtocolError) as e:
        table.begin(a.id)
    assert e.value.code == "unknown_session"


def _open_payload(start=None) -> bytes:
    return wire.encode_session_open(wire.SessionOpen("o", CAMERA, start))


def _step(trackers: Trackers, session_id: str, lines, frames: int = 0, **fields) -> object:
    request = wire.encode_track_request(wire.TrackRequest("r", session_id, segments=lines, **fields))
    reply = trackers.handle(track_job("step", session_id, _open_payload(), frames, request))
    kind = protocols.unpack(reply)["type"]
    return wire.decode_track_reply(reply) if kind == "track_reply" else protocols.decode_error(reply)


def test_worker_trackers_make_one_per_session_and_say_when_one_was_made_again():
    trackers = Trackers(load_fake_engine(), protocols.Limits())
    first = _step(trackers, "s1", frame(0))
    assert first.how == "initialized" and first.frame == 0 and not first.restarted
    assert _step(trackers, "s1", frame(1), frames=1).how == "tracked"
    assert _step(trackers, "s1", frame(2), frames=2, timestamp=float("inf")).code == "bad_request"
    again = _step(trackers, "s2", frame(0), frames=7)  # a session this worker never saw: it lost its worker
    assert again.restarted and again.frame == 7 and len(trackers) == 2
    assert _step(trackers, "s2", frame(1), frames=8).restarted is False
    trackers.handle(track_job("drop", "s1"))
    assert len(trackers) == 1


def test_the_sessions_benchmark_walks_its_orbit_back_and_forth_without_a_jump():
    from linereg.bench.sessions import back_and_forth

    order = back_and_forth(4, 2, 9)
    assert order == [2, 3, 2, 1, 0, 1, 2, 3, 2]
