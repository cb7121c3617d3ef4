"""``linereg bench service --sessions N``: N tracking sessions streaming at once through one service.

Each session streams the frames of a camera orbiting a box of lines (exact segments, as a robot's line
detector would send them, with exact odometry) at ``--session-hz`` frames per second, back and forth along
the orbit, for ``--duration`` seconds; it starts at its known pose (no global registration of 20 sessions at
once). The service runs the real library (``Tracker``) with 2 workers, one BLAS thread each. Measured:
frames sent, answered, lost (an error or no reply), how they were obtained, the worst pose error against the
truth, latency, worker restarts, and resident memory of the service and its workers (sampled every 0.5 s,
the 2nd quarter of the run against the last: the first warms caches up). Target (issue 11): 20 sessions on
2 workers for 10 minutes, no lost frame, memory flat.
"""

from __future__ import annotations

import multiprocessing as mp
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import numpy as np

from ..camera import Camera

CAMERA = Camera(fx=800.0, fy=800.0, cx=320.0, cy=240.0, width=640, height=480)


def orbit_scene(n_frames: int = 90, seed: int = 0) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Returns ((M, 6) map lines, (K, 4, 4) cam_from_world truth, K (N, 4) exact segments): a camera at 4 m
    circling a 3 m box of 44 lines, 2 degrees (0.14 m) per frame."""
    from ..sim.synthetic import look_at, project_visible

    rng = np.random.default_rng(seed)
    directions = np.r_[np.tile(np.eye(3), (12, 1)), rng.normal(size=(8, 3))]
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    starts = rng.uniform(-1.5, 1.5, (len(directions), 3))
    lines3d = np.c_[starts, starts + rng.uniform(0.4, 1.2, (len(directions), 1)) * directions]
    angles = np.radians(2.0) * np.arange(n_frames)
    truth = np.array([look_at(np.array([4 * np.cos(a), 4 * np.sin(a), 0.8]), np.zeros(3)) for a in angles])
    return lines3d, truth, [project_visible(lines3d, CAMERA, T)[0] for T in truth]


def back_and_forth(n: int, start: int, count: int) -> list[int]:
    """Returns ``count`` frame indices going 0..n-1..0.. from ``start`` (a continuous motion, no jump)."""
    period = 2 * (n - 1)
    phase = [(start + k) % period for k in range(count)]
    return [p if p < n else period - p for p in phase]


def stream(
    endpoint: str, map_name: str, first: int, sessions: int, duration_s: float, hz: float
) -> list[dict]:
    """Runs ``sessions`` sessions (threads of this process, one client), returns each one's counts."""
    from service import Client

    _, truth, frames = orbit_scene()
    with Client(endpoint, map_name=map_name) as client:
        results: list[dict] = [{} for _ in range(sessions)]
        threads = [
            threading.Thread(
                target=_session, args=(client, truth, frames, 7 * (first + i), duration_s, hz, results[i])
            )
            for i in range(sessions)
        ]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    return results


def _session(client, truth, frames, start: int, duration_s: float, hz: float, out: dict) -> None:
    from linereg import Prior
    from linereg.geometry import pose_errors
    from linereg.graph import relative_pose
    from service import ServiceError

    counts: Counter[str] = Counter()
    latencies, worst = [], [0.0, 0.0]
    order = back_and_forth(len(frames), start, int(duration_s * hz))
    begin = time.perf_counter()
    with client.open_session(
        CAMERA, Prior(cam_from_world=truth[order[0]], sigma_rot_deg=1.0, sigma_pos_m=0.05)
    ) as s:
        for k, i in enumerate(order):
            time.sleep(max(0.0, begin + k / hz - time.perf_counter()))
            relative = relative_pose(truth[order[k - 1]], truth[i]) if k else None  # cam_prev_from_cam_this
            sent = time.perf_counter()
            try:
                reg = s.step(frames[i], relative, timeout=30.0, return_matches=False)
            except ServiceError as e:
                counts[f"lost:{e.code}"] += 1
                continue
            latencies.append(time.perf_counter() - sent)
            counts[s.event] += 1
            if reg.success:
                rot, pos, _ = pose_errors(reg.cam_from_world, truth[i])
                worst = [max(worst[0], rot), max(worst[1], pos)]
        out.update(counts=dict(counts), latencies_s=latencies, worst_rot_deg=worst[0], worst_pos_m=worst[1],
                   closed_frames=s.close(), seconds=time.perf_counter() - begin)  # fmt: skip


def bench_sessions(sessions: int, duration_s: float, hz: float, clients: int = 4) -> dict:
    """Returns the outcome of ``sessions`` concurrent sessions on 2 workers for ``duration_s`` seconds."""
    from .service import _sample, _service

    lines3d, _, _ = orbit_scene()
    path = Path(tempfile.mkdtemp()) / "orbit.npy"
    np.save(path, lines3d)
    samples: list = []
    clients = max(1, min(clients, sessions))
    groups = [(g * sessions // clients, (g + 1) * sessions // clients) for g in range(clients)]
    with _service(2, "service.engine:load_segments_engine", (str(path), "orbit"), queue=64) as svc:
        pids, stop = svc.pool.pids(), threading.Event()
        sampler = threading.Thread(target=_sample, args=(pids, samples, stop), daemon=True)
        sampler.start()
        start = time.perf_counter()
        with mp.get_context("spawn").Pool(clients) as pool:
            runs = pool.starmap(
                stream, [(svc.config.listen[0], "orbit", a, b - a, duration_s, hz) for a, b in groups]
            )
        seconds = time.perf_counter() - start
        stop.set()
        sampler.join()
        restarts, same_pids, stats = svc.pool.restarts, svc.pool.pids() == pids, svc.snapshot()
    return _summary([r for run in runs for r in run], sessions, duration_s, hz, seconds, samples) | {
        "worker_restarts": restarts, "same_worker_pids": same_pids, "sessions_open_after": stats["sessions"]["open"],
    }  # fmt: skip


def _summary(
    per_session: list[dict], sessions: int, duration_s: float, hz: float, seconds: float, samples: list
) -> dict:
    counts: Counter[str] = Counter()
    for r in per_session:
        counts.update(r["counts"])
    ms = 1e3 * np.concatenate([r["latencies_s"] for r in per_session])
    lost = sum(v for k, v in counts.items() if k.startswith("lost"))
    memory = np.array(samples).reshape(-1, 2)
    quarter = max(1, len(memory) // 4)
    return {
        "sessions": sessions, "duration_s": duration_s, "hz": hz, "seconds": seconds,
        "frames_sent": len(ms) + lost, "frames_answered": len(ms), "frames_lost": lost,
        "frames_closed": int(sum(r["closed_frames"] for r in per_session)),
        "how": dict(counts),
        "worst_rot_deg": max(r["worst_rot_deg"] for r in per_session),
        "worst_pos_m": max(r["worst_pos_m"] for r in per_session),
        "latency_p50_ms": float(np.median(ms)), "latency_p99_ms": float(np.percentile(ms, 99)),
        "memory_mb_q2": memory[quarter : 2 * quarter].max(axis=0).tolist(),
        "memory_mb_q4": memory[-quarter:].max(axis=0).tolist(),
        "memory_mb_samples": memory.tolist(),
    }  # fmt: skip


def summary_rows(r: dict) -> list[dict]:
    """Returns the table rows of a sessions run with the issue's targets."""
    q2, q4 = r["memory_mb_q2"], r["memory_mb_q4"]
    return [
        {"what": f"{r['sessions']} sessions x {r['hz']:g} Hz x {r['duration_s']:g} s: frames answered",
         "value": f"{r['frames_answered']} of {r['frames_sent']}", "target": ""},
        {"what": "  frames lost (error or no reply)", "value": r["frames_lost"], "target": "0"},
        {"what": "  how: " + ", ".join(f"{k} {v}" for k, v in sorted(r["how"].items())), "value": "", "target": ""},
        {"what": "  worst pose error (deg, m)", "value": f"{r['worst_rot_deg']:.2g}, {r['worst_pos_m']:.2g}", "target": ""},
        {"what": "  latency p50 / p99 ms", "value": f"{r['latency_p50_ms']:.1f} / {r['latency_p99_ms']:.1f}", "target": ""},
        {"what": "  worker restarts / same pids", "value": f"{r['worker_restarts']} / {r['same_worker_pids']}", "target": "0 / True"},
        {"what": "  memory 2nd -> last quarter: service, workers (MB)",
         "value": f"{q2[0]:.0f} -> {q4[0]:.0f}, {q2[1]:.0f} -> {q4[1]:.0f}", "target": "flat"},
    ]  # fmt: skip
