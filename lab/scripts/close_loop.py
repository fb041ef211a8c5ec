"""Experiment: can a bent model be mended in place instead of mapped again?

A first model the mapper bent (its verified pairs across the seam contradict it) is mapped again
under another seed, on one thread (`sara.mapping._agreeing`): at 10,000 images over an hour. This
tries the cheap alternative on a model folder and the database it was mapped from: merge the tracks
that the correspondence graph links, with a reprojection limit wide enough for the points of the
two passes of a bent model to be joined, then COLMAP's iterative global refinement (adjustment,
track completion and merging at its usual limits, filtering). Prints for each limit the pairs that
contradict the model before and after, the time, and with --gt the AUC against the true poses
(`sara evaluate`).

    python lab/scripts/close_loop.py MODEL DATABASE OUT [--gt GT] [--merge-px 4,16,64] [--passes K]
"""

from __future__ import annotations

import argparse
import json
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model", type=Path)
    ap.add_argument("database", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--gt", type=Path)
    ap.add_argument("--merge-px", default="4,16,64")
    ap.add_argument("--refinements", type=int, default=5)
    ap.add_argument("--passes", type=int, default=1, help="merge and refine this many times")
    ap.add_argument("--retriangulate", type=Path, metavar="IMAGES",
                    help="then triangulate every match anew on the mended poses and adjust (sara's refinement)")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    before = agreement(pycolmap.Reconstruction(str(args.model)), args.database)
    row = {"model": "as mapped", "contradicted": len(before.contradicted), "checked": before.checked}
    if args.gt:
        row.update(evaluate(args.model, args.gt))
    print(json.dumps(row), flush=True)
    for px in (float(v) for v in args.merge_px.split(",")):
        rec, info = mend(args.model, args.database, px, args.refinements, args.passes)
        folder = args.out / f"merge-{px:g}px-{args.passes}"
        folder.mkdir(exist_ok=True)
        rec.write(str(folder))
        after = agreement(rec, args.database)
        info.update(contradicted=len(after.contradicted), checked=after.checked)
        if args.gt:
            info.update(evaluate(folder, args.gt))
        print(json.dumps(info), flush=True)
        if args.retriangulate:
            tic = time.perf_counter()
            again = folder.with_name(folder.name + "-retriangulated")
            triangulate_and_adjust(folder, args.database, args.retriangulate, again)
            after = agreement(pycolmap.Reconstruction(str(again)), args.database)
            row = {"retriangulated": str(px), "seconds": round(time.perf_counter() - tic, 1),
                   "contradicted": len(after.contradicted), "checked": after.checked}
            if args.gt:
                row.update(evaluate(again, args.gt))
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
