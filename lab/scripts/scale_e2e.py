"""End to end on synthetic street worlds: pairs -> matching -> mapping -> pose AUC, per pair source (issue 31).

For each N in --sizes, the world of N images (`sara.bench.world.make_world`, with keypoints and
descriptors in its database) is made once in `WORK/world-N/`, with its true poses written once as
a COLMAP text model (`WORK/world-N/gt/`, the layout of ../shared/data). Then, one at a time, each
method runs in a fresh subprocess on a fresh copy of the world (`WORK/run-N-METHOD/`: database
copied, features hard-linked, an empty `images/`): the stages of `sara run` after extraction, in
the order `sara.pipeline.run._run_stages` calls them, through the pipeline's own functions
(`select_pairs`, `match_pairs`, the source's rounds in `sara.pipeline.rounds`, `map_model`).
The CLI's `sara match` / `sara map` need a finished extract stage and a recorded image folder,
which a world folder has not, hence the stage functions in-process.

Each stage is timed in the child (wall, and CPU of the process and its reaped children); the
parent takes the child's peak memory from wait4 (ru_maxrss, children included) and polls the
process tree's RSS and PSS (executor workers). The largest model is then scored against the
true poses by `sara evaluate` (its AUC over all N (N - 1) / 2 pairs). Each (N, method) appends
one JSON line to WORK/results.jsonl and is skipped when already there (a stopped bench resumes);
a run past --timeout-min (default 40 minutes per 1,000 images) is killed and recorded as stopped,
with the stages it had finished.
With --resume (and a run folder kept by --keep-runs, in a WORK without that row) a stopped run is
continued in place: the pipeline skips the stages it finished, and the row adds their earlier times.
To run one bench beside another at a lower priority, `nice` is not enough where the kernel shares the
CPU by session (autogroup: each child starts a session of its own): a child started at a niceness
above 0 (`nice -n 19 python lab/scripts/scale_e2e.py ...`) gives its session that niceness too
(/proc/self/autogroup, where the kernel has it).

    python lab/scripts/scale_e2e.py --sizes 200,1000 --out WORK
    python lab/scripts/scale_e2e.py --sizes 200 --methods sara,exhaustive --out WORK
    python lab/scripts/scale_e2e.py --out WORK --report-only   # WORK/scale_e2e.{md,png}

Methods: sara (incremental mapper, its rounds), sara-global (sara's pairs, COLMAP's global
mapper), sequential (overlap 10, loop detection: every 10th image with its 5 nearest by VLAD),
retrieval (VLAD top-20), vocab_tree (a tree built from the collection, top-30), exhaustive.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scale_bench import tree_usage  # noqa: E402  (a sibling lab script)

GIB = 1024**3
POLL_S = 0.5
RESULTS = "results.jsonl"
STAGES = ("pairs", "match", "round_before_map", "map", "rounds_after_map")
METHODS: dict[str, dict[str, str]] = {
    "sara": {"pairs.method": "sara"},
    "sara-global": {"pairs.method": "sara", "map.mapper": "global"},
    "sequential": {"pairs.method": "sequential", "sequential.loop_detection": "true"},
    "retrieval": {"pairs.method": "retrieval"},
    "vocab_tree": {"pairs.method": "vocab_tree"},
    "exhaustive": {"pairs.method": "exhaustive"},
    "retrieval-global": {"pairs.method": "retrieval", "map.mapper": "global"},  # is the global mapper at fault?
}


# ---------------------------------------------------------------------------------------------
# The child: the pipeline's stages after extraction, each timed
# ---------------------------------------------------------------------------------------------


class StageClock:
    """Times each stage (wall, CPU of this process and its reaped children) into a JSON-lines file,
    a line when a stage starts and one when it ends, so a killed run still says how far it got."""

    def __init__(self, path: Path):
        self.path = path
        self.t0 = time.perf_counter()
        self.stages: dict[str, dict[str, float]] = {}

    @staticmethod
    def _cpu() -> float:
        """CPU seconds of this process, its ended children and its live descendants: an executor's
        worker processes outlive the stage that started them, so until the forty-third session,
        which counted ended children only, SARA's stage CPU times left out its selection's workers
        (about 20% of its run's CPU time, which the row's `cpu_s`, taken when the child ends, holds)."""
        return tree_usage(os.getpid())[1]

    def _line(self, row: dict[str, Any]) -> None:
        with self.path.open("a") as fh:
            fh.write(json.dumps({**row, "at_s": round(time.perf_counter() - self.t0, 3)}) + "\n")

    @contextlib.contextmanager
    def stage(self, name: str):
        self._line({"stage": name, "event": "start"})
        tic, cpu = time.perf_counter(), self._cpu()
        yield
        row = {"wall_s": time.perf_counter() - tic, "cpu_s": self._cpu() - cpu}
        self.stages[name] = row
        self._line({"stage": name, "event": "end", **row})


def prepare_run_dir(world_dir: Path, run_dir: Path) -> None:
    """A fresh sara output folder holding the world's features: its own database, the features
    file hard-linked, an empty image folder (the world has no pixels; mapping reads none but colours)."""
    from sara.bench.world import DB_NAME, features_path

    shutil.rmtree(run_dir, ignore_errors=True)
    (run_dir / ".sara").mkdir(parents=True)
    (run_dir / "images").mkdir()
    shutil.copyfile(world_dir / DB_NAME, run_dir / DB_NAME)
    feats = features_path(world_dir)
    os.link(feats, run_dir / feats.name)


def child_main(world_dir: Path, run_dir: Path, method: str, overrides: dict[str, str], resume: bool = False) -> None:
    import dataclasses
    import logging

    from sara import colmap
    from sara.bench.world import image_set
    from sara.config import make_config
    from sara.execute import make_executor
    from sara.io import records
    from sara.pairs import get_source
    from sara.pipeline import map_model, match_pairs, pair_context, rounds, select_pairs
    from sara.pipeline.pairs_stage import current_key

    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(message)s")
    logging.getLogger("sara.colmap.stepwise").setLevel(logging.INFO)  # each global adjustment, timed
    conf = make_config(overrides={**METHODS[method], **overrides})
    if not (resume and (run_dir / ".sara").is_dir()):  # resuming: the stages already done are skipped
        prepare_run_dir(world_dir, run_dir)
    clock = StageClock(run_dir / "progress.jsonl")
    images = dataclasses.replace(image_set(world_dir), root=run_dir / "images")
    features = run_dir / "features-sift.h5"
    colmap.send_log_to(run_dir / "logs")
    colmap.set_seed(conf.seed)
    executor = make_executor(conf.execute.executor, conf.execute.workers, conf.execute.ray_address)
    with clock.stage("pairs"):
        pairs_path = select_pairs(conf, images, features, run_dir, executor=executor, progress=False)
    source = get_source(conf.pairs.method)
    rr = None
    if source.rounds is not None:
        ctx = pair_context(conf, images, features, run_dir, executor=executor, progress=False)
        rr = rounds.RoundsRun(source.rounds, ctx, conf, run_dir, current_key(conf, run_dir), False)
    with clock.stage("match"):
        work = match_pairs(conf, pairs_path, features, run_dir, executor=executor, progress=False, beside=True)
    staged = None
    if rr is not None:
        with clock.stage("round_before_map"):
            work, staged = rounds.before_mapping(rr, work)
    commit_round = (lambda: rounds.commit_staged(rr, staged)) if staged is not None else None
    with clock.stage("map"):
        map_model(conf, images.root, run_dir, db_path=work, progress=False, commit_round=commit_round)
    first_map = records.done_info(run_dir, "map")
    if rr is not None:
        with clock.stage("rounds_after_map"):
            rounds.after_mapping(rr)
    executor.close()
    out = {"stages": clock.stages, "pairs_info": records.done_info(run_dir, "pairs"),
           "match_info": records.done_info(run_dir, "match"), "first_map_info": first_map,
           "map_info": records.done_info(run_dir, "map"),
           "rounds": _ledger_summary(rounds.ledger(run_dir, current_key(conf, run_dir))) if rr is not None else {},
           "num_pairs_matched": sum(1 for line in (run_dir / "pairs.txt").open() if line.strip())}
    (run_dir / "child.json").write_text(json.dumps(out, default=str))


def _ledger_summary(ledger: dict[str, Any]) -> dict[str, Any]:
    """The rounds' ledger with each role's pairs counted, not listed."""
    added = ledger.pop("added", {})
    return {**ledger, "added_per_role": {role: len(pairs) for role, pairs in added.items()}}


# ---------------------------------------------------------------------------------------------
# The parent: worlds, the truth as a COLMAP model, one subprocess per (N, method), evaluation
# ---------------------------------------------------------------------------------------------


def ensure_world(work: Path, n: int) -> Path:
    from sara.bench.world import WorldConfig, make_world

    world_dir = work / f"world-{n}"
    make_world(world_dir, WorldConfig(num_images=n), db_features=True, progress=False)
    write_truth_model(world_dir, world_dir / "gt")
    return world_dir


def write_truth_model(world_dir: Path, gt_dir: Path) -> None:
    """The world's true cam_from_world poses as a COLMAP text model (one PINHOLE camera, no points)."""
    if (gt_dir / "images.txt").exists():
        return
    import h5py
    from scipy.spatial.transform import Rotation

    with h5py.File(world_dir / "truth.h5", "r") as f:
        names = [n.decode() if isinstance(n, bytes) else str(n) for n in f["names"][()]]
        rot, trans = f["cam_from_world_R"][()], f["cam_from_world_t"][()]
        params = [float(v) for v in f.attrs["camera_params"]]
        conf = json.loads(f.attrs["config"])
    tmp = gt_dir.with_name(gt_dir.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    (tmp / "cameras.txt").write_text(f"1 PINHOLE {conf['width']} {conf['height']} {' '.join(map(str, params))}\n")
    quats = Rotation.from_matrix(rot).as_quat()  # x y z w
    lines = [" ".join([str(i + 1), *(f"{float(v):.17g}" for v in (q[3], q[0], q[1], q[2], *t)), "1", name]) + "\n\n"
             for i, (name, q, t) in enumerate(zip(names, quats, trans))]
    (tmp / "images.txt").write_text("".join(lines))
    (tmp / "points3D.txt").write_text("")
    shutil.rmtree(gt_dir, ignore_errors=True)
    os.replace(tmp, gt_dir)


#: minutes a run may take per 1,000 images when --timeout-min is not given (40 for sizes up to
#: 1,000); a 10,000-image SARA run's first mapping alone took over 39 minutes under load
TIMEOUT_MIN_PER_1000 = 40.0


def timeout_min(args: argparse.Namespace, n: int) -> float:
    """--timeout-min, else TIMEOUT_MIN_PER_1000 per 1,000 images, at least TIMEOUT_MIN_PER_1000."""
    return args.timeout_min if args.timeout_min is not None else TIMEOUT_MIN_PER_1000 * max(1.0, n / 1000)


def run_child(args: argparse.Namespace, world_dir: Path, run_dir: Path, method: str,
              limit_min: float) -> dict[str, Any]:
    """One (N, method) in a subprocess, stopped past `limit_min` minutes; its resources as the parent sees them."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(world_dir), str(run_dir), method]
    for item in args.set:
        cmd += ["--set", item]
    if args.resume:
        cmd.append("--resume")
    log_path = run_dir.with_name(run_dir.name + ".log")
    peak = {"tree_rss": 0, "tree_pss": 0}
    loads, stopped, tic = [], None, time.perf_counter()
    with open(log_path, "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                                env=dict(os.environ, PYTHONUNBUFFERED="1"))
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            rss, _, pss, _ = tree_usage(proc.pid)
            peak.update(tree_rss=max(peak["tree_rss"], rss), tree_pss=max(peak["tree_pss"], pss))
            loads.append(os.getloadavg()[0])
            if stopped is None and time.perf_counter() - tic > limit_min * 60:
                stopped = {"reason": "time", "after_s": time.perf_counter() - tic}
                os.killpg(proc.pid, signal.SIGKILL)
            time.sleep(POLL_S)
    out: dict[str, Any] = {
        "wall_s": time.perf_counter() - tic, "returncode": os.waitstatus_to_exitcode(status),
        "cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_gib": usage.ru_maxrss * 1024 / GIB,
        "peak_tree_rss_gib": peak["tree_rss"] / GIB, "peak_tree_pss_gib": peak["tree_pss"] / GIB,
        "load_mean": sum(loads) / len(loads) if loads else os.getloadavg()[0],
        "load_max": max(loads, default=os.getloadavg()[0])}
    if stopped is not None:
        out["stopped"] = stopped
    child_json = run_dir / "child.json"
    if out["returncode"] == 0 and child_json.exists():
        out.update(json.loads(child_json.read_text()))
    else:
        out["progress"] = _progress(run_dir / "progress.jsonl")
        out["log_tail"] = [ln for ln in log_path.read_text(errors="replace").splitlines() if ln.strip()][-8:]
    return out


def _progress(path: Path) -> dict[str, Any]:
    """How far a stopped run got: the stages it finished (with their times) and the one it was in."""
    done, current = {}, None
    for row in map(json.loads, path.read_text().splitlines()) if path.exists() else []:
        if row["event"] == "end":
            done[row["stage"]] = {"wall_s": row["wall_s"], "cpu_s": row["cpu_s"]}
            current = None
        else:
            current = row["stage"]
    return {"finished": done, "stopped_in": current}


def evaluate(run_dir: Path, gt_dir: Path) -> dict[str, Any]:
    """`sara evaluate` of the run's models against the truth (the largest model's AUC over all pairs)."""
    if not (run_dir / "sparse" / "0").is_dir():
        return {"error": "no model"}
    out = run_dir / "metrics.json"
    proc = subprocess.run([sys.executable, "-m", "sara", "evaluate", str(run_dir / "sparse"), str(gt_dir),
                           "--json", str(out), "-q"], capture_output=True, text=True)
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-3:]}
    m = json.loads(out.read_text())
    keys = ("num_registered", "num_registered_any", "num_components", "num_points3d", "rel_rotation_error_median_deg",
            "abs_rotation_error_median_deg", "position_error_median_pct", "reproj_error_mean_px", "auc")
    return {key: m.get(key) for key in keys} | {"local": local_auc(run_dir, gt_dir.parent)}


LOCAL_RADIUS_M = 20.0


def local_auc(run_dir: Path, world_dir: Path, radius_m: float = LOCAL_RADIUS_M) -> dict[str, Any]:
    """AUC@1/@5 of the largest model over the pairs of views whose true centres lie within `radius_m`
    (a pair not both in the model counts as failed): accuracy where the views are near, apart from
    drift or folds between far parts of the model, which the AUC over all pairs also counts."""
    import h5py
    import numpy as np
    from scipy.spatial import cKDTree

    from sara.colmap import load_poses
    from sara.evaluation.metrics import direction_angle_deg, pose_auc, rotation_angle_deg

    with h5py.File(world_dir / "truth.h5", "r") as f:
        names = [n.decode() if isinstance(n, bytes) else str(n) for n in f["names"][()]]
        rot_gt, t_gt, centers = f["cam_from_world_R"][()], f["cam_from_world_t"][()], f["centers"][()]
    pairs = np.array(sorted(cKDTree(centers).query_pairs(radius_m)), dtype=np.int64).reshape(-1, 2)
    est = load_poses(run_dir / "sparse" / "0")
    index = {n: i for i, n in enumerate(names)}
    rot_est, t_est = np.tile(np.eye(3), (len(names), 1, 1)), np.zeros((len(names), 3))
    posed = np.zeros(len(names), bool)
    for name, (r, t) in est.items():
        if name in index:
            rot_est[index[name]], t_est[index[name]], posed[index[name]] = r, t, True
    both = pairs[posed[pairs[:, 0]] & posed[pairs[:, 1]]]
    errors = []
    for rot, trans in ((rot_est, t_est), (rot_gt, t_gt)):
        rel = rot[both[:, 1]] @ np.swapaxes(rot[both[:, 0]], -1, -2)
        errors.append((rel, trans[both[:, 1]] - np.einsum("pij,pj->pi", rel, trans[both[:, 0]])))
    err = np.maximum(rotation_angle_deg(errors[0][0], errors[1][0]), direction_angle_deg(errors[0][1], errors[1][1]))
    auc1, auc5 = pose_auc(err, [1.0, 5.0], len(pairs))
    return {"radius_m": radius_m, "num_pairs": len(pairs), "num_pairs_coregistered": len(both),
            "auc": {"1": auc1, "5": auc5}}


def reevaluate(work: Path) -> None:
    """Score every recorded run whose models are still on disk again (after a change to the truth model)."""
    path = work / RESULTS
    rows = [json.loads(ln) for ln in path.read_text().splitlines() if ln.strip()]
    for row in rows:
        world_dir = work / f"world-{row['N']}"
        write_truth_model(world_dir, world_dir / "gt")
        row["eval"] = evaluate(work / f"run-{row['N']}-{row['method']}", world_dir / "gt")
    tmp = path.with_suffix(".tmp")
    tmp.write_text("".join(json.dumps(r, default=str) + "\n" for r in rows))
    os.replace(tmp, path)


def done_keys(work: Path) -> set[tuple[int, str]]:
    path = work / RESULTS
    if not path.exists():
        return set()
    return {(r["N"], r["method"]) for r in map(json.loads, filter(str.strip, path.read_text().splitlines()))}


def bench(args: argparse.Namespace) -> None:
    work = args.out
    work.mkdir(parents=True, exist_ok=True)
    for n in args.sizes:
        todo = [m for m in args.methods if (n, m) not in done_keys(work)]
        if not todo:
            continue
        world_dir = ensure_world(work, n)
        for method in todo:
            run_dir = work / f"run-{n}-{method}"
            print(f"N={n} {method}: running", flush=True)
            earlier = _progress(run_dir / "progress.jsonl") if args.resume else {}
            row = {**({"resumed_after": earlier} if earlier.get("finished") else {}),
                   "N": n, "method": method, "set": args.set, "started": time.strftime("%Y-%m-%d %H:%M:%S"),
                   **run_child(args, world_dir, run_dir, method, timeout_min(args, n))}
            row["eval"] = evaluate(run_dir, world_dir / "gt")
            with (work / RESULTS).open("a") as fh:
                fh.write(json.dumps(row, default=str) + "\n")
            print(f"N={n} {method}: " + summary_line(row), flush=True)
            if not args.keep_runs:  # the databases are the bulk of the disk; the records stay
                for name in ("database.db", "features-sift.h5", ".sara/database.next.db"):
                    (run_dir / name).unlink(missing_ok=True)


# ---------------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------------


def stage_times(row: dict[str, Any]) -> dict[str, float | None]:
    """pairs, match, map and rounds seconds (rounds: before and after the first mapping together);
    a resumed run's stages add the times its stopped attempt spent on them."""
    st = dict(row.get("stages") or row.get("progress", {}).get("finished", {}))
    for name, earlier in row.get("resumed_after", {}).get("finished", {}).items():
        st[name] = {"wall_s": earlier["wall_s"] + st.get(name, {}).get("wall_s", 0.0)}
    rounds_s = [st[k]["wall_s"] for k in ("round_before_map", "rounds_after_map") if k in st]
    return {"pairs": st.get("pairs", {}).get("wall_s"), "match": st.get("match", {}).get("wall_s"),
            "map": st.get("map", {}).get("wall_s"), "rounds": sum(rounds_s) if rounds_s else None}


def _f(value: float | None, digits: int = 1) -> str:
    return "" if value is None else f"{value:,.{digits}f}"


def summary_line(row: dict[str, Any]) -> str:
    t, ev = stage_times(row), row.get("eval", {})
    if "stopped" in row or row.get("returncode"):
        where = row.get("progress", {}).get("stopped_in")
        return f"STOPPED ({row.get('stopped', {}).get('reason', 'error')}) in {where} after {row['wall_s']:.0f} s"
    auc = ev.get("auc", {})
    return (f"{row.get('num_pairs_matched')} pairs, " + ", ".join(f"{k} {_f(v)} s" for k, v in t.items())
            + f", {row['peak_rss_gib']:.2f} GiB, registered {ev.get('num_registered')}/{row['N']}"
            + f" in {ev.get('num_components')} models, AUC@1/5 {_f(auc.get('1'), 4)}/{_f(auc.get('5'), 4)}")


def table(rows: list[dict[str, Any]]) -> str:
    head = ("| N | method | pairs matched | pairs s | match s | map s | rounds s | total s | CPU s | peak GiB "
            "| registered / models | AUC@1 | AUC@5 | local AUC@1 / @5 | rel. rot. median ° "
            "| position error median % | load |")
    lines = [head, "|---:|---|" + "---:|" * 15]
    for r in sorted(rows, key=lambda r: (r["N"], list(METHODS).index(r["method"]))):
        t, ev = stage_times(r), r.get("eval", {})
        auc = ev.get("auc", {})
        peak = max(r["peak_rss_gib"], r.get("peak_tree_pss_gib", 0.0))
        stopped = "stopped" in r or r.get("returncode")
        total = f"**stopped** {r['wall_s']:.0f} ({r.get('progress', {}).get('stopped_in')})" if stopped \
            else _f(sum(v for v in t.values() if v is not None))
        reg = "" if stopped or "error" in ev else f"{ev.get('num_registered')} / {ev.get('num_components')}"
        lines.append(f"| {r['N']:,} | {r['method']} | {_f(r.get('num_pairs_matched'), 0)} | {_f(t['pairs'])} "
                     f"| {_f(t['match'])} | {_f(t['map'])} | {_f(t['rounds'])} | {total} | {_f(r['cpu_s'], 0)} "
                     f"| {peak:.2f} | {reg} | {_f(auc.get('1'), 4)} | {_f(auc.get('5'), 4)} "
                     f"| {_local(ev)} | {_f(ev.get('rel_rotation_error_median_deg'), 2)} "
                     f"| {_f(ev.get('position_error_median_pct'))} "
                     f"| {r['load_mean']:.1f} |")
    return "\n".join(lines) + "\n"


def _local(ev: dict[str, Any]) -> str:
    auc = ev.get("local", {}).get("auc")
    return "" if not auc else f"{auc['1']:.4f} / {auc['5']:.4f}"


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(18, 4.2), sharey=True)
    for ax, stage in zip(axes, ("pairs", "match", "map", "total")):
        for method in METHODS:
            pts = sorted((r["N"], _stage_or_total(r, stage)) for r in rows if r["method"] == method
                         and "stopped" not in r and not r.get("returncode"))
            pts = [(n, s) for n, s in pts if s]
            if pts:
                ax.plot(*zip(*pts), marker="o", label=method)
        ax.set_title(f"{stage} (wall s)" + (", sara: with its rounds" if stage == "map" else ""))
    save_log_log(fig, axes, path, "seconds")


def save_log_log(fig, axes, path: Path, ylabel: str) -> None:
    """Log-log axes against N with a grid, the y label on the first and the legend on the last; saved."""
    for ax in axes:
        ax.set(xscale="log", yscale="log", xlabel="images N")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel(ylabel)
    axes[-1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def _stage_or_total(row: dict[str, Any], stage: str) -> float | None:
    t = stage_times(row)
    if stage == "total":
        return sum(v for v in t.values() if v is not None)
    if stage == "map" and t["rounds"]:
        return t["map"] + t["rounds"]  # mapping incl. sara's rounds
    return t[stage]


def report(work: Path) -> None:
    path = work / RESULTS
    rows = [json.loads(ln) for ln in path.read_text().splitlines() if ln.strip()] if path.exists() else []
    if not rows:
        raise SystemExit(f"no results in {path}")
    (work / "scale_e2e.md").write_text(table(rows))
    plot(rows, work / "scale_e2e.png")
    print(table(rows))
    print(f"-> {work / 'scale_e2e.md'}, {work / 'scale_e2e.png'}")


def _session_niceness() -> None:
    """The child's session (its own autogroup) at the niceness it was started with, so that `nice`
    lowers the bench against the rest of the machine; nothing where the kernel has no autogroups."""
    niceness = os.nice(0)
    if niceness > 0:
        try:
            Path("/proc/self/autogroup").write_text(str(niceness))
        except OSError:
            pass


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        ap = argparse.ArgumentParser()
        ap.add_argument("world", type=Path)
        ap.add_argument("run", type=Path)
        ap.add_argument("method", choices=list(METHODS))
        ap.add_argument("--set", action="append", default=[])
        ap.add_argument("--resume", action="store_true")
        a = ap.parse_args(sys.argv[2:])
        _session_niceness()
        child_main(a.world, a.run, a.method, dict(item.split("=", 1) for item in a.set), a.resume)
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="WORK: worlds, runs, results.jsonl, report")
    ap.add_argument("--sizes", default="200", help="comma-separated N")
    ap.add_argument("--methods", default="sara,sara-global,sequential,retrieval,vocab_tree",
                    help=f"comma-separated, of {', '.join(METHODS)}")
    ap.add_argument("--timeout-min", type=float, default=None,
                    help=f"minutes per run (default: {TIMEOUT_MIN_PER_1000:g} per 1,000 images, "
                         f"at least {TIMEOUT_MIN_PER_1000:g})")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="sara option for every method")
    ap.add_argument("--keep-runs", action="store_true", help="keep each run's database and features link")
    ap.add_argument("--resume", action="store_true",
                    help="continue a run folder a stopped bench left (kept with --keep-runs): the stages it "
                         "finished are not run again and their earlier times are added to the row")
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--reevaluate", action="store_true", help="with --report-only: score the kept models again")
    args = ap.parse_args()
    args.sizes = [int(s) for s in args.sizes.split(",") if s.strip()]
    args.methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = set(args.methods) - set(METHODS)
    if unknown:
        raise SystemExit(f"unknown methods {sorted(unknown)}; choose from {', '.join(METHODS)}")
    if not args.report_only:
        bench(args)
    elif args.reevaluate:
        reevaluate(args.out)
    report(args.out)


if __name__ == "__main__":
    main()
