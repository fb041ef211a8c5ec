#!/usr/bin/env python
"""Kill `sara run` with SIGKILL at random moments, resume each time, compare with an uninterrupted run.

    python scripts/fault_injection.py ../shared/data/strecha-fountain-P11 --kills 10 --out /tmp/faults

The kills are aimed at every stage in turn (extract, pairs, match, map): before each kill the
script looks at which stages the output folder has finished and waits a random time inside the
next stage's duration, as measured on the reference run. At the end it checks that the final
pairs are identical and the models agree (same registered images; accuracy against the scene's
ground truth, when it has one, within 0.01 AUC@5).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

STAGES = ("extract", "pairs", "match", "map")


def sara_cmd(images: Path, out: Path, extra: list[str]) -> list[str]:
    return [sys.executable, "-m", "sara", "run", str(images), str(out), "-q", *extra]


def stage_done(out: Path, stage: str) -> bool:
    path = out / ".sara" / f"{stage}.json"
    try:
        return json.loads(path.read_text()).get("done") is True
    except (OSError, ValueError):
        return False


def next_stage(out: Path) -> str | None:
    return next((s for s in STAGES if not stage_done(out, s)), None)


def run_reference(images: Path, out: Path, extra: list[str]) -> tuple[dict, float]:
    tic = time.perf_counter()
    subprocess.run(sara_cmd(images, out, extra), check=True)
    total = time.perf_counter() - tic
    return json.loads((out / "run.json").read_text()), total


def registered(out: Path) -> list[str]:
    import pycolmap

    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    return sorted(im.name for im in rec.images.values() if im.has_pose)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path, help="a scene folder with images/ (and gt/)")
    parser.add_argument("--kills", type=int, default=10)
    parser.add_argument("--out", type=Path, default=Path("fault-injection"))
    parser.add_argument("--seed", type=int, default=0, help="seed of the kill times")
    parser.add_argument("--pairs", default="sara")
    args = parser.parse_args()
    rng = random.Random(args.seed)
    images, gt = args.scene / "images", args.scene / "gt"
    extra = ["--pairs", args.pairs] + (["--gt", str(gt)] if gt.exists() else [])
    shutil.rmtree(args.out, ignore_errors=True)
    ref_out, test_out = args.out / "reference", args.out / "interrupted"

    ref, ref_total = run_reference(images, ref_out, extra)
    stage_time = {s: max(0.5, ref["stages"][s]["time_s"]) for s in STAGES}
    startup = max(1.0, ref_total - sum(stage_time.values()))  # imports, image checks, evaluation
    print(f"reference run: {ref_total:.1f} s; stages {({k: round(v, 1) for k, v in stage_time.items()})}")

    kills = []
    for i in range(args.kills):
        target = next_stage(test_out) or "map"
        delay = startup * 0.8 + rng.uniform(0.05, 0.95) * stage_time[target]
        proc = subprocess.Popen(sara_cmd(images, test_out, extra), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        time.sleep(delay)
        finished = proc.poll() is not None
        if not finished:
            os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        reached = next_stage(test_out)
        kills.append({"kill": i + 1, "aimed_at": target, "after_s": round(delay, 2), "finished_first": finished,
                      "stage_when_killed": reached or "done"})
        print(f"kill {i + 1:2d}: aimed at {target:7s} after {delay:5.1f} s -> "
              f"{'run had finished' if finished else 'killed'}, next stage to do: {reached or 'none'}")
        if finished and reached is None:
            shutil.rmtree(test_out / "sparse", ignore_errors=True)  # keep the last stage exercised
            (test_out / ".sara" / "map.json").unlink(missing_ok=True)

    final = subprocess.run(sara_cmd(images, test_out, extra), capture_output=True, text=True)
    if final.returncode != 0:
        print("resumed run failed:\n" + final.stderr)
        return 1
    same_pairs = (ref_out / "pairs.txt").read_text() == (test_out / "pairs.txt").read_text()
    ref_reg, test_reg = registered(ref_out), registered(test_out)
    result = {"kills": kills, "same_pairs": same_pairs, "registered_reference": len(ref_reg),
              "registered_resumed": len(test_reg), "same_registered_images": ref_reg == test_reg}
    ok = same_pairs and ref_reg == test_reg
    if gt.exists():
        test = json.loads((test_out / "run.json").read_text())
        a, b = ref["metrics"]["auc"]["5"], test["metrics"]["auc"]["5"]
        result.update(auc5_reference=a, auc5_resumed=b)
        ok = ok and abs(a - b) <= 0.01
    killed = sum(not k["finished_first"] for k in kills)
    stages_hit = sorted({k["stage_when_killed"] for k in kills if not k["finished_first"]})
    result.update(num_killed=killed, stages_interrupted=stages_hit, ok=ok)
    (args.out / "fault_injection.json").write_text(json.dumps(result, indent=2))
    print(json.dumps({k: v for k, v in result.items() if k != "kills"}, indent=2))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
