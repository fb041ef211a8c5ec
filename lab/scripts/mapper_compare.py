"""COLMAP's incremental mapper against its global one on the matches of finished runs (issue 31).

    python lab/scripts/mapper_compare.py RUNS DATA WORK --scenes strecha-fountain-P11,... \
        [--methods sara,exhaustive] [--mappers incremental,global] [--seeds 0]

RUNS/<scene>/<method> are finished runs (a `sara bench` folder); DATA/<scene>/gt the true poses.
Each run folder is copied (`cp -a`, the original is never written) to WORK/<scene>-<method>-<mapper>,
and its matches are mapped again with the map stage only, once per seed:

    sara map COPY --overwrite --mapper MAPPER --seed SEED -q
    sara evaluate COPY GT --json COPY/eval-seedSEED.json

under `/usr/bin/time -v` (the process's CPU time and peak memory). Mappers alternate within a
scene and seed, so both see the same load of a shared machine. Rows are appended to
WORK/mapper_compare.jsonl; a row already there is not measured again.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

TIME_FIELDS = {"user_s": r"User time \(seconds\): ([\d.]+)", "sys_s": r"System time \(seconds\): ([\d.]+)",
               "max_rss_kb": r"Maximum resident set size \(kbytes\): (\d+)"}


def _sara(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["/usr/bin/time", "-v", sys.executable, "-m", "sara", *args],
                          capture_output=True, text=True)


def measure(src: Path, copy: Path, gt: Path, mapper: str, seed: int) -> dict:
    if not copy.exists():
        subprocess.run(["cp", "-a", str(src), str(copy)], check=True)
    proc = _sara("map", str(copy), "--overwrite", "--mapper", mapper, "--seed", str(seed), "-q")
    row: dict = {"returncode": proc.returncode}
    for key, pattern in TIME_FIELDS.items():
        found = re.search(pattern, proc.stderr)
        row[key] = float(found.group(1)) if found else None
    if proc.returncode != 0:
        row["error"] = proc.stderr.strip().splitlines()[-20:]
        return row
    info = json.loads((copy / ".sara" / "map.json").read_text())["info"]
    row.update(map_s=info["time_s"], component_sizes=info["component_sizes"], num_images=info["num_images"],
               mapper_used=info.get("mapper"), pairs_checked=info.get("first_model_pairs_checked"),
               pairs_contradicted=info.get("first_model_pairs_contradicted"))
    metrics_path = copy / f"eval-seed{seed}.json"
    ev = _sara("evaluate", str(copy), str(gt), "--json", str(metrics_path), "-q")
    if ev.returncode != 0:
        row["error"] = ev.stderr.strip().splitlines()[-20:]
        return row
    metrics = json.loads(metrics_path.read_text())
    row.update(num_registered=metrics["num_registered"], num_points3d=metrics["num_points3d"],
               auc1=metrics["auc"]["1"], auc5=metrics["auc"]["5"], reproj_mean_px=metrics["reproj_error_mean_px"])
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path)
    ap.add_argument("data", type=Path)
    ap.add_argument("work", type=Path)
    ap.add_argument("--scenes", required=True)
    ap.add_argument("--methods", default="sara,exhaustive")
    ap.add_argument("--mappers", default="incremental,global")
    ap.add_argument("--seeds", default="0")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    log = args.work / "mapper_compare.jsonl"
    done = {(r["scene"], r["method"], r["mapper"], r["seed"]) for r in map(json.loads, log.read_text().splitlines())} \
        if log.exists() else set()
    for scene in args.scenes.split(","):
        for method in args.methods.split(","):
            src = args.runs / scene / method
            if not (src / "sparse").is_dir():
                print(f"skip {scene}/{method}: no finished run", flush=True)
                continue
            for seed in map(int, args.seeds.split(",")):
                for mapper in args.mappers.split(","):
                    if (scene, method, mapper, seed) in done:
                        continue
                    copy = args.work / f"{scene}-{method}-{mapper}"
                    row = {"scene": scene, "method": method, "mapper": mapper, "seed": seed,
                           **measure(src, copy, args.data / scene / "gt", mapper, seed)}
                    print(json.dumps(row), flush=True)
                    with log.open("a") as fh:
                        fh.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
