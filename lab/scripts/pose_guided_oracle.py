"""Compare rules for SARA's pose-guided round without matching anything (lab/notes/ACCURACY.md 13.1).

Takes SARA's first model (a run made with ``-s rounds.pose_guided_pairs_per_image=0
-s rounds.extend_tracks=false``), lets each rule choose the round's pairs, takes those pairs' verified
matches from an exhaustive run's database (same features, same matcher), refines as the pipeline
does (re-triangulation with the poses fixed, bundle adjustment, track extension, bundle
adjustment) and scores the result against the ground truth. With ``--drop F --seeds N`` every rule
also runs on N selections perturbed by dropping a fraction F of the candidates at random, which
tells how much of a difference between rules is the luck of one selection.

    python lab/scripts/pose_guided_oracle.py FIRST_RUN EXHAUSTIVE_RUN/database.db IMAGES GT \\
        [--limits 0,2] [--soft] [--drop 0.15 --seeds 5] [--work DIR]

Prints one JSON line per rule and seed, then the mean AUC@1 / AUC@5 of each rule.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sqlite3
import statistics
import tempfile
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pycolmap

from sara.colmap import refine
from sara.config import BudgetConfig, RoundsConfig
from sara.evaluation import evaluate_models
from sara.pairs.sara.pose_guided import candidate_pairs
from sara.selection import pose_guided


def soft_spread(cand: np.ndarray, cov: pose_guided.Covisibility, budget: int, rounds: RoundsConfig) -> np.ndarray:
    """Greedy: the k-th pair of a view counts 1 / (1 + k) of its weight (measured, not shipped)."""
    score = pose_guided.pair_scores(cov, cand, "weight")
    alive = (cov.covisible >= max(rounds.pose_guided_min_points, 1e-9)) & (score > 0)
    used = np.zeros(len(cov.observed))
    chosen: list[int] = []
    for _ in range(budget):
        gain = np.where(alive, score / ((1 + used[cand[:, 0]]) * (1 + used[cand[:, 1]])), -1.0)
        k = int(np.argmax(gain))
        if gain[k] <= 0:
            break
        chosen.append(k)
        alive[k] = False
        used[cand[k]] += 1
    return np.asarray(chosen, dtype=np.int64)


def keep_only(db: Path, names: dict[str, int], pairs: list[tuple[str, str]]) -> None:
    """Delete every match and two-view geometry of `db` but those of `pairs`."""
    keep = [(pycolmap.image_pair_to_pair_id(names[a], names[b]),) for a, b in pairs]
    with sqlite3.connect(db) as con:
        con.execute("CREATE TEMP TABLE keep (pair_id INTEGER PRIMARY KEY)")
        con.executemany("INSERT OR IGNORE INTO keep VALUES (?)", keep)
        for table in ("matches", "two_view_geometries"):
            con.execute(f"DELETE FROM {table} WHERE pair_id NOT IN (SELECT pair_id FROM keep)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("first", type=Path, help="SARA run without the pose-guided round (sparse/0, pairs.txt, features)")
    ap.add_argument("exhaustive_db", type=Path, help="database.db of an exhaustive run on the same features")
    ap.add_argument("images", type=Path)
    ap.add_argument("gt", type=Path)
    ap.add_argument("--limits", default="0,2", help="pose-guided pairs per view to try (0: no limit)")
    ap.add_argument("--soft", action="store_true", help="also the soft spread")
    ap.add_argument("--drop", type=float, default=0.15, help="fraction of candidates dropped per perturbed seed")
    ap.add_argument("--seeds", type=int, default=0, help="perturbed selections per rule (0: the plain one only)")
    ap.add_argument("--work", type=Path, default=None, help="where the refined models go (default: a temp dir)")
    args = ap.parse_args()
    pycolmap.logging.minloglevel = 2

    rounds, budget_conf = RoundsConfig(), BudgetConfig()
    geom = refine.read_geometry(args.first / "sparse" / "0")
    first_round = [tuple(line.split()) for line in (args.first / "pairs.txt").read_text().splitlines() if line.strip()]
    all_cand = candidate_pairs(geom.names, first_round)
    num_images = len(list(args.images.iterdir()))
    budget = max(0, min(math.ceil(rounds.pose_guided_pairs_per_image * len(geom.names) - 1e-9),
                        budget_conf.pair_cap(num_images) - len(first_round)))
    features = next(args.first.glob("features-*.h5"))
    with sqlite3.connect(args.exhaustive_db) as con:
        image_ids = dict(con.execute("SELECT name, image_id FROM images"))
        inliers = dict(con.execute("SELECT pair_id, rows FROM two_view_geometries WHERE config >= 2"))
    rules = [(f"limit={k}", int(k)) for k in args.limits.split(",")] + ([("soft", None)] if args.soft else [])
    work = args.work or Path(tempfile.mkdtemp(prefix="sara-oracle-"))
    results: dict[str, list[tuple[float, float]]] = defaultdict(list)
    for seed in [-1] + list(range(args.seeds)):
        keep = np.ones(len(all_cand), dtype=bool)
        if seed >= 0:
            keep = np.random.default_rng(seed).random(len(all_cand)) >= args.drop
        cand = all_cand[keep]
        cov = pose_guided.covisibility(geom, cand, max_view_angle_deg=rounds.pose_guided_max_view_angle_deg)
        for name, limit in rules:
            if limit is None:
                chosen = soft_spread(cand, cov, budget, rounds)
            else:
                chosen = pose_guided.choose_pairs(cand, cov, budget, min_covisible=rounds.pose_guided_min_points,
                                                  max_per_view=limit)
            extra = [tuple(sorted((geom.names[a], geom.names[b]))) for a, b in cand[chosen]]
            run_dir = work / f"{name}-{seed}"
            shutil.rmtree(run_dir, ignore_errors=True)
            run_dir.mkdir(parents=True)
            db = run_dir / "database.db"
            shutil.copy(args.exhaustive_db, db)
            keep_only(db, image_ids, first_round + extra)
            counts = refine.triangulate_and_adjust(
                args.first / "sparse" / "0", db, args.images, run_dir / "model", features_path=features,
                extension=refine.TrackExtension(radius_px=rounds.extend_tracks_radius_px,
                                                max_view_angle_deg=rounds.pose_guided_max_view_angle_deg))
            metrics = evaluate_models(run_dir / "model", args.gt)
            found = [inliers.get(pycolmap.image_pair_to_pair_id(image_ids[a], image_ids[b]), 0) for a, b in extra]
            per_view = Counter(v for pair in extra for v in pair)
            auc1, auc5 = metrics["auc"]["1"], metrics["auc"]["5"]
            results[name].append((auc1, auc5))
            print(json.dumps({"rule": name, "seed": seed, "pairs": len(extra),
                              "verified": sum(n >= 15 for n in found),
                              "median_inliers": float(np.median(found)) if found else 0.0,
                              "most_per_view": max(per_view.values(), default=0),
                              "views_without": len(geom.names) - len(per_view),
                              "auc@1": round(auc1, 4), "auc@5": round(auc5, 4),
                              "points3d": int(counts["num_points3d"])}), flush=True)
    for name, values in results.items():
        print(f"{name}: {len(values)} runs, AUC@1 mean {statistics.mean(v[0] for v in values):.4f}, "
              f"AUC@5 mean {statistics.mean(v[1] for v in values):.4f}")


if __name__ == "__main__":
    main()
