"""Experiment: mend a first model wrong in one stretch by cutting it at its seam and continuing it.

The views of the verified pairs that contradict the model (`sara.colmap.consistency`) are taken out;
the rest falls apart into parts that share 3D points; the largest part is kept and the model is
continued from it as a repair round's mapping does (`sara.mapping._extend`: re-triangulated with
the database's matches, then COLMAP's incremental mapper registers the views it lacks). Writes
`OUT/cut` (the largest part) and `OUT/mended/<k>` (the continued models), and prints the counts.

    python lab/scripts/cut_at_seam.py MODEL DATABASE IMAGES OUT
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

import numpy as np
import pycolmap

from sara import mapping
from sara.colmap.consistency import model_agreement
from sara.config import make_config


def parts(rec: pycolmap.Reconstruction) -> list[set[int]]:
    """The registered images of `rec` grouped by shared 3D points (union-find), largest first."""
    ids = [i for i, img in rec.images.items() if img.has_pose]
    parent = {i: i for i in ids}

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for point in rec.points3D.values():
        images = np.unique([el.image_id for el in point.track.elements])
        first = root(int(images[0]))
        for other in images[1:]:
            parent[root(int(other))] = first
    groups: dict[int, set[int]] = {}
    for i in ids:
        groups.setdefault(root(i), set()).add(i)
    return sorted(groups.values(), key=len, reverse=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("database", type=Path)
    parser.add_argument("images", type=Path)
    parser.add_argument("out", type=Path)
    args = parser.parse_args()
    tic = time.perf_counter()
    check = model_agreement(args.model, args.database)
    seam = {view for pair in check.contradicted for view in pair}
    print(f"{len(check.contradicted)} of {check.checked} pairs contradict the model; {len(seam)} views in them")
    rec = pycolmap.Reconstruction(str(args.model))
    by_name = {img.name: i for i, img in rec.images.items()}
    for name in seam:
        rec.deregister_frame(rec.images[by_name[name]].frame_id)
    found = parts(rec)
    print(f"without them: parts of {[len(p) for p in found[:8]]} views ({time.perf_counter() - tic:.0f} s)")
    for group in found[1:]:
        for image_id in group:
            rec.deregister_frame(rec.images[image_id].frame_id)
    cut = args.out / "cut"
    shutil.rmtree(args.out, ignore_errors=True)
    cut.mkdir(parents=True)
    rec.write(str(cut))
    work = args.out / "work"
    work.mkdir()
    conf = make_config("sift-offline").map
    recs, _, elapsed = mapping._extend(conf, args.database, args.images, work, 0, False, cut, 15)
    (args.out / "mended").mkdir()
    sizes = recs.write_by_size(args.out / "mended")
    print(f"kept {len(found[0])} views; continued to models of {sizes[:8]} views in {elapsed:.0f} s")


if __name__ == "__main__":
    main()
