"""Scale bench: sara's pair selection on synthetic street worlds of growing size, no photographs.

For each N in --sizes, a world of N images is synthesised into `OUT/world-N/` (see
`sara.bench.world`; not timed as selection, skipped when already there), then the selection
stage runs on it in a fresh subprocess, as the pipeline calls it (`sara.pairs.get_source(method)`
on a `PairContext`), with its outputs in `OUT/run-N/`. Per N the bench reports the time of each
step (retrieval, scoring, graph: the source's own `timings_s`), time per image, peak memory of
the subprocess (ru_maxrss from wait4, and the RSS sampled per step), candidates, selected pairs
per image, whether the selected graph is one connected component, and the share of selected
pairs that truly overlap (at least --min-common common 3D points, from the world's truth).

A run that goes over --timeout-min or --max-rss-gib is stopped and reported as such, with how
far it got. Results go to `OUT/results/N.json`; a size already measured with the same settings
is skipped unless --force. `OUT/scale_bench.{json,md,png}` gather all sizes: a table with the
ratios of time per image against the smallest N, and a log-log plot of time and memory.

    python lab/scripts/scale_bench.py --sizes 1000,3000,10000 --out DIR
    python lab/scripts/scale_bench.py --sizes 1000 --out DIR --profile cprofile    # where time goes
    python lab/scripts/scale_bench.py --sizes 1000 --out DIR --profile tracemalloc # who holds memory
    python lab/scripts/scale_bench.py --out DIR --report-only                       # table and plot again

--sara-src DIR measures another copy of sara (a folder holding the `sara` package, e.g. an
unpacked `git archive HEAD src`): the subprocess imports sara from there.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

RESULTS_DIR = "results"
RSS_SAMPLE_S = 0.2
GIB = 1024**3


# ---------------------------------------------------------------------------------------------
# Settings
# ---------------------------------------------------------------------------------------------


def parse_overrides(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"bad override {item!r}: write key=value")
        out[key.strip()] = value.strip()
    return out


def world_config(num_images: int, seed: int, overrides: dict[str, str]):
    from sara.bench.world import WorldConfig

    fields = {f.name: f for f in dataclasses.fields(WorldConfig)}
    values: dict[str, Any] = {"num_images": num_images, "seed": seed}
    defaults = WorldConfig()
    for key, raw in overrides.items():
        if key not in fields:
            raise SystemExit(f"unknown world option {key!r}; valid: {', '.join(fields)}")
        current = getattr(defaults, key)
        if isinstance(current, tuple):
            values[key] = tuple(float(v) for v in raw.split(",") if v.strip())
        elif isinstance(current, bool):
            values[key] = raw.lower() in ("1", "true", "yes")
        else:
            values[key] = type(current)(raw)
    return WorldConfig(**values)


def settings_key(world_key: str, sara_overrides: dict[str, str], args: argparse.Namespace) -> dict[str, Any]:
    return {"world": world_key, "sara": sara_overrides, "min_common": args.min_common,
            "sara_src": str(args.sara_src) if args.sara_src else "", "profile": args.profile or ""}


# ---------------------------------------------------------------------------------------------
# The child: one selection run, measured from inside
# ---------------------------------------------------------------------------------------------


def tree_usage(pid: int) -> tuple[int, float, int, int]:
    """Resident bytes, CPU seconds (user + system, ended children included) and proportional set
    size (PSS: pages shared between processes, such as a memory-mapped store, counted once) of a
    process and all its live descendants (e.g. an executor's workers), and how many they are."""
    tick = os.sysconf("SC_CLK_TCK")
    rss, cpu, pss, todo, seen = 0, 0.0, 0, [pid], set()
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        one = read_rss_bytes(p)
        rss += one
        pss += read_pss_bytes(p) or one
        try:
            with open(f"/proc/{p}/stat", encoding="ascii") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            cpu += sum(int(v) for v in fields[11:15]) / tick  # utime stime cutime cstime
            for tid in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{tid}/children", encoding="ascii") as f:
                    todo += [int(c) for c in f.read().split()]
        except (OSError, ValueError, IndexError):
            pass
    return rss, cpu, pss, len(seen)


def _proc_field_bytes(path: str, field: str) -> int:
    """A `field: N kB` line of a /proc file, in bytes (0 when unreadable)."""
    try:
        with open(path, encoding="ascii") as f:
            for line in f:
                if line.startswith(field):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def read_pss_bytes(pid: int | str) -> int:
    return _proc_field_bytes(f"/proc/{pid}/smaps_rollup", "Pss:")


def read_rss_bytes(pid: int | str = "self") -> int:
    return _proc_field_bytes(f"/proc/{pid}/status", "VmRSS:")


class RssSampler(threading.Thread):
    """Samples memory and CPU time of this process and its workers every RSS_SAMPLE_S s:
    [(t, rss bytes, cpu_s, pss bytes, processes)]."""

    def __init__(self, start: float):
        super().__init__(daemon=True)
        self.t0 = start
        self.samples: list[tuple[float, int, float, int, int]] = []
        self._halt = threading.Event()
        self.on_sample = None

    def _sample(self) -> None:
        rss, cpu, pss, procs = tree_usage(os.getpid())
        self.samples.append((time.perf_counter() - self.t0, rss, cpu, pss, procs))

    def run(self) -> None:
        while not self._halt.is_set():
            self._sample()
            if self.on_sample is not None:
                self.on_sample()
            self._halt.wait(RSS_SAMPLE_S)

    def stop(self) -> None:
        self._halt.set()
        self.join()
        self._sample()


def child_main(world_dir: Path, run_dir: Path, result_path: Path, sara_overrides: dict[str, str],
               profile: str | None, profile_path: Path) -> None:
    import sara
    from sara.config import make_config
    from sara.io.pairs import write_pairs
    from sara.pairs import get_source
    try:
        from sara.bench.world import selection_context
    except ImportError:  # a copy of sara (--sara-src) from before the world moved to sara.bench
        from sara.scale.world import selection_context

    conf = make_config(overrides=sara_overrides)
    run_dir.mkdir(parents=True, exist_ok=True)
    executor = None
    try:  # a sara with executors: make one as the pipeline does (its start-up is not timed)
        from sara.execute import make_executor
    except ImportError:
        make_executor = None
    if make_executor is not None and hasattr(conf, "execute"):
        executor = make_executor(conf.execute.executor, conf.execute.workers, conf.execute.ray_address)
    extra_args = {"executor": executor} if executor is not None else {}  # an older sara: no executor
    ctx = selection_context(conf, world_dir, run_dir, progress=True, **extra_args)
    source = get_source(conf.pairs.method)
    rss0 = read_rss_bytes()
    tic = time.perf_counter()
    sampler = RssSampler(tic)
    extra: dict[str, Any] = {}
    if profile == "tracemalloc":
        import tracemalloc

        tracemalloc.start(8)
        peak = {"bytes": 0, "at_s": 0.0, "top": []}

        def on_sample() -> None:  # keep the allocations held at the highest traced memory
            current, _ = tracemalloc.get_traced_memory()
            if current > peak["bytes"] * 1.05:
                snap = tracemalloc.take_snapshot().filter_traces(
                    [tracemalloc.Filter(False, tracemalloc.__file__)])
                stats = snap.statistics("traceback")[:12]
                peak.update(bytes=current, at_s=time.perf_counter() - tic, top=[
                    {"size_mib": s.size / 2**20, "count": s.count,
                     "traceback": [f"{fr.filename}:{fr.lineno}" for fr in s.traceback][-6:]} for s in stats])

        sampler.on_sample = on_sample
        extra["tracemalloc"] = peak
    sampler.start()
    if profile == "cprofile":
        import cProfile
        import io
        import pstats

        prof = cProfile.Profile()
        result = prof.runcall(source, ctx)
        buf = io.StringIO()
        stats = pstats.Stats(prof, stream=buf)
        stats.sort_stats("cumulative").print_stats(45)
        stats.sort_stats("tottime").print_stats(30)
        profile_path.with_suffix(".txt").write_text(buf.getvalue())
        stats.dump_stats(str(profile_path.with_suffix(".pstats")))
    else:
        result = source(ctx)
    total = time.perf_counter() - tic
    if executor is not None:
        executor.close()
    sampler.stop()
    if profile == "tracemalloc":
        import tracemalloc

        extra["tracemalloc"]["peak_traced_mib"] = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
    write_pairs(run_dir / "pairs.txt", result.pairs)
    import resource

    out = {
        "sara_file": sara.__file__,
        "selection_s": total,
        "timings_s": dict(result.timings_s),
        "info": result.info,
        "num_selected": len(result.pairs),
        "rss_start_bytes": rss0,
        "workers": getattr(executor, "workers", 1),
        "rss_samples": sampler.samples,
        "ru_maxrss_self_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        **extra,
    }
    result_path.write_text(json.dumps(out, default=_json_default))


def _json_default(obj: Any) -> Any:
    try:
        import numpy as np

        if isinstance(obj, np.generic):
            return obj.item()
        if isinstance(obj, np.ndarray):
            return obj.tolist()
    except ImportError:
        pass
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(type(obj).__name__)


# ---------------------------------------------------------------------------------------------
# The parent: worlds, subprocesses, evaluation, report
# ---------------------------------------------------------------------------------------------


def run_child(args: argparse.Namespace, world_dir: Path, run_dir: Path, child_json: Path,
              log_path: Path, profile_path: Path) -> dict[str, Any]:
    """Run the selection in a subprocess; stop it past the time or memory limit."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(world_dir), str(run_dir), str(child_json),
           str(profile_path)]
    for item in args.set:
        cmd += ["--set", item]
    if args.profile:
        cmd += ["--profile", args.profile]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if args.sara_src:
        env["PYTHONPATH"] = os.pathsep.join([str(Path(args.sara_src).resolve()), env.get("PYTHONPATH", "")])
    limit_s = args.timeout_min * 60
    limit_rss = args.max_rss_gib * GIB
    stopped = None
    peak_rss_polled = 0
    tic = time.perf_counter()
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, start_new_session=True)
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            rss = read_rss_bytes(proc.pid)
            peak_rss_polled = max(peak_rss_polled, rss)
            elapsed = time.perf_counter() - tic
            if stopped is None and (elapsed > limit_s or rss > limit_rss):
                stopped = {"reason": "time" if elapsed > limit_s else "memory", "after_s": elapsed,
                           "rss_gib": rss / GIB}
                os.killpg(proc.pid, signal.SIGKILL)
            time.sleep(0.5)
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - tic
    out: dict[str, Any] = {"wall_s": wall, "returncode": proc.returncode,
                           "peak_rss_bytes": usage.ru_maxrss * 1024, "peak_rss_polled_bytes": peak_rss_polled,
                           "cpu_user_s": usage.ru_utime, "cpu_sys_s": usage.ru_stime}
    if stopped is not None:
        out["stopped"] = stopped
    if child_json.exists() and stopped is None and proc.returncode == 0:
        out["child"] = json.loads(child_json.read_text())
    else:
        out["log_tail"] = _log_tail(log_path)
    return out


def _log_tail(path: Path, lines: int = 8) -> list[str]:
    text = path.read_text(errors="replace").replace("\r", "\n")
    return [ln for ln in text.splitlines() if ln.strip()][-lines:]


def read_scores(path: Path) -> tuple[list[tuple[str, str]], list[bool]] | None:
    if not path.exists():
        return None
    pairs, accepted = [], []
    with open(path, newline="", encoding="utf-8") as f:
        for row in csv.DictReader(f):
            pairs.append((row["name0"], row["name1"]))
            accepted.append(row["accepted"].strip().lower() in ("true", "1"))
    return pairs, accepted


def components(names: list[str], pairs: list[tuple[str, str]]) -> list[int]:
    """Sizes of the connected components of the graph of `pairs` on `names`, largest first."""
    labels = component_labels(names, pairs)
    sizes: dict[int, int] = {}
    for r in labels.values():
        sizes[r] = sizes.get(r, 0) + 1
    return sorted(sizes.values(), reverse=True)


def component_labels(names: list[str], pairs: list[tuple[str, str]]) -> dict[str, int]:
    """name -> a label shared by the images of one connected component (union-find)."""
    parent = list(range(len(names)))
    index = {n: i for i, n in enumerate(names)}

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in pairs:
        ra, rb = find(index[a]), find(index[b])
        if ra != rb:
            parent[ra] = rb
    return {n: find(i) for i, n in enumerate(names)}


def outside_main(names: list[str], selected: list[tuple[str, str]], candidates: list[tuple[str, str]],
                 true_cand: Any, accepted: Any) -> dict[str, Any]:
    """Why the images outside the largest selected component are there.

    retrieval_miss: none of its candidates truly overlaps it; scorer_rejected: some do, but the
    scorer rejected all of them; cut_off: it has accepted candidates, but none leads out of its
    small component (its group's links to the rest were all missed or rejected).
    """
    labels = component_labels(names, selected)
    counts: dict[int, int] = {}
    for r in labels.values():
        counts[r] = counts.get(r, 0) + 1
    main = max(counts, key=lambda r: counts[r]) if counts else -1
    true_any: dict[str, bool] = {}
    acc_any: dict[str, bool] = {}
    for (a, b), t, ok in zip(candidates, true_cand, accepted):
        for n in (a, b):
            true_any[n] = true_any.get(n, False) or bool(t)
            acc_any[n] = acc_any.get(n, False) or bool(ok)
    out = {"retrieval_miss": [], "scorer_rejected": [], "cut_off": []}
    for n in names:
        if labels[n] == main:
            continue
        if not true_any.get(n, False):
            out["retrieval_miss"].append(n)
        elif not acc_any.get(n, False):
            out["scorer_rejected"].append(n)
        else:
            out["cut_off"].append(n)
    return {"counts": {k: len(v) for k, v in out.items()}, "examples": {k: v[:10] for k, v in out.items()}}


def evaluate(world_dir: Path, run_dir: Path, min_common: int) -> dict[str, Any]:
    """Truth of the selected pairs and of the candidates (computed for these pairs only)."""
    import numpy as np

    from sara.bench.world import Truth, image_set
    from sara.io.pairs import read_pairs

    names = image_set(world_dir).names
    truth = Truth(world_dir, min_common=min_common)
    selected = read_pairs(run_dir / "pairs.txt")
    common = truth.common_counts(selected)
    sizes = components(names, selected)
    out: dict[str, Any] = {
        "num_selected": len(selected),
        "selected_per_image": len(selected) / len(names),
        "components": len(sizes),
        "component_sizes": sizes[:10],
        "selected_true_fraction": float((common >= min_common).mean()) if len(common) else 0.0,
        "selected_common_min": int(common.min()) if len(common) else 0,
        "selected_common_median": float(np.median(common)) if len(common) else 0.0,
        "selected_false": [[a, b, int(c)] for (a, b), c in zip(selected, common) if c < min_common][:20],
    }
    scores = read_scores(run_dir / "scores.csv")
    if scores is not None:
        pairs, accepted = scores
        acc = np.array(accepted, bool)
        cand = truth.common_counts(pairs) >= min_common
        out.update({
            "candidates_true_fraction": float(cand.mean()) if len(cand) else 0.0,
            "accepted_precision": float(cand[acc].mean()) if acc.any() else 0.0,
            "accepted_recall": float(acc[cand].mean()) if cand.any() else 0.0,
            "outside_main_component": outside_main(names, selected, pairs, cand, acc),
        })
    return out


def _memory(sample: list) -> int:
    """A sample's memory: with workers, the PSS of the process tree (shared pages once); else RSS."""
    return sample[3] if len(sample) > 4 and sample[4] > 1 and sample[3] else sample[1]


def stage_peaks(child: dict[str, Any]) -> tuple[dict[str, float], dict[str, float]]:
    """Per step (in the order of timings_s): peak sampled RSS (GiB) in its time window, and the
    CPU seconds (user + system, all threads) spent in it."""
    samples = child.get("rss_samples", [])
    peaks, cpu, start = {}, {}, 0.0

    def cpu_at(t: float) -> float:
        before = [sample[2] for sample in samples if sample[0] <= t]
        return before[-1] if before else (samples[0][2] if samples else 0.0)

    for stage, seconds in child.get("timings_s", {}).items():
        window = [_memory(sample) for sample in samples if start <= sample[0] <= start + seconds + RSS_SAMPLE_S]
        peaks[stage] = max(window) / GIB if window else 0.0
        cpu[stage] = cpu_at(start + seconds) - cpu_at(start)
        start += seconds
    return peaks, cpu


def measure(args: argparse.Namespace, n: int) -> dict[str, Any] | None:
    from sara.bench.world import make_world

    wconf = world_config(n, args.seed, parse_overrides(args.world))
    sara_overrides = parse_overrides(args.set)
    key = settings_key(wconf.key(), sara_overrides, args)
    results = args.out / RESULTS_DIR
    results.mkdir(parents=True, exist_ok=True)
    tag = f"{n}" + (f".{args.profile}" if args.profile else "")
    result_path = results / f"{tag}.json"
    if result_path.exists() and not args.force:
        old = json.loads(result_path.read_text())
        if old.get("settings") == key:
            print(f"N={n}: already measured ({result_path}), skipping (--force to redo)", flush=True)
            return old
    world_dir = args.out / f"world-{n}"
    print(f"N={n}: synthesising the world in {world_dir} ...", flush=True)
    tic = time.perf_counter()
    info = make_world(world_dir, wconf, db_features=args.db_features, progress=not args.quiet)
    world_s = time.perf_counter() - tic
    run_dir = args.out / f"run-{tag}"
    if run_dir.exists():
        import shutil

        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    print(f"N={n}: selection in a subprocess (log: {run_dir / 'selection.log'}) ...", flush=True)
    load_before = os.getloadavg()
    run = run_child(args, world_dir, run_dir, run_dir / "child.json", run_dir / "selection.log",
                    results / f"{tag}.profile")
    run["loadavg_before"], run["loadavg_after"] = load_before, os.getloadavg()
    record: dict[str, Any] = {
        "num_images": n, "settings": key, "machine": machine(), "git": git_commit(args.sara_src),
        "label": args.label,
        "world": {k: v for k, v in info.items() if k != "config"}, "world_config": info.get("config"),
        "world_wall_s": world_s, "run": {k: v for k, v in run.items() if k != "child"},
    }
    child = run.get("child")
    if child is not None:
        timings = child["timings_s"]
        record.update({
            "selection_s": child["selection_s"],
            "timings_s": timings,
            "time_per_image_ms": 1e3 * child["selection_s"] / n,
            # the biggest process (ru_maxrss), or all of them together (sampled, shared pages once)
            "peak_rss_gib": max(run["peak_rss_bytes"], max(map(_memory, child["rss_samples"]), default=0)) / GIB,
            "workers": child.get("workers", 1),
            "stage_peak_rss_gib": stage_peaks(child)[0],
            "stage_cpu_s": stage_peaks(child)[1],
            "cpu_s": run["cpu_user_s"] + run["cpu_sys_s"],
            "num_candidates": child["info"].get("num_candidates"),
            "num_accepted": child["info"].get("num_accepted"),
            "info": child["info"],
            "sara_file": child.get("sara_file"),
        })
        if "tracemalloc" in child:
            record["tracemalloc"] = child["tracemalloc"]
        record.update(evaluate(world_dir, run_dir, args.min_common))
    elif "stopped" not in run:
        print(f"N={n}: the selection failed (exit {run['returncode']}):\n  " + "\n  ".join(run.get("log_tail", [])),
              flush=True)
    result_path.write_text(json.dumps(record, indent=1, default=_json_default) + "\n")
    if args.delete_worlds:
        from sara.bench.world import remove_world

        remove_world(world_dir)
    return record


def machine() -> dict[str, Any]:
    import platform

    import numpy

    mem = 0
    try:
        with open("/proc/meminfo") as f:
            mem = int(f.readline().split()[1]) * 1024
    except OSError:
        pass
    return {"cpus": os.cpu_count(), "memory_gib": round(mem / GIB, 1), "python": platform.python_version(),
            "numpy": numpy.__version__, "processor": platform.processor() or platform.machine()}


def git_commit(sara_src: Path | None) -> str:
    where = Path(__file__).resolve().parent
    try:
        head = subprocess.run(["git", "-C", str(where), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        head = "unknown"
    return head + (f" (sara from {sara_src})" if sara_src else "")


# ---------------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------------


def load_results(out: Path) -> list[dict[str, Any]]:
    records = []
    for path in sorted((out / RESULTS_DIR).glob("*.json")):
        if path.stem.isdigit():  # profiled runs (N.cprofile.json, ...) stay out of the table
            records.append(json.loads(path.read_text()))
    return sorted(records, key=lambda r: r["num_images"])


def _fmt(value: Any, spec: str) -> str:
    return "-" if value is None else format(value, spec)


def table_rows(records: list[dict[str, Any]]) -> tuple[list[str], list[list[str]]]:
    stages = []
    for r in records:
        for s in r.get("timings_s", {}):
            if s not in stages:
                stages.append(s)
    base = next((r for r in records if r.get("time_per_image_ms")), None)
    header = (["N"] + [f"{s} (s)" for s in stages]
              + ["total (s)", "CPU (s)", "ms / image", f"x vs N={base['num_images']}" if base else "ratio",
                 "peak RSS (GiB)", "candidates / image", "selected / image", "components", "truly overlapping"])
    rows = []
    for r in records:
        n = r["num_images"]
        if "selection_s" not in r:
            stop = r["run"].get("stopped")
            why = (f"stopped ({stop['reason']}) after {stop['after_s'] / 60:.0f} min at {stop['rss_gib']:.1f} GiB"
                   if stop else f"failed (exit {r['run']['returncode']})")
            rows.append([str(n)] + ["-"] * (len(header) - 2) + [why])
            continue
        ratio = r["time_per_image_ms"] / base["time_per_image_ms"] if base else None
        rows.append([str(n)] + [_fmt(r["timings_s"].get(s), ".1f") for s in stages] + [
            _fmt(r["selection_s"], ".1f"), _fmt(r.get("cpu_s"), ".1f"), _fmt(r["time_per_image_ms"], ".1f"),
            _fmt(ratio, ".2f"),
            _fmt(r["peak_rss_gib"], ".2f"), _fmt((r.get("num_candidates") or 0) / n, ".1f"),
            _fmt(r.get("selected_per_image"), ".2f"), str(r.get("components", "-")),
            _fmt(100 * r["selected_true_fraction"], ".1f") + "%" if "selected_true_fraction" in r else "-",
        ])
    return header, rows


def _outside_text(r: dict[str, Any]) -> str:
    counts = r.get("outside_main_component", {}).get("counts", {})
    if not any(counts.values()):
        return ""
    return (f"; outside the largest component: {counts['retrieval_miss']} images without a truly overlapping "
            f"candidate, {counts['scorer_rejected']} whose true candidates were all rejected, "
            f"{counts['cut_off']} in groups cut off from the rest")


def render_markdown(records: list[dict[str, Any]], plot_name: str | None) -> str:
    header, rows = table_rows(records)
    lines = ["# Scale bench", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    lines += ["", ("Per step: CPU seconds (all threads) and the peak resident memory sampled in its time window; "
                   "load average of the machine before and after the run:"), ""]
    for r in records:
        if r.get("stage_peak_rss_gib"):
            cpu = r.get("stage_cpu_s", {})
            parts = ", ".join(f"{k} {cpu.get(k, 0):.1f} CPU s, {v:.2f} GiB" for k, v in r["stage_peak_rss_gib"].items())
            load = r["run"].get("loadavg_before", [0])[0], r["run"].get("loadavg_after", [0])[0]
            lines.append(f"- N={r['num_images']}: {parts}; load {load[0]:.1f} / {load[1]:.1f}")
    lines += ["", "Scorer and truth (from scores.csv and truth.h5):", ""]
    for r in records:
        if "candidates_true_fraction" in r:
            lines.append(
                f"- N={r['num_images']}: {r['num_candidates']} candidates "
                f"({100 * r['candidates_true_fraction']:.0f}% truly overlapping), "
                f"{r['num_accepted']} accepted (precision {100 * r['accepted_precision']:.1f}%, "
                f"recall {100 * r['accepted_recall']:.1f}%); selected pairs share at least "
                f"{r['selected_common_min']} 3D points (median {r['selected_common_median']:.0f})"
                + _outside_text(r))
    lines += ["", "Worlds:", ""]
    for r in records:
        w = r["world"]
        lines.append(
            f"- N={r['num_images']}: {w['grid_blocks']}x{w['grid_blocks']} blocks, {w['num_points3D']} 3D points, "
            f"{w['keypoints_mean']:.0f} keypoints per image ({w['inlier_keypoints_mean']:.0f} with a 3D point), "
            f"{w['streets_walked_twice_or_more']} of {w['streets']} streets walked twice or more "
            f"({w['street_walks_opposite_direction']} both ways), synthesised in {w['synthesis_s']:.0f} s")
    m = records[0]["machine"] if records else {}
    if m:
        lines += ["", (f"Machine: {m['cpus']} CPUs, {m['memory_gib']} GiB, Python {m['python']}, "
                       f"numpy {m['numpy']}; sara at {records[0].get('git', '?')}"
                       + (f", {records[0]['label']}" if records[0].get("label") else "") + ".")]
    if plot_name:
        lines += ["", f"![time and memory against N]({plot_name})"]
    return "\n".join(lines) + "\n"


def plot(records: list[dict[str, Any]], path: Path) -> bool:
    done = [r for r in records if "selection_s" in r]
    if not done:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ns = [r["num_images"] for r in done]
    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(11, 4.2))
    stages = []
    for r in done:
        stages += [s for s in r["timings_s"] if s not in stages]
    for s in stages:
        ax_t.plot(ns, [max(r.get("stage_cpu_s", {}).get(s, 0), 1e-2) for r in done], "o-", label=f"{s} (CPU)")
    ax_t.plot(ns, [r.get("cpu_s", 0) for r in done], "ks-", lw=2, label="total (CPU)")
    ax_t.plot(ns, [r["selection_s"] for r in done], "s--", color="0.5", lw=1.5, label="total (wall)")
    n0, t0 = ns[0], done[0].get("cpu_s") or done[0]["selection_s"]
    ref = [n0, max(ns[-1], n0 * 10)]
    ax_t.plot(ref, [t0, t0 * ref[1] / n0], "k:", lw=1, label="O(N) from the first")
    ax_t.plot(ref, [t0, t0 * (ref[1] / n0) ** 2], "k--", lw=1, label="O(N^2)")
    ax_t.set(xscale="log", yscale="log", xlabel="images N", ylabel="seconds",
             title="selection time (CPU s, all threads)")
    ax_t.legend(fontsize=8)
    ax_m.plot(ns, [r["peak_rss_gib"] for r in done], "ks-", lw=2, label="peak RSS")
    for s in stages:
        ax_m.plot(ns, [max(r["stage_peak_rss_gib"].get(s, 0), 1e-3) for r in done], "o-", label=f"{s} (sampled)")
    ax_m.axhline(4.0, color="r", ls="--", lw=1, label="4 GiB target")
    ax_m.set(xscale="log", yscale="log", xlabel="images N", ylabel="GiB", title="peak memory")
    ax_m.legend(fontsize=8)
    for ax in (ax_t, ax_m):
        ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def plot_world(world_dir: Path, pairs_path: Path | None, path: Path, min_common: int) -> None:
    """Top view of a world: blocks, the walk, and the selected pairs (red: not truly overlapping)."""
    import h5py
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.patches import Rectangle

    from sara.bench.world import TRUTH_NAME, Truth

    with h5py.File(world_dir / TRUTH_NAME, "r") as h5:
        blocks = h5["blocks"][()]
        centers = h5["centers"][()]
        R = h5["cam_from_world_R"][()]
    fig, ax = plt.subplots(figsize=(7, 7))
    for x0, y0, x1, y1 in blocks:
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, color="0.85"))
    ax.scatter(centers[:, 0], centers[:, 1], c=range(len(centers)), s=2, cmap="viridis", zorder=2)
    step = max(1, len(centers) // 150)
    ax.quiver(centers[::step, 0], centers[::step, 1], R[::step, 2, 0], R[::step, 2, 1], color="0.3",
              scale=40, width=0.002, zorder=3)
    title = f"{len(centers)} images (colour: order along the walk; arrows: viewing direction)"
    if pairs_path is not None and pairs_path.exists():
        from sara.io.pairs import read_pairs

        truth = Truth(world_dir, min_common=min_common)
        pairs = read_pairs(pairs_path)
        ok = truth.overlaps(pairs)
        idx = np.array([[truth.index[a], truth.index[b]] for a, b in pairs]) if pairs else np.zeros((0, 2), int)
        segs = centers[idx][:, :, :2]
        ax.add_collection(LineCollection(segs[ok], colors="tab:blue", linewidths=0.4, alpha=0.5, zorder=1))
        ax.add_collection(LineCollection(segs[~ok], colors="red", linewidths=1.2, zorder=4))
        title += f"\n{len(pairs)} selected pairs, {int((~ok).sum())} not truly overlapping (red)"
    ax.set_title(title, fontsize=9)
    ax.set_aspect("equal")
    ax.autoscale()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def report(out: Path, min_common: int = 20) -> None:
    records = load_results(out)
    if not records:
        print("no results yet")
        return
    plotted = plot(records, out / "scale_bench.png")
    first = records[0]["num_images"]
    if (out / f"world-{first}").exists():
        plot_world(out / f"world-{first}", out / f"run-{first}" / "pairs.txt", out / "scale_world.png", min_common)
    (out / "scale_bench.json").write_text(json.dumps(records, indent=1, default=_json_default) + "\n")
    (out / "scale_bench.md").write_text(render_markdown(records, "scale_bench.png" if plotted else None))
    header, rows = table_rows(records)
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
    print("  ".join(h.rjust(w) for h, w in zip(header, widths)))
    for row in rows:
        print("  ".join(c.rjust(w) for c, w in zip(row, widths)))
    print(f"\nwritten: {out / 'scale_bench.md'}, {out / 'scale_bench.json'}"
          + (f", {out / 'scale_bench.png'}" if plotted else ""))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", default="1000,3000,10000", help="image counts, comma-separated")
    p.add_argument("--out", type=Path, help="bench folder (worlds, runs, results, report)")
    p.add_argument("--force", action="store_true", help="measure sizes already measured again")
    p.add_argument("--seed", type=int, default=0, help="world seed")
    p.add_argument("--min-common", type=int, default=20, help="common 3D points for a true overlap")
    p.add_argument("--timeout-min", type=float, default=20.0, help="stop a selection run after this long")
    p.add_argument("--max-rss-gib", type=float, default=16.0, help="stop a selection run above this memory")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="sara option, e.g. score.num_keypoints=512")
    p.add_argument("--world", action="append", default=[], metavar="KEY=VALUE", help="world option, e.g. step_m=1.5")
    p.add_argument("--profile", choices=["cprofile", "tracemalloc"], help="profile the runs (kept out of the table)")
    p.add_argument("--sara-src", type=Path, help="import sara from this folder in the subprocess")
    p.add_argument("--label", default="", help="what code is measured (e.g. a commit), kept with the results")
    p.add_argument("--db-features", action="store_true", help="write keypoints and descriptors into the database too")
    p.add_argument("--delete-worlds", action="store_true", help="delete each world after its run (saves disk)")
    p.add_argument("--report-only", action="store_true", help="only rebuild the table, JSON, Markdown and plot")
    p.add_argument("--reevaluate", action="store_true",
                   help="with --report-only: judge the stored runs against the truth again (after a change here)")
    p.add_argument("--quiet", action="store_true", help="no progress bars while synthesising")
    p.add_argument("--child", nargs=4, type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        world_dir, run_dir, result_path, profile_path = args.child
        child_main(world_dir, run_dir, result_path, parse_overrides(args.set), args.profile, profile_path)
        return 0
    if args.out is None:
        p.error("--out is required")
    args.out.mkdir(parents=True, exist_ok=True)
    if args.reevaluate:
        for path in sorted((args.out / RESULTS_DIR).glob("*.json")):
            record = json.loads(path.read_text())
            tag = path.stem
            run_dir, world_dir = args.out / f"run-{tag}", args.out / f"world-{record['num_images']}"
            if "selection_s" in record and (run_dir / "pairs.txt").exists() and world_dir.exists():
                record.update(evaluate(world_dir, run_dir, args.min_common))
                path.write_text(json.dumps(record, indent=1, default=_json_default) + "\n")
    if not args.report_only:
        sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
        for n in sizes:
            record = measure(args, n)
            if record and "selection_s" in record:
                print(f"N={n}: {record['selection_s']:.1f} s, {record['peak_rss_gib']:.2f} GiB, "
                      f"{record['selected_per_image']:.2f} pairs/image, {record['components']} component(s), "
                      f"{100 * record['selected_true_fraction']:.1f}% truly overlapping", flush=True)
    report(args.out, args.min_common)
    return 0


if __name__ == "__main__":
    sys.exit(main())
