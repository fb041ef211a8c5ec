"""`sara extract` against plain pycolmap SIFT extraction on the same images, back to back.

Plain: a new COLMAP database, `pycolmap.import_images` with one shared camera (what sara does for
images of one size), `pycolmap.extract_features` with the options sara passes (max_image_size,
max_num_features, CPU) and nothing else. sara: the real entry point, `sara extract IMAGES OUT -q`
in a fresh output folder, so everything it does is counted (digests, the image check, the
features file, the focal check). Each round runs both, alternating which goes first; the ratio is
taken per round and the median reported. Also times sara's phases from its own log (-v).

    python lab/scripts/extract_vs_pycolmap.py IMAGES WORK [--rounds 2] [--threads -1]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pycolmap

from sara.config import make_config


def plain(images: Path, work: Path, threads: int) -> float:
    conf = make_config("sift-offline").extract
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    db = work / "database.db"
    tic = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = conf.camera_model
    opts = pycolmap.FeatureExtractionOptions()
    opts.max_image_size = conf.max_image_size
    opts.num_threads = threads
    opts.sift.max_num_features = conf.max_num_features
    pycolmap.extract_features(str(db), str(images), camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=opts, device=pycolmap.Device.cpu)
    return time.perf_counter() - tic


def sara(images: Path, work: Path, threads: int) -> float:
    shutil.rmtree(work, ignore_errors=True)
    tic = time.perf_counter()
    cmd = [sys.executable, "-m", "sara", "extract", str(images), str(work), "-q", "-s", f"extract.num_threads={threads}"]
    subprocess.run(cmd, check=True, capture_output=True)
    return time.perf_counter() - tic


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("images", type=Path)
    ap.add_argument("work", type=Path)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--threads", type=int, default=-1)
    args = ap.parse_args()
    rows = []
    for r in range(args.rounds):
        order = [("plain", plain), ("sara", sara)] if r % 2 == 0 else [("sara", sara), ("plain", plain)]
        times = {name: fn(args.images, args.work / name, args.threads) for name, fn in order}
        times["ratio"] = times["sara"] / times["plain"]
        rows.append(times)
        print(json.dumps({"round": r, **{k: round(v, 3) for k, v in times.items()}}), flush=True)
    ratios = sorted(t["ratio"] for t in rows)
    print(json.dumps({"images": args.images.name, "rounds": len(rows), "median_ratio": round(ratios[len(ratios) // 2], 3),
                      "ratios": [round(x, 3) for x in ratios]}))


if __name__ == "__main__":
    main()
