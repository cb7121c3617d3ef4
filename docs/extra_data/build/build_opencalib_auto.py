"""extra_data scenes from PJLab-ADG/SensorsCalibration (OpenCalib) lidar2camera auto-calibration samples
(commit 7fe8d46c): one 64-beam spinning-LiDAR sweep (binary_compressed PCD: x y z intensity ring timestamp) + one
1920x1200 raw (distorted) camera image + K, OpenCV distortion and the LiDAR->camera extrinsic shipped as the reference.
Usage: python build_opencalib_auto.py KIND SRC_DIR OUT
  KIND json: SRC_DIR = lidar2camera/auto_calib/data (calib.pcd, calib.png, center_camera-intrinsic.json,
             top_center_lidar-to-center_camera-extrinsic.json)
  KIND txt:  SRC_DIR = lidar2camera/auto_calib_v2.0/data/ours/N (calib.pcd, calib.jpg|png, calib.txt with K:, D:, T:)
World = LiDAR frame (x forward, y left, z up). T_cam_from_world = the extrinsic unchanged (x_cam = T x_lidar)."""

import json
import shutil
import struct
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import cam_entry, edgecheck, overlay, read_pcd_header, set_header, write_ply


def lzf_decompress(src, out_len):
    out = bytearray(out_len)
    ip = op = 0
    while ip < len(src):
        ctrl = src[ip]
        ip += 1
        if ctrl < 32:  # literal run of ctrl+1 bytes
            out[op : op + ctrl + 1] = src[ip : ip + ctrl + 1]
            ip += ctrl + 1
            op += ctrl + 1
        else:  # back reference
            ln = ctrl >> 5
            if ln == 7:
                ln += src[ip]
                ip += 1
            ref = op - ((ctrl & 0x1F) << 8) - src[ip] - 1
            ip += 1
            for _ in range(ln + 2):
                out[op] = out[ref]
                op += 1
                ref += 1
    assert op == out_len, (op, out_len)
    return bytes(out)


def read_pcd(path):
    """PCD v0.7 reader (ascii / binary / binary_compressed), returns {field: array}."""
    with open(path, "rb") as f:
        hdr = read_pcd_header(f)
        body = f.read()
    fields, n = hdr["FIELDS"], int(hdr["POINTS"][0])
    types = [
        "<" + {"F": "f", "U": "u", "I": "i"}[t] + s for t, s in zip(hdr["TYPE"], hdr["SIZE"], strict=True)
    ]
    assert all(c == "1" for c in hdr.get("COUNT", ["1"] * len(fields)))
    mode = hdr["DATA"][0]
    if mode == "ascii":
        a = np.loadtxt(body.decode().splitlines(), ndmin=2)
        return {fn: a[:, i] for i, fn in enumerate(fields)}
    if mode == "binary":
        a = np.frombuffer(body, dtype=np.dtype(list(zip(fields, types, strict=True))), count=n)
        return {fn: a[fn] for fn in fields}
    csize, usize = struct.unpack("<II", body[:8])
    raw, out, off = lzf_decompress(body[8 : 8 + csize], usize), {}, 0
    for fn, t in zip(fields, types, strict=True):  # binary_compressed = field-major (SoA) layout
        w = np.dtype(t).itemsize * n
        out[fn] = np.frombuffer(raw[off : off + w], dtype=t)
        off += w
    return out


def load_calib(kind, src):
    if kind == "json":
        intr = json.load(open(src / "center_camera-intrinsic.json"))["center_camera-intrinsic"]["param"]
        K = np.array(intr["cam_K"]["data"], float)
        D = np.array(intr["cam_dist"]["data"], float).ravel()
        ext = json.load(open(src / "top_center_lidar-to-center_camera-extrinsic.json"))
        T = np.array(
            ext["top_center_lidar-to-center_camera-extrinsic"]["param"]["sensor_calib"]["data"], float
        )
        return K, D, T
    vals = {}
    for line in open(src / "calib.txt"):
        if ":" in line:
            k, v = line.split(":", 1)
            vals[k.strip()] = np.array(v.split(), float)
    K = vals["K"].reshape(3, 3)
    T = np.eye(4)
    T[:3, :4] = vals["T"].reshape(3, 4)
    return K, vals["D"], T


def main(kind, src, out):
    src, out = Path(src), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    K, D, T = load_calib(kind, src)
    R = T[:3, :3]
    print("det", np.linalg.det(R), "orthonormality err", np.abs(R @ R.T - np.eye(3)).max())
    U, _, Vt = np.linalg.svd(R)  # snap to the nearest rotation (values are printed to ~6 digits)
    T[:3, :3] = U @ Vt
    d = read_pcd(src / "calib.pcd")
    xyz = np.stack([d["x"], d["y"], d["z"]], 1).astype(np.float64)
    inten = np.asarray(d["intensity"], np.float32)
    ok = np.isfinite(xyz).all(1) & (np.linalg.norm(xyz, axis=1) > 0.5)
    xyz, inten = xyz[ok], inten[ok]
    print("points", len(xyz), "of", len(d["x"]))
    imgsrc = next(p for p in (src / "calib.png", src / "calib.jpg") if p.exists())
    name = "image" + imgsrc.suffix
    shutil.copyfile(imgsrc, out / name)
    img = cv2.imread(str(out / name))
    h, w = img.shape[:2]
    write_ply(out / "cloud.ply", xyz.astype(np.float32), {"intensity": inten})
    model = "opencv_radtan_k1k2p1p2" if len(D) == 4 else "opencv_radtan_k1k2p1p2k3"
    cams = {
        **set_header(out, len(xyz)),
        "cloud_properties": "x y z (float32, metres, LiDAR frame) + intensity (float32, 0..255 as shipped); "
        "one 360 deg sweep of a 64-beam spinning LiDAR",
        "world_frame": "LiDAR frame of the single sweep: x forward, y left, z up",
        "images": [cam_entry(name, K, w, h, T, D, model)],
    }
    json.dump(cams, open(out / "cameras.json", "w"), indent=1)
    n = overlay(img, xyz, T, K, str(out / f"check_{Path(name).stem}.png"), dist=D, radius=2, zmax=60.0)
    s0, ne, pert = edgecheck(img, xyz, T, K, dist=D)
    print(
        f"in view {n}; edgecheck {s0:.2f} px ({ne} pts); perturbed:",
        " ".join(f"{k} {v:.2f}" for k, v in pert.items()),
    )
    s1 = edgecheck(img, xyz, T, K, dist=None)[0]
    print(f"edgecheck without distortion {s1:.2f} px")


if __name__ == "__main__":
    main(*sys.argv[1:4])
