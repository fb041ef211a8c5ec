"""How much COLMAP's verification draw moves a result: the same run with another RANSAC seed.

sara verifies with the fixed seed `sara.colmap.VERIFICATION_SEED` (0), so runs repeat; but one
seed is one draw, and a margin of 0.001 in AUC can be the draw's. This script redoes a run with
another seed (lab/notes/ACCURACY.md, section 15.6):

    # exhaustive: verify the raw matches of a finished exhaustive run again, map, evaluate
    python lab/scripts/verification_draws.py exhaustive BENCH/SCENE/exhaustive SCENE_DIR SEED OUT
    # any `sara` command, with SIFT matched in this process (the learned matchers verify in workers)
    python lab/scripts/verification_draws.py sara SEED bench SCENE_DIR --methods sara --out OUT

The first avoids matching 7,021 pairs again (bm-moldGoldCape: 16 minutes against 30 for the
whole exhaustive run on two cores); seed 0 reproduces the run it starts from.
"""

from __future__ import annotations

import shutil
import sqlite3
import sys
from pathlib import Path

from sara import colmap, mapping
from sara.cli import main as sara_main
from sara.config import MapConfig
from sara.evaluation import evaluate


def exhaustive(run_dir: Path, scene: Path, seed: int, out: Path) -> None:
    colmap.VERIFICATION_SEED = seed
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    shutil.copy(run_dir / "database.db", out / "database.db")
    with sqlite3.connect(out / "database.db") as db:
        db.execute("DELETE FROM two_view_geometries")
    colmap.verify_pairs(out / "database.db", run_dir / "pairs.txt", min_num_inliers=15)
    mapping.run(MapConfig(), out / "database.db", scene / "images", out, seed=0, progress=False)
    m = evaluate(out / "sparse", scene / "gt", out / "metrics.json")
    print(f"{scene.name} verification seed {seed}: AUC@1 {m['auc']['1']:.5f} AUC@5 {m['auc']['5']:.5f}, "
          f"{m['num_registered']} registered in {m['num_components']}, {m['num_points3d']} points")


def main(argv: list[str]) -> int:
    if len(argv) == 5 and argv[0] == "exhaustive":
        exhaustive(Path(argv[1]), Path(argv[2]), int(argv[3]), Path(argv[4]))
        return 0
    if len(argv) >= 3 and argv[0] == "sara":
        colmap.VERIFICATION_SEED = int(argv[1])
        return sara_main(argv[2:])
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
