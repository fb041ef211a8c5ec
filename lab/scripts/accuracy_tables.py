"""The tables of lab/notes/ACCURACY.md from finished `sara bench` folders.

Each folder given as LABEL=PATH is a bench output (PATH/<scene>/<method>/run.json). Rows: every
scene, every (label, method) found; columns: pairs (with the two caps 4 N and 25% of exhaustive),
registration, AUC@1/@5 with their difference to exhaustive (taken from the folder labelled
`--reference`), 3D points (and their share of exhaustive's), and the end-to-end time (selection +
matching + mapping, every round after mapping included) with its ratio to exhaustive's.

    python lab/scripts/accuracy_tables.py after=BENCH/full before=BENCH/before [--reference after]
        [--extra-exhaustive bm-moldGoldCape=7021,0.943,0.989,52139,2572.9]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

SCENES = ("strecha-fountain-P11", "middlebury-templeSparseRing", "strecha-Herz-Jesus-P25", "strecha-castle-P30",
          "middlebury-templeRing", "bm-moldGoldCape")


def read_run(run_dir: Path) -> dict | None:
    path = run_dir / "run.json"
    if not path.exists():
        return None
    run = json.loads(path.read_text())
    stages, metrics = run["stages"], run.get("metrics") or {}
    if not metrics:
        return None
    repair = stages.get("rounds", {})
    times = {k: float(stages.get(k, {}).get("time_s", 0.0)) for k in ("pairs", "match", "map")}
    return {
        "n": stages["images"]["num_images"],
        "pairs": stages["match"].get("num_pairs"),
        "added": stages["pairs"].get("num_added_after_mapping", 0),
        "reg": metrics["num_registered"], "comps": metrics["num_components"],
        "auc1": metrics["auc"]["1"], "auc5": metrics["auc"]["5"], "points": metrics["num_points3d"],
        "select_s": times["pairs"], "match_s": times["match"], "map_s": times["map"],
        "total_s": sum(times.values()), "rounds": repair.get("rounds", 0),
        "refined": repair.get("refined_rounds", 0),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("benches", nargs="+", help="LABEL=PATH")
    ap.add_argument("--reference", default="", help="label of the folder whose exhaustive rows are the reference")
    ap.add_argument("--extra-exhaustive", action="append", default=[],
                    help="SCENE=pairs,auc1,auc5,points,total_s of an exhaustive run not in the folders")
    args = ap.parse_args()
    benches = dict(b.split("=", 1) for b in args.benches)
    ref_label = args.reference or next(iter(benches))
    reference = {}
    for extra in args.extra_exhaustive:
        scene, values = extra.split("=", 1)
        pairs, auc1, auc5, points, total = (float(v) for v in values.split(","))
        reference[scene] = {"pairs": int(pairs), "auc1": auc1, "auc5": auc5, "points": int(points), "total_s": total}
    for scene in SCENES:
        run = read_run(Path(benches[ref_label]) / scene / "exhaustive")
        if run:
            reference[scene] = run
    header = ("| scene | run | pairs | <= 4N, 25% exh. | reg. | AUC@1 (vs exh.) | AUC@5 (vs exh.) | 3D points (% exh.) "
              "| select + match + map = total (s) | time / exh. |")
    print(header)
    print("|---|---|---:|---|---:|---:|---:|---:|---:|---:|")
    for scene in SCENES:
        ref = reference.get(scene)
        for label, folder in benches.items():
            for method in ("exhaustive", "sara"):
                run = read_run(Path(folder) / scene / method)
                if run is None or (method == "exhaustive" and label != ref_label):
                    continue
                n = run["n"]
                cap_ok = run["pairs"] <= 4 * n and run["pairs"] <= 0.25 * n * (n - 1) / 2
                d1 = f" ({run['auc1'] - ref['auc1']:+.4f})" if ref and method != "exhaustive" else ""
                d5 = f" ({run['auc5'] - ref['auc5']:+.4f})" if ref and method != "exhaustive" else ""
                pts = f" ({100 * run['points'] / ref['points']:.0f}%)" if ref else ""
                ratio = f"{run['total_s'] / ref['total_s']:.2f}" if ref else "-"
                added = f" ({run['added']} after)" if run["added"] else ""
                print(f"| {scene} | {label} {method} | {run['pairs']}{added} | {'yes' if cap_ok else 'no'} "
                      f"| {run['reg']}/{n} in {run['comps']} | {run['auc1']:.4f}{d1} | {run['auc5']:.4f}{d5} "
                      f"| {run['points']}{pts} | {run['select_s']:.1f} + {run['match_s']:.1f} + {run['map_s']:.1f} = "
                      f"{run['total_s']:.1f} | {ratio} |")


if __name__ == "__main__":
    main()
