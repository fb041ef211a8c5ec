"""The executors on the synthetic street world (issue 31): which stages spread, and the wall time of
two local Ray nodes against one.

With SIFT, the stage that runs on the executor is the pair selection (the pre-match scoring in
shards); extraction, matching and mapping are COLMAP's, in the driver (the learned backends put
extraction and matching on the executor too). So each configuration runs the pairs stage of
`sara run` (`sara.pipeline.select_pairs`) on a fresh copy of `WORK/world-N/` (made by
`scale_e2e.py`), then checks that every configuration selected the same pairs:

- serial: one worker in the driver;
- processes: the default executor, one worker per core;
- ray, 1 node: `ray start --head --num-cpus=C` (C = the cores);
- ray, 2 nodes: a head and a second node joined to it, C / 2 CPUs each (as `tests/test_ray.py`
  starts them, on this one machine).

One JSON line per configuration: wall time and the CPU time of the driver and its own workers
(not Ray's) in the stage, the cluster's start excluded.

    python lab/scripts/ray_nodes.py WORK --size 1000 [--repeat 2] [--skip-serial]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import sys
import time
from pathlib import Path

from sara.execute_ray import local_cluster

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scale_e2e import prepare_run_dir  # noqa: E402  (a sibling lab script)


def pairs_stage(world: Path, run_dir: Path, executor: str, workers: int, address: str = "") -> dict:
    import dataclasses

    from sara.bench.world import image_set
    from sara.config import make_config
    from sara.execute import make_executor
    from sara.pipeline import select_pairs

    conf = make_config(overrides={"pairs.method": "sara"})
    prepare_run_dir(world, run_dir)
    images = dataclasses.replace(image_set(world), root=run_dir / "images")
    pool = make_executor(executor, workers, address)
    tic, cpu = time.perf_counter(), _cpu()
    try:
        pairs = select_pairs(conf, images, run_dir / "features-sift.h5", run_dir, executor=pool, progress=False)
    finally:
        pool.close()
    return {"wall_s": time.perf_counter() - tic, "driver_cpu_s": _cpu() - cpu, "pairs": Path(pairs).read_text()}


def _cpu() -> float:
    """CPU seconds of this process and its reaped children (the process pool's workers; Ray's are
    the cluster's, not counted)."""
    return sum(u.ru_utime + u.ru_stime for u in map(resource.getrusage, (resource.RUSAGE_SELF,
                                                                          resource.RUSAGE_CHILDREN)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", type=Path, help="a scale_e2e.py WORK folder holding world-N/")
    ap.add_argument("--size", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--skip-serial", action="store_true", help="the serial run is the slowest by far")
    args = ap.parse_args()
    world, cores = args.work / f"world-{args.size}", os.cpu_count() or 2
    configs = [("serial", "serial", 1, 0), ("processes", "processes", 0, 0),
               ("ray, 1 node", "ray", 0, 1), ("ray, 2 nodes", "ray", 0, 2)]
    configs = configs[1:] if args.skip_serial else configs
    reference = None
    for r in range(args.repeat):
        for label, executor, workers, nodes in configs:
            run_dir = args.work / f"ray-run-{args.size}"
            with local_cluster(nodes, cores // nodes, args.work / "ray-tmp") if nodes else \
                    contextlib.nullcontext("") as address:
                found = pairs_stage(world, run_dir, executor, workers, address)
            reference = reference if reference is not None else found["pairs"]
            print(json.dumps({"N": args.size, "round": r, "executor": label, "nodes": nodes or None,
                              "wall_s": round(found["wall_s"], 2), "driver_cpu_s": round(found["driver_cpu_s"], 2),
                              "same_pairs": found["pairs"] == reference,
                              "num_pairs": found["pairs"].count("\n"), "load": round(os.getloadavg()[0], 2)}),
                  flush=True)


if __name__ == "__main__":
    main()
