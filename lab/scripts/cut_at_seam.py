"""Experiment: mend a first model wrong in one stretch by cutting it at its seam and continuing it.

What the map stage does with a contradicted first model before mapping it again (`map.mend_seam`),
run on a saved model: the views of the verified pairs that contradict it (`sara.colmap.consistency`)
are taken out with every view up to `--hops` verified pairs from them (`sara.colmap.cut_at_seam`;
the map stage uses 2), the largest part of the rest that shares 3D points is kept and continued as
a repair round's mapping does (`sara.mapping._extend`: re-triangulated with the database's matches,
then COLMAP's incremental mapper registers the views it lacks). Writes `OUT/mend/cut` (the part kept)
and `OUT/mended/<k>` (the continued models), and prints the counts and the check of the result.

    python lab/scripts/cut_at_seam.py MODEL DATABASE IMAGES OUT [--hops K]
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

import pycolmap

from sara import colmap, mapping
from sara.config import make_config


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("database", type=Path)
    parser.add_argument("images", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--hops", type=int, default=colmap.SEAM_HOPS,
                        help="also take out the views up to this many verified pairs from the seam's")
    args = parser.parse_args()
    tic = time.perf_counter()
    first = colmap.MappedModels({0: pycolmap.Reconstruction(str(args.model))})
    check = first.agreement(args.database, 15)
    print(f"{len(check.contradicted)} of {check.checked} pairs contradict the model")
    shutil.rmtree(args.out, ignore_errors=True)
    cut = colmap.cut_at_seam(first, check, args.database, args.out / "mend" / "cut", min_num_inliers=15,
                             hops=args.hops)
    print(f"cut ({time.perf_counter() - tic:.0f} s): {cut}")
    if cut is None:
        return
    conf = make_config("sift-offline").map
    recs, _, elapsed = mapping._extend(conf, args.database, args.images, args.out / "mend", 0, False,
                                       args.out / "mend" / "cut", 15)
    (args.out / "mended").mkdir()
    sizes = recs.write_by_size(args.out / "mended")
    again = recs.agreement(args.database, 15)
    print(f"continued to models of {sizes[:8]} views in {elapsed:.0f} s; {len(again.contradicted)} of "
          f"{again.checked} pairs contradict the largest")


if __name__ == "__main__":
    main()
