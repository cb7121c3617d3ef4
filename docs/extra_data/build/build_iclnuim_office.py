"""extra set iclnuim_office from JedrzejCzujewicz/ufomap_localmaps_iclnuim (commit 4f9a9b77, branch
pointcloud_visualizer, path tum_visualizer/src/traj0_frei_png/: rgb/<i>.png, depth/<i>.png, associations.txt,
traj0.gt.freiburg): the ICL-NUIM *office room*, trajectory kt0, in the TUM-compatible PNG release (rendered with
POV-Ray by Handa et al. 2014; depth 16-bit PNG, 5000 per metre, planar z, registered to the colour image).

ICL-NUIM conventions (verified below, not assumed): with the GT pose (traj0.gt.freiburg: `i tx ty tz qx qy qz qw`,
camera-to-world, row i = frame i) the depth back-projects consistently only with fy = -480 (fx 481.2, cx 319.5,
cy 239.5), i.e. the ICL camera has y pointing UP: a left-handed camera, so its world is a mirror image. We output a
proper OpenCV camera (y down) by mirroring the world about x: X_world_out = diag(-1, 1, 1) X_world_icl (this undoes
the "model mirrored about the X-axis" of the ICL renders), and T_cam_from_world = [F R M | F t] with
F = M' = diag(1, -1, 1) on the camera side, M = diag(-1, 1, 1) on the world side (det +1), fy = +480.

cloud.ply = every STEP-th depth map of the trajectory (depth < MAXD) back-projected and merged into VOXEL centroids
(voxels hit by >= MIN_VIEWS maps; the rendered depth is consistent to a few mm, so the plain union gives thin surfaces
and no TSDF is needed; open3d's TSDF volumes returned no surface in this environment); cloud_without_rgb_<i>.ply =
the same WITHOUT the depth maps of frames i-EXCL..i+EXCL.
sequence/ = every 2nd frame of SEQUENCE (15 Hz, 300 frames) with its pose, in the layout of
sevenscenes_redkitchen/sequence (frames.json: camera, rate_hz, frames [file, timestamp, T_cam_from_world]), for
`linereg bench sequence`; its map is ../cloud.ply.
Usage: python build_iclnuim_office.py SRC_TRAJ0_FREI_PNG_DIR OUT     (numpy + opencv + scipy)"""

import json
import os
import shutil
import sys

import cv2
import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import CONVENTION, cam_entry, edgecheck, overlay, set_header, write_ply

W, H, FX, FY_ICL, CX, CY, SCALE = 640, 480, 481.2, -480.0, 319.5, 239.5, 5000.0
VOXEL, MIN_VIEWS, MAXD, STEP, EXCL = 0.01, 2, 6.0, 8, 10
QUERIES = [50, 150, 350, 750, 1150, 1350]  # different views around the room (checked by eye)
SEQUENCE = range(2, 602, 2)  # the first 20 s of the trajectory at 15 Hz (the source renders 30 Hz)
CHECK_PAIRS = [(100, 160), (300, 400), (800, 900), (50, 1450)]
M_WORLD = np.diag([-1.0, 1.0, 1.0])  # world mirror
F_CAM = np.diag([1.0, -1.0, 1.0])  # ICL camera (y up) -> OpenCV camera (y down)
K = np.array([[FX, 0, CX], [0, -FY_ICL, CY], [0, 0, 1]])


def read_depth(src, i):
    return cv2.imread(os.path.join(src, "depth", f"{i}.png"), cv2.IMREAD_UNCHANGED).astype(np.float64) / SCALE


def backproject(d, fx, fy, step=1):
    v, u = np.mgrid[0 : d.shape[0] : step, 0 : d.shape[1] : step]
    z = d[::step, ::step]
    ok = (z > 0) & (z < MAXD)
    z = z[ok]
    return np.stack([(u[ok] - CX) * z / fx, (v[ok] - CY) * z / fy, z], 1)


def transform(T, xyz):
    return xyz @ T[:3, :3].T + T[:3, 3]


def pair_fit(src, gt, a, b, fy, off):
    """Median / quartiles (mm) of NN distances of frame b's depth (every 4th px) to frame a's (every px), both put in
    the ICL world with GT rows a+off / b+off and the given fy; and the overlap fraction (NN < 10 cm)."""
    pa = transform(gt[a + off], backproject(read_depth(src, a), FX, fy, 1))
    pb = transform(gt[b + off], backproject(read_depth(src, b), FX, fy, 4))
    d, _ = cKDTree(pa).query(pb, distance_upper_bound=0.1)
    d = d[np.isfinite(d)] * 1000
    return len(d) / len(pb), np.percentile(d, [25, 50, 75]) if len(d) else [np.nan] * 3


def fuse(src, ids, T_cw_of, step=2):
    """Union of the back-projected depth maps (every `step`-th px, depth < MAXD) in the output world, reduced to
    VOXEL centroids; a voxel is kept only if at least MIN_VIEWS of the maps put a point in it (drops stray pixels)."""
    keys, sums, cnts = [], [], []
    for i in ids:
        T_wc = np.linalg.inv(T_cw_of[i])
        p = transform(T_wc, backproject(read_depth(src, i), K[0, 0], K[1, 1], step))
        g = np.floor(p / VOXEL).astype(np.int64) + (1 << 20)
        k = (g[:, 0] << 42) | (g[:, 1] << 21) | g[:, 2]
        u, inv = np.unique(k, return_inverse=True)
        keys.append(u)
        sums.append(np.stack([np.bincount(inv, p[:, a], len(u)) for a in range(3)], 1))
        cnts.append(np.bincount(inv, minlength=len(u)))
    u, inv = np.unique(np.concatenate(keys), return_inverse=True)
    s = np.stack([np.bincount(inv, np.concatenate(sums)[:, a], len(u)) for a in range(3)], 1)
    n = np.bincount(inv, np.concatenate(cnts), len(u))
    views = np.bincount(inv, minlength=len(u))
    ok = views >= MIN_VIEWS
    return s[ok] / n[ok, None]


def zbuffer_agreement(xyz_w, T_cw, depth_m, r=1):
    """Render the cloud (points splatted over (2r+1)^2 px, z-buffer) and compare with a depth map."""
    Xc = transform(T_cw, xyz_w)
    Xc = Xc[Xc[:, 2] > 0.1]
    z = Xc[:, 2]
    u = np.round(Xc[:, 0] / z * K[0, 0] + K[0, 2]).astype(np.int64)
    v = np.round(Xc[:, 1] / z * K[1, 1] + K[1, 2]).astype(np.int64)
    zb = np.full((H, W), np.inf)
    for du in range(-r, r + 1):
        for dv in range(-r, r + 1):
            a, b = u + du, v + dv
            ok = (a >= 0) & (a < W) & (b >= 0) & (b < H)
            np.minimum.at(zb, (b[ok], a[ok]), z[ok])
    m = np.isfinite(zb) & (depth_m > 0)
    d = zb[m] - depth_m[m]
    return float(np.median(np.abs(d))), float((np.abs(d) < 0.02).mean()), float(m.mean())


src, out = sys.argv[1], sys.argv[2]
os.makedirs(out, exist_ok=True)
gt = {}  # GT row index -> T_world_icl_from_cam_icl
for line in open(os.path.join(src, "traj0.gt.freiburg")):
    v = line.split()
    if len(v) == 8:
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat([float(x) for x in v[4:8]]).as_matrix()
        T[:3, 3] = [float(x) for x in v[1:4]]
        gt[int(v[0])] = T
frames = sorted(i for i in gt if os.path.exists(os.path.join(src, "depth", f"{i}.png")))
print(
    f"GT rows {min(gt)}..{max(gt)} ({len(gt)}); frames with GT and depth {frames[0]}..{frames[-1]} ({len(frames)})"
)

print("convention check: NN distance (mm, q25/median/q75) of frame b's depth to frame a's, in the GT world")
for a, b in CHECK_PAIRS:
    for fy in (FY_ICL, -FY_ICL):
        for off in (-1, 0, 1):
            ov, q = pair_fit(src, gt, a, b, fy, off)
            print(
                f"  {a:4d}-{b:4d} fy {fy:+.0f} GT row offset {off:+d}: overlap {ov:.2f}, {q[0]:.1f}/{q[1]:.1f}/{q[2]:.1f}"
            )

T_cw = {}  # OpenCV camera from mirrored world
for i in frames:
    R, t = gt[i][:3, :3].T, -gt[i][:3, :3].T @ gt[i][:3, 3]
    T = np.eye(4)
    T[:3, :3] = F_CAM @ R @ M_WORLD
    T[:3, 3] = F_CAM @ t
    assert abs(np.linalg.det(T[:3, :3]) - 1) < 1e-6
    T_cw[i] = T

fused = frames[::STEP]
full = fuse(src, fused, T_cw)
write_ply(os.path.join(out, "cloud.ply"), full)
print(
    f"cloud.ply: {len(full)} points from {len(fused)} depth maps ({fused[0]}, {fused[1]}, ..., {fused[-1]})"
)
lo, hi = full.min(0), full.max(0)
print(f"  extent x {lo[0]:.2f}..{hi[0]:.2f}, y {lo[1]:.2f}..{hi[1]:.2f}, z {lo[2]:.2f}..{hi[2]:.2f} m")

images = []
for q in QUERIES:
    name, stem = f"rgb_{q:04d}.png", f"rgb_{q:04d}"
    shutil.copy(os.path.join(src, "rgb", f"{q}.png"), os.path.join(out, name))
    keep = [i for i in fused if abs(i - q) > EXCL]
    loo = fuse(src, keep, T_cw)
    write_ply(os.path.join(out, f"cloud_without_{stem}.ply"), loo)
    img = cv2.imread(os.path.join(out, name))
    n_full = overlay(img, full, T_cw[q], K, os.path.join(out, f"check_{stem}.png"), zmax=6.0)
    n_loo = overlay(img, loo, T_cw[q], K, os.path.join(out, f"check_loo_{stem}.png"), zmax=6.0)
    med, f2, cov = zbuffer_agreement(loo, T_cw[q], read_depth(src, q))
    s0, ne, per = edgecheck(img, full, T_cw[q], K, win=3)
    best = min(per, key=per.get)
    print(
        f"{name}: in view full {n_full}, loo {n_loo}; loo cloud {len(loo)} pts ({len(keep)} depth maps, "
        f"{q - EXCL}..{q + EXCL} left out); loo vs own depth: median|dz| {med * 1000:.1f} mm, <2cm {f2 * 100:.0f}%, "
        f"px covered {cov * 100:.0f}%"
    )
    print(
        f"  edgecheck GT {s0:.2f} px ({ne} edge pts); best perturbation {best} {per[best]:.2f}; "
        + ", ".join(f"{k} {v:.2f}" for k, v in per.items())
    )
    images.append(
        cam_entry(
            name,
            K,
            img.shape[1],
            img.shape[0],
            T_cw[q],
            depth_in_cloud_ply=q in fused,
            cloud_without_this_view=f"cloud_without_{stem}.ply",
            n_points_cloud_without_this_view=len(loo),
            note=f"ICL-NUIM office kt0 frame {q} (rgb/{q}.png, GT row {q}); T_cam_from_world = "
            f"[F R M | F t] of the inverted GT pose (F = diag(1,-1,1), M = diag(-1,1,1)); leave-out cloud drops "
            f"frames {q - EXCL}..{q + EXCL}",
        )
    )
meta = {
    **set_header(out, len(full)),
    "voxel_m": VOXEL,
    "world_frame": "ICL-NUIM office GT world (traj0.gt.freiburg) mirrored about x: X_out = diag(-1,1,1) X_icl; "
    "y is up (gravity along -y)",
    "images": images,
}
with open(os.path.join(out, "cameras.json"), "w") as f:
    json.dump(meta, f, indent=1)

seq = os.path.join(out, "sequence")
os.makedirs(seq, exist_ok=True)
entries = []
for i in SEQUENCE:
    name = f"frame_{i:04d}.png"
    shutil.copy(os.path.join(src, "rgb", f"{i}.png"), os.path.join(seq, name))
    entries.append({"file": name, "timestamp": i / 30.0, "T_cam_from_world": T_cw[i].tolist()})
camera = {"width": W, "height": H, "fx": FX, "fy": -FY_ICL, "cx": CX, "cy": CY}
sequence_meta = {
    "set": os.path.basename(os.path.normpath(out)) + "/sequence",
    "convention": CONVENTION,
    "cloud": "../cloud.ply",
    "camera": camera | {"distortion": {"model": "none", "coeffs": []}},
    "rate_hz": 15,
    "timestamps": "source frame index / 30 s (ICL-NUIM renders 30 Hz; every 2nd frame kept)",
    "frames": entries,
}
with open(os.path.join(seq, "frames.json"), "w") as f:
    json.dump(sequence_meta, f, indent=1)
print(
    f"sequence/: {len(entries)} frames ({SEQUENCE.start}..{SEQUENCE.stop - SEQUENCE.step}, every 2nd), 15 Hz"
)
