"""Experiment: merge two models of one mapping that share views.

COLMAP's mapper may register a view in more than one of its models. This aligns model B to model A
by the projection centres of their shared views (a similarity, Umeyama), writes A's views and B's
other views (moved into A's frame) as one model without points, triangulates every match of the
database on those poses and adjusts (`sara.colmap.refine.triangulate_and_adjust`), then scores the
result against the true poses (`sara evaluate`).

    python lab/scripts/merge_pieces.py MODEL_A MODEL_B DATABASE IMAGES OUT GT
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap
from sweep_standin import write_truth  # this folder's: run as a script

from sara.colmap.refine import triangulate_and_adjust
from sara.evaluation.metrics import umeyama_similarity


def image_line(image_id: int, camera_id: int, name: str, R: np.ndarray, t: np.ndarray) -> str:
    x, y, z, w = pycolmap.Rotation3d(R).quat
    return f"{image_id} {w} {x} {y} {z} {' '.join(map(str, t))} {camera_id} {name}\n\n"


def merged_poses(a: pycolmap.Reconstruction, b: pycolmap.Reconstruction, db: Path, out: Path) -> None:
    """A's posed views and B's others in A's frame, as a text model without points in `out`."""
    in_a = {im.name: im for im in a.images.values() if im.has_pose}
    in_b = {im.name: im for im in b.images.values() if im.has_pose}
    shared = sorted(set(in_a) & set(in_b))
    s, R, t = umeyama_similarity(np.array([in_b[n].projection_center() for n in shared]),
                         np.array([in_a[n].projection_center() for n in shared]))
    moved = s * (R @ np.array([in_b[n].projection_center() for n in shared]).T).T + t
    error = np.linalg.norm(moved - np.array([in_a[n].projection_center() for n in shared]), axis=1)
    print(f"A {len(in_a)} views, B {len(in_b)}, shared {len(shared)}, B's others {len(set(in_b) - set(in_a))}; "
          f"shared centres after alignment: median error {np.median(error):.4f}, max {error.max():.4f}")
    with pycolmap.Database.open(str(db)) as database:
        ids = {im.name: im.image_id for im in database.read_all_images()}
    camera = next(iter(a.cameras.values()))
    lines = []
    for name, im in in_a.items():
        M = im.cam_from_world().matrix()
        lines.append((ids[name], image_line(ids[name], camera.camera_id, name, M[:, :3], M[:, 3])))
    for name in sorted(set(in_b) - set(in_a)):
        M = in_b[name].cam_from_world().matrix()
        # x_b = R^T (x_a - t) / s, so the camera of x_a, in A's units: Rb R^T x_a + s tb - Rb R^T t
        rotation = M[:, :3] @ R.T
        lines.append((ids[name], image_line(ids[name], camera.camera_id, name, rotation, s * M[:, 3] - rotation @ t)))
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    params = " ".join(map(str, camera.params))
    write_truth(out, [f"{camera.camera_id} {camera.model.name} {camera.width} {camera.height} {params}"],
                [line for _, line in sorted(lines)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    for name in ("model_a", "model_b", "database", "images", "out", "gt"):
        ap.add_argument(name, type=Path)
    args = ap.parse_args()
    poses = args.out.with_name(args.out.name + ".poses")
    merged_poses(pycolmap.Reconstruction(str(args.model_a)), pycolmap.Reconstruction(str(args.model_b)),
                 args.database, poses)
    print(triangulate_and_adjust(poses, args.database, args.images, args.out))
    scored = subprocess.run([sys.executable, "-m", "sara", "evaluate", str(args.out), str(args.gt)],
                            capture_output=True, text=True)
    print(scored.stdout or scored.stderr)


if __name__ == "__main__":
    main()
