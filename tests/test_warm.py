"""The warm-up compiles every kernel a localization needs; the kernels it rewrote match numpy's rules."""

from __future__ import annotations

import numpy as np
from numba.core import event

import linereg
from linereg.kernels import stable_argsort
from linereg.search import _solve_symmetric
from linereg.sim.building import make_building
from linereg.sim.views import camera_poses, project_building, street_camera


def _compiled_during(run) -> list[str]:
    with event.install_recorder("numba:compile") as recorder:
        run()
    names = [e.data["dispatcher"].py_func for _, e in recorder.buffer if e.is_start]
    return [f"{f.__module__}.{f.__name__}" for f in names if f.__module__.startswith("linereg")]


def test_after_the_warm_up_a_localization_and_a_tracker_compile_nothing():
    assert linereg.warm_up() > 0.0
    # another building than the warm-up's (a courtyard of four blocks), its faces as the map's surfaces
    rng = np.random.default_rng(3)
    building = make_building(rng)
    camera = street_camera()
    pose = camera_poses(building, rng, 1, camera)[0]
    lines2d, _ = project_building(building, camera, pose)
    line_map = linereg.LineMap.from_segments(building.edges, surfaces=building.mesh())
    results: list[linereg.Registration] = []

    def localize_and_track() -> None:
        results.append(linereg.localize_segments(lines2d, line_map, camera))
        tracker = linereg.Tracker(line_map, camera)
        tracker.start_at(pose)
        results.extend(tracker.step(lines2d, timestamp=t) for t in (0.0, 0.1, 0.2))

    assert _compiled_during(localize_and_track) == []
    assert results[0].cam_from_world is not None and results[-1].success


def test_the_stable_argsort_is_numpys():
    rng = np.random.default_rng(0)
    for n in (0, 1, 2, 3, 7, 64, 1001):
        for keys in (rng.normal(size=n), rng.integers(0, 4, n).astype(float)):  # ties: the stable order
            assert np.array_equal(stable_argsort(keys), np.argsort(keys, kind="stable"))


def test_the_symmetric_solve_and_its_condition_test_are_numpys():
    rng = np.random.default_rng(1)
    out = np.empty(6)
    for _ in range(300):
        J = rng.normal(size=(int(rng.integers(6, 30)), 6)) * rng.uniform(1e-3, 1e3, 6)
        H, rhs = J.T @ J, rng.normal(size=6)
        cond = np.linalg.cond(H)
        if abs(np.log10(cond) - 12.0) < 0.1:  # at the threshold the two may round apart
            continue
        assert _solve_symmetric(H, rhs, 1e12, out) == (cond <= 1e12)
        if cond <= 1e12:
            want = np.linalg.solve(H, rhs)
            assert np.abs(out - want).max() <= 1e-12 * cond * np.abs(want).max()
    singular = np.ones((6, 6))
    assert not _solve_symmetric(singular, np.ones(6), 1e12, out)
    not_finite = np.eye(6)
    not_finite[2, 2] = np.nan
    assert not _solve_symmetric(not_finite, np.ones(6), 1e12, out)


def test_a_failing_warm_up_does_not_stop_a_service_worker_loading_its_map(tmp_path, monkeypatch, caplog):
    import linereg.warm
    from service.engine import load_map_engine

    def broken(*_: object) -> float:
        raise RuntimeError("no compiler")

    rng = np.random.default_rng(5)
    path = tmp_path / "small.linemap"
    linereg.LineMap.from_segments(rng.uniform(-5, 5, (40, 6)), name="small").save(path)
    monkeypatch.setattr(linereg.warm, "warm_up", broken)
    with caplog.at_level("WARNING", logger="service.engine"):
        engine = load_map_engine(str(path))
    assert engine.map_name == "small" and len(engine.line_map.segments) == 40
    assert [r.getMessage() for r in caplog.records] == ["warm-up failed"]


def test_a_service_worker_prepares_its_map_before_the_first_query(tmp_path):
    """``load_map_engine`` warms up with its map: the map's view (corner points, signatures) and its
    occlusion test's ray-casting scene and chunks are built before a query arrives."""
    from service.engine import load_map_engine

    rng = np.random.default_rng(3)
    building = make_building(rng)
    path = tmp_path / "block.linemap"
    linereg.LineMap.from_segments(building.edges, name="block", surfaces=building.mesh()).save(path)
    engine = load_map_engine(str(path))
    line_map = engine.line_map
    assert "view" in line_map.cache
    visibility = line_map.visibility()
    assert visibility._scene is not None and visibility._chunks is not None
