"""extra_data scene mlcc_livox_mid40_courtyard from hku-mars/mlcc (commit 20f3b3a4): scene2, Livox MID-100 clouds
(three Mid-40 units, non-repetitive rosette scans, each accumulated while the platform stood still) + the two 1280x1024
cameras of the same rig, with MLCC's own calibration results:
  scene2/pose.json   base-LiDAR (Livox AVIA) pose of each of the 22 platform stations, `tx ty tz qw qx qy qz`,
                     world = AVIA frame at station 0 (T_world_from_avia_j: x_world = R x_avia + t)
  scene2/ref.json    MID-100 units L0, L1, L2 -> AVIA extrinsics, same format (x_avia = R x_mid + t)
  result/extrinsic.txt  two 4x4 AVIA -> camera extrinsics (x_cam = T x_avia), left camera then right camera
  config/left.yaml, config/right.yaml  K and 5 OpenCV distortion coefficients (k1 k2 p1 p2 k3)
Only three MID-100 clouds are stored in the repo (the others are LFS-less large blobs absent from the snapshot):
scene2/1/10.pcd, scene2/2/12.pcd, scene2/2/13.pcd. The MID-100 faces backwards relative to the AVIA/cameras (ref.json
has a ~180 deg yaw), so these clouds see what the cameras see at stations 0, 1 and 21.
World = MLCC world (AVIA frame at station 0; x forward, y left, z up), metres.
Usage: python build_mlcc_livox.py REPO_EXTRACT_DIR OUT   (REPO_EXTRACT_DIR holds scene2/, config/, result/)"""

import json
import re
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import cam_entry, edgecheck, overlay, read_pcd_header, set_header, write_ply

CLOUDS = [(1, 10), (2, 12), (2, 13)]  # (MID-100 unit, station) present in the repo
IMAGES = [(0, 0), (0, 21), (0, 1), (1, 0), (1, 21)]  # (camera 0=left 1=right, station)


def read_pcd_binary(path):
    with open(path, "rb") as f:
        hdr = read_pcd_header(f)
        body = f.read()
    assert (
        hdr["DATA"][0] == "binary"
        and hdr["FIELDS"] == ["x", "y", "z", "intensity"]
        and hdr["TYPE"] == ["F"] * 4
    )
    a = np.frombuffer(body, dtype="<f4", count=4 * int(hdr["POINTS"][0])).reshape(-1, 4)
    return a[:, :3].astype(np.float64), a[:, 3].copy()


def T7(vals):
    tx, ty, tz, w, x, y, z = vals
    n = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    T = np.eye(4)
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    T[:3, 3] = [tx, ty, tz]
    return T


def read_lines(path):
    return [list(map(float, ln.split())) for ln in open(path) if ln.strip()]


def opencv_yaml_matrix(text, name):
    m = re.search(name + r":\s*!!opencv-matrix.*?data:\s*\[([^\]]*)\]", text, re.S)
    return np.array([float(v) for v in m.group(1).replace("\n", " ").split(",")])


def voxel_down(xyz, inten, vox):
    key = np.floor(xyz / vox).astype(np.int64)
    _, _idx, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inv = inv.ravel()
    cnt = np.bincount(inv).astype(float)
    out = np.stack([np.bincount(inv, xyz[:, i]) / cnt for i in range(3)], 1)
    return out, (np.bincount(inv, inten) / cnt).astype(np.float32)


def main(src, out):
    src, out = Path(src), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    poses = [T7(v) for v in read_lines(src / "scene2/pose.json")]
    refs = [T7(v) for v in read_lines(src / "scene2/ref.json")]
    ext = np.array(
        [float(v) for v in open(src / "result/extrinsic.txt").read().replace(",", " ").split()]
    ).reshape(-1, 4, 4)
    cams = []
    for f in ("config/left.yaml", "config/right.yaml"):
        t = open(src / f).read()
        cams.append((opencv_yaml_matrix(t, "CameraMat").reshape(3, 3), opencv_yaml_matrix(t, "DistCoeffs")))
    for T in list(refs) + list(poses) + list(ext):
        R = T[:3, :3]
        assert abs(np.linalg.det(R) - 1) < 1e-4 and np.abs(R @ R.T - np.eye(3)).max() < 1e-4
    for E in ext:  # snap the printed (6-digit) rotations to SO(3)
        U, _, Vt = np.linalg.svd(E[:3, :3])
        E[:3, :3] = U @ Vt
    pts, its = [], []
    for unit, st in CLOUDS:
        xyz, it = read_pcd_binary(src / f"scene2/{unit}/{st}.pcd")
        ok = np.isfinite(xyz).all(1) & (np.linalg.norm(xyz, axis=1) > 0.3)
        T = poses[st] @ refs[unit]  # MID unit at station st -> world
        pts.append(xyz[ok] @ T[:3, :3].T + T[:3, 3])
        its.append(it[ok])
        print(f"unit L{unit} station {st}: {ok.sum()} points")
    xyz, inten = np.concatenate(pts), np.concatenate(its)
    n_raw = len(xyz)
    xyz, inten = voxel_down(xyz, inten, 0.02)
    print(f"merged {n_raw} -> {len(xyz)} points after 2 cm voxel averaging")
    write_ply(out / "cloud.ply", xyz.astype(np.float32), {"intensity": inten})
    entries = []
    for cam, st in IMAGES:
        K, D = cams[cam]
        name = f"{'left' if cam == 0 else 'right'}_{st:02d}.png"
        shutil.copyfile(src / f"scene2/image/{cam}/{st}.png", out / name)
        img = cv2.imread(str(out / name))
        h, w = img.shape[:2]
        T = ext[cam] @ np.linalg.inv(poses[st])  # world -> AVIA at station st -> camera
        n = overlay(img, xyz, T, K, str(out / f"check_{Path(name).stem}.png"), dist=D, radius=1, zmax=25.0)
        s0, ne, pert = edgecheck(img, xyz, T, K, dist=D)
        print(
            f"{name}: in view {n}; edgecheck {s0:.2f} px ({ne} pts); perturbed min {min(pert.values()):.2f} "
            f"({min(pert, key=pert.get)}); " + " ".join(f"{k} {v:.2f}" for k, v in pert.items())
        )
        entries.append(
            cam_entry(
                name,
                K,
                w,
                h,
                T,
                D,
                "opencv_radtan_k1k2p1p2k3",
                note=f"{'left' if cam == 0 else 'right'} camera at platform station {st}",
            )
        )
    meta = {
        **set_header(out, len(xyz)),
        "cloud_properties": "x y z (float32, metres) + intensity (float32, as shipped); three Livox Mid-40 "
        "rosette scans (MID-100 units L1@station10, L2@station12, L2@station13) merged, "
        "2 cm voxel-averaged",
        "world_frame": "MLCC world = Livox AVIA frame at platform station 0 (x forward, y left, z up)",
        "images": entries,
    }
    json.dump(meta, open(out / "cameras.json", "w"), indent=1)


if __name__ == "__main__":
    main(*sys.argv[1:3])
