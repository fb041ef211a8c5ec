"""What a run records for people: `run.json` (configuration, versions, each stage's counts and
times) and `report.md`, a short summary; the HTML report (`sara.report`) reads `run.json`."""

from __future__ import annotations

import platform
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import __version__, colmap, mapping, match
from ..eta import format_duration
from ..io import records, write_json_atomic
from ..tables import markdown_table
from . import advice, rounds
from .pairs_stage import STAGE as PAIRS_STAGE


@dataclass
class RunReport:
    """Everything `run.json` records about a run."""

    out_dir: Path
    images_root: Path
    config: dict[str, Any]
    stages: dict[str, dict[str, Any]] = field(default_factory=dict)
    skipped_images: dict[str, str] = field(default_factory=dict)
    metrics: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "sara_version": __version__,
            "versions": versions(),
            "images_root": str(self.images_root.resolve()),
            "config": self.config,
            "skipped_images": self.skipped_images,
            "stages": self.stages,
            "metrics": self.metrics,
        }

    def save(self) -> None:
        write_json_atomic(self.out_dir / "run.json", self.to_dict())


def versions() -> dict[str, str]:
    import numpy

    return {"python": platform.python_version(), "pycolmap": colmap.version(), "numpy": numpy.__version__}


def collect_stages(report: RunReport, selection_key: str) -> None:
    """The pairs, match and map stages as the whole run saw them, the rounds included: the pairs of
    every round, and match and map times summed over them (each record keeps only its own)."""
    out_dir = report.out_dir
    pairs = dict(records.done_info(out_dir, PAIRS_STAGE))
    matched = dict(records.done_info(out_dir, match.STAGE))
    mapped = dict(records.done_info(out_dir, mapping.STAGE))
    ledger = rounds.ledger(out_dir, selection_key)
    before = ledger.get("before_mapping", {})
    added_before = before.get("num_pairs", 0)
    added_after = sum(len(p) for p in ledger.get("added", {}).values()) - added_before
    if added_before or added_after:
        pairs.update(num_added_before_mapping=added_before, num_added_after_mapping=added_after)
        pairs["num_pairs"] = pairs.get("num_selected", pairs.get("num_pairs", 0)) + added_before + added_after
        if pairs.get("num_exhaustive_pairs"):  # the pairs of all rounds, as the report counts them
            pairs["fraction_of_exhaustive"] = pairs["num_pairs"] / pairs["num_exhaustive_pairs"]
    if "first_match_time_s" in ledger:
        matched["time_s"] = (ledger["first_match_time_s"] + before.get("match_time_s", 0.0)
                             + ledger.get("match_time_s", 0.0))
        # the estimates of the same matchings, made from each one's first chunk
        matched["estimate_s"] = (ledger.get("first_match_estimate_s", ledger["first_match_time_s"])
                                 + before.get("match_estimate_s", 0.0) + ledger.get("match_estimate_s", 0.0))
        # the rates of the first matching, not of the last round's few pairs
        matched["rate_pairs_per_s"] = ledger.get("first_match_rate_pairs_per_s", matched.get("rate_pairs_per_s"))
        matched.pop("estimate_rate_pairs_per_s", None)
    if "first_map_time_s" in ledger:
        mapped["time_s"] = ledger["first_map_time_s"] + ledger.get("map_time_s", 0.0)
    report.stages.update(pairs=pairs, match=matched, map=mapped)
    if ledger.get("rounds") or ledger.get("extension") or before:
        report.stages["rounds"] = {**ledger, **rounds_share(ledger, pairs.get("time_s", 0.0))}


def rounds_share(ledger: dict[str, Any], pairs_time_s: float) -> dict[str, Any]:
    """The rounds' time (matching before the first mapping, and every round after it with the last
    step on the final model) and its share of the time after extraction (pairs, match, map)."""
    rounds_s = ledger.get("before_mapping", {}).get("match_time_s", 0.0) + ledger.get("time_s", 0.0)
    first_s = pairs_time_s + ledger.get("first_match_time_s", 0.0) + ledger.get("first_map_time_s", 0.0)
    return {"total_time_s": rounds_s, "first_round_time_s": first_s,
            "share_after_extraction": rounds_s / (first_s + rounds_s) if first_s + rounds_s > 0 else 0.0}


def tree_note(pairs_info: dict[str, Any]) -> str:
    """How the SARA selection ranked its spanning tree, for the reports ('' for other sources)."""
    tree = pairs_info.get("tree_overlap")
    if tree is None:
        return ""
    fov = pairs_info.get("field_of_view_deg")
    view = f"{fov:.0f}-degree field of view" if fov is not None else "field of view unknown"
    rank = "the inliers among all matches" if tree == "all" else "the paper's weight"
    how = "" if pairs_info.get("tree_overlap_setting", "auto") == "auto" else ", as set by score.tree_overlap"
    if pairs_info.get("moving_ahead"):
        view += ", views moving along their optical axes"
    return f"; spanning tree by {rank} ({view}{how})"


def update_summary(update: dict[str, Any]) -> str:
    """What an incremental update changed and redid, in one line (`stages.update` of run.json)."""
    return (f"{update.get('num_added', 0)} images added, {update.get('num_removed', 0)} removed, "
            f"{update.get('num_changed', 0)} changed, {update.get('num_renamed', 0)} renamed since the previous "
            f"run; {update.get('num_extracted', 0)} extracted, {update.get('num_pairs_scored', 0)} pairs scored, "
            f"{update.get('num_pairs_matched', 0)} pairs matched ({update.get('num_pairs_kept', 0)} earlier pairs "
            f"kept, {update.get('num_pairs_dropped', 0)} dropped)")


def frames_summary(stage: dict[str, Any]) -> str:
    """`52 frames picked from 2 videos (--frames 26): a.mp4 26 of 26, ...` (`stages.video` of run.json)."""
    videos = stage.get("videos") or []
    text = (f"{sum(v.get('num_picked', 0) for v in videos)} frames picked from {len(videos)} video"
            f"{'s' if len(videos) != 1 else ''}" + (f" ({stage['settings']})" if stage.get("settings") else "") + ": "
            + ", ".join(f"{v.get('name')} {v.get('num_picked', 0)} of {v.get('num_frames', 0)}" for v in videos))
    flat = sum(v.get("num_flat", 0) for v in videos)
    if flat:
        text += f"; {flat} frames without texture (black, one colour) passed over"
    if stage.get("unreadable"):
        text += f"; set aside, unreadable: {', '.join(stage['unreadable'])}"
    return text


CAMERA_MODES = {"single": "one shared", "per_video": "one per video", "per_image": "one per image",
                "per_folder": "one per folder", "per_exif": "one per phone, by EXIF",
                "per_sequence": "one per clip of numbered frames"}


def _cameras_note(extract_info: dict[str, Any]) -> str:
    """`, 2 cameras (one per video)`: how the run's images share cameras (empty where not recorded)."""
    num, mode = extract_info.get("num_cameras"), extract_info.get("camera_mode")
    if num is None:
        return ""
    return f", {num} camera{'s' if num != 1 else ''} ({CAMERA_MODES.get(mode, mode)})"


def _masks_note(extract_info: dict[str, Any]) -> str:
    """` (12 per image on the masks' black pixels left out)` where masks were given."""
    masked = extract_info.get("masked_keypoints") or {}
    if not masked.get("num_images") or not extract_info.get("num_images"):
        return ""
    per_image = masked["num_keypoints"] / extract_info["num_images"]
    return f" ({per_image:.0f} per image on the masks' black pixels left out)"


def render_report(report: RunReport) -> str:
    """A short human-readable summary of a run (Markdown)."""
    s = report.stages
    ex, pr, ma, mp = s.get("extract", {}), s.get("pairs", {}), s.get("match", {}), s.get("map", {})
    added, before = pr.get("num_added_after_mapping", 0), pr.get("num_added_before_mapping", 0)
    rows = [
        [f"extract ({ex.get('backend', 'sift')})", f"{ex.get('time_s', 0):.1f}",
         f"{ex.get('keypoints_mean', 0):.0f} keypoints per image" + _masks_note(ex) + _cameras_note(ex)],
        [f"pairs ({pr.get('method')})", f"{pr.get('time_s', 0):.1f}",
         f"{pr.get('num_pairs', 0)} pairs ({100 * pr.get('fraction_of_exhaustive', 0):.1f}% of exhaustive)"
         + (f", {before} of them added before mapping for weakly matched views" if before else "")
         + (f", {added} of them added after mapping" if added else "") + tree_note(pr)],
        [f"match ({ma.get('matcher', '')})", f"{ma.get('time_s', 0):.1f}",
         f"{ma.get('num_verified_pairs', 0)} verified pairs, "
         f"{ma.get('inlier_matches_per_pair_mean', 0):.0f} inlier matches per pair"],
        ["map", f"{mp.get('time_s', 0):.1f}",
         f"{mp.get('num_components', 0)} model(s): {mp.get('component_sizes', [])} images registered"],
    ]
    lines = [f"# sara run: {report.out_dir.name}", "",
             f"Images: {s['images']['num_images']} used, {s['images']['num_skipped']} skipped "
             f"(from `{report.images_root}`)", "", markdown_table(["stage", "time (s)", "result"], rows)]
    if s.get("video"):
        lines[3:3] = ["", f"Frames: {frames_summary(s['video'])}"]
    update = s.get("update")
    if update:
        lines += ["", f"Update: {update_summary(update)}"]
    notes = time_notes(s)
    if notes:
        lines += [""] + [f"- {note}" for note in notes]
    said = advice.given(s, str(report.config.get("extract", {}).get("backend", "sift")))
    if said:
        lines += ["", "## Advice", ""] + [f"- {text}" for text in said]
    if report.skipped_images:
        lines += ["", "Skipped images:", ""] + [f"- `{n}`: {r}" for n, r in report.skipped_images.items()]
    if report.metrics:
        from ..evaluation import format_table

        lines += ["", "## Accuracy against ground truth", "", "```", format_table(report.metrics), "```"]
    return "\n".join(lines) + "\n"


def time_notes(stages: dict[str, Any]) -> list[str]:
    """Sentences on the time: the matching's estimate against what it took, the rounds' share."""
    notes = []
    ma, ro = stages.get("match", {}), stages.get("rounds", {})
    if ma.get("estimate_s") is not None and ma.get("time_s"):
        error = 100 * (ma["estimate_s"] - ma["time_s"]) / ma["time_s"]
        what = "matching (every round's, each estimated from its first chunk)" if ro else "matching"
        notes.append(f"{what}: estimated {format_duration(ma['estimate_s'])} after the first chunk, took "
                     f"{format_duration(ma['time_s'])} ({error:+.0f}%)")
    if ro.get("total_time_s") is not None:
        budget = ro.get("time_budget_s")
        notes.append(f"rounds after the first selection: {format_duration(ro['total_time_s'])}, "
                     f"{100 * ro.get('share_after_extraction', 0.0):.0f}% of the time after extraction"
                     + (f" (time budget of the rounds after mapping: {format_duration(budget)})" if budget else "")
                     + (f"; the rounds stopped: {ro['stopped']}" if ro.get("stopped") else ""))
    return notes
