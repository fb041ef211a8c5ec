"""Cost of the learned backends on CPU or GPU: extraction per image and matching per pair.

For ALIKED-n16 + LightGlue, DISK + LightGlue and XFeat + LighterGlue, at a given long side
(default 1024 px) and keypoint budgets (default 2048 and 1024), on one pair of images (default
the first two of strecha-fountain-P11). Each time is the median of `--repeats` runs after one
warm-up run. torch runs with `--threads` threads (default 1: on a shared 2-core machine one
thread was faster and steadier than two; parallelism across images or pairs is the better use
of more cores). Prints a Markdown table; `--json` also writes the numbers.

    python lab/scripts/learned_costs.py [--images A.jpg B.jpg] [--long-side 1024] [--keypoints 2048 1024] \
        [--backends aliked-n16,disk,xfeat] [--device cpu|cuda]

On a GPU (`--device cuda`) each timed call ends when its results are back on the host (the
backends return numpy arrays), so the times include the transfers and no asynchronous work is left
out.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from sara.config import ExtractConfig, MatchConfig
from sara.features import make_backend
from sara.io.h5 import Features
from sara.matchers import make_matcher

DATA = Path(os.environ.get("SARA_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))
COMBINATIONS = [("aliked-n16", "LightGlue"), ("disk", "LightGlue"), ("xfeat", "LighterGlue")]


def load_image(path: Path, long_side: int) -> np.ndarray:
    """(H, W, 3) uint8 RGB, downscaled (area) so that the longer side is `long_side`."""
    image = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
    scale = long_side / max(image.shape[:2])
    return cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else image


def timed(func, repeats: int) -> tuple[float, object]:
    """(median seconds of `repeats` runs after a warm-up run, last result)."""
    result = func()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = func()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def measure(backend: str, images: list[np.ndarray], num_keypoints: int, repeats: int, device: str) -> dict:
    extractor = make_backend(ExtractConfig(backend=backend, max_num_features=num_keypoints, device=device))
    matcher = make_matcher(MatchConfig(device=device), backend)
    extract_s = []
    feats = []
    for image in images:
        seconds, kp = timed(lambda image=image: extractor.extract(image), repeats)
        extract_s.append(seconds)
        feats.append(Features(kp.xy, kp.descriptors, kp.scores, (image.shape[1], image.shape[0])))
    match_s, (matches, _) = timed(lambda: matcher.match(feats[0], feats[1]), repeats)
    inliers = 0
    if len(matches) >= 8:
        _, mask = cv2.findFundamentalMat(feats[0].keypoints[matches[:, 0]], feats[1].keypoints[matches[:, 1]],
                                         cv2.FM_RANSAC, 1.0, 0.999)
        inliers = int(mask.sum()) if mask is not None else 0
    return {
        "backend": backend, "matcher": matcher.name, "device": device, "keypoints_asked": num_keypoints,
        "keypoints": [len(f.keypoints) for f in feats], "extract_s_per_image": statistics.mean(extract_s),
        "match_s_per_pair": match_s, "matches": len(matches), "f_inliers_1px": inliers,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    scene = DATA / "strecha-fountain-P11" / "images"
    parser.add_argument("--images", nargs=2, type=Path, default=[scene / "0000.jpg", scene / "0001.jpg"])
    parser.add_argument("--long-side", type=int, default=1024)
    parser.add_argument("--keypoints", nargs="+", type=int, default=[2048, 1024])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--backends", default=",".join(b for b, _ in COMBINATIONS),
                        help="comma-separated local-feature backends, each timed with its usual matcher")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto (where the networks run)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    load_before = tuple(round(v, 1) for v in os.getloadavg())
    torch.set_num_threads(args.threads)  # this script only: library code never changes it
    images = [load_image(p, args.long_side) for p in args.images]
    rows = [measure(backend, images, k, args.repeats, args.device) for backend in backends for k in args.keypoints]
    height, width = images[0].shape[:2]
    where = torch.cuda.get_device_name() if args.device != "cpu" and torch.cuda.is_available() else "CPU"
    print(f"{width}x{height} px, {where}, {args.threads} torch thread(s), median of {args.repeats} runs, "
          f"load average before/after: {load_before} / {tuple(round(v, 1) for v in os.getloadavg())}")
    print("| features + matcher | keypoints | extraction s / image | matching s / pair | matches | F-inliers (1 px) |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['backend']} + {r['matcher']} | {r['keypoints_asked']} | {r['extract_s_per_image']:.4f} "
              f"| {r['match_s_per_pair']:.4f} | {r['matches']} | {r['f_inliers_1px']} |")
    if args.json:
        args.json.write_text(json.dumps({"image_size": [width, height], "device": where, "threads": args.threads,
                                         "rows": rows},
                                        indent=2) + "\n")


if __name__ == "__main__":
    main()
