"""Every file linereg reads or writes: point clouds, images, camera files, JSON / TUM results.

Readers raise ``FileFormatError`` naming the file and the problem; writers are atomic (a temporary file
in the same directory, then ``os.replace``), so a killed batch never leaves a half-written result.
"""

from __future__ import annotations

import json
import logging
import math
import os
import tempfile
import warnings
from collections.abc import Iterable, Sequence
from contextlib import nullcontext
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from .camera import Camera
from .errors import FileFormatError, InvalidInputError

logger = logging.getLogger(__name__)

CLOUD_SUFFIXES = (".ply", ".pcd", ".xyz", ".txt", ".las", ".laz", ".e57")

# COLMAP camera models -> (parameter names, dist from params); COLMAP's distortion order matches OpenCV's
_COLMAP_MODELS = {
    "SIMPLE_PINHOLE": (("f", "cx", "cy"), lambda p: ()),
    "PINHOLE": (("fx", "fy", "cx", "cy"), lambda p: ()),
    "SIMPLE_RADIAL": (("f", "cx", "cy", "k"), lambda p: (p["k"], 0.0, 0.0, 0.0)),
    "RADIAL": (("f", "cx", "cy", "k1", "k2"), lambda p: (p["k1"], p["k2"], 0.0, 0.0)),
    "OPENCV": (
        ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
        lambda p: (p["k1"], p["k2"], p["p1"], p["p2"]),
    ),
}


# ---------------------------------------------------------------------------------------------- clouds


def read_cloud(path: str | os.PathLike) -> np.ndarray:
    """Returns the (P, 3) float64 points of a .ply, .pcd, .xyz / .txt, .las / .laz or .e57 file."""
    return _read(Path(path), with_intensity=False)[0]


def read_cloud_intensity(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Returns ((P, 3) float64 points, (P,) float64 their intensity or None when the file has none) of a
    cloud file (``read_cloud``'s formats): a PLY or PCD ``intensity`` property, LAS intensity, an E57
    ``intensity`` field, the fourth of a text file's four columns (x y z i)."""
    points, intensity, _ = _read(Path(path), with_intensity=True)
    return points, intensity


# a per-point laser number, as LiDAR drivers name it (Velodyne, Ouster, Hesai, RoboSense: ``ring``)
RING_FIELDS = ("ring", "laser_id", "laser_number")


class CloudFields(NamedTuple):
    """A cloud file's (P, 3) float64 ``points`` and, where asked for and present, (P,) float64
    ``intensity`` and (P,) int64 ``rings`` (each point's laser number, -1: none; ``RING_FIELDS``)."""

    points: np.ndarray
    intensity: np.ndarray | None
    rings: np.ndarray | None


def read_cloud_fields(path: str | os.PathLike, intensity: bool = False, rings: bool = True) -> CloudFields:
    """Returns a cloud file's CloudFields (``read_cloud``'s formats): the intensity as
    ``read_cloud_intensity`` reads it, when asked; the rings from a binary or ASCII PLY's, a PCD's or a
    LAS extra dimension's ``ring`` (or ``laser_id``, ``laser_number``) property, when asked and present
    (None: the file has none; E57 and text files hold none)."""
    return CloudFields(*_read(Path(path), with_intensity=intensity, with_rings=rings))


def _read(
    path: Path, with_intensity: bool, with_rings: bool = False
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    suffix = path.suffix.lower()
    if suffix not in CLOUD_SUFFIXES:
        raise FileFormatError(
            f"{path}: unsupported point cloud format {suffix!r}; use {', '.join(CLOUD_SUFFIXES)}"
        )
    _check_readable(path)
    reader = {".ply": _read_open3d, ".pcd": _read_open3d, ".xyz": _read_text, ".txt": _read_text}.get(suffix)
    reader = reader or {".las": _read_las, ".laz": _read_las, ".e57": _read_e57}[suffix]
    try:
        points, intensity, rings = reader(path, with_intensity, with_rings)
    except FileFormatError:
        raise
    except Exception as e:  # each library has its own exceptions for a corrupt file
        raise FileFormatError(f"{path}: cannot read point cloud: {e}") from None
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if intensity is not None:
        intensity = np.asarray(intensity, dtype=np.float64).reshape(-1)
        if len(intensity) != len(points):
            raise FileFormatError(f"{path}: {len(intensity)} intensities for {len(points)} points")
    if rings is not None:
        rings = np.asarray(rings).reshape(-1)
        if len(rings) != len(points):
            raise FileFormatError(f"{path}: {len(rings)} ring values for {len(points)} points")
    if len(points) == 0:
        raise FileFormatError(f"{path}: the point cloud holds no points (empty or corrupt file)")
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():
        logger.warning("%s: dropped %d points with NaN or inf coordinates", path, int((~finite).sum()))
        points = points[finite]
        intensity = None if intensity is None else intensity[finite]
        rings = None if rings is None else rings[finite]
    if rings is not None:
        from .map.build import laser_numbers

        try:
            rings = laser_numbers(rings, len(points))
        except InvalidInputError as e:
            raise FileFormatError(f"{path}: its ring field: {e}") from None
    logger.info("%s: %d points", path, len(points))
    return points, intensity, rings


def _ascii_ply_rings(path: Path) -> np.ndarray | None:
    """Returns the ring property of an ASCII PLY whose first element is its vertices, None if it has none."""
    with open(path, "rb") as f:
        words: list[list[str]] = []
        while not words or words[-1] != ["end_header"]:
            line = f.readline()
            if not line:
                return None
            words.append(line.decode("ascii", "replace").split())
        if len(words) < 2 or words[1][:2] != ["format", "ascii"]:
            return None
        elements = [w for w in words if w[:1] == ["element"]]
        if not elements or elements[0][1] != "vertex":
            return None
        props = []
        for w in words[words.index(elements[0]) + 1 :]:
            if w[:1] != ["property"] or w[1] == "list":
                break
            props.append(w[-1])
        name = _ring_name(props)
        if name is None:
            return None
        rows = np.loadtxt(f, max_rows=int(elements[0][2]), usecols=props.index(name), ndmin=1)
    return rows


def read_sensor_origin(path: str | os.PathLike) -> np.ndarray | None:
    """Returns (3,) where the scanner stood, in the cloud's frame, when the file says so, else None: a PCD
    header's ``VIEWPOINT`` (the default identity viewpoint says nothing), an E57 file of one scan (its
    pose's translation; a file of several scans has several origins). PLY, LAS and text files hold none."""
    path = Path(path)
    _check_readable(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".pcd":
            return _pcd_viewpoint(path)
        if suffix == ".e57":
            import pye57

            e57 = pye57.E57(str(path))
            try:
                if e57.scan_count != 1:
                    return None
                return np.asarray(e57.scan_position(0), dtype=np.float64).reshape(3)
            finally:
                e57.close()
    except FileFormatError:
        raise
    except Exception as e:  # a corrupt header
        raise FileFormatError(f"{path}: cannot read the scanner position: {e}") from None
    return None


def _pcd_viewpoint(path: Path) -> np.ndarray | None:
    """Returns the translation of a PCD header's VIEWPOINT (tx ty tz qw qx qy qz), None if absent or the
    default (0 0 0 1 0 0 0)."""
    with open(path, "rb") as f:
        for _ in range(64):  # a PCD header is a dozen lines, ended by DATA
            line = f.readline()
            words = line.decode("ascii", "replace").split()
            if not line or words[:1] == ["DATA"]:
                return None
            if words[:1] == ["VIEWPOINT"]:
                values = np.array([float(w) for w in words[1:8]])
                if len(values) != 7 or not np.isfinite(values).all():
                    raise FileFormatError(f"{path}: a PCD VIEWPOINT needs 7 numbers, got {words[1:]}")
                default = np.array([0.0, 0, 0, 1, 0, 0, 0])
                return None if np.array_equal(values, default) else values[:3]
    return None


def _check_readable(path: Path) -> None:
    if not path.exists():
        raise FileFormatError(f"{path}: no such file")
    if path.is_dir():
        raise FileFormatError(f"{path}: is a directory, not a file")
    if not path.is_file():
        raise FileFormatError(f"{path}: not a file")
    if not os.access(path, os.R_OK):
        raise FileFormatError(f"{path}: not readable (permission denied)")
    if path.stat().st_size == 0:
        raise FileFormatError(f"{path}: empty file")


def _read_open3d(
    path: Path, with_intensity: bool, with_rings: bool
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    from ._open3d import open3d

    o3d = open3d()
    ply = path.suffix.lower() == ".ply"
    expected = _ply_vertex_count(path) if ply else None
    layout = _ply_layout(path) if ply else None
    ring = _ring_name(layout[0].names or ()) if layout is not None else None
    # the tensor reader keeps every property (the legacy cloud holds no intensity) but skips a PLY's ushort
    # ring with a warning: that one is read from the file's records below
    tensor = with_intensity or (with_rings and not ply)
    quiet = o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error) if ring else nullcontext()
    # open3d reports a corrupt file on stderr and returns an empty or partial cloud: checked here and by the caller
    intensity = rings = None
    with quiet:
        if tensor:
            attributes = o3d.t.io.read_point_cloud(str(path), remove_nan_points=False).point
            has = "positions" in attributes
            points = attributes["positions"].numpy().astype(np.float64) if has else np.zeros((0, 3))
            if with_intensity and "intensity" in attributes:
                intensity = attributes["intensity"].numpy().astype(np.float64).reshape(-1)
            if with_rings and not ply and (name := _ring_name(list(attributes))) is not None:
                rings = attributes[name].numpy().reshape(-1)
        else:
            cloud = o3d.io.read_point_cloud(str(path), format="auto", remove_nan_points=False)
            points = np.asarray(cloud.points, dtype=np.float64)
    if expected is not None and len(points) != expected:
        raise FileFormatError(f"{path}: corrupt PLY: header declares {expected} vertices, read {len(points)}")
    if with_rings and ply:
        if layout is None:
            rings = _ascii_ply_rings(path)
        elif ring is not None:
            dtype, offset, count = layout
            rings = np.array(np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=(count,))[ring])
    return points, intensity, rings


def _ring_name(names: Sequence[str]) -> str | None:
    """Returns the first of ``RING_FIELDS`` among a file's property names, None if none is."""
    return next((n for n in RING_FIELDS if n in names), None)


_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2}
_PLY_SIZES |= {"int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4}
_PLY_SIZES |= {"double": 8, "float64": 8}


def _ply_vertex_count(path: Path) -> int:
    """Returns the vertex count a PLY header declares, after checking x/y/z exist and a binary body fits."""
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise FileFormatError(f"{path}: not a PLY file (no 'ply' magic)")
        header, count, element, props, row = [], 0, None, set(), 0
        for _ in range(10_000):
            line = f.readline()
            if not line:
                raise FileFormatError(f"{path}: corrupt PLY: the header has no end_header")
            words = line.decode("ascii", "replace").split()
            header.append(words)
            if words[:1] == ["end_header"]:
                break
            if words[:1] == ["element"] and len(words) == 3:
                element = words[1]
                if element == "vertex":
                    count = int(words[2])
            elif words[:1] == ["property"] and element == "vertex" and len(words) >= 3:
                props.add(words[-1])
                row += _PLY_SIZES.get(words[1], 0) if words[1] != "list" else 0
        body = os.path.getsize(path) - f.tell()
    if not {"x", "y", "z"} <= props:
        raise FileFormatError(f"{path}: PLY vertices lack x, y, z properties (found {sorted(props)})")
    binary = any(
        w[:2] == ["format", "binary_little_endian"] or w[:2] == ["format", "binary_big_endian"]
        for w in header
    )
    if binary and row and body < count * row:
        raise FileFormatError(
            f"{path}: truncated PLY: {count} vertices need {count * row} bytes, {body} present"
        )
    return count


def _read_text(
    path: Path, with_intensity: bool, with_rings: bool
) -> tuple[np.ndarray, np.ndarray | None, None]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "input contained no data": reported as empty below
        if with_intensity:  # x y z i: exactly four columns (six are x y z r g b)
            for delimiter in (None, ","):
                try:
                    rows = np.loadtxt(path, comments=("#", "//"), ndmin=2, delimiter=delimiter)
                except ValueError:
                    continue
                if rows.shape[1] >= 3:  # read once: the points are its first three columns either way
                    return rows[:, :3], rows[:, 3] if rows.shape[1] == 4 else None, None
                break
        try:
            points = np.loadtxt(path, comments=("#", "//"), usecols=(0, 1, 2), ndmin=2, dtype=np.float64)
        except ValueError:  # comma-separated
            points = np.loadtxt(path, comments=("#", "//"), usecols=(0, 1, 2), ndmin=2, delimiter=",")
        return points, None, None


def _read_las(
    path: Path, with_intensity: bool, with_rings: bool
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    import laspy

    if path.suffix.lower() == ".laz" and not laspy.LazBackend.detect_available():
        raise FileFormatError(
            f"{path}: reading .laz needs a LAZ backend for laspy; install one: pip install 'laspy[lazrs]'"
        )
    las = laspy.read(path)
    points = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1)
    intensity = np.asarray(las.intensity, dtype=np.float64) if with_intensity else None
    names = {n.lower(): n for n in las.point_format.dimension_names}  # an extra dimension's, any case
    ring = _ring_name(list(names)) if with_rings else None
    return points, intensity, None if ring is None else np.asarray(las[names[ring]])


def _read_e57(
    path: Path, with_intensity: bool, with_rings: bool
) -> tuple[np.ndarray, np.ndarray | None, None]:
    import pye57

    e57 = pye57.E57(str(path))
    try:
        scans, values = [], []
        for i in range(e57.scan_count):
            # transform=True applies each scan's pose: every scan lands in the common (world) frame
            data = e57.read_scan(i, intensity=with_intensity, transform=True, ignore_missing_fields=True)
            scans.append(np.stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]], axis=1))
            value = data.get("intensity") if with_intensity else None
            values.append(None if value is None else np.asarray(value, dtype=np.float64).reshape(-1))
    finally:
        e57.close()
    points = np.concatenate(scans) if scans else np.zeros((0, 3))
    # every scan must carry it, or the cloud has none
    have = bool(values) and all(
        v is not None and len(v) == len(p) for v, p in zip(values, scans, strict=True)
    )
    intensity = np.concatenate([v for v in values if v is not None]) if have else None
    return points, intensity, None  # a terrestrial scanner's: no laser rings


# ---------------------------------------------------------------------------------------------- images


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Returns the image as stored (cv2.IMREAD_UNCHANGED: (H, W) or (H, W, C), uint8 or uint16; BGR)."""
    import cv2

    path = Path(path)
    _check_readable(path)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise FileFormatError(f"{path}: cannot read image (unsupported or corrupt)")
    return image


def write_image_atomic(path: str | os.PathLike, image: np.ndarray) -> None:
    """Writes an image, format by suffix (.png, .jpg, ...), atomically."""
    import cv2

    path = Path(path)
    ok, encoded = cv2.imencode(path.suffix or ".png", np.asarray(image))
    if not ok:
        raise InvalidInputError(f"{path}: cannot encode the image as {path.suffix!r}")
    write_bytes_atomic(path, encoded.tobytes())


# ---------------------------------------------------------------------------------------------- cameras


def read_cameras(path: str | os.PathLike) -> dict[str, Camera] | Camera:
    """Returns one shared Camera, or a dict image name (COLMAP: camera id) -> Camera.

    JSON: ``{fx, fy, cx, cy, width, height[, dist]}`` (shared), a list of such with ``file`` / ``image`` /
    ``name`` keys, a dict keyed by image name, or ``{"images": [...]}`` (shared/data cameras.json).
    COLMAP ``cameras.txt``: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV; one camera -> Camera.
    """
    path = Path(path)
    _check_readable(path)
    text = _read_text_file(path)
    if path.suffix.lower() == ".json":
        try:
            obj = json.loads(text)
        except json.JSONDecodeError as e:
            raise FileFormatError(f"{path}: invalid JSON: {e}") from None
        return _cameras_from_json(obj, path)
    cameras = _cameras_from_colmap(text, path)
    return next(iter(cameras.values())) if len(cameras) == 1 else cameras


def camera_for_image(
    cameras: dict[str, Camera] | Camera, image: str | os.PathLike, source: str | os.PathLike = "cameras"
) -> Camera:
    """Returns the camera of one image: the shared one, else the entry keyed by its path, name or stem.

    cameras: what ``read_cameras`` returned for the file ``source`` (named in the error if none fits).
    """
    if isinstance(cameras, Camera):
        return cameras
    image = Path(image)
    for key in (str(image), image.name, image.stem):
        if key in cameras:
            return cameras[key]
    raise InvalidInputError(f"{source}: no camera for image {image.name}")


def _read_text_file(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise FileFormatError(f"{path}: cannot read: {e}") from None


def _camera(d: Any, source: str) -> Camera:
    if not isinstance(d, dict):
        raise FileFormatError(f"{source}: expected a camera object, got {type(d).__name__}")
    try:
        return Camera.from_dict(d, source=source)
    except InvalidInputError as e:
        raise FileFormatError(str(e)) from None


def _cameras_from_json(obj: Any, path: Path) -> dict[str, Camera] | Camera:
    if isinstance(obj, dict) and "images" in obj and "fx" not in obj:
        obj = obj["images"]
    if isinstance(obj, dict) and "camera" in obj and "fx" not in obj:
        obj = obj["camera"]
    if isinstance(obj, dict) and "fx" in obj:
        return _camera(obj, str(path))
    if isinstance(obj, list):
        return {name: _camera(item, f"{path}: {name}") for name, item in named_entries(obj, path, "camera")}
    if isinstance(obj, dict) and obj:
        return {str(name): _camera(item, f"{path}: {name}") for name, item in obj.items()}
    raise FileFormatError(f"{path}: no camera found (expected fx, fy, cx, cy, width, height)")


IMAGE_KEYS = ("file", "image", "name")  # what names an entry's image in a list of per-image entries


def named_entries(items: list, path: Path, kind: str) -> list[tuple[str, dict]]:
    """Returns (image name, entry) of each entry of a JSON list of per-image ``kind`` objects (cameras,
    priors), the name from its ``file``, ``image`` or ``name`` key; FileFormatError naming the entry
    otherwise."""
    out = []
    for i, item in enumerate(items):
        name = next((item[k] for k in IMAGE_KEYS if isinstance(item, dict) and k in item), None)
        if name is None:
            raise FileFormatError(
                f"{path}: {kind} #{i}: missing key 'image' (or 'file', 'name': the image's name)"
            )
        out.append((str(name), item))
    return out


def _cameras_from_colmap(text: str, path: Path) -> dict[str, Camera]:
    cameras = {}
    for number, line in enumerate(text.splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        where = f"{path}:{number}"
        if len(fields) < 4:
            raise FileFormatError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        camera_id, model = fields[0], fields[1].upper()
        if model not in _COLMAP_MODELS:
            raise FileFormatError(
                f"{where}: unsupported camera model {model}; use {', '.join(_COLMAP_MODELS)}"
            )
        names, to_dist = _COLMAP_MODELS[model]
        if len(fields) != 4 + len(names):
            raise FileFormatError(f"{where}: {model} needs {len(names)} parameters ({' '.join(names)})")
        try:
            params = dict(zip(names, map(float, fields[4:]), strict=True))
            width, height = int(fields[2]), int(fields[3])
        except ValueError as e:
            raise FileFormatError(f"{where}: {e}") from None
        fx, fy = params.get("fx", params.get("f")), params.get("fy", params.get("f"))
        # COLMAP puts the centre of the top-left pixel at (0.5, 0.5); linereg at (0, 0)
        d = {"fx": fx, "fy": fy, "cx": params["cx"] - 0.5, "cy": params["cy"] - 0.5}
        cameras[camera_id] = _camera(d | {"width": width, "height": height, "dist": to_dist(params)}, where)
    if not cameras:
        raise FileFormatError(f"{path}: no camera found (COLMAP cameras.txt expected)")
    return cameras


# ---------------------------------------------------------------------------------------------- writers


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Writes ``data`` to ``path`` atomically: a temporary file in the same directory, then os.replace.

    The file gets the permissions of any newly created file (0666 less the umask; mkstemp's are 0600).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            os.chmod(tmp, 0o666 & ~_umask())
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _umask() -> int:
    """Returns the process's umask: from /proc where it can be read, else by setting and restoring it."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)  # the only portable read; not thread-safe, hence /proc first
    os.umask(mask)
    return mask


def read_config(path: str | os.PathLike):
    """Returns the RegisterConfig of a JSON file of overrides, nested per section (``{"match": {...}}``)."""
    from .config import RegisterConfig

    overrides = read_json(path)
    try:
        return RegisterConfig.from_dict(overrides)
    except InvalidInputError as e:
        raise InvalidInputError(f"{path}: {e}") from None


def read_json(path: str | os.PathLike) -> Any:
    """Returns the parsed JSON of a file; missing or malformed -> FileFormatError naming the file."""
    path = Path(path)
    _check_readable(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise FileFormatError(f"{path}: not valid JSON ({e})") from None


def write_json_atomic(path: str | os.PathLike, obj: Any) -> None:
    """Writes ``obj`` as indented JSON, atomically: numpy arrays and scalars become lists and numbers,
    paths strings, NaN and inf ``null`` (strict JSON: no ``NaN`` token other readers reject)."""
    text = json.dumps(jsonable(obj), indent=2, allow_nan=False)
    write_bytes_atomic(path, (text + "\n").encode("utf-8"))


def jsonable(obj: Any) -> Any:
    """Returns ``obj`` with arrays, numpy scalars and paths as plain Python values and NaN/inf as None.

    Anything else that JSON cannot hold raises TypeError.
    """
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if obj is None or isinstance(obj, str | int | bool):
        return obj
    raise TypeError(f"cannot write {type(obj).__name__} as JSON")


def write_tum(path: str | os.PathLike, timestamps: Sequence[float], cam_from_world_list: Iterable) -> None:
    """Writes a TUM trajectory: one line ``timestamp tx ty tz qx qy qz qw`` per frame, atomically.

    TUM stores the camera pose in the world, world_from_cam: t is the camera centre, q its rotation
    (Hamilton, scalar last). timestamps: seconds, one finite number per pose; cam_from_world_list: (4, 4)
    float64 matrices. Lines are written in time order, as TUM tools (evo) expect.
    """
    from scipy.spatial.transform import Rotation

    from .geometry import invert

    poses = [np.asarray(m, dtype=np.float64) for m in cam_from_world_list]
    if len(poses) != len(timestamps):
        raise InvalidInputError(f"write_tum: {len(timestamps)} timestamps but {len(poses)} poses")
    for stamp, cam_from_world in zip(timestamps, poses, strict=True):
        if not isinstance(stamp, int | float | np.number) or not math.isfinite(stamp):
            raise InvalidInputError(f"write_tum: a timestamp must be a finite number, got {stamp!r}")
        if cam_from_world.shape != (4, 4):
            raise InvalidInputError(f"write_tum: a pose must be (4, 4), got {cam_from_world.shape}")
    lines = []
    for stamp, cam_from_world in sorted(zip(timestamps, poses, strict=True), key=lambda pair: pair[0]):
        world_from_cam = invert(cam_from_world)
        q = Rotation.from_matrix(world_from_cam[:3, :3]).as_quat()  # scipy: (x, y, z, w), TUM's order
        lines.append(" ".join(f"{v:.9f}" for v in (float(stamp), *world_from_cam[:3, 3], *q)))
    header = "# timestamp tx ty tz qx qy qz qw (world_from_cam)"
    write_bytes_atomic(path, "\n".join([header, *lines, ""]).encode("utf-8"))


def read_tum(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((K,) float64 timestamps s, (K, 4, 4) float64 cam_from_world) of a TUM trajectory file
    (``timestamp tx ty tz qx qy qz qw`` of world_from_cam per line, ``#`` comments), in time order."""
    from scipy.spatial.transform import Rotation

    from .geometry import invert

    path = Path(path)
    _check_readable(path)
    rows = []
    for number, line in enumerate(_read_text_file(path).splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            values = [float(v) for v in line.replace(",", " ").split()]
        except ValueError:
            raise FileFormatError(f"{path}:{number}: not numbers: {line[:60]!r}") from None
        if len(values) != 8 or not all(math.isfinite(v) for v in values):
            raise FileFormatError(f"{path}:{number}: a TUM line is 8 finite numbers, got {line[:60]!r}")
        rows.append(values)
    if not rows:
        raise FileFormatError(f"{path}: no poses")
    data = np.array(sorted(rows))
    quat = data[:, 4:8]
    if (np.linalg.norm(quat, axis=1) < 1e-9).any():
        raise FileFormatError(f"{path}: a quaternion is zero")
    world_from_cam = np.tile(np.eye(4), (len(data), 1, 1))
    world_from_cam[:, :3, :3] = Rotation.from_quat(quat).as_matrix()  # scipy: (x, y, z, w), TUM's order
    world_from_cam[:, :3, 3] = data[:, 1:4]
    return data[:, 0], np.array([invert(T) for T in world_from_cam])


# ---------------------------------------------------------------------------------------------- streamed clouds

_LAS_WITH_RGB = {
    0: 2,
    1: 3,
    2: 2,
    3: 3,
    4: 5,
    5: 5,
    6: 7,
    7: 7,
    8: 8,
    9: 10,
    10: 10,
}  # point format -> with RGB
_PLY_DTYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2"}
_PLY_DTYPES |= {"ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4"}
_PLY_DTYPES |= {"float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


class CloudReader:
    """Random access to a point cloud file in chunks, without holding it whole (``open_cloud``).

    LAS / LAZ through laspy (LAZ seeks by its chunk table), binary PLY memory-mapped; other formats
    (.pcd, .xyz / .txt, .e57, ASCII PLY) are read whole on open. Rows keep the file's order, NaN included.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        suffix = self.path.suffix.lower()
        if suffix not in CLOUD_SUFFIXES:
            raise FileFormatError(
                f"{self.path}: unsupported point cloud format {suffix!r}; use {', '.join(CLOUD_SUFFIXES)}"
            )
        _check_readable(self.path)
        self.las: Any = None  # laspy reader (LAS / LAZ)
        self._ply: np.ndarray | None = None  # memory-mapped vertex records (binary PLY)
        self._points: np.ndarray | None = None  # everything else, read whole
        self._position = 0
        try:
            self.num_points = self._open(suffix)
        except FileFormatError:
            raise
        except Exception as e:  # each library has its own exceptions for a corrupt file
            raise FileFormatError(f"{self.path}: cannot read point cloud: {e}") from None
        if self.num_points == 0:
            raise FileFormatError(f"{self.path}: the point cloud holds no points (empty or corrupt file)")

    def _open(self, suffix: str) -> int:
        if suffix in (".las", ".laz"):
            import laspy

            if suffix == ".laz" and not laspy.LazBackend.detect_available():
                raise FileFormatError(
                    f"{self.path}: reading .laz needs a LAZ backend: pip install 'laspy[lazrs]'"
                )
            # lazrs' multi-threaded backend deadlocks in a process forked after it ran (its thread pool
            # does not survive fork, and pool workers fork from a parent that has read the cloud)
            single = laspy.LazBackend.Lazrs
            self.las = laspy.open(self.path, laz_backend=single if single.is_available() else None)
            return int(self.las.header.point_count)
        layout = _ply_layout(self.path) if suffix == ".ply" else None
        if layout is not None:
            dtype, offset, count = layout
            self._ply = np.memmap(self.path, dtype=dtype, mode="r", offset=offset, shape=(count,))
            return count
        self._points = read_cloud(self.path)
        return len(self._points)

    @property
    def ply_float32(self) -> bool:
        """Whether the file is a PLY with float32 coordinates (a PLY written from it keeps them float32)."""
        return self._ply is not None and self._ply.dtype["x"] == np.float32

    def read(self, start: int, stop: int) -> np.ndarray:
        """Returns the (stop - start, 3) float64 points of rows [start, stop)."""
        if self.las is not None:
            records = self.read_records(start, stop)
            return np.stack([np.asarray(records.x), np.asarray(records.y), np.asarray(records.z)], axis=1)
        if self._ply is not None:
            rows = self._ply[start:stop]
            return np.stack([rows["x"], rows["y"], rows["z"]], axis=1).astype(np.float64)
        assert self._points is not None
        return self._points[start:stop]

    def read_records(self, start: int, stop: int) -> Any:
        """Returns laspy's point records of rows [start, stop) (LAS / LAZ only), seeking only when needed."""
        if start != self._position:
            self.las.seek(start)
        records = self.las.read_points(stop - start)
        if len(records) != stop - start:
            raise FileFormatError(
                f"{self.path}: truncated: {len(records)} of {stop - start} points at row {start}"
            )
        self._position = stop
        return records

    def close(self) -> None:
        if self.las is not None:
            self.las.close()
        self._ply = None

    def __enter__(self) -> CloudReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_cloud(path: str | os.PathLike) -> CloudReader:
    """Returns a CloudReader of a point cloud file (checked: readable, known format, at least one point)."""
    return CloudReader(path)


def _ply_layout(path: Path) -> tuple[np.dtype, int, int] | None:
    """Returns (record dtype, body offset, vertex count) of a binary PLY whose first element is the vertices
    with scalar properties; None for any other PLY (read whole instead)."""
    count = _ply_vertex_count(path)  # checks x, y, z and that a binary body is long enough
    with open(path, "rb") as f:
        lines: list[list[str]] = []
        while not lines or lines[-1] != ["end_header"]:
            lines.append(f.readline().decode("ascii", "replace").split())
        offset = f.tell()
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(
        lines[1][1] if len(lines[1]) > 1 else ""
    )
    elements = [w for w in lines if w[:1] == ["element"]]
    if order is None or not elements or elements[0][1] != "vertex":
        return None
    fields = []
    for words in lines[lines.index(elements[0]) + 1 :]:
        if words[:1] != ["property"]:
            break
        if words[1] == "list" or words[1] not in _PLY_DTYPES:
            return None
        fields.append((words[2], order + _PLY_DTYPES[words[1]]))
    return np.dtype(fields), offset, count


class ColoredCloudWriter:
    """Writes a coloured copy of a cloud chunk by chunk, atomically: .ply (``red green blue`` uchar and
    ``photo_count`` ushort) or .las / .laz (RGB, 16 bit, and a ``photo_count`` extra dimension).

    ``photo_count`` is the number of photos that coloured the point; 0 flags a point no photo saw (its RGB is
    0, not a colour). The file appears under its name only when the ``with`` block ends without an error;
    before, it is a hidden temporary file in the same folder, removed on error. From a LAS / LAZ ``source``
    every dimension, the scales, offsets and VLRs (the CRS) are kept; otherwise coordinates are stored
    with 1 mm resolution (LAS) or as the source's float type (PLY).
    """

    def __init__(
        self, path: str | os.PathLike, num_points: int, source: CloudReader | None = None, bounds: Any = None
    ) -> None:
        self.path, self.num_points, self.source, self.written = Path(path), int(num_points), source, 0
        suffix = self.path.suffix.lower()
        if suffix not in (".ply", ".las", ".laz"):
            raise InvalidInputError(f"{self.path}: colourized clouds are written as .ply, .las or .laz")
        fd, tmp = tempfile.mkstemp(dir=self.path.parent, prefix=f".{self.path.name}.", suffix=".tmp")
        os.close(fd)
        os.chmod(tmp, 0o666 & ~_umask())
        self._tmp = Path(tmp)
        self._las: Any = None
        self._file: Any = None
        try:
            if suffix == ".ply":
                self._start_ply(source is not None and source.ply_float32)
            else:
                self._start_las(suffix == ".laz", bounds)
        except BaseException:
            self._discard()
            raise

    def _start_ply(self, float32: bool) -> None:
        coord = "float" if float32 else "double"
        self._ply_dtype = np.dtype([(c, "<f4" if float32 else "<f8") for c in "xyz"]
                                   + [(c, "u1") for c in ("red", "green", "blue")] + [("photo_count", "<u2")])  # fmt: skip
        header = [
            "ply",
            "format binary_little_endian 1.0",
            "comment linereg colorize",
            f"element vertex {self.num_points}",
        ]
        header += [f"property {coord} {c}" for c in "xyz"] + [
            f"property uchar {c}" for c in ("red", "green", "blue")
        ]
        header += ["property ushort photo_count", "end_header", ""]
        self._file = open(self._tmp, "wb")  # closed by commit / _discard
        self._file.write("\n".join(header).encode("ascii"))

    def _start_las(self, compress: bool, bounds: Any) -> None:
        import laspy

        src = self.source.las.header if self.source is not None and self.source.las is not None else None
        if src is not None:
            header = laspy.LasHeader(point_format=_LAS_WITH_RGB[src.point_format.id], version=src.version)
            for dim in src.point_format.extra_dimensions:
                header.add_extra_dim(
                    laspy.ExtraBytesParams(name=dim.name, type=dim.dtype, description=dim.description)
                )
            header.offsets, header.scales = src.offsets, src.scales
            header.vlrs.extend(v for v in src.vlrs if not isinstance(v, laspy.vlrs.known.ExtraBytesVlr))
        else:
            header = laspy.LasHeader(point_format=7, version="1.4")
            lo, hi = (np.zeros(3), np.zeros(3)) if bounds is None else np.asarray(bounds, dtype=np.float64)
            header.offsets = np.floor(lo)
            # 1 mm, coarser only if the extent would overflow LAS's 32-bit integers
            header.scales = np.full(3, max(0.001, float(np.max(hi - np.floor(lo))) / 2.0e9))
        if "photo_count" not in header.point_format.dimension_names:
            header.add_extra_dim(laspy.ExtraBytesParams(name="photo_count", type=np.uint16,
                                                        description="photos that coloured it; 0: none"))  # fmt: skip
        self._las_header = header
        self._las = laspy.open(self._tmp, mode="w", header=header, do_compress=compress)

    def write(
        self, points: np.ndarray, rgb: np.ndarray, photo_count: np.ndarray, records: Any = None
    ) -> None:
        """Appends n points: (n, 3) float64 world, (n, 3) uint8 RGB, (n,) photo counts; ``records``: the
        source's laspy records of the same rows (their other dimensions are kept)."""
        n = len(points)
        if self._file is not None:
            rows = np.empty(n, dtype=self._ply_dtype)
            for i, c in enumerate("xyz"):
                rows[c] = points[:, i]
            for i, c in enumerate(("red", "green", "blue")):
                rows[c] = rgb[:, i]
            rows["photo_count"] = np.minimum(photo_count, 65535)
            self._file.write(rows.tobytes())
        else:
            self._write_las(points, rgb, photo_count, records)
        self.written += n

    def _write_las(self, points: np.ndarray, rgb: np.ndarray, photo_count: np.ndarray, records: Any) -> None:
        import laspy

        out = laspy.ScaleAwarePointRecord.zeros(len(points), header=self._las_header)
        if records is not None:  # same scales and offsets: the integer coordinates copy exactly
            for name in records.point_format.dimension_names:
                if name in out.point_format.dimension_names:
                    out[name] = records[name]
        else:
            out.x, out.y, out.z = points[:, 0], points[:, 1], points[:, 2]
        for i, c in enumerate(("red", "green", "blue")):
            out[c] = rgb[:, i].astype(np.uint16) * 257  # 8 -> 16 bit, 255 -> 65535
        out["photo_count"] = np.minimum(photo_count, 65535).astype(np.uint16)
        self._las.write_points(out)

    def commit(self) -> None:
        """Closes the file and moves it to its name (every point must have been written)."""
        if self.written != self.num_points:
            raise InvalidInputError(f"{self.path}: {self.written} of {self.num_points} points written")
        if self._file is not None:
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
        else:
            self._las.close()
        os.replace(self._tmp, self.path)

    def _discard(self) -> None:
        for handle in (self._file, self._las):
            if handle is not None:
                try:
                    handle.close()
                except Exception:  # a half-written LAZ may not close cleanly; it is deleted anyway
                    pass
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> ColoredCloudWriter:
        return self

    def __exit__(self, exc_type: Any, *exc: object) -> None:
        if exc_type is None:
            self.commit()
        else:
            self._discard()
