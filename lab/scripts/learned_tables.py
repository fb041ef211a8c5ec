"""The compact per-scene tables of lab/notes/BENCHMARKS.md's learned-feature section.

Reads the `results.csv` of learned `sara bench` runs (lab/scripts/learned_bench.sh) and, for the SIFT
rows, the Markdown tables already in lab/notes/BENCHMARKS.md (the SIFT run; nothing re-measured), and
prints one table per scene: features x method, with pairs, pairs per image, matching time and its
per-pair cost, AUC@1/5/10 and the ratios against exhaustive with the same features.

    python lab/scripts/learned_tables.py ../bench_learned/*/results.csv [--sift lab/notes/BENCHMARKS.md] \
        [--sift-bench BENCH]

`--sift-bench` takes the SIFT rows from a SIFT `sara bench` folder instead (its results.csv and
finished methods), for the scenes and methods it has; the rest still come from `--sift`.

A bench folder instead of a results.csv also takes the methods it has finished so far.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
from pathlib import Path

METHODS = ("exhaustive", "retrieval", "sara")
FEATURES = {"sift": "SIFT", "aliked": "ALIKED+LightGlue", "disk": "DISK+LightGlue", "xfeat": "XFeat+LighterGlue"}
SCENES = ("bm-moldGoldCape", "strecha-fountain-P11", "middlebury-templeSparseRing", "strecha-Herz-Jesus-P25",
          "strecha-castle-P30", "middlebury-templeRing")


def num(text: str | None) -> float | None:
    try:
        return float(text) if text not in (None, "", "-") else None
    except ValueError:
        return None


def sift_rows(doc: Path) -> list[dict]:
    """Rows of the SIFT tables in lab/notes/BENCHMARKS.md (the headline and the five smaller scenes)."""
    rows, scene, header = [], None, None
    for line in doc.read_text().splitlines():
        m = re.match(r"## (?:Headline: )?([\w-]+) \((\d+) images", line)
        if m:
            scene, header = (m.group(1), int(m.group(2))), None
            continue
        if line.startswith("## "):
            scene = None if "Headline" not in line else scene
        if scene is None or not line.startswith("|") or line.startswith("|---"):
            continue
        cells = [c.strip() for c in line.strip("|").split("|")]
        if cells[0] == "Method":
            header = cells
            continue
        if header and cells[0] in METHODS and len(cells) == len(header):
            r = dict(zip(header, cells))
            rows.append({"scene": scene[0], "num_images": scene[1], "features": "sift", "method": cells[0],
                         "registered_pct": num(r["Reg. %"]), "pairs": num(r["Pairs"]), "match_s": num(r["Match (s)"]),
                         "auc@1": num(r["AUC@1"]), "auc@5": num(r["AUC@5"]), "auc@10": num(r["AUC@10"]),
                         "num_components": None, "num_registered": None})
    headline = next((i for i, line in enumerate(doc.read_text().splitlines()) if line.startswith("## Headline")),
                    None)
    if headline is not None:  # the headline section names the scene as "bm-moldGoldCape (119 images, ...)"
        for r in rows:
            if r["scene"] == "bm-moldGoldCape":
                r["num_images"] = 119
    return rows


def finished_rows(bench_dir: Path) -> list[dict]:
    """Rows of the methods a still-running bench has finished (BENCH/<scene>/<method>/.sara/bench.json):
    the bench writes results.csv only when every method of a scene is done."""
    rows = []
    for record in sorted(bench_dir.glob("*/*/.sara/bench.json")):
        data = json.loads(record.read_text())
        if data.get("done"):
            rows.append({"scene": record.parents[2].name, "method": record.parents[1].name,
                         **{k: "" if v is None else str(v) for k, v in data["info"].items()}})
    return rows


def learned_rows(path: Path, features: str | None = None) -> list[dict]:
    """Rows of a learned bench: its results.csv, or (a folder) results.csv plus finished methods;
    the features are named by the folder (learned_bench.sh's names) unless given."""
    bench_dir = path if path.is_dir() else path.parent
    if features is None:
        features = next((k for k in FEATURES if bench_dir.name.startswith(k)), bench_dir.name)
        if features in FEATURES and "1024" in bench_dir.name:  # -s extract.max_num_features=1024 (learned_bench.sh)
            features += "1024"
    found = []
    if (bench_dir / "results.csv").exists():
        with (bench_dir / "results.csv").open() as f:
            found = list(csv.DictReader(f))
    if path.is_dir():
        have = {(r["scene"], r["method"]) for r in found}
        found += [r for r in finished_rows(bench_dir) if (r["scene"], r["method"]) not in have]
    rows = []
    if True:
        for r in found:
            if r.get("error"):
                continue
            rows.append({"scene": r["scene"], "num_images": int(r["num_images"]), "features": features,
                         "method": r["method"], "registered_pct": num(r["registered_pct"]),
                         "num_registered": num(r["num_registered"]), "num_components": num(r["num_components"]),
                         "pairs": num(r["pairs"]), "match_s": num(r["match_s"]), "auc@1": num(r["auc@1"]),
                         "auc@5": num(r["auc@5"]), "auc@10": num(r["auc@10"])})
    return rows


def label(features: str) -> str:
    base = features.removesuffix("1024")
    return FEATURES.get(base, base) + (" (1,024 kpts)" if features.endswith("1024") else "")


def fmt(value: float | None, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results", nargs="+", type=Path)
    parser.add_argument("--sift", type=Path, default=Path(__file__).resolve().parents[1] / "notes" / "BENCHMARKS.md")
    parser.add_argument("--sift-bench", type=Path, help="a SIFT sara bench folder: its rows replace --sift's")
    args = parser.parse_args()
    rows = sift_rows(args.sift) if args.sift and args.sift.exists() else []
    if args.sift_bench:
        fresh = learned_rows(args.sift_bench, features="sift")
        have = {(r["scene"], r["method"]) for r in fresh}
        rows = [r for r in rows if (r["scene"], r["method"]) not in have] + fresh
    for path in args.results:
        rows += learned_rows(path)
    for scene in SCENES:
        mine = [r for r in rows if r["scene"] == scene]
        if not any(r["features"] != "sift" for r in mine):
            continue
        n = mine[0]["num_images"]
        print(f"\n#### {scene} ({n} images, {n * (n - 1) // 2} exhaustive pairs)\n")
        print("| Features | Method | Reg. % | Models | Pairs | Pairs / N | Match (s) | s / pair | AUC@1 | AUC@5 "
              "| AUC@10 | Pairs / exh. | Match time / exh. |")
        print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
        for feat in dict.fromkeys(r["features"] for r in mine):
            group = {r["method"]: r for r in mine if r["features"] == feat}
            ref = group.get("exhaustive")
            for method in METHODS:
                r = group.get(method)
                if r is None:
                    continue
                pairs, match_s = r["pairs"], r["match_s"]
                ratio_p = pairs / ref["pairs"] if ref and pairs else None
                ratio_t = match_s / ref["match_s"] if ref and match_s and ref["match_s"] else None
                print(f"| {label(feat)} | {method} | {fmt(r['registered_pct'], '.1f')} "
                      f"| {fmt(r['num_components'], '.0f')} | {fmt(pairs, '.0f')} "
                      f"| {fmt(pairs / n if pairs else None, '.2f')} "
                      f"| {fmt(match_s, '.1f')} | {fmt(match_s / pairs if pairs and match_s else None, '.2f')} "
                      f"| {fmt(r['auc@1'], '.3f')} | {fmt(r['auc@5'], '.3f')} | {fmt(r['auc@10'], '.3f')} "
                      f"| {fmt(ratio_p, '.3f')} | {fmt(ratio_t, '.3f')} |")


if __name__ == "__main__":
    main()
