"""The service over zenoh on loopback (fake engine): replies, errors, faults, load, draining on SIGTERM."""

from __future__ import annotations

import contextlib
import multiprocessing as mp
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import protocols
from protocols import Limits, keys
from service import Client, Service, ServiceConfig, ServiceError
from service.fake import expected_pose
from service.loadgen import CAMERA, run_client

ROOT = Path(__file__).resolve().parents[1]


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def fake_config(endpoint: str, **kw) -> ServiceConfig:
    return ServiceConfig(
        loader="service.fake:load_fake_engine", loader_args=("", "fake"), listen=(endpoint,), **kw
    )


@contextlib.contextmanager
def fake_service(**kw):
    """Yields a running Service of the fake engine on a free port (its ``endpoint`` set)."""
    endpoint = free_endpoint()
    with Service(fake_config(endpoint, **kw)) as svc:
        svc.endpoint = endpoint
        yield svc


@pytest.fixture(scope="module")
def service():
    limits = Limits(max_payload_bytes=1_000_000)
    with fake_service(workers=2, queue_size=4, limits=limits, hard_grace_s=2.0) as svc:
        yield svc


@pytest.fixture
def client(service):
    with Client(service.endpoint, map_name="fake") as c:
        yield c


def segments_with(first: list[float]) -> np.ndarray:
    return np.array([first, [1.0, 2.0, 3.0, 4.0]])


def test_localize_image_and_segments(client, rng):
    image = rng.integers(0, 256, size=(240, 320), dtype=np.uint8)
    reg = client.localize(image, CAMERA, timeout=5.0)
    assert reg.success and np.allclose(reg.cam_from_world, expected_pose(image)) and len(reg.matches) == 4
    lines = segments_with([5.0, 6.0, 7.0, 8.0])
    assert np.allclose(client.localize_segments(lines, CAMERA).cam_from_world, expected_pose(lines))


def test_info_stats_liveliness(client, service):
    assert client.instances() == [("fake", service.instance)]
    assert Client(service.endpoint).map_name == "fake"  # discovered through liveliness
    info = client.info()
    assert info["name"] == "fake" and info["instance"] == service.instance and "bounds" in info
    stats = client.stats()
    assert stats["workers_alive"] == 2 and stats["queue_size"] == 4 and "outcomes" in stats


def test_garbage_and_oversize_get_error_codes(client):
    ok, reply = client.request(keys.localize_key("fake"), b"\xc1garbage", 5.0)
    assert not ok and protocols.decode_error(reply).code == "bad_request"
    big = protocols.encode_request(
        protocols.LocalizeRequest("big", CAMERA, np.zeros((240, 320, 4), np.uint16), "raw")
    )  # 600 kB of pixels... over the 1 MB limit once doubled below
    ok, reply = client.request(keys.localize_key("fake"), big + big, 5.0)
    assert not ok and protocols.decode_error(reply).code == "too_large"


def test_deadline_answers_timeout_and_the_service_keeps_answering(client):
    start = time.monotonic()
    with pytest.raises(ServiceError) as e:
        client.localize_segments(segments_with([-2.0, 0.6, 1.0, 1.0]), CAMERA, timeout=0.3)
    assert e.value.code == "timeout" and time.monotonic() - start < 1.0
    assert client.localize_segments(segments_with([1.0, 1.0, 2.0, 2.0]), CAMERA).success


def test_crashed_and_killed_workers_answer_internal_and_are_replaced(client, service):
    with pytest.raises(ServiceError) as e:
        client.localize_segments(segments_with([-1.0, 0.0, 1.0, 1.0]), CAMERA)  # the worker exits
    assert e.value.code == "internal"
    result = {}

    def slow_query():
        try:
            client.localize_segments(segments_with([-2.0, 2.0, 1.0, 1.0]), CAMERA, timeout=5.0)
        except ServiceError as err:
            result["code"] = err.code

    thread = threading.Thread(target=slow_query)
    for _ in range(150):  # the previous tests' slow queries are done
        if not service.pool.in_flight:
            break
        time.sleep(0.02)
    thread.start()
    for _ in range(150):  # a worker has taken the slow query
        if service.pool.in_flight:
            break
        time.sleep(0.02)
    time.sleep(0.1)
    for pid in service.pool.pids():  # one of them is processing the slow query
        with contextlib.suppress(ProcessLookupError):  # the crashed one may still be being replaced
            os.kill(pid, signal.SIGKILL)
    thread.join(10)
    assert result.get("code") == "internal"
    time.sleep(0.2)  # a request sent the very moment its worker is killed is answered ``internal`` too
    lines = segments_with([3.0, 3.0, 2.0, 2.0])
    assert np.allclose(client.localize_segments(lines, CAMERA).cam_from_world, expected_pose(lines))
    for _ in range(100):  # the idle killed worker is replaced within a second or two
        if service.pool.alive() == 2:
            break
        time.sleep(0.1)
    assert service.pool.alive() == 2 and service.pool.restarts >= 2


def test_client_gone_before_reply_does_not_hurt(service):
    with Client(service.endpoint, map_name="fake") as gone:
        with pytest.raises(ServiceError):
            gone.localize_segments(segments_with([-2.0, 0.5, 1.0, 1.0]), CAMERA, timeout=0.1)
    time.sleep(0.6)
    with Client(service.endpoint, map_name="fake") as c:
        assert c.localize_segments(segments_with([1.0, 1.0, 2.0, 2.0]), CAMERA).success
    assert service.pool.alive() == 2


def test_full_queue_answers_busy():
    config = fake_config(free_endpoint(), workers=1, queue_size=1)
    codes = []
    with Service(config) as svc, Client(svc.config.listen[0], map_name="fake") as c:

        def slow():
            try:
                c.localize_segments(segments_with([-2.0, 0.5, 1.0, 1.0]), CAMERA, timeout=5.0)
                codes.append("ok")
            except ServiceError as e:
                codes.append(e.code)

        threads = [threading.Thread(target=slow) for _ in range(4)]
        threads[0].start()
        for _ in range(100):  # the worker has taken the first query: the queue is empty again
            if svc.pool.in_flight == 1 and svc.pool.jobs.qsize() == 0:
                break
            time.sleep(0.02)
        threads[1].start()
        for _ in range(100):  # the second waits in the queue
            if svc.pool.jobs.qsize() == 1:
                break
            time.sleep(0.02)
        for t in threads[2:]:
            t.start()
        for t in threads:
            t.join(10)
    assert sorted(codes) == ["busy", "busy", "ok", "ok"]  # 1 running + 1 queued, the rest refused at once


def test_load_several_clients_with_garbage(service):
    ctx = mp.get_context("spawn")
    args = [(service.endpoint, "fake", 70, 0.1, seed) for seed in range(3)]
    with ctx.Pool(3) as pool:
        results = pool.starmap(run_client, args)
    counts = {}
    for r in results:
        for k, v in r["counts"].items():
            counts[k] = counts.get(k, 0) + v
    assert set(counts) <= {"valid_right", "garbage_refused"}, counts
    assert sum(counts.values()) == 210 and counts["garbage_refused"] > 5
    assert service.pool.alive() == 2


def test_sigterm_drains_in_flight_work():
    endpoint = free_endpoint()
    cmd = [sys.executable, "-m", "service", "--map", "none", "--name", "drain", "--engine",
           "service.fake:load_fake_engine", "--listen", endpoint, "--workers", "1"]  # fmt: skip
    proc = subprocess.Popen(
        cmd, cwd=ROOT, stderr=subprocess.PIPE, text=True, env=os.environ | {"PYTHONPATH": str(ROOT)}
    )
    try:
        with Client(endpoint, map_name="drain", wait_s=30.0) as c:
            for _ in range(100):  # wait until it serves
                if c.instances("drain", timeout=0.2):
                    break
                time.sleep(0.1)
            result = {}
            thread = threading.Thread(
                target=lambda: result.update(
                    reg=c.localize_segments(segments_with([-2.0, 1.0, 1.0, 1.0]), CAMERA)
                )
            )
            thread.start()
            time.sleep(0.3)
            proc.send_signal(signal.SIGTERM)
            thread.join(10)
            assert result["reg"].success  # answered although the service was told to stop
        assert proc.wait(timeout=15) == 0
    finally:
        proc.kill()
    assert '"message": "service stopped"' in proc.stderr.read()


def test_query_cli_prints_one_json_per_image(service, tmp_path, capsys):
    import json

    import cv2

    from linereg.cli import main

    image = np.random.default_rng(5).integers(0, 256, size=(240, 320), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "a.png"), image)
    (tmp_path / "bad.png").write_bytes(b"not an image")
    (tmp_path / "cam.json").write_text(json.dumps(CAMERA.to_dict()))
    args = [
        "query",
        "--connect",
        service.endpoint,
        "--camera",
        str(tmp_path / "cam.json"),
        str(tmp_path / "a.png"),
    ]
    assert main(args) == 0
    record = json.loads(capsys.readouterr().out.splitlines()[0])
    assert record["success"] and np.allclose(record["cam_from_world"], expected_pose(image))
    assert main([*args[:-1], str(tmp_path / "bad.png")]) == 2  # not a PNG: a user error, no traceback


def test_linereg_package_never_imports_zenoh():
    code = "import sys, linereg, linereg.cli; linereg.cli.build_parser(); print('zenoh' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_scale_out_tiles_and_replicas():
    first, second = free_endpoint(), free_endpoint()
    a = fake_config(first, workers=1, instance="i1", tile="a", map_name="tiled")
    b = fake_config(second, workers=1, instance="i2", tile="b", map_name="tiled", connect=(first,))
    with Service(a) as sa, Service(b) as sb, Client(first, map_name="tiled") as c:
        for _ in range(50):  # the second router's declarations take a moment to arrive
            if len(c.instances("tiled")) == 2:
                break
            time.sleep(0.1)
        assert c.instances("tiled") == [("tiled", "i1"), ("tiled", "i2")]
        lines = segments_with([5.0, 6.0, 7.0, 8.0])
        request = protocols.encode_request(protocols.LocalizeRequest("t", CAMERA, segments=lines))
        replies = list(c.session.get(keys.tile_localize_key("tiled", "*"), payload=request, timeout=5.0))
        assert sum(r.ok is not None for r in replies) == 2  # every tile answers a wildcard query
        image = np.zeros((240, 320), np.uint8)
        assert c.localize_tiles(image, CAMERA).success
        balanced = Client(first, map_name="tiled", balance=True)
        for _ in range(6):
            assert balanced.localize_segments(lines, CAMERA).success
        balanced.close()
        served = [s.stats.snapshot()["outcomes"].get("ok", 0) for s in (sa, sb)]
        assert min(served) >= 3  # round robin over the instances' own keys


def test_local_service_context_for_the_demo():
    from service.local import local_service

    with local_service("unused", loader="service.fake:load_fake_engine") as c:
        lines = segments_with([1.0, 1.0, 2.0, 2.0])
        assert np.allclose(c.localize_segments(lines, CAMERA).cam_from_world, expected_pose(lines))


def test_taken_port_fails_cleanly_without_leaving_workers(service):
    config = fake_config(service.endpoint, workers=1)  # the module's service listens there already
    broken = Service(config)
    with pytest.raises(Exception, match=r"(?i)address|bind|listen|endpoint"):
        broken.start()
    assert broken.pool.alive() == 0
