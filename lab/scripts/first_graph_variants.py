"""Experiment: SARA's first graph at scale with and without a chain through time, mapped under seeds.

On the synthetic street SARA's first model bends where the walk passes a place twice. Its graph is
loop-heavy: at 1,000 images 54% of its verified pairs join frames 9 or more apart (the tree itself
jumps between passes: 480 of its 999 edges), where sequential matching with loop detection keeps
most of its pairs between near frames. This maps the first graph of a finished run (the selection's
tree, loop, anchor and weak pairs and the support round's) as it was, and with a chain added: for
each frame its `--chain` best accepted candidates (by the scorer's weight) among the next `--window`
frames, not already in the graph; and, as a control, as many of the best accepted candidates by
weight wherever their frames are (what the fill round adds). Each variant is matched into a fresh
copy of the world's database (`sara.match.run`), then mapped by sara's map stage under each seed
with the remaps off, so the first mapping is seen as it is; each model's check (pairs contradicting
it) and its AUC against the world.
One JSON line per (variant, seed) in OUT/variants.jsonl; a finished one is skipped.

    python lab/scripts/first_graph_variants.py RUN WORLD OUT --seeds 0,1,2,3 --chain 1 --window 8
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scale_e2e import prepare_run_dir  # noqa: E402  (a sibling lab script)

SELECTED_ROLES = ("tree", "loop", "anchor", "weak")


def frame(name: str) -> int:
    return int(Path(name).stem)


def first_graph(run: Path) -> tuple[set[tuple[str, str]], list[dict]]:
    """The run's selected pairs and its support round's (the graph of its first mapping); every scored row."""
    rows = list(csv.DictReader(open(run / "scores.csv")))
    pairs = {tuple(sorted((r["name0"], r["name1"]))) for r in rows if r["role"] in SELECTED_ROLES}
    added = json.loads((run / ".sara" / "rounds.json").read_text())["info"].get("added", {})
    pairs |= {tuple(sorted(p)) for p in added.get("support", [])}
    return pairs, rows


def chain_pairs(rows: list[dict], graph: set[tuple[str, str]], per_frame: int, window: int) -> set[tuple[str, str]]:
    """For each frame, its `per_frame` best accepted candidates among the next `window` frames, not in `graph`."""
    forward: dict[str, list[tuple[float, tuple[str, str]]]] = {}
    for r in rows:
        a, b = sorted((r["name0"], r["name1"]), key=frame)
        if r["accepted"] == "true" and 0 < frame(b) - frame(a) <= window and (min(a, b), max(a, b)) not in graph:
            forward.setdefault(a, []).append((-float(r["weight"]), (min(a, b), max(a, b))))
    return {pair for options in forward.values() for _, pair in sorted(options)[:per_frame]}


def best_pairs(rows: list[dict], graph: set[tuple[str, str]], count: int) -> set[tuple[str, str]]:
    """The `count` best accepted candidates by weight not in `graph`, wherever their frames are (what the
    fill round adds): the control with as many pairs as the chain."""
    ranked = sorted((-float(r["weight"]), tuple(sorted((r["name0"], r["name1"])))) for r in rows
                    if r["accepted"] == "true")
    return set([pair for _, pair in ranked if pair not in graph][:count])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a finished scale_e2e SARA run folder (scores.csv, .sara/rounds.json)")
    ap.add_argument("world", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--seeds", default="0,1,2,3")
    ap.add_argument("--chain", type=int, default=1)
    ap.add_argument("--window", type=int, default=8)
    args = ap.parse_args()
    from sara import mapping
    from sara import match as match_stage
    from sara.config import make_config
    from sara.io import records

    graph, rows = first_graph(args.run)
    chain = chain_pairs(rows, graph, args.chain, args.window)
    variants = {"first": graph, f"first+chain{args.chain}w{args.window}": graph | chain,
                f"first+best{len(chain)}": graph | best_pairs(rows, graph, len(chain))}
    conf = make_config("sift-offline", {"map.contradicted_remaps": "0"})
    results = args.out / "variants.jsonl"
    done = {(d["variant"], d["seed"]) for d in map(json.loads, results.read_text().splitlines())} \
        if results.exists() else set()
    for variant, pairs in variants.items():
        folder = args.out / variant
        if not (folder / ".matched").exists():
            prepare_run_dir(args.world, folder)
            (folder / "pairs.txt").write_text("".join(f"{a} {b}\n" for a, b in sorted(pairs)))
            match_stage.run(conf.match, folder / "pairs.txt", folder / "database.db", folder,
                            features_path=folder / "features-sift.h5", progress=False)
            (folder / ".matched").touch()
        for seed in map(int, args.seeds.split(",")):
            if (variant, seed) in done:
                continue
            out = folder / f"seed-{seed}"
            tic = time.perf_counter()
            mapping.run(conf.map, folder / "database.db", folder / "images", out, seed=seed, progress=False,
                        min_num_inliers=conf.match.min_num_inliers, overwrite=True)
            info = records.done_info(out, mapping.STAGE)
            scored = subprocess.run([sys.executable, "-m", "sara", "evaluate", str(out / "sparse" / "0"),
                                     str(args.world / "gt")], capture_output=True, text=True).stdout
            line = {"variant": variant, "seed": seed, "pairs": len(pairs), "wall_s": time.perf_counter() - tic,
                    "sizes": info.get("component_sizes", [])[:5],
                    "contradicted": info.get("first_model_pairs_contradicted"),
                    "checked": info.get("first_model_pairs_checked"), "evaluate": scored.strip().splitlines()[-6:]}
            with open(results, "a") as f:
                f.write(json.dumps(line) + "\n")
            print(json.dumps(line), flush=True)


if __name__ == "__main__":
    main()
