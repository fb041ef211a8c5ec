"""The bench summed up by kind of capture: for each scene, SARA against every other method, read
against the noise of the file names.

The noise band of a scene is twice exhaustive matching's own range of AUC@1 (AUC@5 likewise) over
the namings that ran (`--name-orders`): a difference smaller than the band is not told apart from the
names' tie-breaks. With one naming there is no band, and the verdict says so.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from ..tables import markdown_table
from .names import base_scene

KINDS_TITLE = "SARA against each method, by kind of capture"
KINDS_NOTE = ("Per method: mean over the namings that ran (range in brackets). Band: twice exhaustive's range of "
              "the same AUC over the namings. Verdict of SARA against the method: `better` / `worse` where the "
              "difference of the means is beyond the band on AUC@1 or AUC@5, else `within band` (`no band` with "
              "one naming). Seconds: after extraction (selection, matching, mapping and the rounds); end to end "
              "adds the extraction every method shares. Methods that pair by name order run under the "
              "original names only.")


def parse_kinds(items: Sequence[str]) -> dict[str, str]:
    """['kitti-seq1=driving', ...] -> {'kitti-seq1': 'driving'}; ValueError for an item without '='."""
    kinds: dict[str, str] = {}
    for item in items:
        scene, sep, kind = item.partition("=")
        if not sep or not scene.strip() or not kind.strip():
            raise ValueError(f"--kind takes SCENE=KIND (the scene folder's name and a kind of capture), got {item!r}")
        kinds[scene.strip()] = kind.strip()
    return kinds


def _stats(values: list[float]) -> dict[str, float] | None:
    return {"mean": sum(values) / len(values), "min": min(values), "max": max(values)} if values else None


def method_stats(rows: Sequence[dict[str, Any]]) -> dict[tuple[str, str], dict[str, Any]]:
    """(scene, method) -> the method's figures over the namings of the scene that ran."""
    out: dict[tuple[str, str], dict[str, Any]] = {}
    for row in rows:
        if row.get("error") or row.get("auc@1") is None:
            continue
        entry = out.setdefault((base_scene(row["scene"]), row["method"]), {"rows": []})
        entry["rows"].append(row)
    for entry in out.values():
        group = entry.pop("rows")
        entry["namings"] = len(group)
        for key in ("auc@1", "auc@5", "pairs", "num_registered", "num_components", "after_extract_s",
                    "end_to_end_s"):
            entry[key] = _stats([float(r[key]) for r in group if r.get(key) is not None])
        entry["num_images"] = group[0].get("num_images")
    return out


def verdict(sara: dict[str, Any], other: dict[str, Any], band: dict[str, float] | None) -> str:
    if band is None:
        return "no band"
    diffs = {key: sara[key]["mean"] - other[key]["mean"] for key in ("auc@1", "auc@5")}
    if any(diffs[key] < -band[key] for key in diffs):
        return "worse"
    if any(diffs[key] > band[key] for key in diffs):
        return "better"
    return "within band"


def kind_summary(rows: Sequence[dict[str, Any]], kinds: Mapping[str, str]) -> list[dict[str, Any]]:
    """One entry per (scene, method): its figures, the scene's band and SARA's verdict against it."""
    stats = method_stats(rows)
    summary = []
    for (scene, method), entry in stats.items():
        exhaustive = stats.get((scene, "exhaustive"))
        band = None
        if exhaustive and exhaustive["namings"] > 1:
            band = {key: 2 * (exhaustive[key]["max"] - exhaustive[key]["min"]) for key in ("auc@1", "auc@5")}
        sara = stats.get((scene, "sara"))
        against = verdict(sara, entry, band) if sara and method != "sara" else ""
        summary.append({"kind": kinds.get(scene, "unspecified"), "scene": scene, "method": method, **entry,
                        "band": band, "sara_verdict": against})
    return sorted(summary, key=lambda e: (e["kind"], e["scene"]))


def _cell(stats: dict[str, float] | None, spec: str) -> str:
    if stats is None:
        return "-"
    mean = format(stats["mean"], spec)
    if stats["max"] - stats["min"] > 0:
        return f"{mean} ({format(stats['min'], spec)}-{format(stats['max'], spec)})"
    return mean


def render_kinds(summary: Sequence[dict[str, Any]]) -> str:
    lines = [f"# {KINDS_TITLE}", ""]
    for kind in dict.fromkeys(e["kind"] for e in summary):
        lines += [f"## {kind}", ""]
        body = []
        for e in (e for e in summary if e["kind"] == kind):
            band = e["band"]
            body.append([e["scene"], e["method"], str(e["namings"]), _cell(e["pairs"], ".0f"),
                         f"{_cell(e['num_registered'], '.0f')} / {_cell(e['num_components'], '.0f')}",
                         _cell(e["auc@1"], ".3f"), _cell(e["auc@5"], ".3f"),
                         "-" if band is None else f"{band['auc@1']:.3f} / {band['auc@5']:.3f}",
                         _cell(e["after_extract_s"], ".0f"), _cell(e["end_to_end_s"], ".0f"),
                         e["sara_verdict"] or "-"])
        lines += [markdown_table(["Scene", "Method", "Namings", "Pairs", "Registered / models", "AUC@1", "AUC@5",
                                  "Band @1 / @5", "After extraction (s)", "End to end (s)", "SARA vs it"], body), ""]
    return "\n".join(lines + [KINDS_NOTE, ""])
