"""Experiment: can a bent model be mended in place instead of mapped again?

A first model the mapper bent (its verified pairs across the seam contradict it) is mapped again
under another seed, on one thread (`sara.map_retries.agreeing`): at 10,000 images over an hour. This
tries the cheap alternative on a model folder and the database it was mapped from: merge the tracks
that the correspondence graph links, with a reprojection limit wide enough for the points of the
two passes of a bent model to be joined, then COLMAP's iterative global refinement (adjustment,
track completion and merging at its usual limits, filtering). Prints for each limit the pairs that
contradict the model before and after, the time, and with --gt the AUC against the true poses
(`sara evaluate`).

    python lab/scripts/close_loop.py MODEL DATABASE OUT [--gt GT] [--merge-px 4,16,64] [--passes K]
        [--images IMAGES --retriangulate --continue-mapping]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pycolmap

from sara.colmap.consistency import agreement
from sara.colmap.refine import triangulate_and_adjust


def mend(model: Path, db_path: Path, merge_px: float, refinements: int,
         passes: int = 1) -> tuple[pycolmap.Reconstruction, dict]:
    rec = pycolmap.Reconstruction(str(model))
    opts = pycolmap.IncrementalPipelineOptions()
    cache_options = pycolmap.DatabaseCacheOptions()
    cache_options.min_num_matches = opts.min_num_matches
    with pycolmap.Database.open(str(db_path)) as database:
        cache = pycolmap.DatabaseCache.create(database, cache_options)
    mapper = pycolmap.IncrementalMapper(cache)
    mapper.begin_reconstruction(rec)
    wide = opts.get_triangulation()
    wide.merge_max_reproj_error = wide.complete_max_reproj_error = merge_px
    tic = time.perf_counter()
    global_ba = opts.get_global_bundle_adjustment()
    global_ba.ceres.max_num_images_direct_sparse_cpu_solver = 20000
    merged, completed = [], []
    for _ in range(passes):
        merged.append(mapper.merge_tracks(wide))
        completed.append(mapper.complete_tracks(wide))
        mapper.iterative_global_refinement(refinements, opts.ba_global_max_refinement_change, opts.get_mapper(),
                                           global_ba, opts.get_triangulation(), True)
        mapper.filter_frames(opts.get_mapper())
    info = {"merge_px": merge_px, "passes": passes, "merged": merged, "completed": completed,
            "seconds": round(time.perf_counter() - tic, 1), "views": rec.num_reg_frames()}
    mapper.end_reconstruction(False)
    return rec, info


def evaluate(model: Path, gt: Path) -> dict:
    proc = subprocess.run([sys.executable, "-m", "sara", "evaluate", str(model), str(gt), "--json",
                           str(model / "metrics.json"), "-q"], capture_output=True, text=True)
    if proc.returncode != 0:
        return {"error": proc.stderr.strip()[-300:]}
    metrics = json.loads((model / "metrics.json").read_text())
    return {"auc": metrics.get("auc"), "registered": metrics.get("num_registered")}


def _row(label: str, folder: Path, database: Path, gt: Path | None, tic: float, **extra) -> None:
    after = agreement(pycolmap.Reconstruction(str(folder)), database)
    row = {"step": label, **extra, "seconds": round(time.perf_counter() - tic, 1),
           "contradicted": len(after.contradicted), "checked": after.checked}
    if gt:
        row.update(evaluate(folder, gt))
    print(json.dumps(row), flush=True)


def _continued(model: Path, database: Path, images: Path, out: Path) -> Path:
    """sara's continuation of a model (the rounds' repair schedule): the views it lacks registered
    into it, then adjusted; the largest model written to `out`."""
    from sara import mapping
    from sara.config import make_config

    tmp = out.with_name(out.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    recs, _, _ = mapping._extend(make_config("sift-offline", {}).map, database, images, tmp, 0, False, model, 15)
    largest = max(recs.reconstructions.values(), key=lambda rec: rec.num_reg_images())
    out.mkdir(parents=True, exist_ok=True)
    largest.write(str(out))
    shutil.rmtree(tmp, ignore_errors=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", type=Path)
    ap.add_argument("database", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--gt", type=Path)
    ap.add_argument("--merge-px", default="4,16,64")
    ap.add_argument("--refinements", type=int, default=5)
    ap.add_argument("--passes", type=int, default=1, help="merge and refine this many times")
    ap.add_argument("--images", type=Path, help="the image folder (for the two steps below)")
    ap.add_argument("--retriangulate", action="store_true",
                    help="then triangulate every match anew on the mended poses and adjust (sara's refinement)")
    ap.add_argument("--continue-mapping", action="store_true",
                    help="then register the views the model lacks into it (sara's continuation)")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    _row("as mapped", args.model, args.database, args.gt, time.perf_counter())
    for px in (float(v) for v in args.merge_px.split(",")):
        tic = time.perf_counter()
        rec, info = mend(args.model, args.database, px, args.refinements, args.passes)
        folder = args.out / f"merge-{px:g}px-{args.passes}"
        folder.mkdir(exist_ok=True)
        rec.write(str(folder))
        _row("mended", folder, args.database, args.gt, tic, **info)
        if args.retriangulate:
            tic = time.perf_counter()
            again = folder.with_name(folder.name + "-retriangulated")
            triangulate_and_adjust(folder, args.database, args.images, again)
            _row("retriangulated", again, args.database, args.gt, tic, merge_px=px)
            folder = again
        if args.continue_mapping:
            tic = time.perf_counter()
            grown = _continued(folder, args.database, args.images, folder.with_name(folder.name + "-continued"))
            _row("continued", grown, args.database, args.gt, tic, merge_px=px)


if __name__ == "__main__":
    main()
