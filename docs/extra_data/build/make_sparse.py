"""Sparse copies of a set: every cloud*.ply thinned at random or voxelised, photos and cameras.json kept.

A sparse RGB-D scan is one of the kinds of cloud the project is judged on; session 53 made them from the
rendered office (iclnuim_office) with this script: thinned at random to 10, 4 and 3 % of its points (one
uniform draw per point, seed 0) and voxelised to 3 and 5 cm (open3d's voxel_down_sample: each voxel's
centroid), each leave-out cloud made sparse the same way. The layout is the set's, so every bench reads
the copies: `linereg bench real --data OUT/thin04`, `linereg bench lines3d --real OUT/vox5 --no-demo`.

Usage: python make_sparse.py SET_DIR OUT_ROOT [--thin 0.1 0.04 0.03] [--voxel 0.03 0.05]
writes OUT_ROOT/thin10/<set>/, OUT_ROOT/thin04/<set>/, OUT_ROOT/vox3/<set>/, ... (needs linereg installed)
"""

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

from linereg._open3d import open3d


def sparse_copies(src: Path, out_root: Path, thin: list[float], voxel: list[float]) -> None:
    o3d = open3d()
    variants = [(f"thin{round(100 * s):02d}", "thin", s) for s in thin]
    variants += [(f"vox{round(100 * v)}", "voxel", v) for v in voxel]
    clouds = sorted(src.glob("cloud*.ply"))
    if not clouds or not (src / "cameras.json").is_file():
        raise SystemExit(f"{src}: no cloud*.ply and cameras.json (a set folder of ../shared/data's layout)")
    for name, how, value in variants:
        out = out_root / name / src.name
        out.mkdir(parents=True, exist_ok=True)
        for ply in clouds:
            cloud = o3d.io.read_point_cloud(str(ply))
            if how == "thin":
                points = np.asarray(cloud.points)
                keep = np.random.default_rng(0).random(len(points)) < value
                cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[keep]))
            else:
                cloud = o3d.geometry.PointCloud(cloud.voxel_down_sample(value).points)
            o3d.io.write_point_cloud(str(out / ply.name), cloud)
        cameras = json.loads((src / "cameras.json").read_text())
        cameras["n_points"] = len(o3d.io.read_point_cloud(str(out / "cloud.ply")).points)
        cameras["sparse_copy"] = {"of": src.name, how: value}
        (out / "cameras.json").write_text(json.dumps(cameras, indent=1))
        for image in {entry["file"] for entry in cameras["images"]}:
            shutil.copy(src / image, out / image)
        print(f"{name}/{src.name}: {cameras['n_points']:,} points")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("set_dir", type=Path)
    parser.add_argument("out_root", type=Path)
    parser.add_argument("--thin", type=float, nargs="*", default=[0.1, 0.04, 0.03])
    parser.add_argument("--voxel", type=float, nargs="*", default=[0.03, 0.05])
    args = parser.parse_args()
    sparse_copies(args.set_dir, args.out_root, args.thin, args.voxel)


if __name__ == "__main__":
    main()
