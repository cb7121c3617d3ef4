"""Believable photos of a procedural building (``linereg.sim.building``) from a known pose, in numpy/OpenCV.

Faces are rasterised into a supersampled z-buffer (inverse depth is affine in the pixel coordinates of
a planar face, so each face's depth is exact), coloured per kind with Lambert shading under a sun and a
sky fill light, textured in world coordinates, then averaged down (anti-aliasing), lens-distorted if the
camera has distortion, blurred and given sensor noise. Edges land where ``Building.edges`` project.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import Camera
from ..geometry import invert
from .building import FACE_KINDS, Building

# albedo of each face kind, BGR display values in [0, 1]; walls get a per-block tint on top
ALBEDO_BGR = {
    "wall": (0.62, 0.70, 0.78),
    "window": (0.16, 0.13, 0.11),
    "door": (0.12, 0.20, 0.32),
    "roof": (0.30, 0.30, 0.32),
    "ground": (0.36, 0.37, 0.38),
    "ledge": (0.80, 0.84, 0.86),
}
# texture (plaster, reflections, asphalt) varies each face kind's brightness by about this share (std)
TEXTURE_AMPLITUDE = {"wall": 0.07, "window": 0.25, "door": 0.10, "roof": 0.1, "ground": 0.08, "ledge": 0.04}
SKY_ZENITH_BGR = np.array([0.78, 0.50, 0.30])  # the sky straight up
SKY_HORIZON_BGR = np.array([0.95, 0.88, 0.80])  # the sky at the horizon (and what glass mirrors)
FAR_GROUND_BGR = np.array([0.40, 0.45, 0.42])  # what lies below the horizon beyond the ground plane


@dataclass(frozen=True)
class RenderConfig:
    """Look of rendered photos: light, optics, sensor."""

    sun_azimuth_deg: float = 35.0  # from +x towards +y
    sun_elevation_deg: float = 40.0
    ambient: float = 0.35  # sky light on every face; a fill term below makes shaded facades differ
    gamma: float = 2.2  # the camera's tone curve on the light falling on a face (1 = linear)
    supersample: int = 2  # rasterise at this factor, then average down: anti-aliased edges
    blur_sigma_px: float = 0.6  # optics
    noise_std: float = 2.0  # sensor noise, grey levels
    near_m: float = 0.05  # faces are clipped to this depth


def render_image(
    building: Building,
    cam_from_world: np.ndarray,
    camera: Camera,
    rng: np.random.Generator,
    config: RenderConfig | None = None,
) -> np.ndarray:
    """Returns a (H, W, 3) uint8 BGR photo of ``building`` seen by ``camera`` at ``cam_from_world`` (4, 4).

    Flat per-face colours are rasterised supersampled and averaged down (anti-aliased edges); the
    surface texture, which needs no anti-aliasing, is applied at the output resolution.
    """
    cfg = config or RenderConfig()
    s = cfg.supersample
    hi_cam = Camera(camera.fx * s, camera.fy * s, (camera.cx + 0.5) * s - 0.5, (camera.cy + 0.5) * s - 0.5,
                    camera.width * s, camera.height * s)  # fmt: skip
    face_id, inv_depth = rasterize(building, cam_from_world, hi_cam, cfg.near_m)
    world_from_cam = invert(cam_from_world)
    colours = _face_colours(building, world_from_cam[:3, 3], rng, cfg)
    size = (camera.width, camera.height)
    sky = cv2.resize(_sky_image(camera, world_from_cam), (hi_cam.width, hi_cam.height))
    flat = np.where((face_id >= 0)[:, :, None], colours[face_id], sky)
    image = cv2.resize(flat, size, interpolation=cv2.INTER_AREA)
    # texture: sample the supersampled buffers at the centre of each output pixel's block
    ids, inv = face_id[s // 2 :: s, s // 2 :: s], inv_depth[s // 2 :: s, s // 2 :: s]
    image *= _texture(building, camera, world_from_cam, ids, inv, rng)[:, :, None]
    if camera.has_distortion:
        image = _distort(image, camera)
    if cfg.blur_sigma_px > 0:
        image = cv2.GaussianBlur(image, (0, 0), cfg.blur_sigma_px)
    noise = np.asarray(rng.normal(0.0, cfg.noise_std, size=image.shape), dtype=np.float32)
    image = image * 255.0 + noise
    return np.clip(image + 0.5, 0, 255).astype(np.uint8)


def rasterize(
    building: Building, cam_from_world: np.ndarray, camera: Camera, near_m: float = 0.05
) -> tuple[np.ndarray, np.ndarray]:
    """Returns ((H, W) int32 face index or -1, (H, W) float64 inverse depth 1/Z or 0) of the nearest faces.

    For a plane ``n . X = d`` (camera frame) the ray ``Z (x, y, 1)`` of pixel (u, v) meets it at
    ``1 / Z = n . (x, y, 1) / d``, affine in (u, v): each face's depth is exact, no interpolation.
    """
    h, w = camera.height, camera.width
    face_id = np.full((h, w), -1, dtype=np.int32)
    inv_depth = np.zeros((h, w))
    corners = (building.faces.reshape(-1, 3) @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]).reshape(
        -1, 4, 3
    )
    normals = building.normals @ cam_from_world[:3, :3].T
    offsets = np.einsum("fk,fk->f", normals, corners[:, 0])
    for f, uv in _screen_polygons(corners, offsets, camera, near_m):
        x0, y0 = np.maximum(np.floor(uv.min(axis=0)).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(uv.max(axis=0)).astype(int) + 1, [w, h])
        if x0 >= x1 or y0 >= y1:
            continue
        mask = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)
        pts = np.round((uv - [x0, y0]) * 16.0).astype(np.int32)  # 4 fractional bits: sub-pixel corners
        cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=4)
        n, d = normals[f], offsets[f]
        u = (np.arange(x0, x1) - camera.cx) / camera.fx
        v = (np.arange(y0, y1) - camera.cy) / camera.fy
        inv = (n[0] * u[None, :] + (n[1] * v[:, None] + n[2])) / d
        win = inv_depth[y0:y1, x0:x1]
        closer = (mask > 0) & (inv > win)
        win[closer] = inv[closer]
        face_id[y0:y1, x0:x1][closer] = f
    return face_id, inv_depth


def _screen_polygons(corners: np.ndarray, offsets: np.ndarray, camera: Camera, near_m: float):
    """Yields (face index, (K, 2) pixel polygon) of the faces that face the camera and overlap the image.

    corners: (F, 4, 3) camera frame; offsets: (F,) ``n . X`` of each face plane (negative: facing us).
    """
    z = corners[:, :, 2]
    front = (offsets < -1e-9) & (z > near_m).any(axis=1)
    whole = front & (z > near_m).all(axis=1)
    uv = np.stack(
        [camera.fx * corners[..., 0] / z + camera.cx, camera.fy * corners[..., 1] / z + camera.cy], -1
    )
    lo, hi = uv.min(axis=1), uv.max(axis=1)
    inside = (hi[:, 0] >= 0) & (hi[:, 1] >= 0) & (lo[:, 0] < camera.width) & (lo[:, 1] < camera.height)
    for f in np.flatnonzero(front & (inside | ~whole)):
        if whole[f]:
            yield f, uv[f]
        else:  # crosses the near plane: clip first
            poly = _clip_near(corners[f], near_m)
            z_f = poly[:, 2]
            yield f, np.c_[camera.fx * poly[:, 0] / z_f + camera.cx, camera.fy * poly[:, 1] / z_f + camera.cy]


def _clip_near(quad_cam: np.ndarray, near_m: float) -> np.ndarray:
    """Returns (K, 3) the part of a camera-frame polygon with Z >= near_m (Sutherland-Hodgman, one plane)."""
    if (quad_cam[:, 2] >= near_m).all():
        return quad_cam
    out = []
    for a, b in zip(quad_cam, np.roll(quad_cam, -1, axis=0), strict=True):
        if a[2] >= near_m:
            out.append(a)
        if (a[2] >= near_m) != (b[2] >= near_m):
            out.append(a + (near_m - a[2]) / (b[2] - a[2]) * (b - a))
    return np.array(out)


def rotate(vectors: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Returns (..., 3) ``R @ v`` for every vector; einsum, as ``(N, 3) @ (3, 3)`` matmul is slow here."""
    return np.einsum("...k,jk->...j", vectors, R)


def _pixel_rays(camera: Camera) -> np.ndarray:
    """Returns (H, W, 3) float64 camera-frame rays (x, y, 1) of every pixel."""
    u = (np.arange(camera.width) - camera.cx) / camera.fx
    v = (np.arange(camera.height) - camera.cy) / camera.fy
    rays = np.ones((camera.height, camera.width, 3))
    rays[:, :, 0] = u[None, :]
    rays[:, :, 1] = v[:, None]
    return rays


def _face_colours(building: Building, eye: np.ndarray, rng: np.random.Generator, cfg: RenderConfig):
    """Returns (F, 3) float32 BGR in [0, 1] of every face: albedo x Lambert shading, glass mirroring sky."""
    kinds_sorted = sorted(FACE_KINDS)
    kind = np.searchsorted(np.array(kinds_sorted), building.face_kind)
    albedo = np.array([ALBEDO_BGR[k] for k in kinds_sorted])[kind]
    # every block its own plaster tint, every window pane and door a slightly different albedo
    num_blocks = int(building.face_block.max()) + 2
    tint = rng.uniform(0.75, 1.15, size=(num_blocks, 3)) * rng.uniform(0.8, 1.1, size=(num_blocks, 1))
    wall = building.face_kind == "wall"
    albedo[wall] *= tint[building.face_block[wall] + 1]
    # walls and the ground are cut into rectangles round openings and footprints: one material per
    # block and one for the ground, or every cut would show as a seam (a line no scan has)
    jitter = rng.uniform(0.9, 1.1, size=(len(albedo), 1))
    albedo *= np.where(np.isin(building.face_kind, ("window", "door"))[:, None], jitter, 1.0)
    # window and door reveals (wall quads as narrow as the recess) lie in the opening's shadow
    quads = building.faces
    narrow = np.minimum(
        np.linalg.norm(quads[:, 1] - quads[:, 0], axis=1), np.linalg.norm(quads[:, 3] - quads[:, 0], axis=1)
    )
    albedo[wall & (narrow < 0.2)] *= 0.55
    az, el = math.radians(cfg.sun_azimuth_deg), math.radians(cfg.sun_elevation_deg)
    sun = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    fill = np.array([math.cos(az + 1.9), math.sin(az + 1.9), 0.6])  # sky is brighter away from the sun
    n = building.normals
    shading = cfg.ambient * (1.0 + 0.35 * (n @ fill)) + (1.0 - cfg.ambient) * np.maximum(n @ sun, 0.0)
    # albedos are display (sRGB-like) values while light adds up linearly: a camera's tone curve (gamma
    # 2.2) encodes the irradiance, which lifts shade as in a real photo (linear shade is near black)
    colour = albedo * shading[:, None] ** (1.0 / cfg.gamma)
    # glass mirrors the sky, more at grazing angles (Schlick's Fresnel), one view angle per pane
    glass = building.face_kind == "window"
    view = eye - building.faces[glass].mean(axis=1)
    cos_view = np.abs(np.einsum("pk,pk->p", view, n[glass])) / np.linalg.norm(view, axis=1)
    mirror = 0.3 + 0.7 * (1.0 - cos_view) ** 5
    mirror *= rng.uniform(0.5, 1.0, size=len(mirror))
    colour[glass] = (1 - mirror[:, None]) * colour[glass] + mirror[:, None] * 0.7 * SKY_HORIZON_BGR
    return np.clip(colour, 0.0, 1.0).astype(np.float32)


def _sky_image(camera: Camera, world_from_cam: np.ndarray) -> np.ndarray:
    """Returns (H, W, 3) float32 BGR sky: gradient by ray elevation, far ground below the horizon."""
    dirs = rotate(_pixel_rays(camera), world_from_cam[:3, :3])
    elevation = dirs[:, :, 2] / np.linalg.norm(dirs, axis=2)
    e = np.clip(elevation, 0.0, 1.0)[..., None] ** 0.6
    colour = (1.0 - e) * SKY_HORIZON_BGR + e * SKY_ZENITH_BGR
    return np.where((elevation < 0.0)[..., None], FAR_GROUND_BGR, colour).astype(np.float32)


def _texture(building, camera, world_from_cam, face_id, inv_depth, rng) -> np.ndarray:
    """Returns (H, W) float32 brightness factors around 1: plaster, asphalt, reflections by face kind."""
    ids = np.maximum(face_id, 0)
    depth = np.where(face_id >= 0, 1.0 / np.maximum(inv_depth, 1e-12), 0.0).astype(np.float32)
    rays = _pixel_rays(camera).astype(np.float32) * depth[:, :, None]
    points = rotate(rays, world_from_cam[:3, :3].astype(np.float32)) + world_from_cam[:3, 3].astype(
        np.float32
    )
    # texture coordinates in the face's plane: (horizontal, z) on facades, (x, y) on the ground
    flat = np.abs(building.normals[:, 2]) > 0.5
    tex_u = np.where(flat[ids], points[:, :, 0], points[:, :, 0] + points[:, :, 1])
    tex_v = np.where(flat[ids], points[:, :, 1], points[:, :, 2])
    kinds = sorted(FACE_KINDS)
    amplitude = np.array([TEXTURE_AMPLITUDE[k] for k in kinds], dtype=np.float32)
    amp = amplitude[np.searchsorted(np.array(kinds), building.face_kind)][ids]
    amp[face_id < 0] = 0.0
    noise = 0.5 * _value_noise(rng, tex_u / 0.06, tex_v / 0.06) + _value_noise(rng, tex_u / 0.8, tex_v / 0.8)
    return 1.0 + amp * noise


def _value_noise(rng: np.random.Generator, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Returns float32 smooth zero-mean noise (about unit std) at texture coordinates u, v (H, W)."""
    size = 256
    blurred = cv2.GaussianBlur(rng.normal(size=(size, size)).astype(np.float32), (0, 0), 1.5)
    tile = np.asarray(blurred / float(blurred.std()), dtype=np.float32)
    # the tile repeats: wrap the coordinates into it so that remap's bilinear lookup stays in range
    mu = np.mod(u, size).astype(np.float32)
    mv = np.mod(v, size).astype(np.float32)
    return cv2.remap(tile, mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


def _distort(image: np.ndarray, camera: Camera) -> np.ndarray:
    """Returns the pinhole image resampled through the camera's lens distortion (same K)."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    src = camera.undistort_points(np.c_[u.ravel(), v.ravel()].astype(np.float64))
    maps = src.reshape(camera.height, camera.width, 2).astype(np.float32)
    return cv2.remap(image, maps[:, :, 0], maps[:, :, 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def scaled_camera(camera: Camera, scale: float) -> Camera:
    """Returns the pinhole camera of the same view at ``scale`` x the resolution (pixel centres kept)."""
    w, h = max(round(camera.width * scale), 1), max(round(camera.height * scale), 1)
    sx, sy = w / camera.width, h / camera.height
    return Camera(camera.fx * sx, camera.fy * sy, (camera.cx + 0.5) * sx - 0.5, (camera.cy + 0.5) * sy - 0.5,
                  w, h)  # fmt: skip


def visible_edge_lengths(
    building: Building,
    cam_from_world: np.ndarray,
    camera: Camera,
    face_id: np.ndarray,
    inv_depth: np.ndarray,
    samples: int = 32,
    tolerance: float = 0.03,
) -> np.ndarray:
    """Returns (E,) float64 the visible image length (px of ``camera``) of every building edge.

    A z-buffer test instead of ray casting (``views.occluded``): each edge is sampled, and a sample is
    visible when it projects into the image, in front of the camera, and no face in the (H', W') buffers
    ``face_id`` / ``inv_depth`` (from ``rasterize`` at any resolution of the same view) is more than
    ``tolerance`` nearer at its pixel or next to it (an edge lies on the border of its own faces).
    """
    t = np.linspace(0.0, 1.0, samples)
    ends = building.edges.reshape(-1, 2, 3)
    pts = ends[:, :1] + t[None, :, None] * (ends[:, 1:] - ends[:, :1])  # (E, S, 3)
    cam = pts @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    z = cam[..., 2]
    front = z > 0.1
    zs = np.where(front, z, 1.0)
    u, v = camera.fx * cam[..., 0] / zs + camera.cx, camera.fy * cam[..., 1] / zs + camera.cy
    h, w = inv_depth.shape
    su, sv = (u + 0.5) * w / camera.width - 0.5, (v + 0.5) * h / camera.height - 0.5
    inside = front & (su > -0.5) & (su < w - 0.5) & (sv > -0.5) & (sv < h - 0.5)
    # the farthest surface around each pixel: a sample on a silhouette sees past the occluder's border
    farthest = cv2.erode(np.where(face_id >= 0, inv_depth, 0.0).astype(np.float32), np.ones((3, 3), np.uint8))
    col = np.clip(np.rint(su), 0, w - 1).astype(np.int64)
    row = np.clip(np.rint(sv), 0, h - 1).astype(np.int64)
    visible = inside & (farthest[row, col] <= (1.0 + tolerance) / zs)
    step = np.hypot(np.diff(u, axis=1), np.diff(v, axis=1))
    return (step * (visible[:, 1:] & visible[:, :-1])).sum(axis=1)
