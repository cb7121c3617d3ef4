"""A deterministic stand-in engine for tests and benchmarks of the service without the geometry.

The "pose" it returns encodes its input (so a test can check every reply is the right one), and a first
segment with ``x1 < 0`` asks for a behaviour: -1 crash the worker, -2 sleep ``y1`` seconds, -3 raise,
-4 answer "not localized", -5 compute for ``y1`` seconds (CPU-bound, like a real localization).
"""

from __future__ import annotations

import os
import time
from dataclasses import replace

import numpy as np

from linereg.registration import Registration

from .engine import Engine


def expected_pose(data: np.ndarray) -> np.ndarray:
    """Returns the (4, 4) pose the fake engine answers for image or segments ``data``."""
    pose = np.eye(4)
    pose[:3, 3] = [
        float(np.asarray(data, dtype=np.float64).sum()),
        float(data.shape[0]),
        float(data.shape[1]),
    ]
    return pose


def _registration(data: np.ndarray) -> Registration:
    k = min(len(data), 4)
    return Registration(
        success=True,
        cam_from_world=expected_pose(data),
        matches=np.stack([np.arange(k), np.arange(k)], axis=1).astype(np.int64),
        num_inliers=k + 10,
        covariance=np.eye(6) * 1e-4,
        score=float(100 * (k + 10)),
        runner_up_score=30.0,
        rms_px=0.5,
        timings={"fake": 1e-4},
    )


def _spin(seconds: float) -> None:
    """Uses ``seconds`` of CPU time of one core (pure Python: no BLAS threads; slower when cores are shared)."""
    end = time.process_time() + seconds
    total = 0
    while time.process_time() < end:
        total += sum(i * i for i in range(1000))


def fake_localize(image, line_map, camera, config=None, prior=None) -> Registration:
    """Returns a Registration whose translation encodes ``image``'s sum and shape."""
    return _registration(np.asarray(image))


def fake_localize_segments(lines2d, line_map, camera, config=None, prior=None) -> Registration:
    """Returns a Registration encoding ``lines2d``; obeys the behaviour codes of the module docstring."""
    lines2d = np.asarray(lines2d)
    code = lines2d[0, 0]
    if code == -1:
        os._exit(3)  # a worker crash: no cleanup, no reply
    if code == -2:
        time.sleep(float(lines2d[0, 1]))
    if code == -3:
        raise RuntimeError("fake engine failure")
    if code == -5:
        _spin(float(lines2d[0, 1]))
    if code == -4:
        return Registration(success=False, reason="too few segments")
    return _registration(lines2d)


def expected_track_pose(data: np.ndarray, steps: int) -> np.ndarray:
    """Returns the (4, 4) pose the fake tracker answers for ``data`` as its ``steps``-th frame (from 1)."""
    pose = expected_pose(data)
    pose[2, 3] = float(steps)  # which tracker answered: a new one counts from 1 again
    return pose


class FakeTracker:
    """A stand-in for ``linereg.Tracker``: the pose encodes the frame and the steps this tracker object made
    (``expected_track_pose``); segment codes as above (-1 crash, -2 sleep, -3 raise, -4 no fix: the pose
    "predicted"); a relative pose is checked like the real tracker's."""

    def __init__(self, line_map, camera, config=None) -> None:
        self.camera, self.steps, self.event, self.started = camera, 0, "none", False

    def start_at(self, cam_from_world, sigma_rot_deg: float = 1.0, sigma_pos_m: float = 0.05) -> None:
        self.started, self.event = True, "initialized"

    def step(self, frame, relative_pose=None, timestamp=None) -> Registration:
        """Returns a Registration encoding ``frame`` and the step count; ``event`` says how."""
        if relative_pose is not None:
            from linereg.geometry import check_rigid

            check_rigid(relative_pose, "relative_pose")
        frame = np.asarray(frame)
        code = frame[0, 0] if frame.ndim == 2 and frame.shape[1:] == (4,) and len(frame) else 0.0
        if code == -4:
            self.event = "predicted"
            return Registration(success=False, reason="from neighbours: 1 frame(s) predicted")
        if code in (-1, -2, -3):
            fake_localize_segments(frame, None, self.camera)
        self.steps += 1
        self.event = "tracked" if self.steps > 1 or self.started else "initialized"
        return replace(_registration(frame), cam_from_world=expected_track_pose(frame, self.steps))


def load_fake_engine(
    map_path: str = "", map_name: str | None = None, config_path: str | None = None, startup_s: float = 0.0
) -> Engine:
    """Returns the fake Engine (``map_path``, ``config_path`` ignored; ``startup_s`` imitates loading a real map)."""
    map_name = map_name or "fake"
    time.sleep(startup_s)
    info = {"name": map_name, "version": "fake-1", "bounds": [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]}
    return Engine(None, fake_localize, fake_localize_segments, map_name, "fake-1", info, tracker=FakeTracker)
