"""End to end: the real library behind the service, a synthetic scene with a known pose, over zenoh."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

import linereg
from linereg.geometry import pose_errors
from linereg.sim import synthetic
from service import Client, Service, ServiceConfig


def _scene():
    return synthetic.paper_scene(np.random.default_rng(7))  # one the library solves (pose known)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    scene = _scene()
    path = tmp_path_factory.mktemp("map") / "lines3d.npy"
    np.save(path, scene.lines3d)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    config = ServiceConfig(loader="service.engine:load_segments_engine", loader_args=(str(path), "e2e"),
                           workers=1, listen=(endpoint,))  # fmt: skip
    with Service(config), Client(endpoint, map_name="e2e") as client:
        yield scene, client


def test_pose_over_zenoh_matches_the_truth_and_the_in_process_call(served):
    scene, client = served
    line_map = linereg.LineMap.from_segments(scene.lines3d, name="e2e")
    local = linereg.localize_segments(scene.lines2d, line_map, scene.camera)
    remote = client.localize_segments(scene.lines2d, scene.camera, timeout=60.0)
    assert remote.success == local.success and remote.num_inliers == local.num_inliers
    assert np.allclose(remote.cam_from_world, local.cam_from_world, atol=1e-6)  # the same computation
    assert np.allclose(remote.covariance, local.covariance, equal_nan=True, atol=1e-9)
    rot_deg, _, rel = pose_errors(remote.cam_from_world, scene.cam_from_world)
    assert remote.success and rot_deg < 2.0 and rel < 0.05
    assert client.info()["name"] == "e2e"


def test_position_prior_travels(served):
    scene, client = served
    center = -scene.cam_from_world[:3, :3].T @ scene.cam_from_world[:3, 3]
    prior = linereg.Prior(position=center, radius_m=100.0)
    remote = client.localize_segments(scene.lines2d, scene.camera, prior=prior, timeout=60.0)
    line_map = linereg.LineMap.from_segments(scene.lines3d, name="e2e")
    local = linereg.localize_segments(scene.lines2d, line_map, scene.camera, prior=prior)
    assert remote.success and local.success
    assert np.allclose(remote.cam_from_world, local.cam_from_world, atol=1e-6)


def test_linereg_serve_cli_serves_a_saved_map(served, tmp_path):
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path

    scene, _ = served
    root = Path(__file__).resolve().parents[1]
    path = tmp_path / "scene.lrmap"
    linereg.LineMap.from_segments(scene.lines3d, name="saved").save(path)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    cmd = [sys.executable, "-m", "linereg", "serve", "--map", str(path), "--name", "saved", "--listen", endpoint,
           "--workers", "1"]  # fmt: skip
    proc = subprocess.Popen(
        cmd, cwd=root, env=os.environ | {"PYTHONPATH": str(root)}, stderr=subprocess.DEVNULL
    )
    try:
        with Client(endpoint, map_name="saved", wait_s=60.0) as client:
            for _ in range(300):  # the service loads the map in its worker before it declares its keys
                if client.instances("saved", timeout=0.2):
                    break
                time.sleep(0.1)
            assert client.info()["name"] == "saved"
            assert client.localize_segments(scene.lines2d, scene.camera, timeout=60.0).reason is not None
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
    finally:
        proc.kill()


def test_tracking_session_over_zenoh_survives_its_worker(tmp_path):
    """The real Tracker in a worker: a global start (posed, not claimed until a later global relocalization
    confirms it), tracked frames, bad frames refused, a killed worker."""
    import os
    import signal

    from linereg.bench.sessions import CAMERA, orbit_scene
    from linereg.graph import relative_pose
    from service import ServiceError

    lines3d, truth, frames = orbit_scene(n_frames=8)
    np.save(tmp_path / "orbit.npy", lines3d)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    config = ServiceConfig(loader="service.engine:load_segments_engine",
                           loader_args=(str(tmp_path / "orbit.npy"), "orbit"), workers=1, listen=(endpoint,))  # fmt: skip
    with Service(config) as svc, Client(endpoint, map_name="orbit", retries=1) as client:
        with client.open_session(CAMERA) as session:

            def step(k: int, **kw):
                odometry = relative_pose(truth[k - 1], truth[k]) if k else None
                reg = session.step(frames[k], kw.pop("relative_pose", odometry), timeout=60.0, **kw)
                rot_deg, pos_m, _ = pose_errors(reg.cam_from_world, truth[k])
                assert rot_deg < 0.1 and pos_m < 0.01, (k, reg.reason, rot_deg, pos_m)
                # a global start is claimed only once a global relocalization 5 frames on agrees with it
                assert not reg.success and reg.reason.startswith("unconfirmed"), (k, reg.reason)
                return session.event

            assert [step(k, timestamp=0.1 * k) for k in range(4)] == ["initialized"] + ["tracked"] * 3
            not_rigid = np.diag([1.0, 1.0, 2.0, 1.0])
            for bad in ({"relative_pose": not_rigid}, {"timestamp": 0.0}):  # the timestamp goes back
                with pytest.raises(ServiceError) as e:
                    step(4, **bad)
                assert e.value.code == "bad_request"
            assert step(4, timestamp=0.4) == "tracked" and session.frames == 5
            os.kill(svc.pool.pids()[0], signal.SIGKILL)
            assert step(5) == "initialized" and session.restarted  # registered globally by a new tracker
            assert step(6) == "tracked" and not session.restarted
