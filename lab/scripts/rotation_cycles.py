"""Could cycle consistency of the scorer's relative rotations reject wrong pairs? (lab/notes/ACCURACY.md 17.1)

For a finished SARA run (RUN with scores.csv, database.db and the features file) and the scene's
ground truth (GT, a COLMAP text model with the images' true intrinsics and poses), re-runs the
scorer's RANSAC on every accepted candidate (same matches, settings and seed as `score_pair`) and
prints per pair class:

- the error of the scorer's relative rotation against the true one (degrees);
- for each pair (i, j), the smallest closure error over the triangles i-j-k of accepted candidates:
  the angle of R_ki R_jk R_ij (a cycle of true rotations closes at 0);
- how many pairs a rule "reject when the best triangle does not close within T degrees" would
  reject, among the wrong and the true pairs, and among those the selection kept.

A pair counts as wrong when the median Sampson distance of the scorer's inlier matches to the true
epipolar geometry is above 5 px (in the true camera's pixels). This needs GT intrinsics that belong
to the images as they are (not the resized internet-photo stand-ins of section 11.3b).

    python lab/scripts/rotation_cycles.py RUN GT [--thresholds 15,25]
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np
import pycolmap

from sara import colmap
from sara.config import ScoreConfig
from sara.descriptors import mutual_nearest_neighbours
from sara.evaluation.metrics import rotation_angle_deg
from sara.scoring.scorer import load_views
from sara.scoring.twoview import estimate_relative_pose, sampson_errors

WRONG_SAMPSON_PX = 5.0


def angle_deg(R: np.ndarray) -> float:
    """Angle of the rotation R (degrees)."""
    return float(rotation_angle_deg(np.eye(3), R))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("gt", type=Path)
    parser.add_argument("--thresholds", default="15,25")
    args = parser.parse_args()
    rows = list(csv.DictReader(open(args.run / "scores.csv")))
    accepted = [(r["name0"], r["name1"]) for r in rows if r["accepted"] == "true"]
    selected = {(r["name0"], r["name1"]) for r in rows if r["role"] not in ("unselected", "")}
    conf = ScoreConfig()
    names = sorted({n for pair in accepted for n in pair})
    features = next(args.run.glob("features-*.h5"))
    views = load_views(names, features, args.run / "database.db", conf.num_keypoints, progress=False)
    db_cams = colmap.cameras_by_image(args.run / "database.db")
    gt = pycolmap.Reconstruction()
    gt.read_text(str(args.gt))
    pose = {im.name: im.cam_from_world() for im in gt.images.values()}
    intrinsics = {im.name: np.asarray(gt.cameras[im.camera_id].params, float) for im in gt.images.values()}

    def true_normalised(name: str, points_norm: np.ndarray) -> np.ndarray:
        f, cx, cy = db_cams[name].params[:3]  # the scorer's camera (SIMPLE_RADIAL, k = 0 at import)
        fx, fy, px, py = intrinsics[name]
        return (points_norm * f + [cx, cy] - [px, py]) / [fx, fy]

    rotation, error, wrong = {}, {}, {}
    for a, b in accepted:
        v0, v1 = views[a], views[b]
        best = mutual_nearest_neighbours(v0.descriptors, v1.descriptors)[0][:conf.num_matches]
        max_error = conf.ransac_max_error_px * 2.0 / (v0.focal_px + v1.focal_px)
        found = estimate_relative_pose(v0.points_norm[best[:, 0]], v1.points_norm[best[:, 1]], max_error=max_error,
                                       iterations=conf.ransac_iterations, seed=0)
        true_R = pose[b].rotation.matrix() @ pose[a].rotation.matrix().T
        true_t = pose[b].translation - true_R @ pose[a].translation
        rotation[a, b] = found.R
        error[a, b] = float(rotation_angle_deg(found.R, true_R))
        inliers = best[found.inliers]
        x0 = true_normalised(a, v0.points_norm[inliers[:, 0]])
        x1 = true_normalised(b, v1.points_norm[inliers[:, 1]])
        sampson = sampson_errors(true_R, true_t / np.linalg.norm(true_t), x0, x1) * intrinsics[a][0]
        wrong[a, b] = float(np.median(sampson)) > WRONG_SAMPSON_PX

    def rel(a: str, b: str) -> np.ndarray:  # cam_b_from_cam_a
        return rotation[a, b] if (a, b) in rotation else rotation[b, a].T

    neighbours: dict[str, set[str]] = {n: set() for n in names}
    for a, b in accepted:
        neighbours[a].add(b)
        neighbours[b].add(a)
    closure = {(a, b): min((angle_deg(rel(c, a) @ rel(b, c) @ rel(a, b)) for c in neighbours[a] & neighbours[b]),
                           default=np.nan) for a, b in accepted}
    is_wrong = np.array([wrong[p] for p in accepted])
    is_selected = np.array([p in selected for p in accepted])
    err = np.array([error[p] for p in accepted])
    best_closure = np.array([closure[p] for p in accepted])
    print(f"{args.run}: {len(accepted)} accepted candidates, {int(is_wrong.sum())} wrong "
          f"({int((is_wrong & is_selected).sum())} of them selected); no triangle: {int(np.isnan(best_closure).sum())}")
    for label, part in (("true", ~is_wrong), ("wrong", is_wrong)):
        if part.any():
            print(f"  rotation error of the {label} pairs: median {np.median(err[part]):.1f}, "
                  f"90th percentile {np.percentile(err[part], 90):.1f} deg")
    for threshold in (float(t) for t in args.thresholds.split(",")):
        flag = best_closure > threshold
        print(f"  best triangle above {threshold:g} deg: wrong {int((flag & is_wrong).sum())}/{int(is_wrong.sum())} "
              f"(selected {int((flag & is_wrong & is_selected).sum())}), true {int((flag & ~is_wrong).sum())}/"
              f"{int((~is_wrong).sum())} (selected {int((flag & ~is_wrong & is_selected).sum())})")


if __name__ == "__main__":
    main()
