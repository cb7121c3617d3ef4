"""extra KITTI object sets: one frame = calib txt (P2, R0_rect, Tr_velo_to_cam) + velodyne bin (float32 x y z
reflectance) + image_2 png (rectified left colour camera, copied byte for byte).
T_cam_from_world = [I | K^-1 P2[:,3]] . R0_rect . Tr_velo_to_cam; K = P2[:, :3]; asserted K.T[:3] == P2.R0.Tr (1e-9).
Usage: python build_kitti.py CALIB.txt VELO.bin IMAGE.png OUT "source note" "cloud note" """

import json
import os
import shutil
import sys

import cv2
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import cam_entry, edgecheck, overlay, set_header, write_ply

calib, velo, image, out, src_note, cloud_note = sys.argv[1:7]
os.makedirs(out, exist_ok=True)
cal = {}
for line in open(calib):
    if ":" in line:
        k, v = line.split(":", 1)
        if v.strip():
            cal[k.strip()] = np.array([float(x) for x in v.split()])
P2 = cal["P2"].reshape(3, 4)
R0 = np.eye(4)
R0[:3, :3] = cal["R0_rect"].reshape(3, 3)
Tv = np.eye(4)
Tv[:3, :] = cal["Tr_velo_to_cam"].reshape(3, 4)
K = P2[:, :3].copy()
T2 = np.eye(4)
T2[:3, 3] = np.linalg.solve(K, P2[:, 3])  # P2 = K [I | t2]
T_cw = T2 @ R0 @ Tv
assert np.allclose(K @ T_cw[:3, :], P2 @ R0 @ Tv, atol=1e-9)
pts = np.fromfile(velo, dtype=np.float32).reshape(-1, 4)
# the KITTI projection itself, for the record: x = P2 R0 Tr X
Xh = np.c_[pts[:, :3].astype(float), np.ones(len(pts))]
a = (P2 @ R0 @ Tv @ Xh.T).T
b = (K @ (T_cw @ Xh.T)[:3]).T
front = a[:, 2] > 0.1
assert np.allclose(a[front, :2] / a[front, 2:], b[front, :2] / b[front, 2:], atol=1e-9)
write_ply(os.path.join(out, "cloud.ply"), pts[:, :3], extra={"intensity": pts[:, 3]})
idx = os.path.splitext(os.path.basename(image))[0]
name = f"image_2_{idx}.png"
shutil.copy(image, os.path.join(out, name))
img = cv2.imread(os.path.join(out, name))
n = overlay(img, pts[:, :3].astype(np.float64), T_cw, K, os.path.join(out, f"check_image_2_{idx}.png"))
s0, ne, per = edgecheck(img, pts[:, :3].astype(np.float64), T_cw, K, win=3)
print(idx, "points", len(pts), "in view", n, "image", img.shape, "t2", T2[:3, 3].round(4))
print(
    f"  edgecheck GT {s0:.2f} px ({ne} edge pts); perturbed: "
    + ", ".join(f"{k} {v:.2f}" for k, v in per.items())
)
meta = {
    **set_header(out, len(pts)),
    "cloud_properties": "x y z (float32, metres, Velodyne HDL-64E frame) + intensity (float32, 0..1); "
    + cloud_note,
    "world_frame": "Velodyne frame of the single scan: x forward, y left, z up",
    "images": [
        cam_entry(
            name,
            K,
            img.shape[1],
            img.shape[0],
            T_cw,
            note="rectified left colour camera (cam 2); T = [I|K^-1 P2[:,3]] * R0_rect * Tr_velo_to_cam; "
            + src_note,
        )
    ],
}
json.dump(meta, open(os.path.join(out, "cameras.json"), "w"), indent=1)
