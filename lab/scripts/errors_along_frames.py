"""Experiment: where along a sequence a model is wrong.

Aligns the model's camera centres to the true ones (a similarity, least squares over every view both
hold) and prints the position error by stretches of frames, the frame index read from the file name
(`006552.jpg` -> 6552). A model bent or folded as a whole is off everywhere; one with a stretch glued
at the wrong place is off only there. Positions are in the true model's units.

    python lab/scripts/errors_along_frames.py MODEL GT [--stretch 500] [--from F --to T]
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np
import pycolmap


def centres(model: Path) -> dict[str, np.ndarray]:
    """Image name -> camera centre, for the posed images of a COLMAP model."""
    rec = pycolmap.Reconstruction(str(model))
    return {img.name: np.asarray(img.projection_center()) for img in rec.images.values() if img.has_pose}


def aligned_errors(est: np.ndarray, true: np.ndarray) -> np.ndarray:
    """(N,) distances between `true` and `est` (both (N, 3)) carried by the least-squares similarity."""
    mean_e, mean_t = est.mean(0), true.mean(0)
    e0, t0 = est - mean_e, true - mean_t
    u, s, vt = np.linalg.svd(t0.T @ e0)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    scale = float((s * np.diag(d)).sum() / (e0 ** 2).sum())
    return np.linalg.norm(scale * e0 @ rot.T + mean_t - true, axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("gt", type=Path)
    parser.add_argument("--stretch", type=int, default=500, help="frames per printed row")
    parser.add_argument("--from", dest="first", type=int, default=None)
    parser.add_argument("--to", dest="last", type=int, default=None)
    args = parser.parse_args()
    est, true = centres(args.model), centres(args.gt)
    names = sorted(set(est) & set(true))
    frame = np.array([int(re.findall(r"\d+", Path(n).stem)[-1]) for n in names])
    err = aligned_errors(np.array([est[n] for n in names]), np.array([true[n] for n in names]))
    span = np.ptp(np.array([true[n] for n in names]), axis=0)
    print(f"{len(names)} views in both; extent of the true positions {np.linalg.norm(span):.1f}; "
          f"median error {np.median(err):.2f}")
    first = frame.min() if args.first is None else args.first
    last = frame.max() if args.last is None else args.last
    for lo in range(first - first % args.stretch, last + 1, args.stretch):
        inside = (frame >= max(lo, first)) & (frame < lo + args.stretch) & (frame <= last)
        if inside.any():
            part = err[inside]
            print(f"frames {lo:6d}-{lo + args.stretch - 1:6d}: {inside.sum():5d} views, median {np.median(part):8.2f}, "
                  f"90th percentile {np.percentile(part, 90):8.2f}, largest {part.max():8.2f}")


if __name__ == "__main__":
    main()
