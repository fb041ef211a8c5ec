"""The extraction of a folder update, two versions of sara side by side (rounds alternating).

    python lab/scripts/update_extract_bench.py IMAGES WORK --src-a OLD/src --src-b NEW/src [--first 15] [--rounds 3]

A first `sara extract` of the first `--first` images of IMAGES (name order, links) into
WORK/first; then per round and version: a copy of it, the folder completed with the other images,
and `sara extract` of the full folder (the update: only the added images are extracted), timed
(wall and the CPU time of the command and its children). Writes WORK/update_extract.json.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path


def _extract(src: Path, images: Path, out: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(src)}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    tic = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "sara", "extract", str(images), str(out), "-q"], env=env,
                          capture_output=True, text=True)
    wall = time.perf_counter() - tic
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise RuntimeError(f"sara extract failed ({src}): {proc.stderr[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": round(wall, 3), "cpu_s": round(cpu, 3)}


def _link(src: Path, dst: Path, names: list[str]) -> None:
    dst.mkdir(parents=True, exist_ok=True)
    for name in names:
        os.symlink((src / name).resolve(), dst / name)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("images", type=Path)
    ap.add_argument("work", type=Path)
    ap.add_argument("--src-a", type=Path, required=True)
    ap.add_argument("--src-b", type=Path, required=True)
    ap.add_argument("--first", type=int, default=15)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    names = sorted(p.name for p in args.images.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    work = args.work
    first_images, first = work / "first_images", work / "first"
    if not (first / ".sara" / "extract.json").exists():
        shutil.rmtree(first_images, ignore_errors=True)
        _link(args.images, first_images, names[:args.first])
        _extract(args.src_b, first_images, first)
    rows = []
    for r in range(args.rounds):
        order = [("a", args.src_a), ("b", args.src_b)] if r % 2 == 0 else [("b", args.src_b), ("a", args.src_a)]
        for label, src in order:
            case = work / f"round{r}-{label}"
            shutil.rmtree(case, ignore_errors=True)
            shutil.copytree(first, case / "out", symlinks=True)
            _link(args.images, case / "images", names)
            row = {"round": r, "version": label, "added": len(names) - args.first, **_extract(src, case / "images",
                                                                                                case / "out")}
            rows.append(row)
            print(json.dumps(row), flush=True)
            shutil.rmtree(case)
    (work / "update_extract.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
