"""Priors for a batch of images from a file (``linereg localize --prior``, ``linereg query --prior``).

Two kinds of file:

- JSON: one prior object for every image (``{"position": [x, y, z], "radius_m": 30}``: a site's GNSS fix;
  ``{"cam_from_world": 4 x 4, "sigma_rot_deg": 5, "radius_m": 0.5}``: a rough camera-LiDAR extrinsic), or
  priors per image as the camera files name them: a dict keyed by the image's path, file name or stem, a
  list of objects with an ``image`` (``file``, ``name``) key, or ``{"images": [...]}``. The keys of a
  prior object are ``Prior.from_dict``'s.
- a TUM trajectory (any other file: ``timestamp tx ty tz qx qy qz qw`` of world_from_cam per line, what
  ``linereg localize --tum`` and SLAM systems write): the row at each image's timestamp (the file stems when
  they are all numbers, else the images' positions 0, 1, 2, ...; within ``MAX_DT_S``), how rough given by
  ``sigma`` (degrees, metres: ``--prior-sigma``).

``sigma`` also fills what a JSON prior leaves out: the rotation sigma of a pose, the radius of a position
or a pose. Every image must find its prior: a batch is checked before its first image is localized.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import FileFormatError, InvalidInputError
from .priors import PRIOR_KEYS, Prior

MAX_DT_S = 0.02  # a TUM row belongs to an image this close in time (the TUM benchmark's association rule)


@dataclass(frozen=True)
class PriorTable:
    """The priors of a file (``read_priors``): ``for_image`` finds an image's."""

    source: str
    shared: Prior | None = None
    by_name: dict[str, Prior] = field(default_factory=dict)
    times: np.ndarray | None = None  # (K,) sorted TUM timestamps, s ...
    by_time: list[Prior] = field(default_factory=list)  # ... and their priors

    def for_image(self, image: str | os.PathLike, timestamp: float | None = None) -> Prior:
        """Returns the prior of an image (path) at ``timestamp`` (s; a TUM file's rows are found by it), or
        raises InvalidInputError naming the file and the image."""
        if self.shared is not None:
            return self.shared
        path = Path(image)
        times = self.times
        if times is not None:
            if timestamp is None or not len(times):
                raise InvalidInputError(f"{self.source}: no timestamp to find the prior of {path.name}")
            k = int(np.searchsorted(times, timestamp))  # the rows either side of it
            near = min(
                (j for j in (k - 1, k) if 0 <= j < len(times)), key=lambda j: abs(float(times[j]) - timestamp)
            )
            if abs(times[near] - timestamp) > MAX_DT_S:
                raise InvalidInputError(
                    f"{self.source}: no pose within {MAX_DT_S} s of {path.name}'s timestamp {timestamp:.6f} "
                    f"(the nearest is {times[near]:.6f})"
                )
            return self.by_time[near]
        for key in (str(path), path.name, path.stem):
            if key in self.by_name:
                return self.by_name[key]
        raise InvalidInputError(f"{self.source}: no prior for image {path.name} (by path, file name or stem)")


def read_priors(path: str | os.PathLike, sigma: tuple[float, float] | None = None) -> PriorTable:
    """Returns the PriorTable of a JSON or TUM file (the module's formats); ``sigma``: (rotation degrees,
    radius metres) for the priors that do not give them (needed for a TUM file)."""
    from .io import IMAGE_KEYS, named_entries, read_tum

    path = Path(path)
    if sigma is not None:
        rot, radius = (float(v) for v in sigma)
        if not (np.isfinite(rot) and rot > 0 and np.isfinite(radius) and radius > 0):
            raise InvalidInputError(f"--prior-sigma must be two positive numbers (deg, m), got {sigma}")
    if path.suffix.lower() != ".json":
        if sigma is None:
            raise InvalidInputError(
                f"{path}: a TUM file of rough poses needs --prior-sigma DEG M (how far the truth may lie "
                "from them: rotation sigma in degrees, radius in metres)"
            )
        times, poses = read_tum(path)
        if len(np.unique(times)) != len(times):
            raise FileFormatError(f"{path}: two poses share a timestamp")
        priors = [Prior(cam_from_world=T, sigma_rot_deg=sigma[0], radius_m=sigma[1]) for T in poses]
        return PriorTable(str(path), times=times, by_time=priors)
    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FileFormatError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise FileFormatError(f"{path}: cannot read: {e}") from None
    except json.JSONDecodeError as e:
        raise FileFormatError(f"{path}: invalid JSON: {e}") from None
    if isinstance(obj, dict) and "images" in obj and not PRIOR_KEYS & set(obj):
        obj = obj["images"]
    if isinstance(obj, dict) and PRIOR_KEYS & set(obj):
        return PriorTable(str(path), shared=_prior(obj, sigma, str(path)))
    if isinstance(obj, list) and obj:
        by_name = {
            name: _prior({k: v for k, v in item.items() if k not in IMAGE_KEYS}, sigma, f"{path}: {name}")
            for name, item in named_entries(obj, path, "prior")
        }
        return PriorTable(str(path), by_name=by_name)
    if isinstance(obj, dict) and obj:
        return PriorTable(
            str(path), by_name={str(k): _prior(v, sigma, f"{path}: {k}") for k, v in obj.items()}
        )
    raise FileFormatError(f"{path}: no prior found (expected position and radius_m, or cam_from_world)")


def _prior(fields: object, sigma: tuple[float, float] | None, source: str) -> Prior:
    """Returns ``Prior.from_dict`` of a JSON object, with ``sigma`` filling a pose's rotation sigma and the
    radius a prior leaves out."""
    if isinstance(fields, dict) and sigma is not None:
        fields = dict(fields)
        pose = fields.get("cam_from_world") is not None or fields.get("world_from_cam") is not None
        if pose and fields.get("sigma_rot_deg") is None:
            fields["sigma_rot_deg"] = float(sigma[0])
        if (pose or fields.get("position") is not None) and (
            fields.get("radius_m") is None and fields.get("sigma_pos_m") is None
        ):
            fields["radius_m"] = float(sigma[1])
    try:
        return Prior.from_dict(fields, source)
    except InvalidInputError as e:
        raise FileFormatError(str(e)) from None
