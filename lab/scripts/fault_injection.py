#!/usr/bin/env python
"""Interrupt `sara run` at random moments and damage its outputs between runs; check that every
resume ends with the result of an uninterrupted run, or refuses in one line without changing a byte.

    python lab/scripts/fault_injection.py ../shared/data/middlebury-templeSparseRing --kills 8 --out /tmp/faults

1. A reference run, uninterrupted.
2. Kills: `sara run` is stopped with SIGKILL and SIGTERM in turn (`--signals`) at a random moment
   inside the next unfinished stage (extract, pairs, match, map: once the stage's work has begun,
   within its duration in the reference run), then resumed. A SIGTERM must end in exit 143 with one
   `sara: error:` line and no native stack dump. The last resume must give the reference's pairs
   and registered images (and, with a ground truth, AUC@5 within 0.01).
3. Damage: for each output file (features, global descriptors, scores, pairs, database, model
   files, run.json, report, metrics, every stage record) and each mode (`--damage`: truncate to
   half, empty, overwrite with garbage, delete), a copy of the finished folder is damaged and run
   again. The run must either finish (exit 0) with the reference's pairs and registered images, or
   refuse with exit 3 and one line that names the file, leaving every file byte-identical.

Figures (printed and written to OUT/fault_injection.json): cases, kills, resumes, identical
results.
"""

from __future__ import annotations

import argparse
import hashlib
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
NATIVE_NOISE = ("Traceback", "*** Aborted", "stack trace", "terminate called")
DAMAGE_MODES = ("truncate", "empty", "garbage", "delete")
#: output files damaged in phase 3 (paths relative to the output folder; globs allowed)
DAMAGED_FILES = ("features-sift.h5", "global-*.h5", "scores.csv", "pairs.txt", "database.db", "sparse/0/cameras.bin",
                 "sparse/0/images.bin", "sparse/0/points3D.bin", "run.json", "report.md", "metrics.json",
                 ".sara/extract.json", ".sara/pairs.json", ".sara/match.json", ".sara/map.json")


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
    subprocess.run(sara_cmd(images, out, extra), check=True, stdout=subprocess.DEVNULL)
    total = time.perf_counter() - tic
    return json.loads((out / "run.json").read_text()), total


def registered(out: Path) -> list[str]:
    from sara.colmap import registered_images

    return sorted(registered_images(out / "sparse" / "0"))


def snapshot(out: Path) -> dict[str, str]:
    """sha256 of every file (COLMAP's logs and the lock aside; a database's change counter aside)."""
    digests = {}
    for path in sorted(out.rglob("*")):
        rel = path.relative_to(out).as_posix()
        if path.is_file() and not rel.startswith("logs/") and rel != ".sara.lock":
            data = bytearray(path.read_bytes())
            if data.startswith(b"SQLite format 3\x00") and len(data) >= 100:
                data[24:28] = data[92:96] = b"\0\0\0\0"
            digests[rel] = hashlib.sha256(data).hexdigest()
    return digests


def clean_stderr(err: str) -> tuple[bool, list[str]]:
    """(no traceback or native dump, the `sara: error:` lines)."""
    lines = [ln for ln in err.splitlines() if ln.startswith("sara: error:")]
    return not any(noise in err for noise in NATIVE_NOISE), lines


def same_result(ref_out: Path, out: Path) -> bool:
    try:
        return (ref_out / "pairs.txt").read_text() == (out / "pairs.txt").read_text() and \
            registered(ref_out) == registered(out)
    except (OSError, ValueError, RuntimeError):
        return False


# ---------------------------------------------------------------------------------------------
# Phase 2: kills
# ---------------------------------------------------------------------------------------------


#: what appears in the output folder when a stage starts its work (None: time from the start)
STAGE_MARKERS = {"extract": None, "pairs": ".sara/pairs.next", "match": ".sara/match_chunk.txt",
                 "map": ".sara/sparse.partial"}


def kill_phase(args, images: Path, extra: list[str], test_out: Path, stage_time: dict, startup: float,
               rng: random.Random) -> tuple[list[dict], int]:
    """Kill each run at a random moment inside the next unfinished stage: after its marker appears
    (the stage's own work has begun), within the stage's duration in the reference run. After two
    kills in one stage, the run is let through it and stopped in the next one."""
    kills, resumes = [], 0
    signals = [getattr(signal, f"SIG{name.strip().upper()}") for name in args.signals.split(",")]
    for i in range(args.kills):
        signum = signals[i % len(signals)]
        target = next_stage(test_out) or "map"
        if len(kills) >= 2 and all(k["aimed_at"] == target and not k["finished_first"] for k in kills[-2:]):
            target = STAGES[min(STAGES.index(target) + 1, len(STAGES) - 1)]  # let it finish, stop in the next
        marker = STAGE_MARKERS[target]
        for stale in STAGE_MARKERS.values():  # left by the last kill: not this run's
            if stale is not None:
                path = test_out / stale
                shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)
        delay = rng.uniform(0.05, 0.95) * stage_time[target] + (startup * 0.8 if marker is None else 0.0)
        if i > 0:
            resumes += 1  # every run after the first resumes an interrupted one
        proc = subprocess.Popen(sara_cmd(images, test_out, extra), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                text=True)
        while marker is not None and not (test_out / marker).exists() and proc.poll() is None:
            time.sleep(0.02)
        time.sleep(delay)
        finished = proc.poll() is not None
        if not finished:
            proc.send_signal(signum)
        _, err = proc.communicate()
        clean, lines = clean_stderr(err)
        reached = next_stage(test_out)
        record = {"kill": i + 1, "signal": signal.Signals(signum).name, "aimed_at": target, "after_s": round(delay, 2),
                  "finished_first": finished, "exit": proc.returncode, "stage_when_killed": reached or "done"}
        if signum == signal.SIGTERM and not finished:
            record["clean"] = clean and len(lines) == 1 and proc.returncode == 143
        kills.append(record)
        print(f"kill {i + 1:2d}: {record['signal']:7s} aimed at {target:7s} {delay:5.1f} s into it -> "
              f"{'run had finished' if finished else f'exit {proc.returncode}'}, next stage to do: {reached or 'none'}"
              + ("" if "clean" not in record else f", clean: {record['clean']}"))
        if reached is None:  # all done: undo a stage, in turn, so that every stage is exercised
            undone = UNDO_ORDER[sum(k["stage_when_killed"] == "done" for k in kills) % len(UNDO_ORDER)]
            for rel in UNDO[undone]:
                path = test_out / rel
                shutil.rmtree(path, ignore_errors=True) if path.is_dir() else path.unlink(missing_ok=True)
    return kills, resumes


#: what to remove so that a finished folder redoes a stage (and the ones after it)
UNDO = {"pairs": ("pairs.txt", ".sara/pairs.json"), "match": (".sara/match.json", ".sara/match-settings.json"),
        "map": ("sparse", ".sara/map.json")}
UNDO_ORDER = ("map", "pairs", "match")


# ---------------------------------------------------------------------------------------------
# Phase 3: damaged outputs
# ---------------------------------------------------------------------------------------------


def damage(path: Path, mode: str, rng: random.Random) -> None:
    if mode == "delete":
        path.unlink()
    elif mode == "empty":
        path.write_bytes(b"")
    elif mode == "truncate":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    else:
        path.write_bytes(bytes(rng.getrandbits(8) for _ in range(max(64, min(4096, path.stat().st_size)))))


def damage_phase(args, images: Path, extra: list[str], finished: Path, ref_out: Path,
                 rng: random.Random) -> list[dict]:
    cases = []
    scratch = args.out / "damaged"
    modes = [m.strip() for m in args.damage.split(",") if m.strip()]
    for pattern in DAMAGED_FILES:
        for target in sorted(finished.glob(pattern)):
            rel = target.relative_to(finished).as_posix()
            for mode in modes:
                shutil.rmtree(scratch, ignore_errors=True)
                shutil.copytree(finished, scratch)
                damage(scratch / rel, mode, rng)
                before = snapshot(scratch)
                proc = subprocess.run(sara_cmd(images, scratch, extra), capture_output=True, text=True)
                clean, lines = clean_stderr(proc.stderr)
                if proc.returncode == 0:
                    outcome, ok = "redone", clean and not lines and same_result(ref_out, scratch)
                elif proc.returncode == 3:
                    outcome, ok = "refused", clean and len(lines) == 1 and snapshot(scratch) == before
                else:
                    outcome, ok = f"exit {proc.returncode}", False
                case = {"file": rel, "damage": mode, "exit": proc.returncode, "outcome": outcome, "ok": ok,
                        "message": lines[0] if lines else ""}
                cases.append(case)
                print(f"damage {rel:24s} {mode:8s} -> {outcome:8s} {'ok' if ok else 'NOT OK'}"
                      + (f"  ({lines[0][:110]})" if lines else ""))
    shutil.rmtree(scratch, ignore_errors=True)
    return cases


# ---------------------------------------------------------------------------------------------


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path, help="a scene folder with images/ (and gt/)")
    parser.add_argument("--kills", type=int, default=10)
    parser.add_argument("--signals", default="KILL,TERM", help="signals used in turn (default KILL,TERM)")
    parser.add_argument("--damage", default=",".join(DAMAGE_MODES),
                        help=f"damage modes, comma-separated (default {','.join(DAMAGE_MODES)}; empty: none)")
    parser.add_argument("--out", type=Path, default=Path("fault-injection"))
    parser.add_argument("--seed", type=int, default=0, help="seed of the kill times and the garbage")
    parser.add_argument("--pairs", default="sara")
    args = parser.parse_args()
    rng = random.Random(args.seed)
    images, gt = args.scene / "images", args.scene / "gt"
    extra = ["--pairs", args.pairs] + (["--gt", str(gt)] if gt.exists() else [])
    shutil.rmtree(args.out, ignore_errors=True)
    ref_out, test_out = args.out / "reference", args.out / "interrupted"
    tic = time.perf_counter()

    ref, ref_total = run_reference(images, ref_out, extra)
    stage_time = {s: max(0.5, ref["stages"][s].get("time_s", 0.5)) for s in STAGES}
    startup = max(1.0, ref_total - sum(stage_time.values()))  # imports, image checks, evaluation
    print(f"reference run: {ref_total:.1f} s; stages {({k: round(v, 1) for k, v in stage_time.items()})}")

    kills, resumes = kill_phase(args, images, extra, test_out, stage_time, startup, rng)
    final = subprocess.run(sara_cmd(images, test_out, extra), capture_output=True, text=True)
    resumes += 1
    if final.returncode != 0:
        print("resumed run failed:\n" + final.stderr)
        return 1
    same_pairs = (ref_out / "pairs.txt").read_text() == (test_out / "pairs.txt").read_text()
    ref_reg, test_reg = registered(ref_out), registered(test_out)
    resumed_ok = same_pairs and ref_reg == test_reg
    result: dict = {"kills": kills, "same_pairs": same_pairs, "registered_reference": len(ref_reg),
                    "registered_resumed": len(test_reg), "same_registered_images": ref_reg == test_reg}
    if gt.exists():
        test = json.loads((test_out / "run.json").read_text())
        a, b = ref["metrics"]["auc"]["5"], test["metrics"]["auc"]["5"]
        result.update(auc5_reference=a, auc5_resumed=b)
        resumed_ok = resumed_ok and abs(a - b) <= 0.01

    damaged = damage_phase(args, images, extra, test_out, ref_out, rng)
    killed = [k for k in kills if not k["finished_first"]]
    terms = [k for k in killed if "clean" in k]
    figures = {
        "cases": len(kills) + len(damaged),
        "kills": len(killed),
        "kills_by_signal": {s: sum(k["signal"] == s for k in killed) for s in sorted({k["signal"] for k in kills})},
        "sigterm_clean": f"{sum(k['clean'] for k in terms)}/{len(terms)}",
        "stages_interrupted": sorted({k["stage_when_killed"] for k in killed}),
        "resumes": resumes + len(damaged),
        "identical_after_kills": resumed_ok,
        "damage_cases": len(damaged),
        "damage_redone_identical": sum(c["ok"] and c["outcome"] == "redone" for c in damaged),
        "damage_refused_unchanged": sum(c["ok"] and c["outcome"] == "refused" for c in damaged),
        "damage_not_ok": [f"{c['file']} {c['damage']}: {c['outcome']}" for c in damaged if not c["ok"]],
        "minutes": round((time.perf_counter() - tic) / 60, 1),
    }
    figures["identical_results"] = (int(resumed_ok) + figures["damage_redone_identical"]
                                    + figures["damage_refused_unchanged"])
    ok = resumed_ok and all(k["clean"] for k in terms) and not figures["damage_not_ok"]
    result.update(damage=damaged, figures=figures, ok=ok)
    (args.out / "fault_injection.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(figures, indent=2))
    return 0 if ok else 1


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "2")
    sys.exit(main())
