"""Multi-frame KITTI-raw rig set: N frames of ONE 2011_09_26 drive sharing ONE camera-LiDAR calibration.

Data:  github.com/udacity/SFND_3D_Object_Tracking @ 3f2864369a4fc3afa88cbff39423566164a83d00
         images/KITTI/2011_09_26/image_02/data/00000000NN.png   (rectified left colour camera, 1242x375)
         images/KITTI/2011_09_26/velodyne_points/data/00000000NN.bin (float32 x y z reflectance, Velodyne frame)
       78 consecutive synced frames 0000000000..0000000077 of one 2011_09_26 drive (drive number not stated).
Calib: github.com/JarnoRalli/python_camera_library @ 8e484063920fc9c96cb7886af0a9440e6041c8c2
         test_data/kitti/2011_09_26_calib/2011_09_26/{calib_cam_to_cam,calib_velo_to_cam}.txt
       (the official 2011_09_26 calibration; cross-checked against the values hard-coded in the Udacity repo's
       src/FinalProject_Camera.cpp: RT = velo_to_cam, R_rect_00, P_rect_00).

T_cam_from_world = [I | K^-1 P_rect_02[:,3]] . R_rect_00 . Tr_velo_to_cam, K = P_rect_02[:, :3]
(the KITTI raw devkit's x = P_rect_02 R_rect_00 Tr_velo_to_cam X; same split as build_kitti.py's P2/R0_rect/Tr).
The same T for every frame. cloud.ply = the full sweep as shipped (all points, x y z + intensity float32).

Usage: python build_kitti_rig.py [--out OUT] [--frames 0,5,10,...] [--check PNG]
Needs: numpy, opencv; git (reads the two bare mirrors with `git show`); common.py
next to this file.
"""

import argparse
import json
import os
import re
import subprocess
import sys

import cv2
import numpy as np

sys.dont_write_bytecode = True
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import cam_entry, edgecheck, overlay, project, set_header, write_ply  # noqa: E402

UDACITY = ("udacity/SFND_3D_Object_Tracking", "3f2864369a4fc3afa88cbff39423566164a83d00")
JARNO = ("JarnoRalli/python_camera_library", "8e484063920fc9c96cb7886af0a9440e6041c8c2")
MIRROR = "/work/.mirror/{}/repo"
IMG = "images/KITTI/2011_09_26/image_02/data/{:010d}.png"
VELO = "images/KITTI/2011_09_26/velodyne_points/data/{:010d}.bin"
CALIB = "test_data/kitti/2011_09_26_calib/2011_09_26/{}.txt"
NAME = "kitti_2011_09_26_sfnd"


def git_show(repo, commit, path):
    gd = MIRROR.format(repo.replace("/", "+"))
    blob = subprocess.run(
        ["git", "--git-dir", gd, "show", f"{commit}:{path}"], check=True, capture_output=True
    ).stdout
    if blob.startswith(b"version https://git-lfs"):
        raise SystemExit(f"{repo}:{path} is a Git LFS pointer, not data")
    return blob


def parse_calib(text):
    cal = {}
    for line in text.splitlines():
        if ":" in line:
            k, v = line.split(":", 1)
            try:
                cal[k.strip()] = np.array([float(x) for x in v.split()])
            except ValueError:
                pass  # calib_time
    return cal


def udacity_hardcoded(src):
    """{name: 4x4} of the RT / R_rect_00 / P_rect_00 .at<double>(i,j) assignments in FinalProject_Camera.cpp."""
    out = {}
    for name, i, j, v in re.findall(r"(\w+)\.at<double>\((\d),(\d)\)\s*=\s*([-+0-9.eE]+)", src):
        out.setdefault(name, np.zeros((4, 4)))[int(i), int(j)] = float(v)
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="/work/extra_data_rig")
    ap.add_argument("--frames", default=",".join(str(i) for i in range(0, 78, 5)))
    ap.add_argument("--check", default=None)
    a = ap.parse_args()
    frames = [int(x) for x in a.frames.split(",")]

    c2c = parse_calib(git_show(*JARNO, CALIB.format("calib_cam_to_cam")).decode())
    v2c = parse_calib(git_show(*JARNO, CALIB.format("calib_velo_to_cam")).decode())
    P2 = c2c["P_rect_02"].reshape(3, 4)
    R0 = np.eye(4)
    R0[:3, :3] = c2c["R_rect_00"].reshape(3, 3)
    Tv = np.eye(4)
    Tv[:3, :3] = v2c["R"].reshape(3, 3)
    Tv[:3, 3] = v2c["T"]
    W, H = (int(x) for x in c2c["S_rect_02"])
    # cross-check against the Udacity repo's own hard-coded calibration (same date)
    hc = udacity_hardcoded(git_show(*UDACITY, "src/FinalProject_Camera.cpp").decode())
    assert np.allclose(hc["RT"], Tv, atol=0), "velo_to_cam differs from the Udacity repo's RT"
    assert np.allclose(hc["R_rect_00"], R0, atol=0), "R_rect_00 differs"
    assert np.allclose(hc["P_rect_00"][:3, :3], P2[:, :3], atol=0), "intrinsics differ"

    K = P2[:, :3].copy()
    T2 = np.eye(4)
    T2[:3, 3] = np.linalg.solve(K, P2[:, 3])  # P_rect_02 = K [I | t2]
    T_cw = T2 @ R0 @ Tv
    assert np.allclose(K @ T_cw[:3, :], P2 @ R0 @ Tv, atol=1e-9)
    R = T_cw[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-5), np.abs(R @ R.T - np.eye(3)).max()
    print("K", K.round(4).tolist(), "image", W, H)
    print("t2", T2[:3, 3].round(5), "T_cam_from_velo\n", T_cw.round(6))

    os.makedirs(a.out, exist_ok=True)
    log, checks = [], []
    for f in frames:
        img_blob = git_show(*UDACITY, IMG.format(f))
        pts = np.frombuffer(git_show(*UDACITY, VELO.format(f)), dtype="<f4").reshape(-1, 4)
        out = os.path.join(a.out, f"{NAME}_{f:010d}")
        os.makedirs(out, exist_ok=True)
        name = f"image_02_{f:010d}.png"
        with open(os.path.join(out, name), "wb") as fh:
            fh.write(img_blob)  # byte for byte
        img = cv2.imread(os.path.join(out, name))
        assert img.shape[:2] == (H, W), img.shape
        # KITTI's own projection equals ours
        Xh = np.c_[pts[:, :3].astype(float), np.ones(len(pts))]
        pa = (P2 @ R0 @ Tv @ Xh.T).T
        pb = (K @ (T_cw @ Xh.T)[:3]).T
        front = pa[:, 2] > 0.1
        assert np.allclose(pa[front, :2] / pa[front, 2:], pb[front, :2] / pb[front, 2:], atol=1e-9)
        write_ply(os.path.join(out, "cloud.ply"), pts[:, :3], extra={"intensity": pts[:, 3]})
        xyz = pts[:, :3].astype(np.float64)
        uv, _ = project(xyz, T_cw, K)
        inside = int(((uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)).sum())
        chk = os.path.join(out, f"check_image_02_{f:010d}.png")
        overlay(img, xyz, T_cw, K, chk)
        s0, ne, per = edgecheck(img, xyz, T_cw, K, win=3)
        best = min(per, key=per.get)
        line = (
            f"{f:010d} points {len(pts)} in front {int(front.sum())} in image {inside}; edgecheck GT {s0:.2f} px "
            f"({ne} edge pts); perturbed min {per[best]:.2f} ({best}); "
            + " ".join(f"{k} {v:.2f}" for k, v in per.items())
        )
        print(line)
        log.append(line)
        checks.append(chk)
        meta = {
            **set_header(out, len(pts)),
            "cloud_properties": "x y z (float32, metres, Velodyne HDL-64E frame) + intensity (float32, 0..1); "
            "full 360 deg sweep as shipped",
            "world_frame": "Velodyne frame of the single scan: x forward, y left, z up",
            "rig": f"{NAME}: {len(frames)} frames of one 2011_09_26 KITTI raw drive, one calibration "
            "(T_cam_from_world identical in every frame)",
            "images": [
                cam_entry(
                    name,
                    K,
                    W,
                    H,
                    T_cw,
                    note="rectified left colour camera (cam 2); T = [I|K^-1 P_rect_02[:,3]] * R_rect_00 * "
                    f"Tr_velo_to_cam (2011_09_26 calib); KITTI raw 2011_09_26 frame {f:010d} "
                    "(udacity/SFND_3D_Object_Tracking)",
                )
            ],
        }
        with open(os.path.join(out, "cameras.json"), "w") as fh:
            json.dump(meta, fh, indent=1)
        with open(os.path.join(out, "SOURCE.md"), "w") as fh:
            fh.write(source_md(f, len(pts), line, K, W, H, T_cw, T2))
    # one montage of four overlays for the report
    pick = [checks[i] for i in np.linspace(0, len(checks) - 1, min(4, len(checks))).astype(int)]
    if a.check:
        cv2.imwrite(a.check, np.vstack([cv2.imread(p) for p in pick]))
    with open(os.path.join(a.out, "README.md"), "w") as fh:
        fh.write(readme_md(frames, K, W, H, T_cw, T2, log))
    print(
        "wrote",
        len(frames),
        "frames to",
        a.out,
        "; montage",
        a.check,
        "(frames",
        [os.path.basename(p)[15:25] for p in pick],
        ")",
    )


SRC_COMMON = f"""**Source (data):** GitHub `{UDACITY[0]}` (Udacity Sensor Fusion Nanodegree camera-course starter), commit
`{UDACITY[1]}`, paths `{IMG.format(0).replace("0000000000", "NNNNNNNNNN")}` and
`{VELO.format(0).replace("0000000000", "NNNNNNNNNN")}` (78 consecutive synced frames 0000000000..0000000077 of one
KITTI raw 2011_09_26 drive; the repo does not say which drive and ships no timestamps; real blobs, not LFS pointers).
**Source (calibration):** GitHub `{JARNO[0]}`, commit `{JARNO[1]}`, paths
`{CALIB.format("calib_cam_to_cam")}`, `{CALIB.format("calib_velo_to_cam")}` (the official 2011_09_26 calibration:
calib_time 09-Jan-2012 / 15-Mar-2012); identical to the RT, R_rect_00 and P_rect_00 hard-coded in the Udacity repo's
`src/FinalProject_Camera.cpp` (asserted by the build).
**Licence:** the data is KITTI raw (Geiger, Lenz, Stiller, Urtasun, IJRR 2013), CC BY-NC-SA 3.0 (non-commercial,
cite KITTI). The Udacity repo has no LICENSE file; python_camera_library's test_data/kitti/README.md credits KITTI.
Nobody on the team produced this data.
"""


def conv_md(K, W, H, T_cw, T2):
    return f"""**Conventions:** KITTI raw projects x = P_rect_02 · R_rect_00 · Tr_velo_to_cam · X_velo. We split P_rect_02 = K [I | t2],
t2 = K⁻¹ P_rect_02[:,3] = {np.round(T2[:3, 3], 4).tolist()} m (cam 2's offset from the rectified cam 0), and store
`T_cam_from_world = [I|t2] · R_rect_00 · Tr_velo_to_cam` (OpenCV axes, as KITTI), the **same matrix in every frame of
the rig**; fx = fy = {K[0, 0]}, cx = {K[0, 2]}, cy = {K[1, 2]}; image {W}x{H}, no distortion (rectified).
Asserted K·T[:3] == P_rect_02·R_rect_00·Tr to 1e-9 and that every in-front point projects to KITTI's own pixel to 1e-9.
T_cam_from_world (rows): {np.round(T_cw[:3], 6).tolist()}
"""


def source_md(f, n, line, K, W, H, T_cw, T2):
    return f"""# {NAME}_{f:010d} — KITTI raw 2011_09_26, frame {f:010d} (one of a multi-frame rig set)

**Scene:** slow stop-and-go traffic on a multi-lane urban arterial under a road bridge (Karlsruhe): a silver VW
(plate KA JS 6312) ahead in the ego lane, a cement tanker truck on the right, cars and a red flat-bed truck on the left,
trees, lamp posts and a second bridge in the distance. The ego car creeps forward over the 78 frames.
{SRC_COMMON}
**Contents:** `image_02_{f:010d}.png` (rectified left colour camera, copied byte for byte); `cloud.ply` = one Velodyne
HDL-64E sweep, all 360° as shipped ({n:,} points; x,y,z + intensity float32; world = Velodyne frame, x forward, y
left, z up); `cameras.json` (one image); `check_image_02_{f:010d}.png` (cloud over the image, JET by depth, near =
red, 0–40 m). The LiDAR covers only the lower part of the image (vertical FOV about +2° to -25°); moving objects
(the cars around) are in the scan.

{conv_md(K, W, H, T_cw, T2)}
**Checks:** build log (edgecheck = mean distance, truncated at 15 px, of the cloud's depth-discontinuity points to
Canny edges at the pose and at ±0.5°/±1° about the camera x, y, z axes; lower is better):
```
{line}
```
Ground truth = KITTI's own calibration (typically ≲ 1–2 px); single sweep, not motion-compensated (the ego moves
slowly here); the synced velodyne frame is the sweep KITTI paired with this image (no timestamps in the source).

## Rebuild
`python docs/extra_data/build/build_kitti_rig.py --out OUT` (numpy + OpenCV + git; it reads the two repositories'
bare mirrors at the commits above with `git show`, which `fetch` brings, and `common.py` beside it).
"""


def readme_md(frames, K, W, H, T_cw, T2, log):
    return f"""# {NAME}: {len(frames)} frames of ONE KITTI raw rig (2011_09_26), one camera-LiDAR calibration

Each sub-folder `{NAME}_NNNNNNNNNN/` is one scene in the `shared/data` layout (cameras.json + cloud.ply + photo +
SOURCE.md): the rectified left colour photo (image_02) and the Velodyne sweep taken with it. The calibration
(intrinsics and T_cam_from_world = camera-from-Velodyne) is the same in every folder, so the set can be used to
estimate one extrinsic over several frames.

Frames: {", ".join(f"{f:010d}" for f in frames)} (every 5th of 78 consecutive 10 Hz frames, ~0.5 s apart).

{SRC_COMMON}
{conv_md(K, W, H, T_cw, T2)}
Build log:
```
{chr(10).join(log)}
```
"""


if __name__ == "__main__":
    main()
