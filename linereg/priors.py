"""What a caller knows of the pose beforehand, and how it narrows the search.

- a position within ``radius_m`` (GNSS, the last fix): the search region shrinks to that ball's box;
- a whole pose ``cam_from_world`` with ``sigma_rot_deg`` (and a radius or ``sigma_pos_m``): the region is
  that ball, rotation candidates farther than 3 sigma from the prior rotation are dropped, and the prior
  rotation is a candidate itself (a rough camera-LiDAR extrinsic, the previous frame's pose);
- the direction of gravity in the camera frame (an IMU) with ``gravity_sigma_deg``: rotation candidates
  that do not put the map's down (``world_down``, +z up by default) along it are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import MAX_COORDINATE, InvalidInputError, beyond_bound
from .geometry import camera_center, check_rigid, rotation_error_deg, unit_vector


@dataclass(frozen=True)
class Prior:
    """What is known of the pose beforehand (all optional; world metres, camera frame x right y down z on).

    position: (3,) camera centre within ``radius_m``. cam_from_world: (4, 4) a whole pose, its rotation
    within ``sigma_rot_deg`` (default 5) and its centre within ``radius_m`` (default 3 x ``sigma_pos_m``);
    a rotation written to a few digits is taken as the nearest rotation (``geometry.check_rigid``).
    gravity: (3,) direction of gravity (down) in the camera frame, within ``gravity_sigma_deg``; world_down:
    the map's down direction (default (0, 0, -1): z up).
    """

    position: np.ndarray | None = None
    radius_m: float | None = None
    cam_from_world: np.ndarray | None = None
    sigma_rot_deg: float | None = None
    sigma_pos_m: float | None = None
    gravity: np.ndarray | None = None
    gravity_sigma_deg: float = 5.0
    world_down: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.cam_from_world is not None:
            T = check_rigid(self.cam_from_world, "prior cam_from_world")
            object.__setattr__(self, "cam_from_world", T)
            if self.position is None:
                object.__setattr__(self, "position", camera_center(T))
            if self.radius_m is None and self.sigma_pos_m is not None:
                object.__setattr__(self, "radius_m", 3.0 * float(self.sigma_pos_m))
            if self.sigma_rot_deg is None:
                object.__setattr__(self, "sigma_rot_deg", 5.0)
        elif self.sigma_rot_deg is not None:
            raise InvalidInputError("prior sigma_rot_deg needs cam_from_world (a rotation to be near)")
        if self.position is not None:
            p = np.asarray(self.position, dtype=np.float64).reshape(-1)
            if p.shape != (3,) or not np.isfinite(p).all() or beyond_bound(p) is not None:
                raise InvalidInputError(
                    f"prior position must be 3 finite numbers within +-{MAX_COORDINATE:g} m"
                )
            object.__setattr__(self, "position", p)
            if self.radius_m is None:
                raise InvalidInputError("prior position needs radius_m (or cam_from_world with sigma_pos_m)")
        if self.radius_m is not None and not (np.isfinite(self.radius_m) and self.radius_m > 0):
            raise InvalidInputError(f"prior radius_m must be positive, got {self.radius_m}")
        if self.sigma_rot_deg is not None and not (
            np.isfinite(self.sigma_rot_deg) and self.sigma_rot_deg > 0
        ):
            raise InvalidInputError(f"prior sigma_rot_deg must be positive, got {self.sigma_rot_deg}")
        for name in ("gravity", "world_down"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, _unit3(value, name))
        if not (np.isfinite(self.gravity_sigma_deg) and self.gravity_sigma_deg > 0):
            raise InvalidInputError(f"prior gravity_sigma_deg must be positive, got {self.gravity_sigma_deg}")

    @property
    def down(self) -> np.ndarray:
        """(3,) the map's down direction (world frame)."""
        return self.world_down if self.world_down is not None else np.array([0.0, 0.0, -1.0])

    def to_dict(self) -> dict:
        """Returns the prior as JSON-ready numbers (the fields set; ``from_dict`` reads it back)."""
        out: dict = {}
        if self.cam_from_world is not None:
            out["cam_from_world"] = self.cam_from_world.tolist()
            out["sigma_rot_deg"] = float(self.sigma_rot_deg)  # type: ignore[arg-type]
        elif self.position is not None:
            out["position"] = self.position.tolist()
        if self.radius_m is not None:
            out["radius_m"] = float(self.radius_m)
        if self.gravity is not None:
            out["gravity"] = self.gravity.tolist()
            out["gravity_sigma_deg"] = float(self.gravity_sigma_deg)
        if self.world_down is not None:
            out["world_down"] = self.world_down.tolist()
        return out

    @classmethod
    def from_dict(cls, d: object, source: str = "prior") -> Prior:
        """Returns the Prior of a JSON object: ``position`` + ``radius_m``, or a pose (``cam_from_world``, or
        ``world_from_cam``: the camera's pose in the world, as TUM files and SLAM systems write it) with
        ``sigma_rot_deg`` and ``radius_m`` (or ``sigma_pos_m``), and/or ``gravity`` (camera frame) with
        ``gravity_sigma_deg``, ``world_down``. InvalidInputError naming ``source`` and the key otherwise."""
        if not isinstance(d, dict):
            raise InvalidInputError(f"{source}: a prior must be a JSON object, got {type(d).__name__}")
        unknown = sorted(set(d) - PRIOR_KEYS)
        if unknown:
            raise InvalidInputError(
                f"{source}: unknown prior key(s) {', '.join(map(repr, unknown))} "
                f"(known: {', '.join(sorted(PRIOR_KEYS))})"
            )
        if "cam_from_world" in d and "world_from_cam" in d:
            raise InvalidInputError(f"{source}: give cam_from_world or world_from_cam, not both")
        fields = dict(d)
        if "world_from_cam" in fields:
            from .geometry import invert

            fields["cam_from_world"] = invert(
                check_rigid(fields.pop("world_from_cam"), f"{source}: world_from_cam")
            )
        if fields.get("cam_from_world") is not None and fields.get("position") is not None:
            raise InvalidInputError(
                f"{source}: give a position or a pose, not both (a pose holds its position)"
            )
        for key in ("radius_m", "sigma_rot_deg", "sigma_pos_m", "gravity_sigma_deg"):
            value = fields.get(key)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int | float)):
                raise InvalidInputError(f"{source}: {key} must be a number, got {value!r}")
        try:
            return cls(**fields)
        except InvalidInputError as e:
            raise InvalidInputError(f"{source}: {e}") from None


PRIOR_KEYS = frozenset(
    {"position", "radius_m", "cam_from_world", "world_from_cam", "sigma_rot_deg", "sigma_pos_m", "gravity",
     "gravity_sigma_deg", "world_down"}
)  # fmt: skip


def _unit3(value: object, name: str) -> np.ndarray:
    """Returns ``value`` as a (3,) unit vector (``geometry.unit_vector``)."""
    v = np.asarray(value, dtype=np.float64).reshape(-1)
    if v.shape != (3,) or not np.isfinite(v).all() or not np.abs(v).max() > 0:
        raise InvalidInputError(f"prior {name} must be 3 finite numbers, not all zero")
    return unit_vector(v)


def admits(prior: Prior | None, R: np.ndarray) -> bool:
    """Returns True if the world -> camera rotation R (3, 3) agrees with the prior's rotation and gravity."""
    if prior is None:
        return True
    if prior.cam_from_world is not None and prior.sigma_rot_deg is not None:
        if rotation_error_deg(R, prior.cam_from_world[:3, :3]) > 3.0 * prior.sigma_rot_deg:
            return False
    if prior.gravity is not None:
        angle = np.degrees(np.arccos(np.clip(float((R @ prior.down) @ prior.gravity), -1.0, 1.0)))
        if angle > 3.0 * prior.gravity_sigma_deg:
            return False
    return True


def admits_pose(prior: Prior | None, cam_from_world: np.ndarray) -> bool:
    """Returns True if a (4, 4) pose lies where the prior allows: its rotation admitted (``admits``) and its
    centre within the prior's ball (a pose the search or a refinement carried out of it is not an answer
    the prior allows, nor a rival to one)."""
    if prior is None:
        return True
    if not admits(prior, cam_from_world[:3, :3]):
        return False
    if prior.position is None or prior.radius_m is None:
        return True
    return float(np.linalg.norm(camera_center(cam_from_world) - prior.position)) <= prior.radius_m


def search_region(
    lines3d: np.ndarray, prior: Prior | None, margin_fraction: float
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((3,) low, (3,) high) corners of the camera centres to search: the map's bounding box grown
    by ``margin_fraction`` of its largest extent (photos are taken from outside a mapped building as well as
    inside a mapped room), cut to the prior's ball where one is given. A ball wider than the box does not
    widen the search (it would only coarsen its grid); a ball wholly outside the box is searched as it is (a
    photo of the map from farther away)."""
    ends = lines3d.reshape(-1, 3)
    lo, hi = ends.min(axis=0), ends.max(axis=0)
    margin = margin_fraction * float(np.max(hi - lo))
    lo, hi = lo - margin, hi + margin
    if prior is None or prior.position is None or prior.radius_m is None:
        return lo, hi
    ball_lo, ball_hi = prior.position - prior.radius_m, prior.position + prior.radius_m
    cut_lo, cut_hi = np.maximum(lo, ball_lo), np.minimum(hi, ball_hi)
    if np.any(cut_lo >= cut_hi):
        return ball_lo, ball_hi
    return cut_lo, cut_hi
