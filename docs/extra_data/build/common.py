"""Shared helpers for the extra_data builders (numpy + opencv only)."""

import os

import cv2
import numpy as np

CONVENTION = (
    "OpenCV pinhole: camera x right, y down, z forward (optical axis). "
    "T_cam_from_world is 4x4 row-major; X_cam = T[:3,:3] @ X_world + T[:3,3]; "
    "u = fx*X/Z + cx, v = fy*Y/Z + cy (before distortion, if any). "
    "World = the frame of cloud.ply, metres."
)


def write_ply(path, xyz, extra=None):
    """Binary little-endian PLY, float32 x y z (+ float32 scalar properties)."""
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")] + [(k, "<f4") for k in (extra or {})]
    rec = np.empty(len(xyz), dtype=fields)
    for i, k in enumerate("xyz"):
        rec[k] = xyz[:, i]
    for k, a in (extra or {}).items():
        rec[k] = a
    hdr = ["ply", "format binary_little_endian 1.0", f"element vertex {len(xyz)}"]
    hdr += [f"property float {k}" for k, _ in fields] + ["end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(hdr) + "\n").encode("ascii"))
        f.write(rec.tobytes())


def read_pcd_header(f):
    """Reads a PCD header from the binary file f up to its DATA line; returns {key: [values]} (f then holds
    the body)."""
    hdr = {}
    while True:
        line = f.readline().decode("ascii").strip()
        if not line or line.startswith("#"):
            continue
        k, *v = line.split()
        hdr[k] = v
        if k == "DATA":
            return hdr


def read_ply_xyz(path):
    with open(path, "rb") as f:
        n, props = 0, []
        while True:
            line = f.readline().decode("ascii").strip()
            if line.startswith("element vertex"):
                n = int(line.split()[-1])
            elif line.startswith("property"):
                props.append(line.split()[-1])
            elif line == "end_header":
                break
        a = np.frombuffer(f.read(), dtype=[(p, "<f4") for p in props], count=n)
    return np.stack([a["x"], a["y"], a["z"]], 1).astype(np.float64)


def project(xyz_w, T_cw, K, dist=None):
    Xc = xyz_w @ T_cw[:3, :3].T + T_cw[:3, 3]
    keep = Xc[:, 2] > 0.1
    Xc = Xc[keep]
    if dist is not None and len(dist):
        uv = cv2.projectPoints(Xc.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.asarray(dist, float))[
            0
        ].reshape(-1, 2)
    else:
        uv = Xc[:, :2] / Xc[:, 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    return uv, Xc[:, 2]


def overlay(img, xyz_w, T_cw, K, out_path, dist=None, radius=1, alpha=0.75, zmax=40.0, max_pts=400000):
    """Cloud points coloured by depth (JET, near = red) blended over the image."""
    h, w = img.shape[:2]
    if len(xyz_w) > max_pts:
        xyz_w = xyz_w[np.random.default_rng(0).choice(len(xyz_w), max_pts, replace=False)]
    uv, z = project(xyz_w, T_cw, K, dist)
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    uv, z = uv[ok], z[ok]
    layer = img.copy()
    zmax = zmax or np.percentile(z, 98)
    cols = cv2.applyColorMap(
        (255 * (1 - np.clip(z / zmax, 0, 1))).astype(np.uint8).reshape(-1, 1), cv2.COLORMAP_JET
    ).reshape(-1, 3)
    for i in np.argsort(-z):
        cv2.circle(layer, (int(uv[i, 0]), int(uv[i, 1])), radius, tuple(int(c) for c in cols[i]), -1)
    cv2.imwrite(out_path, cv2.addWeighted(layer, alpha, img, 1 - alpha, 0))
    return len(z)


def rot(axis, deg):
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    if axis == 0:
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == 1:
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def edge_points(uv, z, w, h, win=3, ratio=1.25):
    """Foreground depth-discontinuity points: a projected point with a point at least `ratio` times farther
    within +-win px (z-buffer on a pixel grid)."""
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    uv, z = uv[ok], z[ok]
    ui, vi = uv[:, 0].astype(int), uv[:, 1].astype(int)
    zmin = np.full((h, w), np.inf)
    np.minimum.at(zmin, (vi, ui), z)
    zmax = np.zeros((h, w))
    np.maximum.at(zmax, (vi, ui), z)
    k = np.ones((2 * (win // 3) + 3, 2 * win + 1), np.uint8)  # wider along the scan lines
    zfar = cv2.dilate(zmax.astype(np.float32), k)
    e = (z <= zmin[vi, ui] + 1e-6) & (zfar[vi, ui] > ratio * z)
    return uv[e]


def edgecheck(img, xyz_w, T_cw, K, dist=None, trunc=15.0, win=3):
    """Mean (truncated) distance of cloud depth-discontinuity points to Canny edges, at the pose and at
    +-0.5/1 deg rotations about the camera x, y, z axes. Returns (score_gt, {perturbation: score})."""
    h, w = img.shape[:2]
    g = cv2.GaussianBlur(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), (5, 5), 1.2)
    edges = cv2.Canny(g, 40, 120)
    dt = cv2.distanceTransform(255 - edges, cv2.DIST_L2, 5)

    def score(T):
        uv, z = project(xyz_w, T, K, dist)
        p = edge_points(uv, z, w, h, win)
        if len(p) == 0:
            return np.nan, 0
        return float(np.minimum(dt[p[:, 1].astype(int), p[:, 0].astype(int)], trunc).mean()), len(p)

    s0, n0 = score(T_cw)
    out = {}
    for ax in range(3):
        for d in (-1, -0.5, 0.5, 1):
            T = T_cw.copy()
            T[:3, :3] = rot(ax, d) @ T_cw[:3, :3]
            T[:3, 3] = rot(ax, d) @ T_cw[:3, 3]
            out["xyz"[ax] + f"{d:+.1f}"] = score(T)[0]
    return s0, n0, out


def set_header(out, n_points):
    """The fields every set's cameras.json starts with: its folder name, the convention, its cloud and size."""
    name = os.path.basename(os.path.normpath(str(out)))
    return {"set": name, "convention": CONVENTION, "cloud": "cloud.ply", "n_points": int(n_points)}


def mat(T):
    return [[float(x) for x in row] for row in T]


def cam_entry(name, K, w, h, T, dist=None, model=None, **kw):
    d = {
        "file": name,
        "width": int(w),
        "height": int(h),
        "fx": float(K[0, 0]),
        "fy": float(K[1, 1]),
        "cx": float(K[0, 2]),
        "cy": float(K[1, 2]),
        "distortion": {
            "model": model or "none",
            "coeffs": [float(x) for x in (dist if dist is not None else [])],
        },
        "T_cam_from_world": mat(T),
    }
    d.update(kw)
    return d
