"""A pair selection killed part-way and run again, against the same selection uninterrupted.

    python lab/scripts/pairs_resume.py WORK --size 1000 --kill-at 0.6

Makes (or reuses) the synthetic world of `scale_e2e.py` in WORK/world-N, then runs SARA's pairs
stage (`sara.pipeline.select_pairs`, this release's defaults) on two fresh copies of its run folder,
each call in a process of its own: `whole` uninterrupted; `killed` killed with SIGKILL (nothing
cleans up) after --kill-at times the uninterrupted wall time, then the same call again, which finds
the scores kept in `.sara/score-journal/`. Writes WORK/pairs_resume.json: wall times, the journal's
files and pairs at the kill, the pairs the second call scored, and whether `pairs.txt` and
`scores.csv` are byte-identical to the uninterrupted run's.

    python lab/scripts/pairs_resume.py WORK --size 1000 --then budget.max_pairs_per_image=3

With --then KEY=VALUE, the finished `killed` folder then selects again with that setting (its
journal kept from the calls before), against a fresh copy of the world selecting with it from
nothing (`fresh`): wall times, pairs scored by each, and whether their outputs are identical.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))


def _child(world: Path, run: Path, settings: list[str]) -> None:
    import dataclasses
    import logging

    from sara.bench.world import image_set
    from sara.config import make_config
    from sara.execute import make_executor
    from sara.pipeline import select_pairs

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    conf = make_config(overrides={"pairs.method": "sara", **dict(item.split("=", 1) for item in settings)})
    images = dataclasses.replace(image_set(world), root=run / "images")
    executor = make_executor(conf.execute.executor, conf.execute.workers, conf.execute.ray_address)
    select_pairs(conf, images, run / "features-sift.h5", run, executor=executor, progress=False)
    executor.close()


def _select(world: Path, run: Path, kill_after_s: float | None, settings: tuple[str, ...] = ()) -> dict:
    from map_resume import run_child

    return run_child([sys.executable, __file__, "--child", str(world), str(run), *settings], run / "log.txt",
                     kill_after_s)


def _scored(log: str) -> int:
    """Pairs a call scored, from its log (the scorer's summary line of each of its scorings)."""
    return sum(int(n) for n in re.findall(r"\((\d+) scored in", log))


def _journal(run: Path) -> dict:
    files = sorted((run / ".sara" / "score-journal").glob("*.json"))
    return {"files": len(files), "pairs": sum(len(json.loads(p.read_text())) for p in files)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        _child(Path(sys.argv[2]), Path(sys.argv[3]), sys.argv[4:])
        return
    ap.add_argument("work", type=Path)
    ap.add_argument("--size", type=int, default=1000)
    ap.add_argument("--kill-at", type=float, default=0.6, help="share of the uninterrupted wall time")
    ap.add_argument("--then", metavar="KEY=VALUE", help="then select again with this setting (see above)")
    args = ap.parse_args()
    from scale_e2e import ensure_world, prepare_run_dir

    world = ensure_world(args.work, args.size)
    result: dict = {"N": args.size}
    runs = {name: args.work / f"pairs-{args.size}-{name}" for name in ("whole", "killed")}
    for run in runs.values():
        prepare_run_dir(world, run)
    result["whole"] = _select(world, runs["whole"], None)
    kill_after = args.kill_at * result["whole"]["wall_s"]
    result["killed"] = {"kill_after_s": round(kill_after, 1), **_select(world, runs["killed"], kill_after),
                        "journal_at_kill": _journal(runs["killed"])}
    result["resumed"] = _select(world, runs["killed"], None)
    log = (runs["killed"] / "log.txt").read_text()
    result["resumed"]["kept_lines"] = re.findall(r"score: (\d+) of the (\d+) pairs were scored by an earlier", log)
    result["identical"] = {name: (runs["whole"] / name).read_bytes() == (runs["killed"] / name).read_bytes()
                           for name in ("pairs.txt", "scores.csv")}
    result["journal_after"] = _journal(runs["killed"])
    if args.then:
        fresh = args.work / f"pairs-{args.size}-fresh"
        prepare_run_dir(world, fresh)
        for name, run in (("then", runs["killed"]), ("fresh", fresh)):
            before = (run / "log.txt").read_text() if (run / "log.txt").exists() else ""
            result[name] = {"setting": args.then, **_select(world, run, None, (args.then,))}
            result[name]["pairs_scored"] = _scored((run / "log.txt").read_text()[len(before):])
        result["then_identical"] = {name: (runs["killed"] / name).read_bytes() == (fresh / name).read_bytes()
                                    for name in ("pairs.txt", "scores.csv")}
    (args.work / "pairs_resume.json").write_text(json.dumps(result, indent=1))
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
