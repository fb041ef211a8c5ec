"""Where does the accuracy go? Per-view pose errors of finished runs against the ground truth.

For every scene folder of a bench output (BENCH/<scene>/<method>/ with database.db and sparse/0)
and every method given, prints and writes (JSON) per view:

- ``err_med``: median over the other views of max(rotation, translation) relative pose error (deg);
- ``rot_abs``: absolute rotation error after a similarity alignment of the camera centres (deg);
- ``deg`` / ``inl``: verified pairs of the view in the database and their median inlier count;
- ``obs``: keypoints of the view with a 3D point in the model;
- and per method: the focal length of the model against the ground truth's, AUC@1/5, and the share
  of AUC@1 that is lost on pairs touching the worst 10% of views.

    python lab/scripts/accuracy_analysis.py BENCH [--scenes a,b] [--methods exhaustive,sara] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pycolmap

from sara.colmap.model import database_pairs
from sara.evaluation.metrics import (
    direction_angle_deg,
    rotation_angle_deg,
    umeyama_similarity,
)

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"


def poses(rec: pycolmap.Reconstruction) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {}
    for im in rec.images.values():
        if im.has_pose:
            p = im.cam_from_world()
            out[im.name] = (np.asarray(p.rotation.matrix()), np.asarray(p.translation).reshape(3))
    return out


def pair_errors(est: dict, gt: dict, names: list[str]) -> np.ndarray:
    """(n, n) max(rotation, translation) relative pose error in degrees; inf where not co-registered."""
    n = len(names)
    err = np.full((n, n), np.inf)
    for i in range(n):
        for j in range(i + 1, n):
            a, b = names[i], names[j]
            if a not in est or b not in est:
                continue
            (Ra, ta), (Rb, tb) = est[a], est[b]
            (Ga, ga), (Gb, gb) = gt[a], gt[b]
            R_est, R_gt = Rb @ Ra.T, Gb @ Ga.T
            t_est, t_gt = tb - R_est @ ta, gb - R_gt @ ga
            e = max(float(rotation_angle_deg(R_est, R_gt)), float(direction_angle_deg(t_est, t_gt)))
            err[i, j] = err[j, i] = e
    return err


def analyse_run(run_dir: Path, gt_dir: Path) -> dict:
    gt_rec = pycolmap.Reconstruction(str(gt_dir))
    gt = poses(gt_rec)
    names = sorted(gt)
    rec = pycolmap.Reconstruction(str(run_dir / "sparse" / "0"))
    est = poses(rec)
    err = pair_errors(est, gt, names)
    _, verified = database_pairs(run_dir / "database.db")
    index = {n: i for i, n in enumerate(names)}
    inliers: list[list[int]] = [[] for _ in names]
    for (a, b), k in verified.items():
        inliers[index[a]].append(k)
        inliers[index[b]].append(k)
    obs = {im.name: im.num_points3D for im in rec.images.values() if im.has_pose}
    common = [n for n in names if n in est]
    rot_abs = {}
    if len(common) >= 3:
        c_est = np.array([-est[n][0].T @ est[n][1] for n in common])
        c_gt = np.array([-gt[n][0].T @ gt[n][1] for n in common])
        _, R_al, _ = umeyama_similarity(c_est, c_gt)
        for n in common:
            rot_abs[n] = float(rotation_angle_deg(est[n][0] @ R_al.T, gt[n][0]))
    gt_focal = float(np.mean([np.mean(gt_rec.cameras[im.camera_id].params[:2]) for im in gt_rec.images.values()]))
    est_focal = float(np.mean([rec.cameras[im.camera_id].params[0] for im in rec.images.values() if im.has_pose]))
    est_k = [float(c.params[3]) for c in rec.cameras.values() if len(c.params) > 3]
    views = []
    for i, n in enumerate(names):
        row = err[i, np.arange(len(names)) != i]
        views.append({"name": n, "err_med": float(np.median(row)), "rot_abs": rot_abs.get(n),
                      "deg": len(inliers[i]), "inl": float(np.median(inliers[i])) if inliers[i] else 0.0,
                      "obs": int(obs.get(n, 0))})
    iu = np.triu_indices(len(names), 1)
    e = err[iu]
    auc1 = float(np.clip(1 - e / 1, 0, 1).sum() / len(e))
    auc5 = float(np.clip(1 - e / 5, 0, 1).sum() / len(e))
    return {"views": views, "auc1": auc1, "auc5": auc5, "focal_est": est_focal, "focal_gt": gt_focal,
            "radial_k": est_k, "num_points": rec.num_points3D(), "pairs": len(verified), "err": err.tolist(),
            "names": names}


def print_scene(scene: str, results: dict[str, dict]) -> None:
    print(f"\n## {scene}")
    for method, r in results.items():
        print(f"{method:>12}: AUC@1 {r['auc1']:.3f} AUC@5 {r['auc5']:.3f} focal {r['focal_est']:.1f} "
              f"(gt {r['focal_gt']:.1f}, {100 * (r['focal_est'] / r['focal_gt'] - 1):+.2f}%) k {r['radial_k']} "
              f"points {r['num_points']} verified pairs {r['pairs']}")
    methods = list(results)
    base = results[methods[0]]
    order = np.argsort([-v["err_med"] for v in results[methods[-1]]["views"]])
    head = "view".ljust(16) + "".join(f"| {m[:10]:>10} err rotabs deg  inl   obs " for m in methods)
    print(head)
    for i in order[: max(5, len(order) // 5)]:
        line = base["views"][i]["name"][:15].ljust(16)
        for m in methods:
            v = results[m]["views"][i]
            line += (f"| {v['err_med']:14.3f} {v['rot_abs'] or float('nan'):6.3f} {v['deg']:3d} "
                     f"{v['inl']:5.0f} {v['obs']:5d} ")
        print(line)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("bench", type=Path)
    ap.add_argument("--scenes", default="")
    ap.add_argument("--methods", default="exhaustive,sara")
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    scenes = args.scenes.split(",") if args.scenes else sorted(p.name for p in args.bench.iterdir() if p.is_dir())
    everything = {}
    for scene in scenes:
        results = {}
        for method in args.methods.split(","):
            run = args.bench / scene / method
            if (run / "sparse" / "0").is_dir():
                results[method] = analyse_run(run, args.data / scene / "gt")
        if results:
            print_scene(scene, results)
            everything[scene] = results
    if args.out:
        args.out.write_text(json.dumps(everything))


if __name__ == "__main__":
    main()
