"""``linereg localize`` as a batch (issue 12): the same poses on a Dask cluster as locally; a killed batch
resumes from the results saved per image, with nothing done twice.

Localization itself is replaced by a stand-in that reads the image's number from its first pixels (the
batch machinery is under test here, not the registration; tests/test_cli.py runs the real one)."""

import json

import cv2
import numpy as np
import pytest
from conftest import save_box_map

from linereg.cli import main
from linereg.registration import Registration

NUM_IMAGES = 1000
CALLS: list[int] = []


class Killed(BaseException):
    """The batch process is killed (not an Exception, which the command would report)."""


@pytest.fixture(scope="module")
def batch_files(tmp_path_factory):
    """A small map, a camera file and NUM_IMAGES images numbered in their first two pixels."""
    from linereg.sim.views import street_camera

    folder = tmp_path_factory.mktemp("batch")
    save_box_map(folder / "map.npz")
    (folder / "camera.json").write_text(json.dumps(street_camera().to_dict()))
    images = []
    for k in range(NUM_IMAGES):
        image = np.zeros((480, 640), np.uint8)
        image[0, :2] = divmod(k, 256)
        images.append(folder / f"img{k:04d}.png")
        assert cv2.imwrite(str(images[-1]), image)
    return folder, images


@pytest.fixture
def stand_in(monkeypatch):
    """Replaces linereg.localization.localize; ``stand_in["kill_after"] = n``: the command is killed after
    saving n results."""
    import linereg.cli.localize
    import linereg.localization

    state = {"kill_after": None, "saved": 0}
    CALLS.clear()
    save = linereg.cli.localize.ResultParts.write

    def write(self, image, record):
        if state["kill_after"] is not None and state["saved"] >= state["kill_after"]:
            raise Killed
        save(self, image, record)
        state["saved"] += 1

    def localize(image, line_map, camera, config=None, prior=None):
        k = int(image[0, 0]) * 256 + int(image[0, 1])
        CALLS.append(k)
        return Registration(True, cam_from_world=expected_pose(k), num_inliers=k % 7)

    monkeypatch.setattr(linereg.localization, "localize", localize)
    monkeypatch.setattr(linereg.cli.localize.ResultParts, "write", write)
    return state


def expected_pose(k: int) -> np.ndarray:
    """Returns the stand-in's pose of image k (what a local run gives: test_a_process_pool_...)."""
    pose = np.eye(4)
    pose[:3, 3] = [k, 0.5 * k, 2.0]
    return pose


def localize(folder, images, out, *extra) -> int:
    argv = [
        "localize",
        "--map",
        folder / "map.npz",
        "--camera",
        folder / "camera.json",
        *images,
        "--out",
        out,
    ]
    return main([str(a) for a in [*argv, *extra]])


def poses(path) -> dict[str, list]:
    return {image: r["cam_from_world"] for image, r in json.loads(path.read_text()).items()}


def test_a_killed_batch_on_a_dask_cluster_resumes_with_nothing_done_twice(batch_files, stand_in, tmp_path):
    distributed = pytest.importorskip("distributed")
    folder, images = batch_files
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        address = cluster.scheduler_address
        CALLS.clear()
        stand_in.update(kill_after=NUM_IMAGES // 2, saved=0)  # the batch is killed halfway
        with pytest.raises(Killed):
            localize(folder, images, tmp_path / "dask.json", "--scheduler", address)
        assert not (tmp_path / "dask.json").exists()
        parts = list((tmp_path / ".dask.json.parts").glob("*.json"))
        assert len(parts) == NUM_IMAGES // 2
        saved = {int(json.loads(p.read_text())["image"][-8:-4]) for p in parts}
        CALLS.clear()
        stand_in["kill_after"] = None
        assert localize(folder, images, tmp_path / "dask.json", "--scheduler", address, "--resume") == 0
    assert not saved & set(CALLS)  # nothing saved was localized again
    assert saved | set(CALLS) == set(range(NUM_IMAGES))
    assert poses(tmp_path / "dask.json") == {str(p): expected_pose(k).tolist() for k, p in enumerate(images)}
    assert list(json.loads((tmp_path / "dask.json").read_text())) == [str(p) for p in images]  # input order
    assert not (tmp_path / ".dask.json.parts").exists()


def test_a_process_pool_gives_the_inline_answer(batch_files, stand_in, tmp_path):
    folder, images = batch_files
    assert localize(folder, images[:40], tmp_path / "inline.json") == 0
    assert localize(folder, images[:40], tmp_path / "pool.json", "--workers", "2") == 0
    assert poses(tmp_path / "pool.json") == poses(tmp_path / "inline.json")
    assert poses(tmp_path / "inline.json") == {
        str(p): expected_pose(k).tolist() for k, p in enumerate(images[:40])
    }


def test_an_unreachable_scheduler_is_one_line(batch_files, stand_in, tmp_path, capsys, monkeypatch):
    pytest.importorskip("distributed")
    import linereg.batch

    monkeypatch.setattr(linereg.batch, "CONNECT_TIMEOUT", "1s")
    folder, images = batch_files
    code = localize(folder, images[:2], tmp_path / "p.json", "--scheduler", "tcp://127.0.0.1:9")
    err = capsys.readouterr().err
    assert code == 2 and "--scheduler tcp://127.0.0.1:9" in err and "Traceback" not in err
