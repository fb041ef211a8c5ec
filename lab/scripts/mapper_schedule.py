"""How often COLMAP's incremental mapper runs its global bundle adjustment, against time and accuracy
on a synthetic street world (issue 31: mapping is most of the wait at 1,000 images and more).

COLMAP adjusts the whole model each time the registered views (or points) grew by
`ba_global_frames_ratio` (`ba_global_points_ratio`), 1.1 by default, or by 500 views: about
ln(N / N0) / ln(1.1) global adjustments of a growing model, their cost summing to about
N / (1 - 1 / 1.1) = 11 N view-adjustments. This script maps one matched database under several
ratios, each in its own subprocess, and scores each model against the world's true poses.

    python lab/scripts/mapper_schedule.py WORK --size 1000 --method sequential --ratios 1.1,1.4

WORK is shared with `scale_e2e.py` (the same `world-N/`). The pairs are selected and matched once
(`WORK/sched-N-METHOD/`, the first round only for SARA); each mapping writes
`WORK/sched-N-METHOD/map-rRATIO-sSEED/` and appends one JSON line to `WORK/schedule.jsonl`
(a finished variant is skipped, so a stopped run resumes).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import resource
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scale_e2e import METHODS, ensure_world, evaluate, prepare_run_dir  # noqa: E402  (a sibling lab script)

RESULTS = "schedule.jsonl"


def matched(world_dir: Path, run_dir: Path, method: str) -> dict:
    """The method's pairs selected and matched in `run_dir` (once); their counts and times."""
    done = run_dir / "matched.json"
    if done.exists():
        return json.loads(done.read_text())
    from sara.bench.world import image_set
    from sara.config import make_config
    from sara.execute import make_executor
    from sara.pipeline import match_pairs, select_pairs

    conf = make_config(overrides=METHODS[method])
    prepare_run_dir(world_dir, run_dir)
    images = dataclasses.replace(image_set(world_dir), root=run_dir / "images")
    executor = make_executor(conf.execute.executor, conf.execute.workers, conf.execute.ray_address)
    tic = time.perf_counter()
    pairs_path = select_pairs(conf, images, run_dir / "features-sift.h5", run_dir, executor=executor, progress=False)
    t_pairs = time.perf_counter() - tic
    work = match_pairs(conf, pairs_path, run_dir / "features-sift.h5", run_dir, executor=executor,
                       progress=False, beside=True)
    executor.close()
    if Path(work) != run_dir / "database.db":
        os.replace(work, run_dir / "database.db")
    info = {"pairs": sum(1 for ln in pairs_path.open() if ln.strip()), "pairs_s": t_pairs,
            "match_s": time.perf_counter() - tic - t_pairs}
    done.write_text(json.dumps(info))
    return info


def parse_variant(spec: str) -> tuple[float, bool, int | None]:
    """`1.4`, `1.4p`, `1.4r1`, `1.4d`: the growth factor, a trailing `p` for COLMAP's pruning of
    redundant points in each global adjustment, `rN` for at most N refinement rounds of it (COLMAP:
    5), `d` for sara's step-by-step mapping with the direct sparse solver at any size."""
    found = re.fullmatch(r"([0-9.]+)(p?)(?:r([0-9]+))?(d?)", spec)
    if not found:
        raise SystemExit(f"not a variant: {spec!r} (e.g. 1.4, 1.4p, 1.4r1)")
    return float(found[1]), bool(found[2]), int(found[3]) if found[3] else None, bool(found[4])


def child_map(db: Path, out: Path, spec: str, seed: int) -> None:
    """One mapping of `db` by sara's mapper call and settings, the global adjustment as `spec` says
    (`parse_variant`)."""
    ratio, prune, refinements, direct = parse_variant(spec)
    import pycolmap

    made = pycolmap.IncrementalPipelineOptions

    def options() -> pycolmap.IncrementalPipelineOptions:  # sara's call with the variant's settings on top
        opts = made()
        opts.mapper.ba_global_ignore_redundant_points3D = prune
        if refinements is not None:
            opts.ba_global_max_refinements = refinements
        return opts

    pycolmap.IncrementalPipelineOptions = options
    from sara.colmap import sfm
    from sara.config import make_config

    conf = make_config().map
    for sub in ("images", "raw", "sparse"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    tic, cpu0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
    mapped = sfm.incremental_mapping(
        db, out / "images", out / "raw", seed=seed, min_model_size=conf.min_model_size,
        abs_pose_min_num_inliers=conf.abs_pose_min_num_inliers,
        abs_pose_min_inlier_ratio=conf.abs_pose_min_inlier_ratio, ba_global_ratio=ratio,
        direct_solver_up_to=100_000 if direct else None)
    wall, cpu1 = time.perf_counter() - tic, resource.getrusage(resource.RUSAGE_SELF)
    sizes = mapped.write_by_size(out / "sparse")
    (out / "child.json").write_text(json.dumps({
        "map_s": wall, "map_cpu_s": cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime,
        "peak_rss_gib": cpu1.ru_maxrss / 1024**2, "model_sizes": sizes}))


def main() -> None:
    if sys.argv[1:2] == ["--child"]:
        db, out, spec, seed = sys.argv[2:6]
        import logging

        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
        child_map(Path(db), Path(out), spec, int(seed))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("--size", type=int, default=1000)
    ap.add_argument("--method", default="sequential", choices=[m for m in METHODS if "global" not in m])
    ap.add_argument("--ratios", default="1.1,1.4", help="variants: growth factor, then p to prune "
                    "redundant points in each global adjustment, rN for at most N refinements (1.4,1.4p,1.4r1)")
    ap.add_argument("--seeds", default="0")
    args = ap.parse_args()
    world_dir = ensure_world(args.work, args.size)
    run_dir = args.work / f"sched-{args.size}-{args.method}"
    info = matched(world_dir, run_dir, args.method)
    results = args.work / RESULTS
    rows = map(json.loads, results.read_text().splitlines()) if results.exists() else []
    done = {(r["N"], r["method"], r["ratio"], r.get("prune", False), r.get("refinements"), r.get("direct", False),
             r["seed"]) for r in rows if r["returncode"] == 0}
    for seed in (int(s) for s in args.seeds.split(",")):
        for spec in args.ratios.split(","):
            ratio, prune, refinements, direct = parse_variant(spec)
            if (args.size, args.method, ratio, prune, refinements, direct, seed) in done:
                continue
            out = run_dir / f"map-r{spec}-s{seed}"
            log = out.with_name(out.name + ".log")
            with open(log, "w") as fh:
                proc = subprocess.run([sys.executable, __file__, "--child", str(run_dir / "database.db"), str(out),
                                       spec, str(seed)], stdout=fh, stderr=subprocess.STDOUT)
            row = {"N": args.size, "method": args.method, "ratio": ratio, "prune": prune,
                   "refinements": refinements, "direct": direct, "seed": seed, **info,
                   "returncode": proc.returncode, "started": time.strftime("%Y-%m-%d %H:%M:%S")}
            if proc.returncode == 0:
                row.update(json.loads((out / "child.json").read_text()))
                row["eval"] = evaluate(out, world_dir / "gt")
            with results.open("a") as fh:
                fh.write(json.dumps(row) + "\n")
            ev = row.get("eval", {})
            print(f"N={args.size} {args.method} ratio {spec} seed {seed}: map {row.get('map_s', 0):.0f} s "
                  f"(CPU {row.get('map_cpu_s', 0):.0f} s), registered {ev.get('num_registered')} in "
                  f"{ev.get('num_components')} models, AUC@1/5 {ev.get('auc', {}).get('1')} / "
                  f"{ev.get('auc', {}).get('5')}", flush=True)


if __name__ == "__main__":
    main()
