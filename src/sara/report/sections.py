"""The sections of `report.html`, each a function of the run's data that returns HTML ("" when the run
lacks what the section shows): summary cards, the view graph, the top-down plot, pairs against
exhaustive matching, the pre-matching scores, time per stage, the reconstruction, the evaluation
against ground truth, the advice the run gave, and the commands to run next.
"""

from __future__ import annotations

import shlex
from collections import Counter

import numpy as np

from .. import colmap
from ..export import FORMATS
from ..io.pairs import Pair
from ..pipeline import advice as run_advice
from ..pipeline.record import frames_summary, time_notes, tree_note, update_summary
from . import SELECTED_ROLES, RunData, Scores
from .markup import esc, fmt, section, table
from .svg import histogram_svg, node_positions, role_order, role_swatch, top_down_svg, view_graph_svg
from .thumbnails import degrees


def summary(data: RunData) -> str:
    """One card per headline number: images, registered, pairs, points, models, time (and AUC@5)."""
    n = len(data.names)
    registered = len(data.model.names) if data.model is not None else 0
    total_s = sum(float(s.get("time_s", 0.0)) for k, s in data.stages.items() if isinstance(s, dict) and k != "rounds")
    cards = [("images", str(n)),
             ("registered", f"{registered} / {n}" if data.model is not None else "no model"),
             ("pairs matched", f"{len(data.pairs)}"),
             ("of exhaustive", f"{100 * len(data.pairs) / max(data.num_exhaustive, 1):.1f}%"),
             ("verified pairs", str(len(data.verified)) if data.verified else "&ndash;"),
             ("3D points", str(len(data.model.points_xyz)) if data.model is not None else "&ndash;"),
             ("models", str(len(data.model_sizes))),
             ("total time", f"{total_s:.1f} s" if total_s else "&ndash;")]
    if data.metrics and isinstance(data.metrics.get("auc"), dict) and "5" in data.metrics["auc"]:
        cards.append(("AUC@5&deg;", f"{100 * float(data.metrics['auc']['5']):.1f}"))
    return "<div class=\"cards\">" + "".join(
        f"<div class=\"card\"><div class=\"v\">{v}</div><div class=\"k\">{k}</div></div>" for k, v in cards) + "</div>"


# ---------------------------------------------------------------------------------------------
# View graph and top-down plot
# ---------------------------------------------------------------------------------------------


def _inliers(s: Scores, e: int) -> str:
    """The pre-match's inliers: among the best matches, and among all mutual matches when known."""
    text = f"{s.num_inliers[e]} inliers"
    if s.num_inliers_all is not None and s.num_inliers_all[e] > s.num_inliers[e]:
        text += f" ({s.num_inliers_all[e]} of all matches)"
    return text


def _edge_title(pair: Pair, role: str, data: RunData, score_index: dict[Pair, int]) -> str:
    """The hover text of an edge: its role, its scores when scored, its verified matches when matched."""
    text = f"{pair[0]} \u2013 {pair[1]}: {role}"
    s = data.scores
    if s is not None and pair in score_index:
        e = score_index[pair]
        text += (f"; O={s.overlap[e]:.4f}, P={degrees(s.parallax_deg[e])}, w={s.weight[e]:.4f}, "
                 f"{_inliers(s, e)}" + (f", {s.reason[e]}" if s.reason[e] else ""))
    if pair in data.verified:
        text += f"; {data.verified[pair]} verified matches"
    return text


def view_graph(data: RunData) -> str:
    """The view graph: every scored or matched pair as an edge coloured by its role."""
    if not data.names:
        return ""
    pos, registered, how = node_positions(data)
    roles = data.edge_roles()
    score_index = {p: e for e, p in enumerate(data.scores.pairs)} if data.scores is not None else {}
    svg = view_graph_svg(data, roles, pos, registered,
                         lambda pair, role: _edge_title(pair, role, data, score_index))
    left_out = data.model is not None and not registered.all()
    note = (f"Nodes at {how}; hover an edge or a node for its numbers. "
            + ("Hollow red nodes: images the model left out. " if left_out else "") + "Untick a role to hide it.")
    return section("View graph", _legend(Counter(roles.values())) + svg, note)


def _legend(counts: Counter) -> str:
    items = [f"<label><input type=\"checkbox\" checked data-role=\"{role}\"> {role_swatch(role)} {role} "
             f"<span class=\"count\">{counts[role]}</span></label>" for role in reversed(role_order(counts))]
    return f"<div class=\"legend\" data-for=\"viewgraph\">{''.join(items)}</div>"


def top_down(data: RunData) -> str:
    """The cameras and the 3D points of model 0 seen from above."""
    if data.model is None or len(data.model.names) < 2:
        return section("Cameras and points from above", "<p>No model: nothing to plot.</p>")
    m = data.model
    svg, num_drawn = top_down_svg(m)
    note = (f"{len(m.names)} cameras (red: centre and viewing direction) and {num_drawn} of "
            f"{len(m.points_xyz)} points of model 0 in their colours, seen from above.")
    return section("Cameras and points from above", svg, note)


# ---------------------------------------------------------------------------------------------
# Pairs against exhaustive, and the scores
# ---------------------------------------------------------------------------------------------


def pairs_against_exhaustive(data: RunData) -> str:
    """How many pairs each step kept, as bars against the exhaustive n(n-1)/2, and the pairs per role."""
    rows = [("exhaustive", data.num_exhaustive)]
    if data.scores is not None:
        rows += [("retrieval candidates", len(data.scores.pairs)),
                 ("accepted by the scorer", int(data.scores.accepted.sum()))]
    rows += [("matched (pairs.txt)", len(data.pairs))]
    if data.verified:
        rows.append(("verified by COLMAP", len(data.verified)))
    top = max(max(v for _, v in rows), 1)
    bars = "".join(
        f"<div class=\"bar\"><span class=\"lbl\">{esc(k)}</span><span class=\"track\"><span class=\"fill\" "
        f"style=\"width:{100 * v / top:.2f}%\"></span></span><span class=\"val\">{v:,} "
        f"({100 * v / max(data.num_exhaustive, 1):.1f}%)</span></div>" for k, v in rows)
    roles = Counter(data.edge_roles().values())
    role_rows = "".join(f"<tr><td>{esc(r)}</td><td>{roles[r]}</td></tr>" for r in reversed(role_order(roles)))
    body = f"<div class=\"bars\">{bars}</div>"
    if role_rows:
        body = (f"<div class=\"side\">{body}<table class=\"small\"><tr><th>role</th><th>pairs</th></tr>"
                f"{role_rows}</table></div>")
    tree = tree_note(data.stages.get("pairs", {})).removeprefix("; ")
    return section("Pairs against exhaustive matching", body, "Percentages are of the exhaustive n(n-1)/2 pairs."
                   + (f" The {esc(tree)}." if tree else ""))


def scores(data: RunData) -> str:
    """Histograms of O, P, inliers and w with the scorer's thresholds, and why candidates were rejected."""
    s = data.scores
    if s is None:
        return section("Pre-matching scores", "<p>No scores.csv: only the SARA pair source scores pairs before "
                       f"matching, and this run's pairs came from <b>{esc(data.method)}</b>.</p>")
    score_conf = data.config.get("score", {})
    selected = np.array([r in SELECTED_ROLES for r in s.role], dtype=bool)
    split = [("accepted", s.accepted, "#4c78a8"), ("rejected", ~s.accepted, "#e45756")]
    by_role = [("selected", selected, "#1f4e9c"), ("accepted, not selected", s.accepted & ~selected, "#9ecae9"),
               ("rejected", ~s.accepted, "#e45756")]
    figs = [
        histogram_svg(s.overlap, split, title="overlap O = inliers / sqrt(Ni Nj)",
                      threshold=score_conf.get("min_overlap"), threshold_label=f"min {score_conf.get('min_overlap')}"),
        histogram_svg(s.parallax_deg, split, title="parallax P (deg, median triangulation angle)",
                      threshold=score_conf.get("min_parallax_deg"),
                      threshold_label=f"min {score_conf.get('min_parallax_deg')}\u00b0"),
        histogram_svg(s.num_inliers.astype(float), split, title="RANSAC inliers of the pre-match",
                      threshold=score_conf.get("min_inliers"), threshold_label=f"min {score_conf.get('min_inliers')}"),
        histogram_svg(s.weight, by_role, title="weight w = O \u00b7 g(P)^\u03b2"),
    ]
    reasons = Counter(r for r in s.reason if r)
    legend = ("<p class=\"keys\"><span style=\"background:#4c78a8\"></span>accepted <span style=\"background:#e45756\">"
              "</span>rejected <span style=\"background:#1f4e9c\"></span>selected <span style=\"background:#9ecae9\">"
              "</span>accepted, not selected</p>")
    why = ", ".join(f"{esc(k)}: {v}" for k, v in reasons.most_common()) or "none"
    if reasons.get("inconsistent"):
        why += (" (inconsistent: accepted by the scorer, but its relative rotation does not close around most of "
                "its triangles of other candidates, as repeated or symmetric structures give; "
                "graph.reject_inconsistent)")
    return section("Pre-matching scores", legend + f"<div class=\"hists\">{''.join(figs)}</div>",
                   f"{len(s.pairs)} candidate pairs; rejected by reason: {why}. Dashed lines: the scorer's "
                   "thresholds from run.json; values above the 99th percentile are counted in the last bin.")


# ---------------------------------------------------------------------------------------------
# Time, reconstruction, evaluation, next steps
# ---------------------------------------------------------------------------------------------


def timing(data: RunData) -> str:
    """A bar per stage (and per step of the pairs stage) from run.json's times; the rounds, whose
    time the match and map stages include, as a bar of their own that the total does not add, and
    the matching's estimate against its time."""
    rows = [(name, float(info["time_s"])) for name, info in data.stages.items()
            if name != "rounds" and isinstance(info, dict) and isinstance(info.get("time_s"), int | float)]
    if not rows:
        return ""
    sub = data.stages.get("pairs", {}).get("timings_s", {})
    rounds_s = data.stages.get("rounds", {}).get("total_time_s")
    total = max(sum(t for _, t in rows), 1e-9)
    top = max(t for _, t in rows) or 1.0
    html_rows = []
    for name, t in rows:
        html_rows.append(_time_bar(name, t, top, total))
        if name == "pairs":
            html_rows += [_time_bar(f"\u2003{k}", float(v), top, total, sub=True) for k, v in sub.items()]
    if isinstance(rounds_s, int | float):
        html_rows.append(_time_bar("rounds (in match and map)", float(rounds_s), top, total, sub=True))
    notes = "".join(f" {esc(note[0].upper() + note[1:])}." for note in time_notes(data.stages))
    return section("Time per stage", f"<div class=\"bars\">{''.join(html_rows)}</div>",
                   f"Total {total:.1f} s (from run.json; stages skipped on resume count their first run).{notes}")


def _time_bar(name: str, seconds: float, top: float, total: float, *, sub: bool = False) -> str:
    cls = "fill sub" if sub else "fill"
    return (f"<div class=\"bar\"><span class=\"lbl\">{esc(name)}</span><span class=\"track\"><span class=\"{cls}\" "
            f"style=\"width:{100 * seconds / top:.2f}%\"></span></span><span class=\"val\">{seconds:.2f} s "
            f"({100 * seconds / total:.0f}%)</span></div>")


def reconstruction(data: RunData) -> str:
    """The numbers of model 0 (and the sizes of the others), or why there is none."""
    if data.model is None:
        return section("Reconstruction", "<p>No model was built (no sparse/0). Too few verified pairs, or the "
                       "map stage did not run.</p>")
    m = data.model
    cams = Counter(c.model for c in m.cameras.values())
    rows = [("models (registered images each)", ", ".join(map(str, data.model_sizes))),
            ("registered images (model 0)", f"{len(m.names)} of {len(data.names)}"),
            ("3D points", f"{len(m.points_xyz):,}"),
            ("observations", f"{int(m.track_lengths.sum()):,}"),
            ("mean track length", fmt(float(m.track_lengths.mean()) if len(m.track_lengths) else None)),
            ("mean reprojection error (px)", fmt(float(m.points_error_px.mean()) if len(m.points_error_px) else None)),
            ("3D points per image (median)", f"{np.median(m.num_observations):,.0f}" if len(m.names) else "&ndash;"),
            ("cameras", ", ".join(f"{v} {esc(k)}" for k, v in cams.items()))]
    if data.agreement is not None:
        rows.append(("verified pairs that contradict it", _contradicted(data.agreement)))
    asked, used = data.config.get("map", {}).get("mapper"), data.stages.get("map", {}).get("mapper")
    if asked and used and used != asked:
        rows.append(("mapper", f"{esc(used)}: the {esc(asked)} mapper's model was contradicted by its pairs"))
    first = _first_model(data.stages.get("map", {}))
    if first:
        rows.append(("first model", first))
    history = (data.stages.get("rounds") or {}).get("history", [])
    mended = [h.get("role", "?") for h in history if h.get("continued_mended")]
    if mended:
        rows.append(("models of the rounds", f"contradicted by their verified pairs after the {esc(', '.join(mended))} "
                     "round(s): mended at the seam (map.mend_seam)"))
    if data.stages.get("map", {}).get("distortion_held"):
        rows.append(("lens distortion", "held while mapping: few keypoints per image and a guessed camera "
                     "(map.hold_distortion_starved), or with it refined the first model held under half the views "
                     "(map.refine_distortion)"))
    if data.stages.get("map", {}).get("two_view_points"):
        rows.append(("points", "those seen in two views only triangulated too: without them no model could be "
                     "built (map.two_view_points)"))
    if data.stages.get("video"):
        rows.append(("frames", esc(frames_summary(data.stages["video"]))))
    left_out = [n for n in data.names if n not in set(m.names)]
    if left_out:
        shown = ", ".join(esc(n) for n in left_out[:20]) + (" ..." if len(left_out) > 20 else "")
        rows.append(("not in model 0", shown))
    return section("Reconstruction", table(rows))


def _first_model(stage: dict) -> str:
    """What the map stage did with a first model its pairs contradicted (empty when none was). The
    record's pair counts are the kept model's check, not the first model's, so they are not shown."""
    if stage.get("mended"):
        return ("contradicted by its verified pairs: mended at the seam (the views around those pairs taken out "
                "and registered again; map.mend_seam)")
    if stage.get("remaps"):
        return (f"contradicted by its verified pairs: mapped again {stage['remaps']} time(s) under other seeds, "
                f"seed {stage.get('seed')} kept (map.contradicted_remaps)")
    return ""


def _contradicted(check: colmap.Agreement) -> str:
    """The pairs whose matches lie off the model's epipolar lines, of those between its views."""
    text = f"{len(check.contradicted)} of {check.checked}"
    if check.contradicted:
        shown = ", ".join(f"{esc(a)}&ndash;{esc(b)}" for a, b in check.contradicted[:5])
        text += f" ({shown}{' ...' if len(check.contradicted) > 5 else ''}): the model may be bent there"
    return text


def evaluation(data: RunData) -> str:
    """The metrics against ground truth (`metrics.json`), when the run has them."""
    if not data.metrics:
        return ""
    rows = []
    for key, value in data.metrics.items():
        if isinstance(value, dict):
            rows += [(f"{key}@{k}", fmt(v)) for k, v in value.items()]
        elif not isinstance(value, list):
            rows.append((key, fmt(value)))
    return section("Evaluation against ground truth", table(rows), "From metrics.json (`sara run --gt` or "
                   "`sara evaluate`); angles in degrees, AUC as a fraction.")


def advice(data: RunData) -> str:
    """What the run said before matching (SIFT starved; cameras from guessed focal lengths; 360-degree
    panoramas), after mapping (views moving straight ahead without the intrinsics) and what an update
    of the folder redid: the console's warnings, kept with the run."""
    backend = str(data.run.get("config", {}).get("extract", {}).get("backend", "sift"))
    notes = run_advice.given(data.stages, backend)
    update = data.stages.get("update")
    if isinstance(update, dict):
        notes.append(f"An update of a finished run: {update_summary(update)}")
    if not notes:
        return ""
    return section("Advice", "<ul>" + "".join(f"<li>{esc(text)}</li>" for text in notes) + "</ul>")


def next_steps(data: RunData) -> str:
    """The commands that take the run further: export the model for a renderer, rebuild this page."""
    out = data.out_dir.resolve()
    commands = []
    if data.model is not None:
        commands += [f"sara export {shlex.quote(str(out))} {shlex.quote(str(out / fmt_name))} --format {fmt_name}"
                     for fmt_name in FORMATS]
    commands.append(f"sara report {shlex.quote(str(out))}")
    code = "<pre class=\"cmds\">" + "\n".join(esc(c) for c in commands) + "</pre>"
    if data.model is not None:
        note = ("Export model 0 in the layout another tool reads (3dgs: 3D Gaussian Splatting's "
                "<code>train.py -s DEST</code>; nerfstudio; colmap: a COLMAP project) into any destination "
                "folder, here one inside the run's; the last command rebuilds this page, after a resume for example.")
    else:
        note = ("No model to export: <code>sara export</code> needs sparse/0. The command below rebuilds this "
                "page, after a resume for example.")
    return section("Next", code, note)
