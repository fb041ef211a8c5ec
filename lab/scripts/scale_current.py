"""Experiment report: time against N per method and stage, from the end-to-end rows of this release's code.

`lab/notes/scale_e2e_results.jsonl` holds every end-to-end row of every session (`scale_e2e.py`),
most of them from code since changed. This picks the rows that ran the code as it stands for each
method (`CURRENT`, with the reason in a comment), groups them by size and method (several seeds:
mean and range), and writes a markdown table and a log-log plot of wall time per stage against N.

    python lab/scripts/scale_current.py lab/notes/scale_e2e_results.jsonl OUT   # OUT/scale_current.{md,png}
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scale_e2e import METHODS, save_log_log, stage_times  # noqa: E402  (a sibling lab script)

#: (session, N, method, set) of the rows that ran this release's code path for that method. The
#: baselines' pairs have not changed since the sessions named; their mapping is the map stage of
#: the session (checked and mended as SARA's).
CURRENT: list[tuple[int, int, str, tuple[str, ...]]] = [
    # 1,000 images: three seeds per method, one after the other (forty-second session)
    *[(42, 1000, m, (f"seed={k}",)) for m in ("sara", "sequential", "retrieval") for k in range(3)],
    (30, 1000, "vocab_tree", ()),  # one run; its pairs are COLMAP's tree, unchanged since
    # 3,000 images: SARA with the chain under seeds 0 (thirty-ninth session), 1 and 2 (forty-second)
    (39, 3000, "sara", ()), (42, 3000, "sara", ("seed=1",)), (42, 3000, "sara", ("seed=2",)),
    (36, 3000, "sequential", ()), (42, 3000, "sequential", ("seed=1",)), (42, 3000, "sequential", ("seed=2",)),
    (29, 3000, "retrieval", ()),  # one run, the step-by-step mapping of this release
    (33, 3000, "vocab_tree", ()),
    # 10,000 images: one run each on the world made in the thirty-sixth session
    # SARA under seed 1 in one go, its final extension run afterwards (forty-fourth session)
    (44, 10000, "sara", ("seed=1", "rounds.extend_tracks=false")),
    (38, 10000, "sequential", ()),
]

PANELS = ("pairs", "match", "map", "total")
LABELS = {"sara": "SARA", "sequential": "sequential + loop detection", "retrieval": "retrieval top-k",
          "vocab_tree": "vocabulary tree"}


def picked(rows: list[dict[str, Any]]) -> dict[tuple[int, str], list[dict[str, Any]]]:
    """(N, method) -> the rows of `CURRENT`, in its order; a selector matching no row is an error."""
    groups: dict[tuple[int, str], list[dict[str, Any]]] = {}
    for session, n, method, sets in CURRENT:
        hits = [r for r in rows if r.get("session") == session and r["N"] == n and r["method"] == method
                and tuple(r.get("set") or ()) == sets and not r.get("returncode") and "stopped" not in r]
        if not hits:
            raise SystemExit(f"no finished row for session {session}, N {n}, {method}, set {list(sets)}")
        groups.setdefault((n, method), []).append(hits[-1])
    return groups


def final_eval(row: dict[str, Any]) -> dict[str, Any]:
    """The row's scores, or those of its model extended afterwards (`extended_after`)."""
    return (row.get("extended_after") or row)["eval"]


def times(n: int, method: str, row: dict[str, Any]) -> dict[str, float | None]:
    """Wall seconds by stage (rounds: SARA's before and after the first mapping, and a track extension
    run afterwards by `extend_model.py`, `extended_after`), total and CPU."""
    t = dict(stage_times(row)) | {"cpu": row.get("cpu_s")}
    if after := row.get("extended_after"):
        t["rounds"] = (t["rounds"] or 0.0) + after["wall_s"]
        t["cpu"] = None if t["cpu"] is None else t["cpu"] + after["cpu_s"]
    t["total"] = sum(t[k] or 0.0 for k in ("pairs", "match", "map", "rounds"))
    return t


def _span(values: list[float], digits: int) -> str:
    mean = statistics.fmean(values)
    if len(values) == 1:
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} ({min(values):.{digits}f}-{max(values):.{digits}f})"


def _mean(values: list[float | None]) -> str:
    present = [v for v in values if v is not None]
    return f"{statistics.fmean(present):,.0f}" if present else ""


def table(groups: dict[tuple[int, str], list[dict[str, Any]]]) -> str:
    lines = ["| N | method | runs | pairs | registered / models | AUC@1 mean (range) | AUC@5 mean (range) "
             "| pairs s | match s | map s | rounds s | total s | CPU s | peak GiB |",
             "|---:|---|---:|---:|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for (n, method), rows in sorted(groups.items(), key=lambda g: (g[0][0], list(METHODS).index(g[0][1]))):
        ts = [times(n, method, r) for r in rows]
        auc = [final_eval(r)["auc"] for r in rows]
        pairs = sorted({r["num_pairs_matched"] for r in rows})
        reg = sorted({f"{final_eval(r)['num_registered']:,} / {final_eval(r)['num_components']}" for r in rows})
        peak = max(max(r["peak_rss_gib"], r.get("peak_tree_pss_gib", 0.0)) for r in rows)
        pair_text = f"{pairs[0]:,}" if len(pairs) == 1 else f"{pairs[0]:,}-{pairs[-1]:,}"
        lines.append(
            f"| {n:,} | {method} | {len(rows)} | {pair_text} | {', '.join(reg)} "
            f"| {_span([a['1'] for a in auc], 4)} | {_span([a['5'] for a in auc], 4)} "
            + "".join(f"| {_mean([t[k] for t in ts])} " for k in ("pairs", "match", "map", "rounds", "total", "cpu"))
            + f"| {peak:.2f} |")
    return "\n".join(lines) + "\n"


def plot(groups: dict[tuple[int, str], list[dict[str, Any]]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(PANELS), figsize=(18, 4.2), sharey=True)
    for ax, panel in zip(axes, PANELS):
        for method in METHODS:
            pts = []
            for (n, m), rows in sorted(groups.items()):
                if m != method:
                    continue
                values = [t[panel] + (t["rounds"] or 0.0 if panel == "map" else 0.0)
                          for t in (times(n, m, r) for r in rows) if t[panel]]
                if values:
                    pts.append((n, statistics.fmean(values), min(values), max(values)))
            if pts:
                ns, means, lows, highs = zip(*pts)
                err = [[m - lo for m, lo in zip(means, lows)], [hi - m for m, hi in zip(means, highs)]]
                ax.errorbar(ns, means, yerr=err, marker="o", capsize=3, label=LABELS.get(method, method))
        ax.set_title({"pairs": "selection", "match": "matching", "map": "mapping, with SARA's rounds",
                      "total": "after extraction"}[panel] + " (wall s)")
    save_log_log(fig, axes, path, "seconds (mean over seeds; bars: range)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, help="scale_e2e_results.jsonl")
    parser.add_argument("out", type=Path)
    args = parser.parse_args()
    rows = [json.loads(line) for line in args.results.read_text().splitlines() if line.strip()]
    groups = picked(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    text = table(groups)
    (args.out / "scale_current.md").write_text(text)
    plot(groups, args.out / "scale_current.png")
    print(text)


if __name__ == "__main__":
    main()
