"""How well the pre-match scorer's acceptance predicts full matching: candidates against exhaustive verification.

Scores the candidate pairs of a sara run (its `scores.csv`; every pair of images when there is none)
with the scorer under each SETTING (comma-separated score.* fields; "" for the defaults) and compares
with the pairs that exhaustive matching verified in EXHAUSTIVE_RUN/database.db: how many verified
pairs each setting accepts, how many others, the inlier counts of both groups, and the same counts
for every inlier threshold from 6 to 15 (pairs rejected for too few inliers are counted there too).

    python lab/scripts/prematch_recall.py SARA_RUN EXHAUSTIVE_RUN "" max_descriptor_ratio=0.8

SARA_RUN needs features-sift.h5 and database.db (or they are taken from EXHAUSTIVE_RUN).
"""

from __future__ import annotations

import csv
import sqlite3
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from sara.config import make_config
from sara.scoring import score_pairs

PAIR_ID_BASE = 2147483647  # COLMAP's pair_id = id1 * base + id2


def verified_pairs(db: Path) -> dict[tuple[str, str], int]:
    con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
    names = dict(con.execute("select image_id, name from images"))
    out = {}
    for pair_id, rows in con.execute("select pair_id, rows from two_view_geometries where rows > 0"):
        j = pair_id % PAIR_ID_BASE
        i = (pair_id - j) // PAIR_ID_BASE
        out[tuple(sorted((names[i], names[j])))] = rows
    con.close()
    return out


def main() -> None:
    run, exhaustive = Path(sys.argv[1]), Path(sys.argv[2])
    settings = [dict(kv.split("=") for kv in s.split(",")) if s else {} for s in sys.argv[3:]] or [{}]
    verified = verified_pairs(exhaustive / "database.db")
    if (run / "scores.csv").exists():
        with open(run / "scores.csv", newline="") as f:
            candidates = [(r["name0"], r["name1"]) for r in csv.DictReader(f)]
    else:
        names = sorted({n for pair in verified for n in pair})
        candidates = [(a, b) for k, a in enumerate(names) for b in names[k + 1:]]
    source = run if (run / "features-sift.h5").exists() else exhaustive
    truth = np.array([tuple(sorted(p)) in verified for p in candidates])
    print(f"{len(candidates)} candidates, {truth.sum()} of them verified by exhaustive matching "
          f"({len(verified)} in all)")
    base = make_config("sift-offline").score
    for setting in settings:
        conf = replace(base, **{k: type(getattr(base, k))(v) for k, v in setting.items()})
        scores = score_pairs(candidates, source / "features-sift.h5", source / "database.db", conf, progress=False)
        accepted, inliers = np.asarray(scores.accepted), np.asarray(scores.num_inliers)
        reason = np.asarray(scores.reason)
        print(f"{setting or 'defaults'}: accepted {accepted.sum()}: {np.sum(accepted & truth)} verified, "
              f"{np.sum(accepted & ~truth)} not; inliers of the verified p10/p50 "
              f"{np.percentile(inliers[truth], [10, 50])}, of the others p50/p90/p99/max "
              f"{np.percentile(inliers[~truth], [50, 90, 99, 100])}")
        usable = (reason == "") | (reason == "few_inliers")
        counts = [(k, np.sum(usable & truth & (inliers >= k)), np.sum(usable & ~truth & (inliers >= k)))
                  for k in range(6, 16)]
        print("  at least k inliers, verified/not: " + "  ".join(f"{k}:{a}/{b}" for k, a, b in counts))


if __name__ == "__main__":
    main()
