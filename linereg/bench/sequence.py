"""Sequences: per-frame registration vs one smoothed GTSAM graph vs live tracking; ATE/RPE, timings, plots.

``linereg bench sequence [--scene synthetic|real|all|SET] [--seeds N ...] [--duration S] [--data DIR] [--out DIR]``

synthetic: the demo building scanned and mapped (``LineMap.build``), a walk round its courtyard
(``sim.paths``: 1.4 m/s, 10 Hz, ``--duration`` s) rendered by the demo renderer, with a 2 s blackout of
the sky and single blank frames, and odometry drifting by 2 % of the distance and 0.5 deg of yaw per metre.
real: every ``SET/sequence/frames.json`` under ``--data`` (``../shared/data``'s ``sevenscenes_redkitchen``: 300
real frames, 15 Hz; ``docs/extra_data``'s ``iclnuim_office``: 300 rendered frames, 15 Hz), in a map of the set's
``cloud.ply``, with odometry simulated from the ground truth the same way (``--scene kitchen`` names the first).

Rows: ``odometry`` (dead reckoning from the true first pose), ``per-frame`` (each frame by its own lines:
refined from its prediction or relocalized near it; ``localize_sequence``'s first step), ``smoothed`` (the
graph), ``tracking`` (``Tracker.step`` with odometry), ``tracking-cv`` (no odometry: constant velocity,
relocalization), ``tracking-reach`` (tracking-cv knowing the camera's top speed, ``--max-speed``: after a
long loss it relocalizes within reach of its last fix), and ``at-truth``, not a method: each frame refined
alone from its ground truth, what a frame's own lines allow (a graph pooling frames and odometry can do
better). ATE / RPE are evo's APE / RPE
(translation part, RMSE, no alignment, delta 1 frame) over the frames each row poses; ``posed`` counts frames with a pose (success, or from neighbours); ``wrong``
counts frames claiming success farther than ``--max-pos-m`` / ``--max-rot-deg`` from the truth; ``within``
is the share of ALL frames posed within ``--good-pos-m`` / ``--good-rot-deg``. With ``--global-every N``
every N-th frame is also localized globally, alone (``linereg.localize``): its ATE on those frames beside
the per-frame row's. Writes TUM files of every row (evo reads them), ``results.json``, ``trajectory.png``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..bench import honesty
from ..bench.real import default_data_dir


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--scene",
        default="all",
        help="synthetic, real (every SET/sequence/frames.json under --data), all (both; the default), or one "
        "set's folder name (kitchen: sevenscenes_redkitchen)",
    )
    parser.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        default=[0],
        help="synthetic scene seeds (default 0): one walk each, and a table of every row's wrong claims and "
        "frames within summed over them (a lost track's wrong claims come in runs: one walk can hide them)",
    )
    parser.add_argument("--duration", type=float, default=32.0, help="synthetic walk, seconds (default 32)")
    parser.add_argument("--data", type=Path, help="real data folder (default: shared/data beside the repo)")
    parser.add_argument("--out", type=Path, default=Path("bench_sequence"), help="output folder")
    parser.add_argument(
        "--global-every", type=int, default=20, help="global localize every N-th frame (0: off)"
    )
    parser.add_argument("--max-pos-m", type=float, default=0.3, help="a success farther than this is wrong")
    parser.add_argument("--max-rot-deg", type=float, default=5.0, help="... or turned more than this")
    parser.add_argument("--good-pos-m", type=float, default=0.1, help="'within': this close to the truth")
    parser.add_argument("--good-rot-deg", type=float, default=2.0, help="... and this little turned")
    parser.add_argument(
        "--odometry-seeds",
        type=int,
        nargs="+",
        default=[0],
        help="real sequences: the simulated odometry drawn from each of these seeds in turn (default 0), "
        "one evaluation each: how much a row owes to one draw of its odometry",
    )
    parser.add_argument(
        "--max-speed",
        type=float,
        default=2.0,
        help="the camera's top speed for the tracking-reach row (TrackingConfig.max_speed_m_s; default 2: "
        "walking and handheld cameras; 0: no such row)",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..cli import check_output_dir

    check_output_dir("--out", args.out)
    from ..errors import InvalidInputError

    for flag, values in (("--seeds", args.seeds), ("--odometry-seeds", args.odometry_seeds)):
        if len(set(values)) != len(values):
            raise InvalidInputError(f"{flag} must differ, got {values}")
        if any(v < 0 for v in values):
            raise InvalidInputError(f"{flag} must be >= 0, got {values}")
    data = args.data or default_data_dir()
    sets = real_sequences(data)
    scene = KITCHEN if args.scene == "kitchen" else args.scene
    if scene not in ("synthetic", "real", "all") and scene not in sets:
        raise InvalidInputError(
            f"--scene {args.scene}: not synthetic, real, all or a set with sequence/frames.json under {data} "
            f"(found: {', '.join(sets) or 'none'})"
        )
    summary = {}
    if scene in ("synthetic", "all"):
        for seed in args.seeds:
            name = "synthetic" if len(args.seeds) == 1 else f"synthetic-seed{seed}"
            summary[name] = evaluate(synthetic_problem(seed, args.duration), args, args.out / name)
        if len(args.seeds) > 1:
            _print_seeds(args.seeds, [summary[f"synthetic-seed{seed}"] for seed in args.seeds])
    if scene != "synthetic":
        if not sets:
            print(f"real sequences: none under {data} (a set folder with sequence/frames.json), skipped")
        for name in sets if scene in ("real", "all") else [scene]:
            problem = real_problem(data / name)
            draws = args.odometry_seeds
            keys = [name if len(draws) == 1 else f"{name}-odometry{seed}" for seed in draws]
            for key, seed in zip(keys, draws, strict=True):
                summary[key] = evaluate(with_odometry(problem, seed), args, args.out / key)
            if len(draws) > 1:
                _print_draws(name, draws, [summary[key] for key in keys])
    from .. import io

    io.write_json_atomic(args.out / "results.json", summary)
    return 0


def synthetic_problem(seed: int, duration_s: float) -> dict[str, Any]:
    """Returns the synthetic sequence: map, camera, frames, truth, odometry (``sim.paths``)."""
    from ..map.linemap import LineMap
    from ..sim import paths
    from ..sim.building import make_building
    from ..sim.demo_scene import DEMO_SCAN, scanner_positions
    from ..sim.render import render_image
    from ..sim.scanner import scan
    from ..sim.views import street_camera

    rng_building, rng_scan, rng_render, rng_odometry = (
        np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4)
    )
    start = time.perf_counter()
    building = make_building(rng_building)
    line_map = LineMap.build(scan(building, scanner_positions(building), rng_scan, DEMO_SCAN))
    walk = paths.WalkConfig(duration_s=duration_s)
    times, truth = paths.courtyard_walk(building, walk)
    blank = paths.blank_frames(times, walk)
    camera = street_camera()
    frames = [
        paths.blank_image(camera, rng_render) if b else render_image(building, T, camera, rng_render)
        for T, b in zip(truth, blank, strict=True)
    ]
    relative, covariances = paths.drifting_odometry(truth, rng_odometry)
    print(
        f"synthetic: map of {len(line_map)} segments, {len(frames)} frames in {time.perf_counter() - start:.0f} s"
    )
    problem = dict(name="synthetic", line_map=line_map, camera=camera, frames=frames, times=times)
    return problem | dict(truth=truth, relative=relative, covariances=covariances, blank=blank)


KITCHEN = "sevenscenes_redkitchen"  # ``--scene kitchen``: the shared data's real sequence


def real_sequences(data: Path) -> list[str]:
    """Returns the names of the set folders under ``data`` holding a ``sequence/frames.json``, sorted."""
    if not data.is_dir():
        return []
    return sorted(p.name for p in data.iterdir() if (p / "sequence" / "frames.json").is_file())


def real_problem(folder: Path) -> dict[str, Any]:
    """Returns a set's image sequence (``sequence/frames.json`` and its frames; the map of the set's
    ``cloud.ply``) with odometry simulated from its ground truth."""
    from .. import io
    from ..camera import Camera
    from ..errors import FileFormatError
    from ..map.linemap import LineMap

    meta_path = folder / "sequence" / "frames.json"
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, ValueError) as e:
        raise FileFormatError(f"{meta_path}: {type(e).__name__}: {e}") from None
    c = meta["camera"]
    camera = Camera(
        fx=c["fx"],
        fy=c["fy"],
        cx=c["cx"],
        cy=c["cy"],
        width=c["width"],
        height=c["height"],
        dist=tuple(c["distortion"]["coeffs"]),
    )
    cloud = io.read_cloud_fields(folder / "cloud.ply")
    line_map = LineMap.build(cloud.points, rings=cloud.rings)
    frames = [io.read_image(folder / "sequence" / f["file"]) for f in meta["frames"]]
    truth = np.array([f["T_cam_from_world"] for f in meta["frames"]], dtype=np.float64)
    times = np.array([f["timestamp"] for f in meta["frames"]], dtype=np.float64)
    print(f"{folder.name}: map of {len(line_map)} segments, {len(frames)} frames")
    problem = dict(name=folder.name, line_map=line_map, camera=camera, frames=frames, times=times)
    blank = np.zeros(len(frames), bool)
    return with_odometry(problem | dict(truth=truth, blank=blank), 0)


def with_odometry(problem: dict[str, Any], seed: int) -> dict[str, Any]:
    """Returns a real sequence's ``problem`` with its odometry simulated from its ground truth by
    ``paths.drifting_odometry`` with the generator of ``seed`` (the bench's own draw: 0)."""
    from ..sim import paths

    relative, covariances = paths.drifting_odometry(problem["truth"], np.random.default_rng(seed))
    return problem | dict(relative=relative, covariances=covariances)


def evaluate(p: dict[str, Any], args: argparse.Namespace, out: Path) -> dict[str, Any]:
    """Runs every row on one sequence; prints the table, writes TUM files, the plot; returns the numbers."""
    from ..graph import frame_lines
    from ..priors import Prior
    from ..score import image_lines
    from ..sequence import SequenceConfig, frames_alone, map_coverable, smooth
    from ..sim.paths import chain

    out.mkdir(parents=True, exist_ok=True)
    config = SequenceConfig()
    cam, truth = p["camera"].undistorted(), p["truth"]
    start = time.perf_counter()
    lines = [frame_lines(f, p["camera"], config.detect) for f in p["frames"]]
    detect_s = (time.perf_counter() - start) / len(lines)
    images = [image_lines(s, cam, config.register.score) for s in lines]
    rel, cov = list(p["relative"]), list(p["covariances"])
    first = Prior(cam_from_world=truth[0], radius_m=0.3, sigma_rot_deg=2.0)
    start = time.perf_counter()
    alone = frames_alone(lines, images, p["line_map"], cam, rel, cov, config, first)
    alone_s = (time.perf_counter() - start) / len(lines)
    print(
        f"  per-frame: {sum(r.success for r in alone)}/{len(alone)} fixed alone, {alone_s:.2f} s a frame",
        flush=True,
    )
    start = time.perf_counter()
    smoothed = smooth(
        images, p["line_map"].segments, cam, alone, rel, cov, config, p["line_map"].accuracy_m,
        map_coverable(p["line_map"], cam, config.register.score),
    )  # fmt: skip
    graph_s = (time.perf_counter() - start) / len(lines)
    print(f"  graph: {graph_s * len(lines):.1f} s", flush=True)
    rows = {
        "odometry": _row(
            chain(truth[0], p["relative"]), np.ones(len(truth), bool), np.zeros(len(truth), bool), truth, args
        ),
        "per-frame": _row_of(alone, truth, args),
        "smoothed": _row_of(smoothed, truth, args),
    }
    rows["per-frame"]["seconds_per_frame"] = alone_s + detect_s
    rows["smoothed"]["ate_m_same_frames"] = _ate_on(rows["smoothed"], rows["per-frame"]["posed_mask"], truth)
    rows["smoothed"]["seconds_per_frame"] = alone_s + detect_s + graph_s
    tracked = [("tracking", True, None), ("tracking-cv", False, None)]
    if args.max_speed:
        tracked.append(("tracking-reach", False, args.max_speed))
    for name, odometry, speed in tracked:
        results, steps, events, aligned = _track(p, odometry, speed)
        rows[name] = _row_of(results, truth, args) | _timing(steps, events, results, p)
        rows[name]["window_alignments"] = int(aligned.sum())
        rows[name]["align_step_s_median"] = float(np.median(steps[aligned])) if aligned.any() else None
        print(f"  {name}: {json.dumps(rows[name]['events'])}", flush=True)
    rows["tracking"] |= _segment_steps(p, lines)
    if args.global_every:
        rows["global"] = _global(p, alone, args)
    rows["at-truth"] = _at_truth(images, p["line_map"], cam, truth, config, args)
    global_start = _global_start(p, truth, args)
    _write(out, p, rows, alone, smoothed)
    _print(p["name"], rows, global_start)
    return {
        "rows": rows,
        "global_start": global_start,
        "frames": len(truth),
        "blank_frames": int(p["blank"].sum()),
    }


def _ate_on(row: dict[str, Any], frames: np.ndarray, truth: np.ndarray) -> float:
    """Returns the row's ATE (m) over ``frames`` ((K,) bool): the issue's comparison of the smoothed
    trajectory with per-frame registration is on the frames the per-frame stage claims."""
    from .trajectory import ape

    return ape(row["poses"][frames], truth[frames])[0].rmse


def _row_of(results: list, truth: np.ndarray, args: argparse.Namespace) -> dict[str, Any]:
    from ..sequence import FROM_NEIGHBOURS

    poses = np.array([r.cam_from_world for r in results])
    success = np.array([r.success for r in results])
    posed = success | np.array([r.reason.startswith(FROM_NEIGHBOURS) for r in results])
    return _row(poses, posed, success, truth, args) | _covariance(results, truth)


def _covariance(results: list, truth: np.ndarray) -> dict[str, Any]:
    """Returns {"covariance": ``honesty.summary``} of the claims (success) among a row's Registrations."""
    values = [
        honesty.nees(r.cam_from_world, T, r.covariance)
        for r, T in zip(results, truth, strict=True)
        if r.success
    ]
    return {"covariance": honesty.summary(values)}


def _row(
    poses: np.ndarray, posed: np.ndarray, success: np.ndarray, truth: np.ndarray, args: argparse.Namespace
) -> dict[str, Any]:
    from ..geometry import pose_errors
    from .trajectory import ape, rpe

    errors = np.array([pose_errors(T, G)[:2] for T, G in zip(poses, truth, strict=True)])  # (rot deg, pos m)
    rot, pos = errors[:, 0], errors[:, 1]
    wrong = success & ((pos > args.max_pos_m) | (rot > args.max_rot_deg))
    within = posed & (pos <= args.good_pos_m) & (rot <= args.good_rot_deg)
    ate, ate_rot = ape(poses[posed], truth[posed])
    rpe_t, rpe_r = rpe(poses[posed], truth[posed])
    return {
        "posed": float(posed.mean()), "success": float(success.mean()), "wrong": int(wrong.sum()),
        "within": float(within.mean()), "ate_m": ate.rmse, "ate_deg": ate_rot.rmse, "rpe_m": rpe_t.rmse,
        "rpe_deg": rpe_r.rmse, "poses": poses, "posed_mask": posed,
    }  # fmt: skip


def _at_truth(
    images: list, line_map: Any, camera: Any, truth: np.ndarray, config: Any, args: argparse.Namespace
) -> dict[str, Any]:
    """Returns the row of every frame refined alone from its ground truth (``refine_from``): not a method
    but what a frame's own lines allow. Where the map's lines and the ground truth disagree (a map off by
    centimetres, a colour camera not registered to the depth camera that posed it), the refinement moves
    off the truth, and the share it leaves within ``--good-*`` is about what a row placing each frame by
    its own lines can reach (a graph pooling frames and odometry can do better). A frame whose lines fix
    no pose (a blank wall, the sky: the refinement leaves the truth untouched) is not posed; ``success``
    is the tracker's fix test at the truth, with its own radius (``wrong``: the frames whose own lines
    would make it claim a wrong fix)."""
    from ..sequence import refine_from

    results = [
        refine_from(image, line_map, camera, T, config.relocalize_radius_m, config)
        for image, T in zip(images, truth, strict=True)
    ]
    poses = np.array([r.cam_from_world for r in results])
    fitted = np.array([np.isfinite(r.rms_px) for r in results])
    row = _row(poses, fitted, np.array([r.success for r in results]), truth, args)
    return row | _covariance(results, truth)


def _track(
    p: dict[str, Any], odometry: bool, max_speed: float | None
) -> tuple[list, np.ndarray, list[str], np.ndarray]:
    """Returns (Registrations, step seconds, events, (K,) bool: the step ran a window alignment) of a
    Tracker (``max_speed_m_s``: ``max_speed``) started at the true first pose (as the batch rows are),
    stepping through every frame from its image."""
    from ..tracking import Tracker, TrackingConfig

    tracker = Tracker(p["line_map"], p["camera"], TrackingConfig(max_speed_m_s=max_speed))
    tracker.start_at(p["truth"][0])
    results, steps, events, aligned = [], [], [], []
    for k, frame in enumerate(p["frames"]):
        relative = p["relative"][k - 1] if odometry and k else None
        before = tracker.alignments
        start = time.perf_counter()
        results.append(tracker.step(frame, relative, float(p["times"][k])))
        steps.append(time.perf_counter() - start)
        events.append(tracker.event)
        aligned.append(tracker.alignments > before)
    return results, np.array(steps), events, np.array(aligned, dtype=bool)


def _timing(steps: np.ndarray, events: list[str], results: list, p: dict[str, Any]) -> dict[str, Any]:
    """Returns the median tracked step (image in), relocalization step times and the recovery after the
    longest blackout: sequence seconds from its end to the first fix (tracked or relocalized, claimed or
    not: a global relocalization waits for confirmation) and to the first claimed frame."""
    ev = np.array(events)
    tracked = ev == "tracked"
    blank = p["blank"]
    recovery = claimed = None
    ends = np.flatnonzero(blank[:-1] & ~blank[1:]) + 1
    if len(ends):
        end = ends[np.argmax([_run_length(blank, int(e)) for e in ends])]
        fixed = np.flatnonzero(np.isin(ev[end:], ("tracked", "relocalized", "initialized")))
        recovery = float(p["times"][end + fixed[0]] - p["times"][end]) if len(fixed) else None
        success = np.flatnonzero([r.success for r in results[end:]])
        claimed = float(p["times"][end + success[0]] - p["times"][end]) if len(success) else None
    return {
        "step_ms_image_median": float(np.median(steps[tracked]) * 1e3) if tracked.any() else None,
        "relocalize_s": [round(float(s), 2) for s in steps[ev == "relocalized"]],
        "events": {e: int((ev == e).sum()) for e in sorted(set(events))},
        "recovery_after_blackout_s": recovery,
        "claimed_after_blackout_s": claimed,
    }


def _run_length(blank: np.ndarray, end: int) -> int:
    k = end - 1
    while k >= 0 and blank[k]:
        k -= 1
    return end - 1 - k


def _segment_steps(p: dict[str, Any], lines: list[np.ndarray]) -> dict[str, Any]:
    """Returns the median tracked step from segments (detection done beforehand), with odometry."""
    from ..tracking import Tracker

    tracker = Tracker(p["line_map"], p["camera"].undistorted())
    tracker.start_at(p["truth"][0])
    steps = []
    for k in range(len(lines)):
        start = time.perf_counter()
        tracker.step(lines[k], p["relative"][k - 1] if k else None)
        if tracker.event == "tracked":
            steps.append(time.perf_counter() - start)
    return {"step_ms_segments_median": float(np.median(steps) * 1e3) if steps else None}


def _global(p: dict[str, Any], alone: list, args: argparse.Namespace) -> dict[str, Any]:
    """Returns every N-th frame localized globally and alone, with the per-frame row's errors there."""
    from ..localization import localize

    index = np.arange(0, len(p["frames"]), args.global_every)
    results, seconds = [], []
    for k in index:
        start = time.perf_counter()
        results.append(localize(p["frames"][k], p["line_map"], p["camera"]))
        seconds.append(time.perf_counter() - start)
    row = _row_of(results, p["truth"][index], args)
    same = _row_of([alone[k] for k in index], p["truth"][index], args)
    return row | {
        "frames": index.tolist(),
        "per_frame_ate_m_same_frames": same["ate_m"],
        "seconds_per_frame": float(np.mean(seconds)),
    }


def _global_start(p: dict[str, Any], truth: np.ndarray, args: argparse.Namespace) -> dict[str, Any]:
    """Returns whether the sequence starts on its own: frame 0..4 localized globally, no prior."""
    from ..geometry import pose_errors
    from ..localization import localize

    out = []
    for k in range(min(5, len(truth))):
        r = localize(p["frames"][k], p["line_map"], p["camera"])
        rot, pos, _ = pose_errors(r.cam_from_world, truth[k])
        out.append({"frame": k, "success": r.success, "reason": r.reason, "pos_m": pos, "rot_deg": rot})
        if r.success:
            break
    return {"attempts": out, "found": bool(out and out[-1]["success"] and out[-1]["pos_m"] <= args.max_pos_m)}


def _write(out: Path, p: dict[str, Any], rows: dict[str, Any], alone: list, smoothed: list) -> None:
    from .. import io

    times, truth = p["times"], p["truth"]
    io.write_tum(out / "truth.tum", times.tolist(), truth)
    for name, row in rows.items():
        if "poses" not in row:
            continue
        mask = row.pop("posed_mask")
        poses = row.pop("poses")
        if name == "global":
            continue
        io.write_tum(out / f"{name}.tum", times[mask].tolist(), poses[mask])
    _plot(out / "trajectory.png", p["name"], truth, {n: r for n, r in _tum_rows(out).items()})


def _tum_rows(out: Path) -> dict[str, np.ndarray]:
    rows = {}
    for path in sorted(out.glob("*.tum")):
        data = np.loadtxt(path, ndmin=2)
        rows[path.stem] = data[:, 1:4] if len(data) else np.zeros((0, 3))
    return rows


def _plot(path: Path, title: str, truth: np.ndarray, rows: dict[str, np.ndarray]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 7))
    style = {
        "truth": ("k", 2.5),
        "odometry": ("tab:red", 1.0),
        "per-frame": ("tab:orange", 1.0),
        "smoothed": ("tab:blue", 1.5),
        "tracking": ("tab:green", 1.0),
        "tracking-cv": ("tab:purple", 0.8),
        "tracking-reach": ("tab:brown", 0.8),
        "at-truth": ("tab:grey", 0.8),
    }
    for name, xyz in rows.items():
        colour, width = style.get(name, ("grey", 1.0))
        marker = "." if name == "per-frame" else None
        ax.plot(xyz[:, 0], xyz[:, 1], color=colour, lw=width, marker=marker, ms=2, label=name)
    centres = rows["truth"] if "truth" in rows else np.zeros((1, 3))
    lo, hi = centres[:, :2].min(axis=0) - 3.0, centres[:, :2].max(axis=0) + 3.0  # a lost row may run off
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"{title}: camera centres, top view")
    ax.legend()
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def _print_seeds(seeds: list[int], results: list[dict[str, Any]]) -> None:
    """Prints every row's wrong claims and frames within per walk and summed over the walks."""
    frames = [r["frames"] for r in results]
    print(
        f"\nsynthetic walks, seeds {' '.join(map(str, seeds))}: wrong claims / frames within, per walk and in all"
    )
    for row_name in results[0]["rows"]:
        cells = [r["rows"][row_name] for r in results]
        # the global row registers every N-th frame only: its shares are of those frames
        counts = [len(c["frames"]) if "frames" in c else n for c, n in zip(cells, frames, strict=True)]
        within = [round(c["within"] * n) for c, n in zip(cells, counts, strict=True)]
        per = "  ".join(f"{c['wrong']:3d} / {w:3d}" for c, w in zip(cells, within, strict=True))
        wrong = sum(c["wrong"] for c in cells)
        print(f"{row_name:<14} {per}   all: {wrong:4d} / {sum(within):4d} of {sum(counts)}")
    beyond = []  # claims whose error lies beyond their reported 3 sigma (``honesty``), summed over the walks
    for row_name in results[0]["rows"]:
        known = [r["rows"][row_name]["covariance"] for r in results if "covariance" in r["rows"][row_name]]
        if known:
            out, claims = sum(c["beyond_3sigma"] for c in known), sum(c["claims"] for c in known)
            beyond.append(f"{row_name} {out}/{claims}")
    if beyond:
        print(f"claims beyond their reported 3 sigma (NEES), all walks: {', '.join(beyond)}")
    ratios = [r["rows"]["smoothed"]["ate_m_same_frames"] / r["rows"]["per-frame"]["ate_m"] for r in results]
    print(f"smoothed ATE / per-frame ATE on the per-frame frames: {'  '.join(f'{x:.2f}' for x in ratios)}")


def _print_draws(name: str, seeds: list[int], results: list[dict[str, Any]]) -> None:
    """Prints every row's share of frames within and wrong claims per odometry draw of one sequence."""
    print(f"\n{name}, odometry seeds {' '.join(map(str, seeds))}: frames within / wrong claims per draw")
    for row_name in results[0]["rows"]:
        cells = [r["rows"][row_name] for r in results]
        print(f"{row_name:<14} " + "  ".join(f"{100 * c['within']:5.1f} % / {c['wrong']:3d}" for c in cells))


# a row's keys the table shows (or that need no line): the rest are printed as JSON below it
TABLED = (
    "posed",
    "success",
    "wrong",
    "within",
    "ate_m",
    "ate_deg",
    "rpe_m",
    "rpe_deg",
    "frames",
    "covariance",
)


def _print(name: str, rows: dict[str, Any], global_start: dict[str, Any]) -> None:
    print(f"\n{name}")
    print(
        f"{'row':<14} {'posed':>6} {'success':>7} {'wrong':>5} {'within':>6} {'ATE m':>7} {'ATE deg':>7} {'RPE m':>7} {'RPE deg':>7} {'>3 sigma':>9}"
    )
    for row_name, r in rows.items():
        c = r.get("covariance")  # claims whose error lies beyond their reported 3 sigma (``honesty``)
        beyond = f"{c['beyond_3sigma']}/{c['claims']}" if c else "-"
        print(
            f"{row_name:<14} {r['posed']:6.1%} {r['success']:7.1%} {r['wrong']:5d} {r['within']:6.1%} {r['ate_m']:7.3f} {r['ate_deg']:7.2f} {r['rpe_m']:7.3f} {r['rpe_deg']:7.2f} {beyond:>9}"
        )
    for row_name, r in rows.items():
        extra = {k: v for k, v in r.items() if k not in TABLED}
        if extra:
            print(f"  {row_name}: {json.dumps(extra)}")
    print(f"  global start found alone: {global_start['found']} ({json.dumps(global_start['attempts'])})")
