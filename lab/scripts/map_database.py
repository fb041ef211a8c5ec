"""Experiment: map a matched database from scratch with sara's map stage, and score the model.

The map stage as `sara run` calls it (`sara.mapping.run`: the first-model check, the retries, the
checkpoints), on a copy of a finished run's database, for instance a run's final graph where the
run's first mapping saw only its first pairs. A run stopped part-way resumes from its checkpoint
when started again with the same arguments. Prints the stage's record and `sara evaluate`'s scores.

    python lab/scripts/map_database.py DATABASE IMAGES OUT GT [-s KEY=VALUE ...] [--seed S]
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import subprocess
import sys
import time
from pathlib import Path

from sara import mapping
from sara.config import make_config
from sara.io import records


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("database", type=Path, help="a matched COLMAP database (copied into OUT once)")
    ap.add_argument("images", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("gt", type=Path, help="the true model (a COLMAP model folder)")
    ap.add_argument("-s", "--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s: %(message)s")
    args.out.mkdir(parents=True, exist_ok=True)
    db = args.out / "database.db"
    if not db.exists():
        shutil.copy(args.database, db.with_suffix(".partial"))
        db.with_suffix(".partial").rename(db)
    overrides = dict(item.split("=", 1) for item in args.set)
    conf = make_config("sift-offline", overrides)
    tic = time.perf_counter()
    mapping.run(conf.map, db, args.images, args.out, seed=args.seed, upstream_key=str(args.database),
                progress=False, min_num_inliers=conf.match.min_num_inliers)
    info = records.done_info(args.out, mapping.STAGE)
    print(json.dumps({"wall_s": time.perf_counter() - tic, **info}, default=str))
    scored = subprocess.run([sys.executable, "-m", "sara", "evaluate", str(args.out / "sparse" / "0"), str(args.gt)],
                            capture_output=True, text=True)
    print(scored.stdout or scored.stderr)


if __name__ == "__main__":
    main()
