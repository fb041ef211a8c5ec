"""Issue 31: the matching estimate against the time taken, and SARA's time after extraction against
exhaustive matching's with the rounds' share. One `sara run` per scene and method, one after the
other (never in parallel: the figures are times).

    python lab/scripts/eta_measure.py WORK [SCENE ...]   # from the repository root

WORK: a scratch folder for the runs (one sub-folder per scene and method). Scenes are read from
`../shared/data` (or $SARA_DATA). Prints a Markdown table per question and writes WORK/eta.json.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

from sara.pipeline import share_features

DATA = Path(os.environ.get("SARA_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))
SCENES = ["strecha-fountain-P11", "strecha-Herz-Jesus-P25", "middlebury-templeRing"]
METHODS = {"exhaustive": ["--pairs", "exhaustive"], "sara": []}
ESTIMATE_LINE = re.compile(r"match: ([\d,]+) pairs, about (.+?) at ([\d.]+) pairs/s \(first chunk\)")


def load() -> float:
    return os.getloadavg()[0]


def run_one(scene: str, method: str, work: Path) -> dict:
    """One `sara run`; SARA's takes the features of exhaustive's run (`share_features`): the
    extraction is not what is measured."""
    out = work / f"{scene}-{method}"
    cmd = [sys.executable, "-m", "sara", "run", str(DATA / scene / "images"), str(out), "--gt",
           str(DATA / scene / "gt"), *METHODS[method]]
    features = work / f"{scene}-features"  # a folder whose extraction to reuse, if there is one
    if method == "exhaustive" and not features.is_dir():
        cmd.append("--overwrite")
    else:
        share_features(features if method == "exhaustive" else work / f"{scene}-exhaustive", out)
    before, tic = load(), time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - tic
    if proc.returncode != 0:
        raise SystemExit(f"{scene} {method}: exit {proc.returncode}\n{proc.stderr[-2000:]}")
    (out / "stderr.log").write_text(proc.stderr)
    stages = json.loads((out / "run.json").read_text())["stages"]
    metrics = json.loads((out / "metrics.json").read_text())
    first = ESTIMATE_LINE.search(proc.stderr)
    rounds = stages.get("rounds", {})
    # the rounds' ledger holds their whole time (choosing pairs included), the stages only match and map
    after_extraction = (rounds["first_round_time_s"] + rounds["total_time_s"] if "total_time_s" in rounds
                        else sum(stages[s].get("time_s", 0.0) for s in ("pairs", "match", "map")))
    return {
        "scene": scene, "method": method, "wall_s": wall, "load_before": before, "load_after": load(),
        "pairs": stages["pairs"]["num_pairs"], "match_time_s": stages["match"]["time_s"],
        "match_estimate_s": stages["match"].get("estimate_s"),
        "first_estimate_line": first.group(0) if first else None,
        "first_match_time_s": rounds.get("first_match_time_s", stages["match"]["time_s"]),
        "first_match_estimate_s": rounds.get("first_match_estimate_s", stages["match"].get("estimate_s")),
        "after_extraction_s": after_extraction, "extract_s": stages["extract"].get("time_s", 0.0),
        "rounds_s": rounds.get("total_time_s", 0.0), "rounds_share": rounds.get("share_after_extraction", 0.0),
        "rounds_budget_s": rounds.get("time_budget_s"), "rounds_stopped": rounds.get("stopped"),
        "rounds_history": rounds.get("history", []),
        "registered": metrics.get("num_registered"), "auc": metrics.get("auc", {}),
    }


def main() -> None:
    work = Path(sys.argv[1])
    scenes = sys.argv[2:] or SCENES
    work.mkdir(parents=True, exist_ok=True)
    results = []
    for scene in scenes:
        for method in METHODS:
            results.append(run_one(scene, method, work))
            print(json.dumps({k: v for k, v in results[-1].items() if k != "rounds_history"}), flush=True)
            (work / "eta.json").write_text(json.dumps(results, indent=1))
    print("\n| scene | method | pairs | first chunk's estimate | matching took | error |\n"
          "|---|---|---:|---:|---:|---:|")
    for r in results:
        est, took = r["first_match_estimate_s"], r["first_match_time_s"]
        print(f"| {r['scene']} | {r['method']} | {r['pairs']} | {est:.1f} s | {took:.1f} s | "
              f"{100 * (est - took) / took:+.0f}% |")
    print("\n| scene | exhaustive after extraction | sara after extraction | sara / exh. | rounds | rounds' share | "
          "AUC@5 exh. / sara |\n|---|---:|---:|---:|---:|---:|---:|")
    by = {(r["scene"], r["method"]): r for r in results}
    for scene in scenes:
        exh, sara = by[(scene, "exhaustive")], by[(scene, "sara")]
        print(f"| {scene} | {exh['after_extraction_s']:.1f} s | {sara['after_extraction_s']:.1f} s | "
              f"{sara['after_extraction_s'] / exh['after_extraction_s']:.2f} | {sara['rounds_s']:.1f} s | "
              f"{100 * sara['rounds_share']:.0f}% | {exh['auc'].get('5', 0):.4f} / {sara['auc'].get('5', 0):.4f} |")


if __name__ == "__main__":
    main()
