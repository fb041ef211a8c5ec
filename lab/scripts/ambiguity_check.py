"""What the cycle check (graph.reject_inconsistent) and the ratio test (score.max_descriptor_ratio) change on
a finished SARA run, without matching or mapping (lab/notes/AMBIGUITY.md).

For RUN (a `sara run` output or a bench's `SCENE/sara` folder: scores.csv, database.db, features-*.h5,
run.json) re-scores every candidate of scores.csv with this tree's scorer (which records the rotations),
then selects pairs as the pair source does, with the check off and on at each threshold, and prints:
candidates rejected as inconsistent, kept to stay connected, and how many selected pairs change.
With GT (a COLMAP text model of the true poses) it also prints the true error of each accepted pair's
pre-match rotation (degrees): median and 90th percentile of the kept pairs, and each rejected pair's.

    python lab/scripts/ambiguity_check.py RUN [--gt GT] [--thresholds 10,20,30] [--ratio 1.0] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from sara.config import config_from_dict
from sara.io.scores import PairScores, read_scores_csv
from sara.pairs.sara.source import _choose
from sara.scoring import score_pairs
from sara.selection import SELECTED_ROLES


def true_rotation_errors(gt_dir: Path, scores: PairScores) -> np.ndarray:
    """(P,) degrees between each pair's pre-match rotation and the true cam1_from_cam0 (NaN without)."""
    import pycolmap

    gt = pycolmap.Reconstruction()
    gt.read_text(str(gt_dir))
    rot = {im.name: Rotation.from_matrix(im.cam_from_world().rotation.matrix()) for im in gt.images.values()}
    out = np.full(len(scores), np.nan)
    for k, (a, b) in enumerate(zip(scores.name0, scores.name1)):
        if a in rot and b in rot and np.all(np.isfinite(scores.rotvec[k])):
            true = rot[b] * rot[a].inv()
            out[k] = np.degrees((Rotation.from_rotvec(scores.rotvec[k]).inv() * true).magnitude())
    return out


def copy_scores(s: PairScores) -> PairScores:
    return replace(s, accepted=s.accepted.copy(), reason=list(s.reason), rotvec=s.rotvec.copy())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--gt", type=Path)
    parser.add_argument("--thresholds", default="10,15,20,30")
    parser.add_argument("--ratio", type=float, default=1.0, help="score.max_descriptor_ratio of the re-scoring")
    parser.add_argument("--wrong-deg", type=float, default=30.0,
                        help="an accepted pair whose pre-match rotation errs by more counts as wrong")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    record = json.loads((args.run / "run.json").read_text())
    raw = record["config"]
    raw.setdefault("score", {})["max_descriptor_ratio"] = args.ratio
    conf = config_from_dict(raw)
    conf = replace(conf, score=replace(conf.score, tree_overlap=record["stages"]["pairs"]["tree_overlap"]))
    old, old_roles = read_scores_csv(args.run / "scores.csv")
    names = sorted(set(old.name0) | set(old.name1))
    index = {n: i for i, n in enumerate(names)}
    pairs = [(a, b) if index[a] < index[b] else (b, a) for a, b in zip(old.name0, old.name1)]
    edges = np.array([(index[a], index[b]) for a, b in pairs], dtype=np.int64)
    features = next(args.run.glob("features-*.h5"))
    scores = score_pairs(pairs, features, args.run / "database.db", conf.score, progress=False, seed=conf.seed)
    errors = true_rotation_errors(args.gt, scores) if args.gt else None
    off_conf = replace(conf, graph=replace(conf.graph, reject_inconsistent=False))
    off_roles, _, _ = _choose(len(names), edges, copy_scores(scores), off_conf)
    off_selected = {e for e, r in enumerate(off_roles) if r in SELECTED_ROLES or r == "rescue"}
    before = {(a, b) if index[a] < index[b] else (b, a)
              for a, b, r in zip(old.name0, old.name1, old_roles or []) if r in SELECTED_ROLES or r == "rescue"}
    result = {"run": str(args.run), "candidates": len(pairs), "accepted": int(scores.accepted.sum()),
              "ratio": args.ratio, "selected_off": len(off_selected),
              "selected_off_changed_vs_run": len(before ^ {pairs[e] for e in off_selected}), "thresholds": {}}
    print(f"{args.run}: {len(pairs)} candidates, {result['accepted']} accepted (ratio {args.ratio:g}); "
          f"selection without the check: {len(off_selected)} pairs, {result['selected_off_changed_vs_run']} "
          "differ from the run's")
    if errors is not None:
        ok = scores.accepted & np.isfinite(errors)
        wrong = ok & (errors > args.wrong_deg)
        result["true_error_accepted_deg"] = [float(np.median(errors[ok])), float(np.percentile(errors[ok], 90))]
        result["wrong"] = int(wrong.sum())
        result["wrong_selected_off"] = sum(bool(wrong[e]) for e in off_selected)
        print(f"  true rotation error of accepted pairs: median {np.median(errors[ok]):.1f}, "
              f"90th pct {np.percentile(errors[ok], 90):.1f} deg; {result['wrong']} err by more than "
              f"{args.wrong_deg:g} deg ({result['wrong_selected_off']} selected without the check)")
    for threshold in (float(t) for t in args.thresholds.split(",")):
        on = copy_scores(scores)
        on_conf = replace(conf, graph=replace(conf.graph, reject_inconsistent=True, max_cycle_error_deg=threshold))
        roles, _, _ = _choose(len(names), edges, on, on_conf)
        rejected = [e for e, r in enumerate(on.reason) if r == "inconsistent"]
        selected = {e for e, r in enumerate(roles) if r in SELECTED_ROLES or r == "rescue"}
        entry = {"rejected": len(rejected), "rejected_selected_off": sum(e in off_selected for e in rejected),
                 "selected": len(selected), "selection_changed": len(selected ^ off_selected)}
        line = (f"  T={threshold:g}: {len(rejected)} rejected ({entry['rejected_selected_off']} of them selected "
                f"without the check); selection {len(selected)} pairs, {entry['selection_changed']} changed")
        if errors is not None and rejected:
            entry["rejected_true_error_deg"] = sorted(round(float(errors[e]), 1) for e in rejected)
            entry["rejected_wrong"] = sum(bool(wrong[e]) for e in rejected)
            entry["wrong_selected"] = sum(bool(wrong[e]) for e in selected)
            line += (f"; {entry['rejected_wrong']} of the {result['wrong']} wrong rejected, {entry['wrong_selected']} "
                     f"wrong selected; true errors of the rejected: {entry['rejected_true_error_deg']}")
        print(line)
        result["thresholds"][f"{threshold:g}"] = entry
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
