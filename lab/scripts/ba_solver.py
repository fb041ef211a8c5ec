"""How long one global bundle adjustment of a model takes with Ceres' direct sparse solver against
the iterative one COLMAP switches to above 1,000 images (issue 31: past about 1,000 registered views
each global adjustment of the incremental mapper took minutes on the 3,000-image world).

    python lab/scripts/ba_solver.py MODEL [--direct-up-to 500,1000] [--jitter 0.001]

MODEL is a COLMAP model folder. For each value, a fresh copy of the model is adjusted with the
options COLMAP's incremental mapper uses for its global adjustments
(`IncrementalPipelineOptions.get_global_bundle_adjustment`), Ceres' direct sparse solver allowed up
to that many images (COLMAP: 1,000; a smaller value than the model's views forces the iterative
solver). `--jitter` moves every 3D point by that fraction of the scene's extent first, so that
the adjustment has work to do as it has in the middle of a mapping. Prints wall time and the mean
reprojection error after.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pycolmap


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("--direct-up-to", default="500,1000")
    ap.add_argument("--jitter", type=float, default=0.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    for limit in (int(v) for v in args.direct_up_to.split(",")):
        rec = pycolmap.Reconstruction(args.model)
        if args.jitter > 0:
            xyz = np.array([p.xyz for p in rec.points3D.values()])
            extent = float(np.linalg.norm(xyz.max(axis=0) - xyz.min(axis=0)))
            rng = np.random.default_rng(args.seed)
            for point in rec.points3D.values():
                point.xyz = point.xyz + rng.normal(scale=args.jitter * extent, size=3)
        options = pycolmap.IncrementalPipelineOptions().get_global_bundle_adjustment()
        options.print_summary = False
        options.ceres.max_num_images_direct_sparse_cpu_solver = limit
        before = rec.compute_mean_reprojection_error()
        tic = time.perf_counter()
        pycolmap.bundle_adjustment(rec, options)
        wall = time.perf_counter() - tic
        solver = "direct sparse" if rec.num_reg_images() <= limit else "iterative"
        print(f"{rec.num_reg_images()} views, {rec.num_points3D()} points, {solver} (direct up to {limit}): "
              f"{wall:.1f} s, mean reprojection error {before:.3f} -> {rec.compute_mean_reprojection_error():.3f} px",
              flush=True)


if __name__ == "__main__":
    main()
