"""The judge of ``bench lines3d --real``: does a map, seen at a photo's true pose, hold the photo's lines?

A projected map segment and an image segment *agree* when they are within ``ANGLE_DEG`` of parallel and,
over at least ``MIN_SHARE`` of the shorter one's length, the shorter lies within ``DISTANCE_PX`` of the
longer (issue 10's rule). Recall: the image line length covered by agreeing visible map segments, as a
share of all image line length. Precision: the share of the map segments in view (visible, at least as
long in the image as the shortest image segment kept) that agree with some image segment.

The ceiling (``ceiling``): the cloud rendered at the true pose as a z-buffer of point splats; pixels on a
depth discontinuity (neighbours' depths differ by more than ``JUMP_FRACTION`` of the depth) or a crease
(the points' normals differ by more than ``CREASE_DEG``) are edges; the share of the image line length
lying within ``DISTANCE_PX`` of an edge is what no geometry-only map can beat.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from ..camera import Camera

DISTANCE_PX = 3.0
ANGLE_DEG = 3.0
MIN_SHARE = 0.5
# depth discontinuity: neighbouring pixels' points lie off each other's tangent plane by more than 3 noise
# rms of the cloud (at least 3 cm) plus 2 % of the depth (a Kinect's noise grows with depth)
JUMP_NOISES = 3.0
JUMP_FRACTION = 0.02
JUMP_MIN_M = 0.03  # fused RGB-D frames leave layers a few cm apart (misregistration)
STEP = 3  # px between the pixels compared on either side of an edge pixel
CREASE_DEG = 30.0
NORMAL_NEIGHBOURS = 24
MAX_CURVATURE = 0.02  # lambda_min / sum: a smooth patch whose normal is fit to compare
MIN_EDGE_PX = 15  # edge pixels in a smaller blob are specks, no line
MAX_RING_SPLAT = 20  # px: a sweep's splats reach at most this far up and down (``render``)


def project(segments: np.ndarray, camera: Camera, cam_from_world: np.ndarray) -> np.ndarray:
    """Returns (K, 4) pixels of (K, 6) world segments in front of the camera (pinhole, no distortion)."""
    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    ends = segments.reshape(-1, 3) @ R.T + t
    uv = np.c_[
        camera.fx * ends[:, 0] / ends[:, 2] + camera.cx, camera.fy * ends[:, 1] / ends[:, 2] + camera.cy
    ]
    return uv.reshape(-1, 4)


def agreement(image: np.ndarray, projected: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns the agreeing pairs of (N, 4) image and (K, 4) projected map segments: (q,) image index,
    (q,) map index, (q, 2) the stretch of the image segment (fractions 0..1 of it) the map segment covers."""
    if len(image) == 0 or len(projected) == 0:
        z = np.zeros(0, np.int64)
        return z, z, np.zeros((0, 2))
    a, b = image[:, :2], image[:, 2:]
    p, q = projected[:, :2], projected[:, 2:]
    la, lp = np.linalg.norm(b - a, axis=1), np.linalg.norm(q - p, axis=1)
    da, dp = (b - a) / np.maximum(la, 1e-9)[:, None], (q - p) / np.maximum(lp, 1e-9)[:, None]
    cos = np.abs(da @ dp.T)
    i, j = np.nonzero(cos >= np.cos(np.radians(ANGLE_DEG)))
    # the shorter one projected onto the longer one's line
    img_short = la[i] <= lp[j]
    s0 = np.where(img_short[:, None], a[i], p[j])
    s1 = np.where(img_short[:, None], b[i], q[j])
    l0 = np.where(img_short[:, None], p[j], a[i])
    ld = np.where(img_short[:, None], dp[j], da[i])
    llen = np.where(img_short, lp[j], la[i])
    slen = np.where(img_short, la[i], lp[j])
    t0, t1 = np.einsum("nk,nk->n", s0 - l0, ld), np.einsum("nk,nk->n", s1 - l0, ld)
    n = np.c_[-ld[:, 1], ld[:, 0]]
    d0, d1 = np.einsum("nk,nk->n", s0 - l0, n), np.einsum("nk,nk->n", s1 - l0, n)
    # the part of the shorter within DISTANCE_PX of the longer's line and inside its extent
    lo_t, hi_t = np.minimum(t0, t1), np.maximum(t0, t1)
    span = np.maximum(hi_t - lo_t, 1e-9)
    # fractions u of the shorter (from s0) where |d| <= DISTANCE_PX: d(u) = d0 + u (d1 - d0)
    dd = d1 - d0
    with np.errstate(divide="ignore", invalid="ignore"):
        ua, ub = (-DISTANCE_PX - d0) / dd, (DISTANCE_PX - d0) / dd
    near_lo = np.where(np.abs(dd) < 1e-9, np.where(np.abs(d0) <= DISTANCE_PX, 0.0, 1.0), np.minimum(ua, ub))
    near_hi = np.where(np.abs(dd) < 1e-9, np.where(np.abs(d0) <= DISTANCE_PX, 1.0, 0.0), np.maximum(ua, ub))
    # fractions where the shorter's projection lies within [0, llen] of the longer
    u_in = np.sort(
        np.stack(
            [(0.0 - t0) / np.where(t1 != t0, t1 - t0, 1e-9), (llen - t0) / np.where(t1 != t0, t1 - t0, 1e-9)],
            1,
        ),
        axis=1,
    )
    u0 = np.clip(np.maximum.reduce([near_lo, u_in[:, 0], np.zeros(len(i))]), 0, 1)
    u1 = np.clip(np.minimum.reduce([near_hi, u_in[:, 1], np.ones(len(i))]), 0, 1)
    share = np.maximum(u1 - u0, 0.0)
    ok = share * slen >= MIN_SHARE * slen
    del span
    # the covered stretch of the image segment: u of the image itself, or the map's ends on the image's line
    ti0, ti1 = (np.einsum("nk,nk->n", x - a[i], da[i]) / np.maximum(la[i], 1e-9) for x in (p[j], q[j]))
    cover = np.where(img_short[:, None], np.c_[u0, u1], np.sort(np.clip(np.c_[ti0, ti1], 0, 1), axis=1))
    return i[ok], j[ok], cover[ok]


def covered_length(image: np.ndarray, pairs_i: np.ndarray, cover: np.ndarray) -> np.ndarray:
    """Returns (N,) the length (px) of each image segment covered by the union of its pairs' stretches."""
    lengths = np.linalg.norm(image[:, 2:] - image[:, :2], axis=1)
    out = np.zeros(len(image))
    for k in np.unique(pairs_i):
        iv = cover[pairs_i == k]
        iv = iv[np.argsort(iv[:, 0])]
        total, end = 0.0, 0.0
        for lo, hi in iv:
            lo = max(lo, end)
            if hi > lo:
                total += hi - lo
                end = hi
        out[k] = total * lengths[k]
    return out


def judge(
    image: np.ndarray,
    parts: np.ndarray,
    rows: np.ndarray,
    kinds: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    min_px: float,
) -> dict[str, Any]:
    """Returns recall, precision and their split by kind of (N, 4) image segments against the (K, 6) visible
    map parts (of map ``rows``, whose map segments have ``kinds``) at the true pose."""
    projected = project(parts, camera, cam_from_world)
    plen = np.linalg.norm(projected[:, 2:] - projected[:, :2], axis=1)
    pi, pj, cover = agreement(image, projected)
    lengths = np.linalg.norm(image[:, 2:] - image[:, :2], axis=1)
    total = float(lengths.sum())
    explained = covered_length(image, pi, cover)
    # a map segment is in view when its visible parts are as long as the image's shortest kept segment
    view_len = np.bincount(rows, plen, minlength=int(rows.max(initial=-1)) + 1)
    in_view = np.flatnonzero(view_len >= min_px)
    backed = np.zeros(len(view_len), dtype=bool)
    backed[rows[pj]] = True
    out: dict[str, Any] = {
        "image_segments": len(image),
        "image_length_px": total,
        "in_view": len(in_view),
        "backed": int(backed[in_view].sum()),
        "recall": float(explained.sum() / total) if total else float("nan"),
        "precision": float(backed[in_view].mean()) if len(in_view) else float("nan"),
        "by_kind": {},
    }
    for k in np.unique(kinds[in_view]) if len(in_view) else []:
        mine = kinds[rows[pj]] == k
        view_k = in_view[kinds[in_view] == k]
        out["by_kind"][int(k)] = {
            "recall": float(covered_length(image, pi[mine], cover[mine]).sum() / total) if total else 0.0,
            "in_view": len(view_k),
            "precision": float(backed[view_k].mean()) if len(view_k) else float("nan"),
        }
    out["_pairs"] = (pi, pj)
    out["_explained"] = explained
    return out


def ceiling(
    image: np.ndarray,
    cloud: np.ndarray,
    camera: Camera,
    cam_from_world: np.ndarray,
    profile: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Returns {ceiling, covered, edge_mask}: the share of the (N, 4) image segments' length within
    DISTANCE_PX of a depth discontinuity or crease of the (P, 3) cloud rendered at the pose, the share
    lying where the cloud covers the image, and the (H, W) bool edge mask. ``profile``: the cloud's
    (``CloudProfile.as_dict``, its map's: rings a file's ring field gave; None: profiled here)."""
    from ..map.profile import profile_cloud

    if profile is None:
        profile = profile_cloud(cloud).as_dict()
    noise_m = float(profile["noise_m"])
    depth, points, normals = render(cloud, camera, cam_from_world, float(profile["ring_gap_deg"]))
    h, w = depth.shape
    valid = np.isfinite(depth)
    edge = np.zeros((h, w), dtype=bool)
    has = np.abs(normals).sum(-1) > 0
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        # pixels STEP apart on both sides of the marked one: a crease's rough band is a few pixels wide
        sl = [
            (slice(max(0, k * dy), h + min(0, k * dy)), slice(max(0, k * dx), w + min(0, k * dx)))
            for k in (-STEP, 0, STEP)
        ]
        a = (slice(0, h - 2 * STEP * dy), slice(max(0, -2 * STEP * dx), w - max(0, 2 * STEP * dx)))
        b = (slice(2 * STEP * dy, h), slice(max(0, 2 * STEP * dx), w - max(0, -2 * STEP * dx)))
        mid = (
            slice(STEP * dy, h - STEP * dy),
            slice(STEP * max(0, dx) + STEP * max(0, -dx), w - STEP * max(0, dx) - STEP * max(0, -dx)),
        )
        del sl
        both = valid[a] & valid[b]
        delta = points[b] - points[a]
        # off each other's tangent plane by more than the noise: a discontinuity (a slanted floor's depth
        # changes fast between pixels, but it stays on its plane); rough patches: the distance itself
        off_a = np.where(has[a], np.abs(np.einsum("ijk,ijk->ij", delta, normals[a])), np.inf)
        off_b = np.where(has[b], np.abs(np.einsum("ijk,ijk->ij", delta, normals[b])), np.inf)
        off = np.where(has[a] | has[b], np.minimum(off_a, off_b), np.linalg.norm(delta, axis=-1))
        near = np.minimum(np.where(both, depth[a], 1.0), np.where(both, depth[b], 1.0))
        jump = both & (off > max(JUMP_NOISES * noise_m, JUMP_MIN_M) + JUMP_FRACTION * near)
        cos = np.abs(np.einsum("ijk,ijk->ij", normals[a], normals[b]))
        crease = both & has[a] & has[b] & ~jump & (cos < np.cos(np.radians(CREASE_DEG)))
        edge[mid] |= jump | crease
    # specks (a stray point's splat, noise on a rough surface) are no edge an image line could follow
    _, labels, stats, _ = cv2.connectedComponentsWithStats(edge.astype(np.uint8), connectivity=8)
    long = np.maximum(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT]) >= MIN_EDGE_PX
    long[0] = False
    edge = long[labels]
    k = int(2 * DISTANCE_PX + 1)
    near_edge = cv2.dilate(edge.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    covered = cv2.dilate(valid.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    on, cov = _share_on(image, near_edge), _share_on(image, covered)
    return {"ceiling": on, "covered": cov, "edge_mask": edge}


def render(
    cloud: np.ndarray, camera: Camera, cam_from_world: np.ndarray, ring_gap_deg: float = 0.0
) -> tuple[np.ndarray, ...]:
    """Returns ((H, W) depth (inf: no point), (H, W, 3) camera-frame point, (H, W, 3) unit normal facing the
    camera) of the (P, 3) cloud as a z-buffer of splats half the local spacing wide; points with fewer
    than 4 neighbours within 3 spacings (strays) are left out, normals by PCA of 16 neighbours. A single
    sweep's points (``ring_gap_deg`` > 0: the angle between its rings) are splatted half that angle tall
    too (at most ``MAX_RING_SPLAT`` px): a point's neighbours along its ring are near, the next ring's
    may be tens of pixels away (a 32-laser sweep's rings lie 1.3 deg apart: ~30 px), and splats as small
    as the ring's spacing leave the image striped, with hardly a depth edge between its stripes."""
    from scipy.spatial import cKDTree

    R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
    x = cloud @ R.T + t
    uv = np.c_[camera.fx * x[:, 0] / x[:, 2] + camera.cx, camera.fy * x[:, 1] / x[:, 2] + camera.cy]
    margin = 10
    inside = (x[:, 2] > 0.1) & (uv[:, 0] > -margin) & (uv[:, 0] < camera.width + margin)
    inside &= (uv[:, 1] > -margin) & (uv[:, 1] < camera.height + margin)
    idx = np.flatnonzero(inside)
    dist, nb = cKDTree(cloud).query(cloud[idx], k=NORMAL_NEIGHBOURS)
    spacing = dist[:, 4]
    keep = dist[:, 4] <= 3.0 * np.median(dist[:, 1])
    idx, nb, spacing = idx[keep], nb[keep], spacing[keep]
    nbp = x[nb] - x[nb].mean(axis=1, keepdims=True)
    values, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", nbp, nbp))
    normals = vectors[:, :, 0]
    # a rough patch (clutter, noise, a crease itself) has no normal to compare: marked by a zero normal
    normals[values[:, 0] > MAX_CURVATURE * values.sum(axis=1)] = 0.0
    normals *= np.where(np.einsum("nk,nk->n", normals, x[idx]) > 0, -1.0, 1.0)[:, None]
    z = x[idx, 2]
    radius = np.clip(np.rint(0.5 * camera.fx * spacing / z), 0, 6).astype(np.int64)
    tall = int(min(np.rint(0.5 * camera.fy * np.radians(ring_gap_deg)), MAX_RING_SPLAT))
    height = np.maximum(radius, tall)
    h, w = camera.height, camera.width
    best = np.full(h * w, np.inf)
    writes = []
    for r, rv in np.unique(np.c_[radius, height], axis=0):
        sel = np.flatnonzero((radius == r) & (height == rv))
        px0, py0 = np.rint(uv[idx[sel], 0]).astype(np.int64), np.rint(uv[idx[sel], 1]).astype(np.int64)
        for dx in range(-r, r + 1):
            for dy in range(-rv, rv + 1):
                px, py = px0 + dx, py0 + dy
                ok = (px >= 0) & (px < w) & (py >= 0) & (py < h)
                flat = py[ok] * w + px[ok]
                np.minimum.at(best, flat, z[sel][ok])
                writes.append((flat, sel[ok]))
    owner = np.full(h * w, -1)
    for flat, who in writes:
        win = best[flat] == z[who]
        owner[flat[win]] = who[win]
    points = np.zeros((h * w, 3))
    nrm = np.zeros((h * w, 3))
    has = owner >= 0
    points[has], nrm[has] = x[idx[owner[has]]], normals[owner[has]]
    return best.reshape(h, w), points.reshape(h, w, 3), nrm.reshape(h, w, 3)


def _share_on(image: np.ndarray, mask: np.ndarray) -> float:
    """Returns the share of the (N, 4) segments' length (sampled every pixel) on True pixels of mask."""
    if len(image) == 0:
        return float("nan")
    lengths = np.linalg.norm(image[:, 2:] - image[:, :2], axis=1)
    count = np.maximum(np.ceil(lengths), 1).astype(np.int64) + 1
    seg = np.repeat(np.arange(len(image)), count)
    f = (np.arange(len(seg)) - np.repeat(np.cumsum(count) - count, count)) / (count[seg] - 1)
    xy = image[seg, :2] + f[:, None] * (image[seg, 2:] - image[seg, :2])
    px = np.clip(np.rint(xy).astype(np.int64), 0, [mask.shape[1] - 1, mask.shape[0] - 1])
    hit = mask[px[:, 1], px[:, 0]]
    per = np.bincount(seg, hit, len(image)) / count
    return float((per * lengths).sum() / lengths.sum())
