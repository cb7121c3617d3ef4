"""extra set nuscenes_n015_demo from open-mmlab/mmdetection3d (commit fe25f7a5, demo/data/nuscenes/):
n015-2018-07-24-11-22-45+0800.pkl (mmdet3d v2 info of one nuScenes v1.0-mini keyframe: per camera cam2img,
lidar2cam), the LIDAR_TOP sweep .pcd.bin (float32 x y z intensity ring) and the 6 camera JPEGs (1600x900,
nuScenes images are undistorted). World = LIDAR_TOP frame of the sweep. .pkl read with a whitelist unpickler.
Usage: python build_nuscenes_mmdet3d.py DEMO_NUSCENES_DIR OUT"""

import importlib
import json
import os
import pickle
import shutil
import sys

import cv2
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import cam_entry, edgecheck, overlay, set_header, write_ply

ALLOWED = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "scalar"),
    ("collections", "OrderedDict"),
    ("builtins", "set"),
    ("builtins", "slice"),
    ("_codecs", "encode"),
}


class SafeUnpickler(pickle.Unpickler):
    def find_class(self, mod, name):
        if (mod, name) in ALLOWED:
            return getattr(importlib.import_module(mod), name)
        raise pickle.UnpicklingError(f"blocked {mod}.{name}")


src, out = sys.argv[1], sys.argv[2]
os.makedirs(out, exist_ok=True)
info = SafeUnpickler(open(os.path.join(src, "n015-2018-07-24-11-22-45+0800.pkl"), "rb")).load()["data_list"][
    0
]
lp = info["lidar_points"]
pts = np.fromfile(os.path.join(src, lp["lidar_path"]), dtype=np.float32).reshape(-1, lp["num_pts_feats"])
r = np.linalg.norm(pts[:, :2], axis=1)
keep = np.isfinite(pts[:, :3]).all(1) & (r > 1.0)  # drop ego-vehicle returns (as the nuScenes devkit does)
pts = pts[keep]
print("points", len(pts), "of", len(keep))
write_ply(os.path.join(out, "cloud.ply"), pts[:, :3], extra={"intensity": pts[:, 3]})
L2E = np.asarray(lp["lidar2ego"], float)
images = []
for cam in ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT"]:
    c = info["images"][cam]
    K = np.asarray(c["cam2img"], float)[:3, :3]
    T = np.asarray(c["lidar2cam"], float)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    static = np.linalg.inv(np.asarray(c["cam2ego"], float)) @ L2E  # same instant (no ego motion)
    d = T @ np.linalg.inv(static)
    motion = (np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1))), np.linalg.norm(d[:3, 3]))
    name = f"{cam.lower()}.jpg"
    shutil.copy(os.path.join(src, c["img_path"]), os.path.join(out, name))
    img = cv2.imread(os.path.join(out, name))
    n = overlay(
        img, pts[:, :3].astype(float), T, K, os.path.join(out, f"check_{cam.lower()}.png"), radius=2, zmax=40
    )
    s0, ne, per = edgecheck(
        img, pts[:, :3].astype(float), T, K, win=int(np.ceil(K[0, 0] * np.radians(0.33) * 1.6))
    )
    print(
        f"{cam}: in view {n}, det {np.linalg.det(T[:3, :3]):.6f}, dt {c['timestamp'] - info['timestamp']:+.3f}s, "
        f"ego-motion part of lidar2cam {motion[0]:.3f} deg / {motion[1]:.3f} m; edgecheck {s0:.2f} px ({ne} pts), "
        f"perturbed min {min(per.values()):.2f} ({min(per, key=per.get)})"
    )
    images.append(
        cam_entry(
            name,
            K,
            img.shape[1],
            img.shape[0],
            T,
            note=f"nuScenes {cam}, image {c['img_path']} (timestamp {c['timestamp']:.6f} s; lidar "
            f"{info['timestamp']:.6f} s); T = mmdet3d lidar2cam (includes the ego motion between "
            "the two timestamps)",
        )
    )
meta = {
    **set_header(out, len(pts)),
    "cloud_properties": "x y z (float32, metres, nuScenes LIDAR_TOP frame, Velodyne HDL-32E) + intensity (float32, "
    "0..255 as shipped); one sweep, points within 1 m (horizontal) of the sensor removed",
    "world_frame": "LIDAR_TOP frame of the single sweep (nuScenes: x right, y forward, z up)",
    "images": images,
}
json.dump(meta, open(os.path.join(out, "cameras.json"), "w"), indent=1)
