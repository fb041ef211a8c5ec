"""The bench's tables (JSON, CSV, Markdown) and plot."""

from __future__ import annotations

import csv
import io
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..io import atomic_path, write_json_atomic, write_text_atomic
from ..tables import format_number, markdown_table
from .names import base_scene

logger = logging.getLogger(__name__)

AUC_THRESHOLDS = ("1", "3", "5", "10")
TABLE_TITLE = "Pair sources side by side"
ABLATION_TITLE = "SARA ablation (graph stages)"

# (row key, column title, number format) of the main table: the paper's Table 1, then ours.
TABLE_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("registered_pct", "Reg. %", ".1f"),
    ("rot_error_deg", "Rot. err (deg)", ".3f"),
    ("trans_error_deg", "Trans. err (deg)", ".3f"),
    ("matches_per_pair", "Matches/pair", ".0f"),
    ("reproj_mean_px", "Reproj. mean (px)", ".3f"),
    ("reproj_median_px", "Reproj. median (px)", ".3f"),
    ("points3d", "3D points", "d"),
    ("track_length", "Track len.", ".2f"),
    ("pairs", "Pairs", "d"),
    ("match_s", "Match (s)", ".1f"),
    ("auc@1", "AUC@1", ".3f"),
    ("auc@3", "AUC@3", ".3f"),
    ("auc@5", "AUC@5", ".3f"),
    ("auc@10", "AUC@10", ".3f"),
    ("select_s", "Select (s)", ".2f"),
    ("map_s", "Map (s)", ".1f"),
    ("pairs_vs_exhaustive", "Pairs / exh.", ".3f"),
    ("match_time_vs_exhaustive", "Match time / exh.", ".3f"),
    ("select_time_vs_exhaustive_match", "Select time / exh. match", ".3f"),
)
ABLATION_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("num_registered", "Registered", "d"),
    ("points3d", "3D points", "d"),
    ("track_length", "Track len.", ".2f"),
    ("pairs", "Pairs", "d"),
    ("auc@5", "AUC@5", ".3f"),
    ("match_s", "Match (s)", ".1f"),
)
# Every field of a row, in the order of the CSV files.
ROW_FIELDS = (
    "scene", "method", "num_images", "num_registered", "registered_pct", "num_components", "rot_error_deg",
    "trans_error_deg", "matches_per_pair", "verified_pairs", "reproj_mean_px", "reproj_median_px", "points3d",
    "track_length", "pairs", "repair_pairs", "select_s", "tree_build_s", "match_s", "map_s",
    "auc@1", "auc@3", "auc@5", "auc@10", "pairs_vs_exhaustive", "match_time_vs_exhaustive",
    "select_time_vs_exhaustive_match", "error",
)




def method_table(rows: Sequence[dict[str, Any]], columns: Sequence[tuple[str, str, str]], *,
                 first: str = "Method") -> str:
    """A Markdown table, one row per method, one column per `columns` entry; failures say so."""
    body = []
    for row in rows:
        if row.get("error"):
            cells = [f"failed: {row['error']}"] + [""] * (len(columns) - 1)
        else:
            cells = [format_number(row.get(key), spec) for key, _, spec in columns]
        body.append([row["method"], *cells])
    return markdown_table([first, *(title for _, title, _ in columns)], body)


TABLE_NOTE = ("Errors are medians over co-registered pairs (relative poses, degrees); matches/pair are inlier "
              "matches per verified pair; AUC of max(rotation, translation) error over all gt pairs. Select (s) "
              "leaves out the one-off build of a vocabulary tree (tree_build_s in the CSV). Times are seconds "
              "on this machine in this run; ratios are against exhaustive on the same scene.")
ABLATION_NOTE = ("SARA with parts of its graph stage switched off (graph.use_loops / use_anchors / use_weak); "
                 "registered images of the largest model; AUC@5 over all gt pairs.")


def render_markdown(rows: Sequence[dict[str, Any]], columns: Sequence[tuple[str, str, str]], title: str, *,
                    note: str = TABLE_NOTE, first: str = "Method") -> str:
    lines = [f"# {title}", ""]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        scene_rows = [r for r in rows if r["scene"] == scene]
        num_images = next((r.get("num_images") for r in scene_rows if r.get("num_images")), None)
        lines += [f"## {scene}" + (f" ({num_images} images)" if num_images else ""), "",
                  method_table(scene_rows, columns, first=first), ""]
    return "\n".join(lines + [note, ""])


def rows_to_csv(rows: Sequence[dict[str, Any]]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(ROW_FIELDS), extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: "" if row.get(k) is None else row.get(k) for k in ROW_FIELDS})
    return buffer.getvalue()


def write_tables(stem: Path, rows: Sequence[dict[str, Any]], columns: Sequence[tuple[str, str, str]],
                 meta: dict[str, Any], *, title: str, note: str = TABLE_NOTE, first: str = "Method") -> list[Path]:
    """`<stem>.json`, `<stem>.csv` and `<stem>.md`; returns their paths."""
    paths = [stem.with_suffix(".json"), stem.with_suffix(".csv"), stem.with_suffix(".md")]
    write_json_atomic(paths[0], {**meta, "rows": list(rows)})
    write_text_atomic(paths[1], rows_to_csv(rows))
    write_text_atomic(paths[2], render_markdown(rows, columns, title, note=note, first=first))
    return paths


NAMES_TITLE = "Over file-name orders"
NAMES_NOTE = ("Each scene under its own names and under random ones (`--name-orders`); mean and range over "
              "the namings where the method ran; the difference to exhaustive matching is taken per naming "
              "(mean, range, and under how many namings the method was at least exhaustive's). COLMAP and "
              "SARA break ties by image name, so a difference between methods smaller than a method's own "
              "range is not told apart by one naming.")


def names_summary(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per scene (renamed copies counted with their original) and method: how many namings ran, AUC@1
    and AUC@5 mean, min and max, the fewest images registered and the mean pairs. Where exhaustive
    ran under the same naming, also the difference to it per naming (``auc@1_vs_exhaustive``: mean,
    min, max) and under how many namings the method was at least exhaustive's."""
    ran = [r for r in rows if not r.get("error") and r.get("auc@1") is not None]
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for row in ran:
        groups.setdefault((base_scene(row["scene"]), row["method"]), []).append(row)
    exhaustive = {r["scene"]: r for r in ran if r["method"] == "exhaustive"}
    summary = []
    for (scene, method), group in groups.items():
        entry: dict[str, Any] = {"scene": scene, "method": method, "namings": len(group)}
        for key in ("auc@1", "auc@5"):
            values = [float(r[key]) for r in group]
            entry.update({f"{key}_mean": sum(values) / len(values), f"{key}_min": min(values),
                          f"{key}_max": max(values)})
            paired = [float(r[key]) - float(exhaustive[r["scene"]][key]) for r in group
                      if method != "exhaustive" and r["scene"] in exhaustive]
            if paired:
                entry[f"{key}_vs_exhaustive"] = {"mean": sum(paired) / len(paired), "min": min(paired),
                                                 "max": max(paired), "namings": len(paired),
                                                 "at_least": sum(d >= 0 for d in paired)}
        entry["registered_pct_min"] = min(float(r.get("registered_pct") or 0.0) for r in group)
        entry["pairs_mean"] = sum(float(r.get("pairs") or 0) for r in group) / len(group)
        summary.append(entry)
    return summary


def _versus(entry: dict[str, Any], key: str) -> str:
    diff = entry.get(f"{key}_vs_exhaustive")
    if not diff:
        return "-"
    return (f"{diff['mean']:+.4f} ({diff['min']:+.4f} to {diff['max']:+.4f}); "
            f"at least in {diff['at_least']} of {diff['namings']}")


def render_names(summary: Sequence[dict[str, Any]]) -> str:
    body = [[e["scene"], e["method"], str(e["namings"]),
             f"{e['auc@1_mean']:.4f} ({e['auc@1_min']:.4f}-{e['auc@1_max']:.4f})",
             f"{e['auc@5_mean']:.4f} ({e['auc@5_min']:.4f}-{e['auc@5_max']:.4f})",
             _versus(e, "auc@1"), _versus(e, "auc@5"),
             f"{e['registered_pct_min']:.1f}", f"{e['pairs_mean']:.0f}"] for e in summary]
    table = markdown_table(["Scene", "Method", "Namings", "AUC@1 mean (range)", "AUC@5 mean (range)",
                            "AUC@1 - exhaustive's, same naming", "AUC@5 - exhaustive's, same naming",
                            "Reg. % (fewest)", "Pairs (mean)"], body)
    return "\n".join([f"# {NAMES_TITLE}", "", table, "", NAMES_NOTE, ""])


def plot_results(rows: Sequence[dict[str, Any]], path: Path) -> Path | None:
    """Pairs vs AUC@5 and matching time vs pairs, every method on every scene; None without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.ticker import LogFormatter
    except ImportError:
        logger.warning("matplotlib is not installed: no plot (pip install 'sara[plot]')")
        return None
    done = [r for r in rows if not r.get("error") and r.get("pairs")]
    methods = list(dict.fromkeys(r["method"] for r in done))
    scenes = list(dict.fromkeys(r["scene"] for r in done))
    markers = "osD^vP*Xh<>"
    fig, (ax_auc, ax_time) = plt.subplots(1, 2, figsize=(12, 5))
    for s, scene in enumerate(scenes):
        for m, method in enumerate(methods):
            for r in (r for r in done if r["scene"] == scene and r["method"] == method):
                style = {"marker": markers[m % len(markers)], "color": f"C{s % 10}", "linestyle": "none"}
                ax_auc.plot(r["pairs"], r.get("auc@5") or 0.0, **style)
                if r.get("match_s") is not None:
                    ax_time.plot(r["pairs"], r["match_s"], **style)
    handles = [plt.Line2D([], [], marker=markers[m % len(markers)], color="gray", linestyle="none", label=method)
               for m, method in enumerate(methods)]
    handles += [plt.Line2D([], [], color=f"C{s % 10}", linewidth=5, label=scene) for s, scene in enumerate(scenes)]
    ax_auc.set(xscale="log", ylim=(0.0, 1.02), xlabel="pairs matched", ylabel="AUC@5",
               title="Accuracy vs pairs matched")
    ax_time.set(xscale="log", yscale="log", xlabel="pairs matched", ylabel="matching time (s)",
                title="Matching time vs pairs matched")
    for ax in (ax_auc, ax_time):
        ax.grid(True, which="both", alpha=0.3)
        for axis in (ax.xaxis, ax.yaxis):  # 30, 100, 300 rather than 3x10^1
            if axis.get_scale() == "log":
                axis.set_major_formatter(LogFormatter(labelOnlyBase=False, minor_thresholds=(2, 0.5)))
                axis.set_minor_formatter(LogFormatter(labelOnlyBase=False, minor_thresholds=(2, 0.5)))
    ax_time.legend(handles=handles, fontsize="small", loc="best")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)
    return path


