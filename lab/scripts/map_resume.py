"""A mapping killed part-way and resumed from its checkpoint, against the same mapping uninterrupted.

    python lab/scripts/map_resume.py RUN_DIR GT WORK --kill-after-s 150 [--checkpoint-minutes 1]

RUN_DIR: a run folder kept by `scale_e2e.py --keep-runs` (its `database.db` and `images`). The map
stage (`sara.mapping.run`, this release's defaults: step by step from 1,000 images) maps a copy of
its database three times, each in a process of its own: `whole` uninterrupted; `killed` killed
(SIGKILL: nothing cleans up) after --kill-after-s seconds, then the same call again, which resumes
from the checkpoint. (SIGINT would not do: a process started in the background of a script
inherits SIGINT ignored.)
Writes WORK/map_resume.json: wall times, the checkpoint's views at the kill, and for both models
the registered views and AUC (`sara evaluate` against GT).
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path


def _child(db: Path, images: Path, out: Path, minutes: float) -> None:
    import logging

    from sara import mapping
    from sara.config import make_config

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")  # sara's own lines

    conf = make_config("sift-offline", {"map.checkpoint_minutes": minutes}).map
    mapping.run(conf, db, images, out, progress=False)


def _map(args: argparse.Namespace, case: Path, kill_after_s: float | None) -> dict:
    cmd = [sys.executable, __file__, "--child", str(case / "database.db"), str(args.run_dir / "images"), str(case),
           str(args.checkpoint_minutes)]
    return run_child(cmd, case / "log.txt", kill_after_s)


def run_child(cmd: list[str], log: Path, kill_after_s: float | None) -> dict:
    """Run `cmd`, its stderr appended to `log`; SIGKILL it after `kill_after_s` (None: let it end).
    Returns its wall seconds and return code."""
    tic = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=open(log, "a"))
    try:
        proc.wait(timeout=kill_after_s)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    return {"wall_s": round(time.perf_counter() - tic, 1), "returncode": proc.returncode}


def _evaluate(case: Path, gt: Path) -> dict:
    out = case / "metrics.json"
    proc = subprocess.run([sys.executable, "-m", "sara", "evaluate", str(case / "sparse"), str(gt), "--json", str(out),
                           "-q"], capture_output=True, text=True)
    if proc.returncode != 0:
        return {"error": proc.stderr[-500:]}
    metrics = json.loads(out.read_text())
    return {k: metrics.get(k) for k in ("num_registered", "num_components", "auc")}


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        _child(Path(sys.argv[2]), Path(sys.argv[3]), Path(sys.argv[4]), float(sys.argv[5]))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("gt", type=Path)
    ap.add_argument("work", type=Path)
    ap.add_argument("--kill-after-s", type=float, required=True)
    ap.add_argument("--checkpoint-minutes", type=float, default=1.0)
    ap.add_argument("--keep-whole", action="store_true", help="reuse WORK/whole and its time from WORK/map_resume.json")
    args = ap.parse_args()
    result: dict = {"kill_after_s": args.kill_after_s, "checkpoint_minutes": args.checkpoint_minutes}
    earlier = json.loads((args.work / "map_resume.json").read_text()) if args.keep_whole else None
    for name in ("killed",) if earlier else ("whole", "killed"):
        case = args.work / name
        shutil.rmtree(case, ignore_errors=True)
        case.mkdir(parents=True)
        shutil.copyfile(args.run_dir / "database.db", case / "database.db")
    result["whole"] = earlier["whole"] if earlier else _map(args, args.work / "whole", None)
    result["killed"] = _map(args, args.work / "killed", args.kill_after_s)
    ckpt = args.work / "killed" / ".sara" / "map-checkpoint" / "checkpoint.json"
    result["checkpoint_at_kill"] = json.loads(ckpt.read_text()) if ckpt.exists() else None
    result["resumed"] = _map(args, args.work / "killed", None)
    result["resumed"]["log_says_resumed"] = "resuming the mapping from its checkpoint" in \
        (args.work / "killed" / "log.txt").read_text()
    for name in ("whole", "killed"):
        result[f"eval_{name}"] = _evaluate(args.work / name, args.gt)
    (args.work / "map_resume.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
