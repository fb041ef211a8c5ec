"""Per-pair matcher cost of the pairs each method selects, timed side by side under the same load.

`sara bench` reports the wall-clock time of a method's whole matching stage. On a shared machine
that time moves with the load of whatever else runs, and exhaustive learned matching on a large
scene takes hours. This script times the learned matcher alone (LightGlue / LighterGlue forward
pass, 1 torch thread, no verification, no database) on the features a bench already extracted:
a random sample of each method's pairs, interleaved (one pair of each method in turn), so that
the same load weighs on every method. From the sample means it *estimates* each method's total
matcher time (pairs x mean per-pair time), labelled as an estimate.

    python lab/scripts/learned_pair_costs.py BENCH/SCENE [--methods exhaustive,retrieval,sara] \
        [--samples 60] [--seed 0] [--device cpu] [--json out.json]

`--samples 0` times every pair of every method (then the totals are measured, not estimated: on a
GPU, where a pair takes milliseconds, that is the way to use it). `--device cuda` runs the matcher
on the GPU; each timed call ends when the matches are back on the host.

BENCH/SCENE is a scene folder of a `sara bench` run with a learned preset; the pairs of method M
are read from BENCH/SCENE/M/pairs.txt when it exists, else (exhaustive) all pairs of the images.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import random
import statistics
import time
from pathlib import Path

import torch

from sara.config import MatchConfig
from sara.io.h5 import FeatureCache
from sara.io.pairs import read_pairs
from sara.matchers import make_matcher


def features_file(scene_dir: Path) -> tuple[Path, str]:
    """(features h5, local-feature backend) of a bench scene folder."""
    found = sorted((scene_dir / "features").glob("features-*.h5"))
    if not found:
        raise SystemExit(f"no features-*.h5 in {scene_dir / 'features'}: run the bench first")
    return found[0], found[0].stem.removeprefix("features-")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene_dir", type=Path, help="BENCH/<scene> of a sara bench run")
    parser.add_argument("--methods", default="exhaustive,retrieval,sara")
    parser.add_argument("--samples", type=int, default=60, help="pairs timed per method (0: all of them)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto (where the matcher runs)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)  # this script only
    h5_path, backend = features_file(args.scene_dir)
    cache = FeatureCache(h5_path, capacity=512)
    import h5py

    with h5py.File(h5_path, "r") as h5:
        names = sorted(h5.keys())
    pairs: dict[str, list[tuple[str, str]]] = {}
    for method in [m.strip() for m in args.methods.split(",") if m.strip()]:
        path = args.scene_dir / method / "pairs.txt"
        if path.exists():
            pairs[method] = [tuple(p) for p in read_pairs(path, known_names=names)]
        elif method == "exhaustive":
            pairs[method] = list(itertools.combinations(names, 2))
        else:
            raise SystemExit(f"{path} is missing")
    rng = random.Random(args.seed)
    samples = {m: rng.sample(p, min(args.samples, len(p)) if args.samples > 0 else len(p)) for m, p in pairs.items()}
    matcher = make_matcher(MatchConfig(device=args.device), backend)
    warm = next(iter(samples.values()))[0]
    matcher.match(cache.get(warm[0]), cache.get(warm[1]))  # warm-up, not timed
    times: dict[str, list[float]] = {m: [] for m in samples}
    cpu: dict[str, list[float]] = {m: [] for m in samples}  # process CPU time: less sensitive to the load
    found: dict[str, list[int]] = {m: [] for m in samples}
    load_before = os.getloadavg()
    for i in range(max(len(s) for s in samples.values())):
        for method, sample in samples.items():
            if i >= len(sample):
                continue
            a, b = cache.get(sample[i][0]), cache.get(sample[i][1])
            tic, cpu_tic = time.perf_counter(), time.process_time()
            matches = matcher.match(a, b)[0]
            times[method].append(time.perf_counter() - tic)
            cpu[method].append(time.process_time() - cpu_tic)
            found[method].append(len(matches))
    load_after = os.getloadavg()
    rows = []
    for method, t in times.items():
        mean = statistics.mean(t)
        rows.append({"method": method, "pairs": len(pairs[method]), "sampled": len(t), "mean_s": mean,
                     "median_s": statistics.median(t), "p90_s": sorted(t)[int(0.9 * (len(t) - 1))],
                     "cpu_mean_s": statistics.mean(cpu[method]), "matches_mean": statistics.mean(found[method]),
                     "estimated_total_s": mean * len(pairs[method])})
    reference = next((r for r in rows if r["method"] == "exhaustive"), None)
    where = torch.cuda.get_device_name() if args.device != "cpu" and torch.cuda.is_available() else "CPU"
    every = all(len(s) == len(pairs[m]) for m, s in samples.items())
    print(f"{h5_path} ({backend} + {matcher.name}), {where}, {args.threads} torch thread(s), seed {args.seed}, "
          f"{'every pair timed (totals measured)' if every else 'sampled (totals estimated)'}, "
          f"load average before/after: {tuple(round(v, 1) for v in load_before)} / "
          f"{tuple(round(v, 1) for v in load_after)}")
    print("| Method | Pairs | Sampled | Mean s/pair | Median s/pair | p90 s/pair | Mean CPU s/pair "
          "| Matches/pair (raw) | Estimated matcher total (s) | Estimated exh. / method |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        ratio = reference["estimated_total_s"] / r["estimated_total_s"] if reference else float("nan")
        r["exhaustive_over_method"] = ratio if reference else None
        print(f"| {r['method']} | {r['pairs']} | {r['sampled']} | {r['mean_s']:.4f} | {r['median_s']:.4f} "
              f"| {r['p90_s']:.4f} | {r['cpu_mean_s']:.4f} | {r['matches_mean']:.0f} "
              f"| {r['estimated_total_s']:.1f} | {ratio:.1f} |")
    if args.json:
        args.json.write_text(json.dumps({"features": str(h5_path), "backend": backend, "matcher": matcher.name,
                                         "device": where,
                                         "threads": args.threads, "seed": args.seed, "rows": rows,
                                         "load_before": load_before, "load_after": load_after}, indent=2) + "\n")


if __name__ == "__main__":
    main()
