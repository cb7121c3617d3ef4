"""extra set sun3d_cubicles from andyzeng/3dmatch-toolbox (commit 4b4a3687, data/sample/depth-fusion-demo/:
camera-intrinsics.txt, fragment-1-rgbd-frames/frame-000935..000984.{color.png,depth.png,pose.txt},
fragment-2-rgbd-frames/frame-003160..003209.{color.png,depth.png,pose.txt}); a SUN3D scene (real Asus Xtion) in
3DMatch RGB-D format: depth 16-bit PNG in mm registered to the colour image (one K for both), pose.txt = 4x4
camera-to-world (OpenCV camera axes).
cloud.ply = TSDF fusion of every 2nd depth map of both fragments (50 maps, depth < MAXD; voxel TSDF_VOXEL, truncation
TRUNC, weight 1 per frame; surface = zero crossings between neighbouring voxels, then VOXEL centroids);
cloud_without_rgb_<frame>.ply = the same fusion WITHOUT the depth of that frame and of its neighbours within +-EXCL
frames of the same fragment (consecutive 30 Hz frames are near-identical views).
Usage: python build_sun3d_cubicles.py SRC_DEPTH_FUSION_DEMO_DIR OUT     (numpy + opencv + scipy)"""

import json
import os
import shutil
import sys

import cv2
import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import cam_entry, edgecheck, overlay, set_header, write_ply

VOXEL, MAXD, EXCL, TSDF_VOXEL, TRUNC, STEP = 0.01, 4.5, 10, 0.015, 0.06, 2
FRAGMENTS = {"fragment-1-rgbd-frames": range(935, 985), "fragment-2-rgbd-frames": range(3160, 3210)}
QUERIES = [945, 967, 984, 3172, 3193, 3209]  # sharpest (variance of Laplacian) in each third of each fragment


def voxel_downsample(xyz, voxel):
    keys = np.floor(xyz / voxel).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    out = np.zeros((counts.size, 3))
    np.add.at(out, inv.ravel(), xyz)
    return out / counts[:, None]


def transform(T, xyz):
    return xyz @ T[:3, :3].T + T[:3, 3]


def backproject(depth_m, K, max_depth, step=1):
    v, u = np.mgrid[0 : depth_m.shape[0] : step, 0 : depth_m.shape[1] : step]
    d = depth_m[::step, ::step]
    ok = (d > 0) & (d < max_depth)
    z = d[ok]
    return np.stack([(u[ok] - K[0, 2]) * z / K[0, 0], (v[ok] - K[1, 2]) * z / K[1, 1], z], 1)


def tsdf_surface(fr, K, shape, origin, dims):
    """TSDF-fuse the (T_wc, depth_m) pairs `fr` on a dense grid (origin, dims, TSDF_VOXEL); return the surface points
    (zero crossings between 6-neighbours with weight > 0 on both sides), then VOXEL centroids."""
    h, w = shape
    tsdf = np.ones(int(np.prod(dims)), np.float32)
    wgt = np.zeros(int(np.prod(dims)), np.float32)
    ii, jj, kk = np.unravel_index(np.arange(int(np.prod(dims))), dims)
    centres = origin + (np.stack([ii, jj, kk], 1) + 0.5) * TSDF_VOXEL
    del ii, jj, kk
    for T_wc, d in fr:
        T_cw = np.linalg.inv(T_wc)
        for lo in range(0, len(centres), 4_000_000):
            c = transform(T_cw, centres[lo : lo + 4_000_000])
            z = c[:, 2]
            front = z > 0.1
            u = np.full(len(c), -1, np.int64)
            v = np.full(len(c), -1, np.int64)
            u[front] = np.round(c[front, 0] / z[front] * K[0, 0] + K[0, 2]).astype(np.int64)
            v[front] = np.round(c[front, 1] / z[front] * K[1, 1] + K[1, 2]).astype(np.int64)
            ok = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            idx = np.nonzero(ok)[0]
            dm = d[v[idx], u[idx]]
            sdf = dm - z[idx]
            good = (dm > 0) & (sdf >= -TRUNC)
            idx, sdf = idx[good], np.minimum(sdf[good] / TRUNC, 1.0)
            g = lo + idx
            tsdf[g] = (tsdf[g] * wgt[g] + sdf) / (wgt[g] + 1)
            wgt[g] += 1
    tsdf, wgt = tsdf.reshape(dims), wgt.reshape(dims)
    pts = []
    for ax in range(3):
        a = [slice(None)] * 3
        b = [slice(None)] * 3
        a[ax] = slice(0, -1)
        b[ax] = slice(1, None)
        ta, tb, wa, wb = tsdf[tuple(a)], tsdf[tuple(b)], wgt[tuple(a)], wgt[tuple(b)]
        m = (wa > 0) & (wb > 0) & (np.sign(ta) != np.sign(tb)) & (np.abs(ta) < 1) & (np.abs(tb) < 1)
        i = np.argwhere(m).astype(np.float64)
        f = ta[m] / (ta[m] - tb[m])
        i[:, ax] += f
        pts.append(origin + (i + 0.5) * TSDF_VOXEL)
    return voxel_downsample(np.concatenate(pts), VOXEL)


def depth_agreement_splat(xyz_w, T_cw, K, depth_m, voxel=0.01, max_r=4):
    """Render the cloud (points splatted over ~their voxel footprint, z-buffer) and compare with a depth map."""
    h, w = depth_m.shape
    Xc = transform(T_cw, xyz_w)
    Xc = Xc[Xc[:, 2] > 0.1]
    z = Xc[:, 2]
    u = np.round(Xc[:, 0] / z * K[0, 0] + K[0, 2]).astype(np.int64)
    v = np.round(Xc[:, 1] / z * K[1, 1] + K[1, 2]).astype(np.int64)
    r = np.clip(np.round((K[0, 0] * voxel / z - 1) / 2), 0, max_r).astype(np.int64)
    zb = np.full((h, w), np.inf)
    for rr in np.unique(r):
        s = r == rr
        for du in range(-rr, rr + 1):
            for dv in range(-rr, rr + 1):
                a, b = u[s] + du, v[s] + dv
                ok = (a >= 0) & (a < w) & (b >= 0) & (b < h)
                np.minimum.at(zb, (b[ok], a[ok]), z[s][ok])
    m = np.isfinite(zb) & (depth_m > 0)
    d = zb[m] - depth_m[m]
    return (
        float(np.median(np.abs(d))),
        float((np.abs(d) < 0.02).mean()),
        float(np.median(d[np.abs(d) < 0.1])),
        int(m.sum()),
    )


def rot(axis, deg):
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return [
        np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    ][axis]


def nn_fit(tree, pts_cam, T_wc, trunc=0.05):
    """Truncated mean distance of camera-frame points (put in the world by camera-to-world T_wc) to the tree."""
    d, _ = tree.query(transform(T_wc, pts_cam), distance_upper_bound=trunc)
    return float(np.minimum(d, trunc).mean())


src, out = sys.argv[1], sys.argv[2]
os.makedirs(out, exist_ok=True)
K = np.loadtxt(os.path.join(src, "camera-intrinsics.txt"))  # 570.342, 570.342, 320, 240
frames = []  # (fragment, index, T_wc, depth_m)
depth_of = {}
for frag, ids in FRAGMENTS.items():
    for i in ids:
        p = os.path.join(src, frag, f"frame-{i:06d}")
        d = cv2.imread(p + ".depth.png", cv2.IMREAD_UNCHANGED).astype(np.float64) / 1000.0
        d = np.where(d < MAXD, d, 0)
        T_wc = np.loadtxt(p + ".pose.txt")
        assert abs(np.linalg.det(T_wc[:3, :3]) - 1) < 1e-4, p
        frames.append((frag, i, T_wc, d))
        if i in QUERIES:
            depth_of[i] = d
fused = [f for f in frames if (f[1] - next(iter(FRAGMENTS[f[0]]))) % STEP == 0]
allpts = np.concatenate([transform(f[2], backproject(f[3], K, MAXD, step=4)) for f in fused])
origin = np.percentile(allpts, 0.1, axis=0) - 3 * TSDF_VOXEL
dims = tuple(
    int(x) for x in np.ceil((np.percentile(allpts, 99.9, axis=0) + 3 * TSDF_VOXEL - origin) / TSDF_VOXEL)
)
print("TSDF grid", dims, "origin", origin.round(3), "fused depth maps", len(fused))
H, W = frames[0][3].shape
full = tsdf_surface([(f[2], f[3]) for f in fused], K, (H, W), origin, dims)
write_ply(os.path.join(out, "cloud.ply"), full)
print("cloud.ply points", len(full))
frag_cloud = {
    fr: tsdf_surface([(f[2], f[3]) for f in fused if f[0] == fr], K, (H, W), origin, dims) for fr in FRAGMENTS
}
images = []
for q in QUERIES:
    frag, _, T_wc, _ = next(f for f in frames if f[1] == q)
    own_fused = any(f[1] == q for f in fused)
    T_cw = np.linalg.inv(T_wc)
    name, stem = f"rgb_{q:06d}.png", f"rgb_{q:06d}"
    shutil.copy(os.path.join(src, frag, f"frame-{q:06d}.color.png"), os.path.join(out, name))
    keep = [(f[2], f[3]) for f in fused if not (f[0] == frag and abs(f[1] - q) <= EXCL)]
    loo = tsdf_surface(keep, K, (H, W), origin, dims)
    write_ply(os.path.join(out, f"cloud_without_{stem}.ply"), loo)
    img = cv2.imread(os.path.join(out, name))
    n_full = overlay(img, full, T_cw, K, os.path.join(out, f"check_{stem}.png"), zmax=5.0)
    n_loo = overlay(img, loo, T_cw, K, os.path.join(out, f"check_loo_{stem}.png"), zmax=5.0)
    med, f2, sgn, npx = depth_agreement_splat(loo, T_cw, K, depth_of[q], VOXEL)
    s0, ne, per = edgecheck(img, full, T_cw, K, win=3)
    print(
        f"{name} ({frag}): in view full {n_full}, loo {n_loo}; loo cloud {len(loo)} pts ({len(keep)} depth frames); "
        f"loo vs own depth: median|dz| {med * 100:.1f} cm, <2cm {f2 * 100:.0f}%, signed median {sgn * 100:+.1f} cm ({npx} px)"
    )
    print(
        f"  edgecheck GT {s0:.2f} px ({ne} edge pts); perturbed: "
        + ", ".join(f"{k} {v:.2f}" for k, v in per.items())
    )
    # cross-fragment check: this view's depth (< 4 m) against the OTHER fragment's points, pose perturbed
    other = next(fr for fr in FRAGMENTS if fr != frag)
    tree = cKDTree(frag_cloud[other])
    pc = backproject(np.where(depth_of[q] < 4.0, depth_of[q], 0), K, 4.0, step=4)
    base = nn_fit(tree, pc, T_wc)
    res = {}
    for ax in range(3):
        for dg in (-1.0, 1.0):
            T = T_wc.copy()
            T[:3, :3] = T_wc[:3, :3] @ rot(ax, dg)  # rotate about the camera's own axes
            res["rxyz"[ax] + f"{dg:+.0f}deg"] = nn_fit(tree, pc, T)
        for dt in (-0.03, 0.03):
            T = T_wc.copy()
            T[:3, 3] = T_wc[:3, 3] + T_wc[:3, ax] * dt  # shift along the camera's own axes
            res["txyz"[ax] + f"{dt * 100:+.0f}cm"] = nn_fit(tree, pc, T)
    print(
        f"  vs {other}: truncated mean NN {base * 1000:.1f} mm at GT; "
        + ", ".join(f"{k} {v * 1000:.1f}" for k, v in res.items())
    )
    images.append(
        cam_entry(
            name,
            K,
            img.shape[1],
            img.shape[0],
            T_cw,
            depth_in_cloud_ply=bool(own_fused),
            cloud_without_this_view=f"cloud_without_{stem}.ply",
            n_points_cloud_without_this_view=len(loo),
            note=f"{frag}/frame-{q:06d}; T_cam_from_world = inv(pose.txt); leave-out cloud drops "
            f"frames {q - EXCL}..{q + EXCL} of this fragment",
        )
    )
meta = {
    **set_header(out, len(full)),
    "voxel_m": VOXEL,
    "world_frame": "world frame of the 3DMatch/SUN3D pose files (unchanged)",
    "images": images,
}
with open(os.path.join(out, "cameras.json"), "w") as f:
    json.dump(meta, f, indent=1)
