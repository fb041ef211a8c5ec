"""Incremental runs against from-scratch runs of the final folder (issue 30), one run at a time.

    python lab/scripts/incremental_bench.py ../shared/data WORK [--cases add,remove,retouch,rename]

For each case: a first run of the starting folder (links to the scene's images), the change, the
same command again (the update), then a run from scratch of the final folder; every run with
--gt (for `rename`, every file renamed `r_NAME`, the truth under the new names after the change).
Writes WORK/incremental.json (times, the update's counts, registered views, AUC).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from PIL import Image


def _link_folder(src: Path, dst: Path, names: list[str]) -> Path:
    shutil.rmtree(dst, ignore_errors=True)
    dst.mkdir(parents=True)
    for name in names:
        os.symlink((src / name).resolve(), dst / name)
    return dst


def _run(images: Path, out: Path, gt: Path) -> dict:
    tic = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "sara", "run", str(images), str(out), "-q", "--gt", str(gt)],
                          capture_output=True, text=True)
    wall = time.perf_counter() - tic
    if proc.returncode != 0:
        raise RuntimeError(f"sara run {images} {out} failed: {proc.stderr[-2000:]}")
    run = json.loads((out / "run.json").read_text())
    metrics = run.get("metrics") or {}
    return {"wall_s": wall, "update": run["stages"].get("update"), "registered": run["stages"]["map"]["num_registered"],
            "num_images": run["stages"]["images"]["num_images"], "metrics": metrics,
            "stage_times_s": {k: run["stages"].get(k, {}).get("time_s") for k in ("extract", "pairs", "match", "map")},
            "warnings": [line for line in proc.stderr.splitlines() if "update:" in line]}


def _retouch(src: Path, dst: Path) -> None:
    """Rewrite `src` into `dst` with slightly changed pixels (every 7th row, 5th column +3)."""
    dst.unlink(missing_ok=True)
    pixels = np.asarray(Image.open(src)).astype(np.int16)
    pixels[::7, ::5] += 3
    Image.fromarray(np.clip(pixels, 0, 255).astype(np.uint8)).save(dst, quality=95)


def case(data: Path, work: Path, name: str) -> dict:
    scene, change = {"add": ("strecha-Herz-Jesus-P25", "add"), "remove": ("strecha-castle-P30", "remove"),
                     "retouch": ("strecha-fountain-P11", "retouch"), "rename": ("strecha-castle-P30", "rename")}[name]
    src, gt = data / scene / "images", data / scene / "gt"
    names = sorted(os.listdir(src))
    images, out, scratch = work / f"{name}-images", work / f"{name}-out", work / f"{name}-scratch"
    for folder in (out, scratch):
        shutil.rmtree(folder, ignore_errors=True)
    start = names[:20] if change == "add" else names
    _link_folder(src, images, start)
    result: dict = {"scene": scene, "change": change, "first": _run(images, out, gt)}
    if change == "add":
        for n in names[20:]:
            os.symlink((src / n).resolve(), images / n)
    elif change == "remove":
        for n in names[-5:]:
            (images / n).unlink()
    elif change == "rename":
        from sara.colmap.model import write_model

        for n in names:
            (images / n).rename(images / f"r_{n}")
        gt = write_model(gt, work / f"{name}-gt", rename={n: f"r_{n}" for n in names}, text=True)
    else:
        target = names[len(names) // 2]
        (images / target).unlink()
        _retouch(src / target, images / target)
        result["retouched"] = target
    result["update"] = _run(images, out, gt)
    result["scratch"] = _run(images, scratch, gt)
    result["update_over_scratch"] = result["update"]["wall_s"] / result["scratch"]["wall_s"]
    return result


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("data", type=Path)
    parser.add_argument("work", type=Path)
    parser.add_argument("--cases", default="add,remove,retouch")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    path = args.work / "incremental.json"
    results = json.loads(path.read_text()) if path.exists() else {}
    for name in args.cases.split(","):
        results[name] = case(args.data, args.work, name)
        path.write_text(json.dumps(results, indent=1))
        print(name, json.dumps({k: results[name][k] for k in ("update_over_scratch",)}), flush=True)


if __name__ == "__main__":
    main()
