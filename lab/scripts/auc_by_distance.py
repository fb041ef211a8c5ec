"""Experiment: a model's pose AUC by how far apart the two views of a pair are, in frames and in space.

For a walk that passes places again, a model can be right between near frames and wrong between
passes (drift), or the other way round. Every pair of views registered in the model is put in one
class: near in time (at most `--near-frames` frames apart), a revisit (more frames apart but closer
than `--revisit-m` in space), or far (in between, and beyond `--far-m`). The matched pairs of
`pairs.txt` are counted in the same classes. AUC over the registered views only (a view the model
lacks is not counted as a failure, unlike `sara evaluate`). Frame index from the file name.

    python lab/scripts/auc_by_distance.py MODEL GT PAIRS_TXT [--near-frames 50 --revisit-m 30 --far-m 150]
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np
import pycolmap

from sara.evaluation.metrics import relative_pose_errors


def poses(model: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Image name -> (R_cam_from_world, t_cam_from_world) of the posed images of a COLMAP model."""
    rec = pycolmap.Reconstruction(str(model))
    out = {}
    for img in rec.images.values():
        if img.has_pose:
            pose = img.cam_from_world() if callable(img.cam_from_world) else img.cam_from_world
            out[img.name] = (np.asarray(pose.rotation.matrix()), np.asarray(pose.translation))
    return out


def frame(name: str) -> int:
    return int(re.findall(r"\d+", Path(name).stem)[-1])


def classes(gap: np.ndarray, dist: np.ndarray, args: argparse.Namespace) -> dict[str, np.ndarray]:
    far_in_time = gap > args.near_frames
    return {f"<= {args.near_frames} frames apart": ~far_in_time,
            f"revisit (< {args.revisit_m:g} m)": far_in_time & (dist < args.revisit_m),
            f"{args.revisit_m:g}-{args.far_m:g} m": far_in_time & (dist >= args.revisit_m) & (dist < args.far_m),
            f">= {args.far_m:g} m": far_in_time & (dist >= args.far_m)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("gt", type=Path)
    parser.add_argument("pairs", type=Path, help="the run's pairs.txt")
    parser.add_argument("--near-frames", type=int, default=50)
    parser.add_argument("--revisit-m", type=float, default=30.0)
    parser.add_argument("--far-m", type=float, default=150.0)
    args = parser.parse_args()
    est, true = poses(args.model), poses(args.gt)
    names = sorted(true)
    common = [n for n in names if n in est]
    rot, tra = relative_pose_errors(est, true, common)
    err = np.maximum(rot, tra)
    first, second = np.triu_indices(len(common), 1)
    frames = np.array([frame(n) for n in common])
    centres = np.array([-true[n][0].T @ true[n][1] for n in common])
    gap = np.abs(frames[second] - frames[first])
    dist = np.linalg.norm(centres[second] - centres[first], axis=1)
    print(f"{args.model}: {len(common)} of {len(names)} views")
    print("| pairs of views | count | AUC@1 | AUC@5 | median rotation error (deg) |\n|---|---:|---:|---:|---:|")
    for label, inside in classes(gap, dist, args).items():
        e = err[inside]
        auc1, auc5 = np.clip(1 - e, 0, 1).mean(), np.clip(1 - e / 5, 0, 1).mean()
        print(f"| {label} | {inside.sum():,} | {auc1:.4f} | {auc5:.4f} | {np.median(rot[inside]):.3f} |")
    index = {n: k for k, n in enumerate(names)}
    all_frames = np.array([frame(n) for n in names])
    all_centres = np.array([-true[n][0].T @ true[n][1] for n in names])
    matched = [line.split()[:2] for line in args.pairs.read_text().splitlines() if line.strip()]
    a = np.array([index[p[0]] for p in matched])
    b = np.array([index[p[1]] for p in matched])
    counts = {label: int(inside.sum()) for label, inside in
              classes(np.abs(all_frames[a] - all_frames[b]), np.linalg.norm(all_centres[a] - all_centres[b], axis=1),
                      args).items()}
    print(f"matched pairs ({len(matched):,}): " + ", ".join(f"{k}: {v:,}" for k, v in counts.items()))


if __name__ == "__main__":
    main()
