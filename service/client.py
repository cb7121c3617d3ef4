"""Python client: ``Client(connect=...).localize(image, camera) -> linereg.Registration`` over zenoh.

with Client(connect="tcp/127.0.0.1:7447") as client:
    reg = client.localize(image, camera, timeout=5.0)   # image: (H, W[, C]) uint8 array, path or PNG/JPEG bytes
    with client.open_session(camera) as session:         # live tracking: one tracker in the service
        for frame, odometry in stream:                   # frame: an image or (N, 4) float64 segments
            reg = session.step(frame, relative_pose=odometry)   # session.event: tracked, relocalized, ...
"""

from __future__ import annotations

import itertools
import os
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np
import zenoh

import protocols
from linereg.camera import Camera
from linereg.errors import InvalidInputError, LineregError
from linereg.registration import Registration
from protocols import LocalizeRequest, keys, session
from protocols.images import JPEG_MAGIC, PNG_MAGIC

from .zconfig import DEFAULT_ENDPOINT, session_config

RETRYABLE = ("busy", "timeout", "internal")


class ServiceError(LineregError):
    """The service answered with an Error (``code`` from protocols.ERROR_CODES) or did not answer."""

    def __init__(self, code: str, message: str):
        super().__init__(f"{code}: {message}")
        self.code, self.message = code, message


class Client:
    """A zenoh session to a linereg service; ``map_name`` None = the only map being served.

    ``connect``: router endpoint(s), default the config file's or tcp/127.0.0.1:7447; ``config_file``: a
    zenoh json5 file (TLS, credentials); ``balance``: send each request to one live instance's own key in turn (replicas); ``wait_s``: keep
    trying to connect this long (a router that is starting); ``retries``: localize again (on the next
    instance with ``balance``) after ``busy``, ``timeout`` or ``internal``.
    """

    def __init__(
        self,
        connect: str | Sequence[str] | None = None,
        map_name: str | None = None,
        config_file: str | None = None,
        mode: str | None = "client",
        balance: bool = False,
        wait_s: float = 0.0,
        retries: int = 0,
    ) -> None:
        if connect is None:  # the config file's endpoints, else the default local router
            connect = () if config_file else DEFAULT_ENDPOINT
        endpoints = [connect] if isinstance(connect, str) else list(connect)
        self.session = _open_retrying(
            session_config(mode, connect=endpoints, config_file=config_file), wait_s
        )
        self._map_name = map_name
        self.balance = balance  # spread requests over the instances' own keys (replicas)
        self.retries = retries
        self._ids = itertools.count()
        self._prefix = f"{os.getpid()}-{uuid.uuid4().hex[:6]}"
        self._instances: itertools.cycle | None = None
        self._opened = itertools.count()  # tracking sessions opened: spread over the instances

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.session.close()

    @property
    def map_name(self) -> str:
        """Returns the map queried: the one given, or the only one alive."""
        if self._map_name is None:
            maps = sorted({m for m, _ in self.instances()})
            if not maps:
                raise ServiceError("not_found", "no service for any map (no live linereg instance)")
            if len(maps) > 1:
                raise ServiceError(
                    "not_found", f"several maps are served ({', '.join(maps)}); choose one (--map)"
                )
            self._map_name = maps[0]
        return self._map_name

    def check_served(self, timeout: float = 1.0) -> list[str]:
        """Returns the instances serving ``map_name`` (liveliness tokens, answered at once by the router).

        ServiceError("not_found") when there is none: a query would only wait for its timeout.
        """
        name = self.map_name
        found = [instance for _, instance in self.instances(name, timeout)]
        if not found:
            served = sorted({m for m, _ in self.instances("*", timeout)})
            others = f"; served: {', '.join(served)}" if served else ""
            raise ServiceError("not_found", f"no service for map {name!r}{others}")
        return found

    def instances(self, map_name: str = "*", timeout: float = 2.0) -> list[tuple[str, str]]:
        """Returns the (map, instance) pairs whose liveliness tokens are alive."""
        found = []
        for reply in self.session.liveliness().get(keys.alive_selector(map_name), timeout=timeout):
            if reply.ok is not None:
                found.append(keys.instance_of_alive_key(str(reply.ok.key_expr)))
        return sorted(found)

    def localize(
        self, image, camera: Camera, prior=None, timeout: float = 10.0, return_matches: bool = True
    ) -> Registration:
        """Returns the Registration of ``image`` ((H, W[, C]) uint8 array, PNG/JPEG bytes or a file path)."""
        data, fmt = encode_image(image)
        req = LocalizeRequest(self._next_id(), camera, data, fmt, None, wire_prior(prior),
                              _deadline_ms(timeout), return_matches)  # fmt: skip
        return self._localize(req, timeout)

    def localize_segments(self, lines2d, camera: Camera, prior=None, timeout: float = 10.0) -> Registration:
        """Returns the Registration of (N, 4) float64 pixel segments detected by the caller."""
        lines2d = np.asarray(lines2d, dtype=np.float64)
        req = LocalizeRequest(
            self._next_id(), camera, None, "", lines2d, wire_prior(prior), _deadline_ms(timeout), True
        )
        return self._localize(req, timeout)

    def localize_tiles(self, image, camera: Camera, prior=None, timeout: float = 10.0) -> Registration:
        """Returns the Registration with the most inliers among every tile's answer (map split over instances)."""
        data, fmt = encode_image(image)
        req = LocalizeRequest(
            self._next_id(), camera, data, fmt, None, wire_prior(prior), _deadline_ms(timeout), True
        )
        key = keys.tile_localize_key(self.map_name, "*")
        replies = list(self.session.get(key, payload=protocols.encode_request(req), timeout=timeout))
        answers = [protocols.decode_reply(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
        if not answers:
            errors = [r.err.payload.to_bytes() for r in replies if r.err is not None]
            raise _error_of(errors[0]) if errors else ServiceError("timeout", f"no tile answered on {key}")
        best = max(answers, key=lambda a: (a.success, a.score))
        return best.to_registration()

    def open_session(self, camera: Camera, start=None, timeout: float = 10.0) -> TrackingSession:
        """Returns a tracking session for frames of ``camera`` on one live instance (in turn over them);
        ``start``: a pose prior (``linereg.Prior(cam_from_world=..., sigma_rot_deg=..., sigma_pos_m=...)``)
        where tracking begins, else the first frame is registered globally."""
        instances = self.check_served()
        instance = instances[next(self._opened) % len(instances)]
        msg = protocols.SessionOpen(self._next_id(), camera, None if start is None else wire_prior(start))
        reply = self._ask(
            keys.instance_session_key(self.map_name, instance), session.encode_session_open(msg), timeout
        )
        return TrackingSession(self, session.decode_session_opened(reply))

    def track(self, frames, camera: Camera, relative_poses=None, timestamps=None, start=None,
              timeout: float = 10.0) -> Iterator[Registration]:  # fmt: skip
        """Yields the Registration of each frame through one tracking session (opened and closed here);
        ``relative_poses[k]``: the measured (4, 4) ``cam_k_from_cam_k+1``, K - 1 of them (as in
        ``linereg.localize_sequence``); ``timestamps[k]``: seconds."""
        with self.open_session(camera, start, timeout) as tracking:
            for k, frame in enumerate(frames):
                relative = None if relative_poses is None or k == 0 else relative_poses[k - 1]
                stamp = None if timestamps is None else float(timestamps[k])
                yield tracking.step(frame, relative, stamp, timeout)

    def info(self, timeout: float = 5.0) -> dict:
        """Returns the served map's metadata (name, version, bounds, ...)."""
        return self._document(keys.info_key(self.map_name), timeout)["map"]

    def stats(self, timeout: float = 5.0) -> dict:
        """Returns the service's counters, latency percentiles and queue depth."""
        return self._document(keys.stats_key(self.map_name), timeout)

    def request(self, key: str, payload: bytes, timeout: float) -> tuple[bool, bytes]:
        """Returns (ok, reply bytes) of one raw query; ServiceError("timeout") when nothing came back."""
        for reply in self.session.get(key, payload=payload, timeout=timeout):
            if reply.ok is not None:
                return True, reply.ok.payload.to_bytes()
            if reply.err is not None:
                return False, reply.err.payload.to_bytes()
        raise ServiceError("timeout", f"no reply on {key} within {timeout} s")

    # --- internals -------------------------------------------------------------------------------------

    def _next_id(self) -> str:
        return f"{self._prefix}-{next(self._ids)}"

    def _localize_key(self) -> str:
        if not self.balance:
            return keys.localize_key(self.map_name)
        if self._instances is None:
            self._instances = itertools.cycle([i for _, i in self.instances(self.map_name)] or [None])
        instance = next(self._instances)
        if instance is None:
            return keys.localize_key(self.map_name)
        return keys.instance_localize_key(self.map_name, instance)

    def _localize(self, req: LocalizeRequest, timeout: float) -> Registration:
        # with balance, a retry goes to the next instance
        reply = self._ask(self._localize_key, protocols.encode_request(req), timeout, RETRYABLE)
        return protocols.decode_reply(reply).to_registration()

    def _ask(
        self, key: str | Callable[[], str], payload: bytes, timeout: float, retry_on=("busy", "internal")
    ) -> bytes:
        """Returns the normal reply of a query on ``key`` (or on ``key()`` each attempt), retried up to
        ``retries`` times after an error coded ``retry_on`` (a tracking frame never after ``timeout``: it
        may have been processed); ServiceError otherwise."""
        for attempt in range(self.retries + 1):
            try:
                ok, reply = self.request(key() if callable(key) else key, payload, timeout)
                if ok:
                    return reply
                raise _error_of(reply)
            except ServiceError as e:
                if e.code not in retry_on or attempt == self.retries:
                    raise
        raise AssertionError("unreachable")

    def _document(self, key: str, timeout: float) -> dict:
        ok, payload = self.request(key, b"", timeout)
        if not ok:
            raise _error_of(payload)
        return protocols.unpack(payload)


class TrackingSession:
    """A tracking session in the service (``Client.open_session``): ``step`` like ``linereg.Tracker``'s.

    After each step: ``event`` says how the pose was obtained (initialized, tracked, relocalized,
    predicted, lost), ``restarted`` whether the service had to make the tracker again (its worker was
    lost: this frame was registered globally), ``frames`` how many frames were answered.
    """

    def __init__(self, client: Client, opened: protocols.SessionOpened) -> None:
        self.client, self.id, self.instance = client, opened.session, opened.instance
        self.idle_timeout_s = opened.idle_timeout_s
        self.key = keys.instance_session_key(client.map_name, opened.instance)
        self.event, self.restarted, self.frames = "none", False, 0

    def __enter__(self) -> TrackingSession:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def step(self, frame, relative_pose=None, timestamp: float | None = None, timeout: float = 10.0,
             return_matches: bool = True) -> Registration:  # fmt: skip
        """Returns the Registration of the next frame: (N, 4) float64 segments, or an image ((H, W[, C])
        uint8 array, PNG/JPEG bytes or a path) of the session camera's size; ``relative_pose``: the
        measured (4, 4) ``cam_prev_from_cam_this``; ``timestamp``: seconds, increasing."""
        segments = _segments_or_none(frame)
        image, fmt = (None, "") if segments is not None else encode_image(frame)
        relative = None if relative_pose is None else np.asarray(relative_pose, dtype=np.float64)
        msg = protocols.TrackRequest(self.client._next_id(), self.id, image, fmt, segments, relative,
                                     timestamp, _deadline_ms(timeout), return_matches)  # fmt: skip
        reply = session.decode_track_reply(
            self.client._ask(self.key, session.encode_track_request(msg), timeout)
        )
        self.event, self.restarted, self.frames = reply.how, reply.restarted, reply.frame + 1
        return reply.reply.to_registration()

    def close(self, timeout: float = 5.0) -> int:
        """Closes the session; returns the frames it answered (0 if it had expired already)."""
        msg = protocols.SessionClose(self.client._next_id(), self.id)
        try:
            reply = self.client._ask(self.key, session.encode_session_close(msg), timeout)
        except ServiceError as e:
            if e.code != "unknown_session":
                raise
            return 0
        return session.decode_session_closed(reply).frames


def _segments_or_none(frame) -> np.ndarray | None:
    """Returns ``frame`` as (N, 4) float64 segments if it is a float array of 4 columns, else None (an image)."""
    if isinstance(frame, np.ndarray) and frame.ndim == 2 and frame.shape[1] == 4 and frame.dtype.kind == "f":
        return np.asarray(frame, dtype=np.float64)
    return None


def _deadline_ms(timeout_s: float) -> int:
    """Returns the request deadline for a client timeout: a little shorter, so the service's ``timeout``
    error arrives before zenoh gives up on the query."""
    return max(1, min(120_000, int(timeout_s * 1000 * 0.95)))


def _open_retrying(conf: zenoh.Config, wait_s: float) -> zenoh.Session:
    """Returns an open session, retrying for up to ``wait_s`` seconds while the router is not up yet."""
    end = time.monotonic() + wait_s
    while True:
        try:
            return zenoh.open(conf)
        except zenoh.ZError:
            if time.monotonic() > end:
                raise
            time.sleep(0.1)


def _error_of(payload: bytes) -> ServiceError:
    """Returns the ServiceError of an error reply (zenoh's own ``Timeout`` included)."""
    if payload == b"Timeout":  # zenoh's reply when the query's timeout expires first
        return ServiceError("timeout", "no reply before the timeout")
    try:
        err = protocols.decode_error(payload)
    except protocols.ProtocolError:
        return ServiceError("internal", f"unreadable error reply: {payload[:80]!r}")
    return ServiceError(err.code, err.message)


def encode_image(image) -> tuple[bytes | np.ndarray, str]:
    """Returns (wire image, format): PNG/JPEG bytes as they are, a path's file bytes, an array as PNG."""
    if isinstance(image, str | Path):
        image = Path(image).read_bytes()
    if isinstance(image, bytes | bytearray):
        data = bytes(image)
        if data.startswith(PNG_MAGIC):
            return data, "png"
        if data.startswith(JPEG_MAGIC):
            return data, "jpeg"
        raise LineregError("image bytes are neither PNG nor JPEG")
    import cv2

    ok, buffer = cv2.imencode(".png", np.asarray(image), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise LineregError("image cannot be encoded as PNG")
    return buffer.tobytes(), "png"


def wire_prior(prior) -> protocols.Prior | None:
    """Returns the wire Prior of a library or wire prior (same field names), or None: a pose's radius
    travels as its 3-sigma ``sigma_pos_m`` (the library reads it back as that radius), gravity with its
    sigma. A library prior whose map is not z-up (``world_down``) cannot be sent: the wire has no field
    for it."""
    if prior is None or isinstance(prior, protocols.Prior):
        return prior
    down = getattr(prior, "world_down", None)
    if down is not None and not np.allclose(down, [0.0, 0.0, -1.0]):
        raise InvalidInputError("prior world_down cannot be sent to the service (its maps are z-up)")
    gravity = getattr(prior, "gravity", None)
    gravity = None if gravity is None else np.asarray(gravity, dtype=np.float64)
    gravity_sigma = float(getattr(prior, "gravity_sigma_deg", 5.0))
    if getattr(prior, "cam_from_world", None) is not None:  # a pose prior (its position is derived from it)
        rot_deg = prior.sigma_rot_deg
        sigma_pos = prior.sigma_pos_m if prior.sigma_pos_m is not None else prior.radius_m / 3.0
        return protocols.Prior(
            cam_from_world=np.asarray(prior.cam_from_world, dtype=np.float64),
            sigma_rot_deg=5.0 if rot_deg is None else float(rot_deg),  # None: the library Prior's default
            sigma_pos_m=float(sigma_pos),
            gravity=gravity,
            gravity_sigma_deg=gravity_sigma,
        )
    if getattr(prior, "position", None) is not None:
        return protocols.Prior(
            position=np.asarray(prior.position, dtype=np.float64),
            radius_m=float(prior.radius_m),
            gravity=gravity,
            gravity_sigma_deg=gravity_sigma,
        )
    return protocols.Prior(gravity=gravity, gravity_sigma_deg=gravity_sigma)
