"""Colour a point cloud from localized photos: every point takes its colour from the photos that see it.

    colors, seen = linereg.colorize(points, photos, camera, cam_from_world)

The steps (``linereg.color``): local spacing and normals from voxel statistics (``surface``); a depth buffer
per photo from the cloud's own point splats (``depth``); exposure / white-balance gains per photo from the
points several photos see (``gains``); every photo's colour at the points it sees, weighted for viewing
angle, range, image border and blur, blended (``blend``). Clouds larger than memory go through
``colorize_file``, chunk by chunk, on any runner of ``linereg.batch`` (a process pool, a Dask cluster).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .camera import Camera
from .color.blend import Photo
from .color.config import ColorizeConfig
from .color.engine import ArraySource, FileSource, Progress, colorize_source
from .errors import FileFormatError, InvalidInputError

__all__ = ["ColorizeConfig", "colorize", "colorize_file", "make_photos", "read_localized_photos"]


def colorize(
    points: np.ndarray,
    photos: Sequence[np.ndarray],
    cameras: Camera | Sequence[Camera],
    cam_from_world: np.ndarray,
    config: ColorizeConfig | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((P, 3) uint8 RGB colours, (P,) int64 number of photos that coloured each point).

    points: (P, 3) float64 world; photos: K images, (H, W, 3) uint8 BGR (as ``linereg.io.read_image``
    reads them) or (H, W) grey; cameras: one shared Camera or K; cam_from_world: (K, 4, 4) float64.
    A point no photo sees has count 0 and colour (0, 0, 0): no colour, not black.
    """
    config = config or ColorizeConfig()
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidInputError(f"points must be (P, 3), got shape {points.shape}")
    if len(points) == 0:
        raise InvalidInputError("points: the cloud holds no points")
    views = make_photos(photos, cameras, cam_from_world)
    colors = np.zeros((len(points), 3), dtype=np.uint8)
    seen = np.zeros(len(points), dtype=np.int64)
    for start, stop, rgb, count in colorize_source(ArraySource(points), views, config):
        colors[start:stop], seen[start:stop] = rgb, count
    return colors, seen


def colorize_file(
    cloud: str | os.PathLike,
    out: str | os.PathLike,
    photos: list[Photo],
    config: ColorizeConfig | None = None,
    run=None,
    progress: Progress | None = None,
) -> np.ndarray:
    """Writes the coloured ``cloud`` file to ``out`` (.ply / .las / .laz, atomically), chunk by chunk, and
    returns (K + 1,) int64: how many points 0, 1, ..., K photos coloured.

    Memory stays bounded whatever the cloud's size: a chunk, the photos and their depth buffers. ``run``: a
    runner of ``linereg.batch`` (default: this process); workers read the cloud file themselves.

    With a local process pool, a script must keep its work under ``if __name__ == "__main__":``: the
    workers start clean (``batch.runner(workers, fork=False)``, as ``linereg colorize`` does; a worker
    forked after OpenCV's thread pool ran can hang), and a clean worker imports the script that started
    it again. Without the guard it runs the script anew and the pool breaks (``BrokenProcessPool``)::

        if __name__ == "__main__":
            photos = read_localized_photos("poses.json", "camera.json")
            with batch.runner(workers=2, fork=False) as run:
                colorize_file("scan.laz", "scan_rgb.laz", photos, run=run)

    The CLI (``linereg colorize``, ``python -m linereg colorize``) needs nothing.
    """
    from . import io

    config = config or ColorizeConfig()
    out = Path(out)
    histogram = np.zeros(len(photos) + 1, dtype=np.int64)
    with io.open_cloud(cloud) as reader:
        source = FileSource(str(Path(cloud).resolve()), reader.num_points)
        bounds = _bounds(reader, config.chunk_points) if out.suffix.lower() in (".las", ".laz") else None
        las_in = reader.las is not None
        with io.ColoredCloudWriter(out, reader.num_points, reader, bounds) as writer:
            for start, stop, rgb, count in colorize_source(source, photos, config, run, progress):
                records = reader.read_records(start, stop) if las_in else None
                points = reader.read(start, stop) if records is None else _xyz(records)
                writer.write(points, rgb, count, records)
                histogram += np.bincount(np.minimum(count, len(photos)), minlength=len(photos) + 1)
    return histogram


def make_photos(
    photos: Sequence[np.ndarray], cameras: Camera | Sequence[Camera], cam_from_world: np.ndarray
) -> list[Photo]:
    """Returns the checked Photos: one camera per photo, poses (K, 4, 4) finite, images of the camera's size."""
    cam_from_world = np.asarray(cam_from_world, dtype=np.float64).reshape(-1, 4, 4)
    k = len(photos)
    if len(cam_from_world) != k:
        raise InvalidInputError(f"cam_from_world: {len(cam_from_world)} poses for {k} photos")
    if not np.isfinite(cam_from_world).all():
        raise InvalidInputError("cam_from_world: poses must be finite")
    cams = [cameras] * k if isinstance(cameras, Camera) else list(cameras)
    if len(cams) != k:
        raise InvalidInputError(f"cameras: {len(cams)} cameras for {k} photos")
    out = []
    for i, (image, camera, pose) in enumerate(zip(photos, cams, cam_from_world, strict=True)):
        image = np.asarray(image)
        if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
            raise InvalidInputError(
                f"photos[{i}]: expected (H, W, 3) or (H, W) uint8, got {image.dtype} {image.shape}"
            )
        if image.shape[:2] != (camera.height, camera.width):
            raise InvalidInputError(
                f"photos[{i}]: {image.shape[1]}x{image.shape[0]} px, its camera is {camera.width}x{camera.height}"
            )
        out.append(Photo(image, camera, pose))
    return out


def read_localized_photos(
    poses_path: str | os.PathLike, camera_path: str | os.PathLike, images_dir: str | os.PathLike | None = None
) -> list[Photo]:
    """Returns the Photos of the successful records of a ``linereg localize --out`` file.

    A record's key is its image path; with ``images_dir`` the image is that folder's file of the same name,
    else the path as written (relative: to the working directory, then to the pose file's folder).
    Cameras come from ``camera_path`` as ``linereg localize`` reads it. Raises a LineregError naming the
    file at fault: the pose file (malformed, no successful pose, photos missing), the camera file (no
    camera for a photo), a photo (unreadable, another size than its camera).
    """
    from . import io

    poses_path = Path(poses_path)
    records = io.read_json(poses_path)
    if not isinstance(records, dict):
        raise FileFormatError(
            f"{poses_path}: expected an object image -> result (as `linereg localize` writes)"
        )
    chosen: list[tuple[Path, np.ndarray]] = []
    for name, record in records.items():
        if not isinstance(record, dict) or "success" not in record:
            raise FileFormatError(f"{poses_path}: the entry of {name} is not a localization result")
        if record["success"]:
            pose = np.asarray(record.get("cam_from_world"), dtype=np.float64)
            if pose.shape != (4, 4) or not np.isfinite(pose).all():
                raise FileFormatError(f"{poses_path}: {name}: cam_from_world is not a finite 4x4 matrix")
            chosen.append((_photo_path(name, poses_path, images_dir), pose))
    if not chosen:
        raise InvalidInputError(f"{poses_path}: no successfully localized photo to colour with")
    missing = [str(path) for path, _ in chosen if not path.is_file()]
    if missing:
        more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
        raise InvalidInputError(f"{poses_path}: photo(s) not found: {', '.join(missing[:5])}{more}")
    cameras = io.read_cameras(camera_path)
    photos = []
    for path, pose in chosen:
        camera = io.camera_for_image(cameras, path, camera_path)
        image = _as_uint8(io.read_image(path), path)
        if image.shape[:2] != (camera.height, camera.width):
            raise InvalidInputError(
                f"{path}: {image.shape[1]}x{image.shape[0]} px, but {camera_path} gives its camera "
                f"{camera.width}x{camera.height}"
            )
        photos.append(Photo(image, camera, pose))
    return photos


def _photo_path(name: str, poses_path: Path, images_dir: str | os.PathLike | None) -> Path:
    if images_dir is not None:
        return Path(images_dir) / Path(name).name
    path = Path(name)
    if path.is_absolute() or path.exists():
        return path
    return poses_path.parent / path


def _as_uint8(image: np.ndarray, path: Path) -> np.ndarray:
    """Returns an image as (H, W, 3) uint8 BGR or (H, W) uint8 grey: 16 bit scaled, alpha dropped."""
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    if image.dtype != np.uint8:
        raise FileFormatError(f"{path}: {image.dtype} pixels; photos must be 8 or 16 bit")
    if image.ndim == 3 and image.shape[2] == 4:
        image = np.ascontiguousarray(image[:, :, :3])
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    return image


def _bounds(reader, chunk_points: int) -> np.ndarray:
    """Returns (2, 3) min / max of the finite points (the LAS header's for a LAS source, else a pass)."""
    if reader.las is not None:
        return np.array([reader.las.header.mins, reader.las.header.maxs], dtype=np.float64)
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for start in range(0, reader.num_points, chunk_points):
        points = reader.read(start, min(start + chunk_points, reader.num_points))
        points = points[np.isfinite(points).all(axis=1)]
        if len(points):
            lo, hi = np.minimum(lo, points.min(axis=0)), np.maximum(hi, points.max(axis=0))
    return np.array([lo, hi]) if np.isfinite(lo).all() else np.zeros((2, 3))


def _xyz(records) -> np.ndarray:
    return np.stack([np.asarray(records.x), np.asarray(records.y), np.asarray(records.z)], axis=1)
