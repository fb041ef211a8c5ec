"""report.html: built for a synthetic SARA run, a run without scores or model, and opened in headless
Chromium (Debian's `chromium`, installed by .ci/run) to check that it renders without a console
error and that every image loads, with no network."""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import tomllib
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from sara.export import FORMATS
from sara.io.scores import read_scores_csv, write_scores_csv
from sara.pipeline.record import RunReport, render_report
from sara.report import SELECTED_ROLES, load_run, read_scores
from sara.report.html import ASSETS, asset, render, write_report
from sara.report.svg import graph_layout, histogram_svg, top_down_frame
from sara.report.thumbnails import example_pairs

CHROMIUM = Path("/usr/bin/chromium")

# Injected into a copy of the page: collect errors from the start, then report once everything loaded.
PROBE_HEAD = """<script>window.__errors = [];
window.addEventListener('error', function (e) { window.__errors.push('error: ' + (e.message || e.target.src)); }, true);
(function () { var orig = console.error; console.error = function () {
  window.__errors.push('console.error: ' + Array.prototype.join.call(arguments, ' '));
  orig.apply(console, arguments); };
})();</script>"""
PROBE_TAIL = """<script>window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var broken = imgs.filter(function (im) { return !(im.complete && im.naturalWidth > 0); })
    .map(function (im) { return im.alt; });
  var svgs = Array.prototype.slice.call(document.querySelectorAll('svg'));
  var empty = svgs.filter(function (s) { var r = s.getBoundingClientRect(); return !(r.width > 0 && r.height > 0); })
    .length;
  var box = document.getElementById('viewgraph');
  var status = {images: imgs.length, broken: broken, errors: window.__errors, svgs: svgs.length, empty_svgs: empty,
                edges: document.querySelectorAll('#viewgraph line').length,
                graph_width: box ? box.getBoundingClientRect().width : 0};
  var pre = document.createElement('pre'); pre.id = 'probe'; pre.textContent = JSON.stringify(status);
  document.body.appendChild(pre);
});</script>"""


@pytest.fixture(scope="module")
def sara_run(finished_run_template: Path, tmp_path_factory) -> Path:
    """The session's finished run, copied once for this module (its tests write pages beside it)."""
    out = tmp_path_factory.mktemp("report") / "out"
    shutil.copytree(finished_run_template, out, ignore=shutil.ignore_patterns("*.lock"))
    return out


@pytest.fixture()
def bare_run(sara_run: Path, tmp_path: Path) -> Path:
    """The same run as a non-SARA source without a model would leave it: no scores, no sparse/, no metrics."""
    out = tmp_path / "bare"
    shutil.copytree(sara_run, out, ignore=shutil.ignore_patterns("sparse", "scores.csv", "metrics.json", "*.lock"))
    run_json = json.loads((out / "run.json").read_text())
    run_json["metrics"] = None
    run_json["stages"]["pairs"]["method"] = "exhaustive"
    (out / "run.json").write_text(json.dumps(run_json))
    return out


def open_in_chromium(page: Path, tmp_path: Path) -> dict:
    """Load a probed copy of `page` in headless Chromium (no network) and return the probe's findings."""
    text = page.read_text(encoding="utf-8")
    probed = tmp_path / "probed.html"
    probed.write_text(text.replace("<head>", "<head>" + PROBE_HEAD, 1).replace("</body>", PROBE_TAIL + "</body>", 1),
                      encoding="utf-8")
    cmd = [str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
           "--disable-component-update", "--no-first-run", "--disable-dev-shm-usage",
           f"--user-data-dir={tmp_path / 'chromium-profile'}", "--virtual-time-budget=5000",
           "--window-size=1280,2000", "--dump-dom", probed.as_uri()]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    match = re.search(r'<pre id="probe">(.*?)</pre>', result.stdout, re.DOTALL)
    assert match, f"the page did not finish loading in Chromium:\n{result.stderr[-2000:]}"
    return json.loads(match.group(1).replace("&quot;", '"').replace("&amp;", "&").replace("&lt;", "<")
                      .replace("&gt;", ">"))


def assert_self_contained(text: str) -> None:
    assert not re.search(r"""(src|href)\s*=\s*["'](?!data:|#)""", text), "the page loads something from outside"
    assert "url(" not in text and "@import" not in text


@pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed (/usr/bin/chromium)")
def test_sara_report_renders_in_chromium(sara_run: Path, tmp_path: Path):
    page = write_report(sara_run)
    assert page == sara_run / "report.html"
    text = page.read_text(encoding="utf-8")
    assert_self_contained(text)
    status = open_in_chromium(page, tmp_path)
    assert status["errors"] == []
    assert status["broken"] == []
    assert status["images"] >= 6  # weakest views and pair thumbnails
    assert status["empty_svgs"] == 0 and status["svgs"] >= 6
    scores = read_scores(sara_run / "scores.csv")
    assert status["edges"] == len(set(scores.pairs) | set(load_run(sara_run).pairs))
    assert status["graph_width"] > 300


@pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed (/usr/bin/chromium)")
def test_report_without_scores_or_model_renders(bare_run: Path, tmp_path: Path):
    page = write_report(bare_run)
    text = page.read_text(encoding="utf-8")
    assert "force-directed layout" in text and "only the SARA pair source scores pairs" in text
    assert "No model was built" in text
    status = open_in_chromium(page, tmp_path)
    assert status["errors"] == [] and status["broken"] == []
    assert status["edges"] == len(load_run(bare_run).pairs)


def test_chromium_probe_catches_errors(tmp_path: Path):
    """The check can fail: a script error and a missing image are both reported."""
    if not CHROMIUM.exists():
        pytest.skip("Debian's chromium is not installed (/usr/bin/chromium)")
    page = tmp_path / "bad.html"
    page.write_text("<!DOCTYPE html><html><head></head><body><img src=\"data:image/png;base64,AAAA\" alt=\"x\">"
                    "<script>undefinedFunction();</script></body></html>")
    status = open_in_chromium(page, tmp_path)
    assert status["broken"] == ["x"]
    assert any("undefinedFunction" in e for e in status["errors"])


def test_report_content(sara_run: Path):
    data = load_run(sara_run)
    text = write_report(sara_run, sara_run / "copy.html").read_text(encoding="utf-8")
    for title in ("View graph", "Cameras and points from above", "Pairs against exhaustive matching",
                  "Pre-matching scores", "Weakest views", "Selected pairs", "Time per stage", "Reconstruction",
                  "Evaluation against ground truth"):
        assert title in text
    score = data.config["score"]
    assert f"min {score['min_overlap']}" in text and f"min {score['min_inliers']}" in text
    assert text.count("data:image/jpeg;base64,") >= 6
    assert "camera positions seen from above" in text
    assert data.agreement is not None and data.agreement.checked > 0
    assert f"verified pairs that contradict it</th><td>{len(data.agreement.contradicted)} of {data.agreement.checked}" \
        in text
    s = data.scores
    more = [e for e in range(len(s.pairs)) if s.num_inliers_all[e] > s.num_inliers[e]]
    assert more and f"{s.num_inliers[more[0]]} inliers ({s.num_inliers_all[more[0]]} of all matches)" in text


def test_the_report_says_when_another_mapper_built_the_model(sara_run: Path):
    """A global model its pairs contradicted is mapped again by the incremental mapper: the report's
    Reconstruction section says which mapper built model 0, only when it is not the one asked for."""
    from sara.report import sections

    data = load_run(sara_run)
    assert ">mapper</th>" not in sections.reconstruction(data)
    data.run["config"]["map"]["mapper"] = "global"
    data.run["stages"]["map"]["mapper"] = "incremental"
    assert ">mapper</th><td>incremental: the global mapper's model was contradicted by its pairs" \
        in sections.reconstruction(data)


def test_the_report_says_when_the_lens_distortion_was_held(sara_run: Path):
    """The map stage's retry with the distortion held built model 0: the Reconstruction section says so."""
    from sara.report import sections

    data = load_run(sara_run)
    assert "lens distortion" not in sections.reconstruction(data)
    data.run["stages"]["map"]["distortion_held"] = True
    assert ">lens distortion</th><td>held while mapping" in sections.reconstruction(data)


def test_the_report_keeps_the_runs_advice_and_the_two_view_points(sara_run: Path):
    """The warnings given before matching (cameras from guessed focal lengths, SIFT starved), after
    mapping (views moving straight ahead) and an update's counts are in an Advice section, absent
    when the run gave none (report.md's advice too); how the spanning tree was ranked is said under
    the pairs; a model that needed the points seen in two views says so in the
    Reconstruction section."""
    from sara.report import sections

    data = load_run(sara_run)
    assert sections.advice(data) == "" and ">points</th>" not in sections.reconstruction(data)
    data.run["stages"]["extract"]["cameras_guessed"] = [5, 5]
    data.run["stages"]["update"] = {"num_added": 0, "num_removed": 0, "num_changed": 0, "num_renamed": 2}
    data.run["stages"]["map"]["two_view_points"] = True
    data.run["stages"]["extract"]["panoramas"] = data.run["stages"]["extract"]["num_images"]
    data.run["stages"]["map"]["forward_start"] = True
    text = sections.advice(data)
    assert "<h2>Advice</h2>" in text and "5 of the 5 cameras" in text and "2 renamed" in text
    assert "360-degree camera" in text and "move along their optical axes" in text
    assert ">points</th><td>those seen in two views only" in sections.reconstruction(data)
    data.run["stages"]["pairs"].update(tree_overlap="best", field_of_view_deg=82.0, moving_ahead=True)
    assert ("The spanning tree by the paper&#x27;s weight (82-degree field of view, views moving along their "
            "optical axes).") in sections.pairs_against_exhaustive(data)
    plain = render_report(RunReport(sara_run, sara_run, data.run["config"], data.run["stages"]))
    assert "## Advice" in plain and "5 of the 5 cameras" in plain and "move along their optical axes" in plain
    assert "## Advice" not in (sara_run / "report.md").read_text()  # the run itself gave none


def test_the_report_says_how_a_contradicted_first_model_was_set_right(sara_run: Path):
    """Mended at its seam, or mapped again under other seeds: the Reconstruction section says which."""
    from sara.report import sections

    data = load_run(sara_run)
    assert "first model" not in sections.reconstruction(data)
    stage = data.run["stages"]["map"]
    stage.update(remaps=1, seed=1)
    assert ">first model</th><td>contradicted by its verified pairs: mapped again 1 time(s) under other seeds, " \
           "seed 1 kept" in sections.reconstruction(data)
    stage.update(remaps=0, mended=True, first_model_pairs_contradicted=0, first_model_pairs_checked=26170)
    assert ">first model</th><td>contradicted by its verified pairs: mended at the seam" \
        in sections.reconstruction(data)
    assert "models of the rounds" not in sections.reconstruction(data)
    data.run["stages"]["rounds"] = {"history": [{"role": "repair", "continued_pairs_contradicted": 0},
                                                {"role": "fill", "continued_pairs_contradicted": 3,
                                                 "continued_mended": True}]}
    assert ">models of the rounds</th><td>contradicted by their verified pairs after the fill round(s): mended" \
        in sections.reconstruction(data)


def test_no_run_is_a_clear_error(tmp_path: Path):
    with pytest.raises(FileNotFoundError, match="no sara run"):
        write_report(tmp_path)


def test_top_down_frame_is_the_ground_plane():
    """Cameras on a circle in z = 1 looking at the origin, COLMAP axes (y down = -z world): up is +z."""
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    centers = np.stack([3 * np.cos(angles), 2 * np.sin(angles), np.ones(8)], 1)
    rotations = []
    for c in centers:
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        rotations.append(np.stack([x, np.cross(z, x), z]))  # rows: camera axes in world
    basis = top_down_frame(centers, np.array(rotations))
    np.testing.assert_allclose(basis @ basis.T, np.eye(2), atol=1e-9)
    np.testing.assert_allclose(basis @ [0, 0, 1.0], [0, 0], atol=0.2)  # orthogonal to up (cameras tilt down)
    np.testing.assert_allclose(np.abs(basis[0]), [1, 0, 0], atol=0.2)  # x: the long side of the ellipse
    assert np.cross(basis[0], basis[1])[2] > 0  # seen from above, not mirrored


def test_graph_layout_is_deterministic_and_spreads_nodes():
    edges = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5]])
    a, b = graph_layout(6, edges), graph_layout(6, edges)
    np.testing.assert_array_equal(a, b)
    dist = np.linalg.norm(a[:, None] - a[None], axis=2)
    assert np.all(dist[~np.eye(6, dtype=bool)] > 1e-3)
    assert dist[0, 1] < dist[0, 4]  # neighbours closer than strangers


def test_histogram_marks_the_threshold():
    svg = histogram_svg(np.array([0.1, 0.2, 0.9]), [("all", np.ones(3, bool), "#000")], title="t",
                        threshold=0.5, threshold_label="min 0.5", upper=1.0)
    x = re.search(r'<line x1="([\d.]+)" y1="17"', svg)
    assert x and abs(float(x.group(1)) - (34 + 0.5 * (340 - 34 - 8))) < 0.1
    assert svg.count("<rect") == 3


def test_example_pairs_show_each_role(sara_run: Path):
    data = load_run(sara_run)
    selected, rejected = example_pairs(data, count=8)
    roles = {data.scores.role[e] for e in selected}
    present = {r for r in data.scores.role if r in ("tree", "loop", "anchor", "weak")}
    assert present <= roles
    assert all(data.scores.role[e] == "rejected" for e in rejected)


def test_pairs_added_after_the_first_round_are_drawn_by_what_added_them(sara_run: Path):
    from sara.io import records

    data = load_run(sara_run)
    roles = data.edge_roles()
    first = {p for p, r in zip(data.scores.pairs, data.scores.role) if r in SELECTED_ROLES}
    added = [p for p in data.pairs if p not in first]
    assert added  # the synthetic run adds pairs for weak views (and may run the pose-guided round)
    for stage, role in (("support", "support"), ("pose_guided", "pose-guided")):
        listed = {tuple(sorted(p)) for p in (records.done_info(sara_run, stage) or {}).get("pairs", [])}
        assert all(roles[p] == role for p in listed)
    assert {roles[p] for p in added} <= {"support", "pose-guided", "repair"}
    assert "support" in {roles[p] for p in added}
    text = write_report(sara_run, sara_run / "roles.html").read_text(encoding="utf-8")
    assert 'data-role="support"' in text


def _figcaptions(text: str, heading: str) -> list[str]:
    """The captions under one <h3> of the "Views and pairs" section, tags removed."""
    part = text.split(f"<h3>{heading}</h3>", 1)[1].split("<h3>", 1)[0].split("</section>", 1)[0]
    return [re.sub(r"<[^>]+>", "|", c) for c in re.findall(r"<figcaption>(.*?)</figcaption>", part)]


def test_pair_captions_tell_capped_pairs_apart(sara_run: Path, tmp_path: Path):
    """A well-textured scene: every selected pair has all b best matches as inliers, so O and w are the
    same capped value for all. The captions still differ, by the inliers among all mutual matches."""
    out = tmp_path / "capped"
    shutil.copytree(sara_run, out)
    table, roles = read_scores_csv(out / "scores.csv")
    selected = np.array([r in SELECTED_ROLES for r in roles])
    b, m = 50, 1024
    table.num_matches[selected] = b
    table.num_inliers[selected] = b
    table.overlap[selected] = b / m
    table.weight[selected] = b / m
    table.num_inliers_all[selected] = 100 + 7 * np.arange(int(selected.sum()))
    write_scores_csv(out / "scores.csv", table, roles)
    captions = _figcaptions(write_report(out).read_text(encoding="utf-8"), "Selected pairs")
    assert len(captions) >= 2
    first_lines = [c.split("|O=")[0] for c in captions]
    assert len(set(first_lines)) == len(first_lines), first_lines
    for caption in captions:
        shown = int(re.search(r"([\d,]+) inliers among all mutual matches", caption).group(1).replace(",", ""))
        assert shown in set(table.num_inliers_all[selected].tolist())
        assert f"O={b / m:.4f} ({b} of the {b} best matches, all inliers: the cap)" in caption


def test_captions_name_what_each_number_is(sara_run: Path):
    data = load_run(sara_run)
    s = data.scores
    selected, _ = example_pairs(data)
    captions = _figcaptions(write_report(sara_run, sara_run / "captions.html").read_text(encoding="utf-8"),
                            "Selected pairs")
    for e, caption in zip(selected, captions):
        assert f"{s.num_inliers_all[e]:,} inliers among all mutual matches" in caption
        assert f"of the {s.num_matches[e]} best matches" in caption and "parallax P=" in caption
        if s.pairs[e] in data.verified:
            assert f"{data.verified[s.pairs[e]]:,} verified matches" in caption


def test_thumbnails_say_how_many_they_show(sara_run: Path):
    data = load_run(sara_run)
    text = write_report(sara_run, sara_run / "counts.html").read_text(encoding="utf-8")
    selected, rejected = example_pairs(data)
    num_selected = sum(r in SELECTED_ROLES for r in data.scores.role)
    assert 0 < len(selected) < num_selected  # the synthetic run selects more pairs than the page shows
    assert f"{len(selected)} of {num_selected} selected pairs shown (the best of each role" in text
    assert f"of {len(data.names)} views shown" in text
    if rejected:
        num_rejected = data.scores.role.count("rejected")
        assert f"{len(rejected)} of {num_rejected} rejected candidates shown" in text


def test_page_ends_with_the_next_commands(sara_run: Path, bare_run: Path):
    text = write_report(sara_run, sara_run / "next.html").read_text(encoding="utf-8")
    assert "<h2>Next</h2>" in text and text.index("<h2>Next</h2>") > text.index("Reconstruction")
    commands = re.search(r'<pre class="cmds">(.*?)</pre>', text, re.DOTALL).group(1).splitlines()
    out = str(sara_run.resolve())
    formats = list(FORMATS)
    assert [shlex.split(c)[:2] for c in commands] == [["sara", "export"]] * len(formats) + [["sara", "report"]]
    assert formats and set(formats) >= {"3dgs", "nerfstudio", "colmap"}
    for command, fmt in zip(commands, formats):
        assert shlex.split(command) == ["sara", "export", out, str(sara_run.resolve() / fmt), "--format", fmt]
    assert shlex.split(commands[-1]) == ["sara", "report", out]
    bare = write_report(bare_run).read_text(encoding="utf-8")
    assert "<h2>Next</h2>" in bare and "sara export " not in bare and f"sara report {bare_run.resolve()}" in bare


def test_style_and_script_come_from_package_data(sara_run: Path):
    """The page's CSS and JS are files of the package, declared as package data so a wheel ships them."""
    folder = resources.files("sara.report").joinpath("assets")
    text = write_report(sara_run, sara_run / "assets.html").read_text(encoding="utf-8")
    for name in ASSETS:
        content = folder.joinpath(name).read_text(encoding="utf-8")
        assert content.strip() and asset(name) == content and content in text
    source = "".join(p.read_text(encoding="utf-8") for p in Path(write_report.__code__.co_filename).parent.glob("*.py"))
    assert "body{" not in source and "addEventListener" not in source  # not inline in the code any more
    pyproject = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text(encoding="utf-8"))
    patterns = pyproject["tool"]["setuptools"]["package-data"]["sara"]
    package = Path(write_report.__code__.co_filename).parents[1]
    declared = {p.relative_to(package).as_posix() for pattern in patterns for p in package.glob(pattern)}
    assert {f"report/assets/{name}" for name in ASSETS} <= declared


def test_a_round_of_another_pair_source_is_drawn_in_its_own_role(sara_run: Path):
    """A pair source's rounds may name roles this page does not know: their edges are drawn and listed."""
    data = load_run(sara_run)
    first = {p for p, r in zip(data.scores.pairs, data.scores.role) if r in SELECTED_ROLES}
    added = [p for p in data.pairs if p not in first]
    data.added = {**data.added, added[0]: "next-view"}
    text = render(data)
    graph = text.split('<svg id="viewgraph"', 1)[1].split("</svg>", 1)[0]
    assert 'class="edges role-next-view"' in graph and graph.count("<line") == len(data.edge_roles())
    assert 'data-role="next-view"' in text and "<td>next-view</td><td>1</td>" in text


def test_the_next_commands_run(sara_run: Path, tmp_path: Path, capsys):
    """The page's commands work as printed, through the command line's entry point."""
    from sara.cli import main

    out = tmp_path / "run"
    shutil.copytree(sara_run, out, ignore=shutil.ignore_patterns("*.html", "*.lock"))
    text = write_report(out).read_text(encoding="utf-8")
    commands = [shlex.split(c) for c in re.search(r'<pre class="cmds">(.*?)</pre>', text, re.DOTALL)
                .group(1).splitlines()]
    for argv in (c for c in commands if c[1] == "report" or c[-1] == "colmap"):
        assert main(argv[1:] + ["--quiet"]) == 0, argv
    assert (out / "colmap" / "sparse" / "0").is_dir() and (out / "report.html").exists()
    assert f"report: {out / 'report.html'}" in capsys.readouterr().out


def test_added_pairs_are_named_from_the_ledger_or_the_records_of_sara_0_1(tmp_path: Path) -> None:
    from sara.io import records
    from sara.report import _added_roles

    old = tmp_path / "old"
    records.mark_done(old, "support", "k", {"pairs": [["b", "a"]]})
    records.mark_done(old, "pose_guided", "k", {"pairs": [["c", "d"]]})
    assert _added_roles(old) == {("a", "b"): "support", ("c", "d"): "pose-guided"}
    new = tmp_path / "new"
    records.mark_done(new, "support", "k", {"pairs": [["a", "b"]]})  # the ledger wins where there is one
    records.mark_done(new, "rounds", "k", {"added": {"two-apart": [["a", "c"]]}})
    assert _added_roles(new) == {("a", "c"): "two-apart"}
