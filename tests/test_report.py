"""report.html: built for a synthetic SARA run, a run without scores or model, and opened in headless
Chromium (Debian's `chromium`, installed by .ci/run) to check that it renders without a console
error and that every image loads, with no network."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from sara.config import make_config
from sara.pipeline import run
from sara.report import load_run, read_scores
from sara.report.html import (
    example_pairs,
    graph_layout,
    histogram_svg,
    top_down_frame,
    write_report,
)

CHROMIUM = Path("/usr/bin/chromium")

# Injected into a copy of the page: collect errors from the start, then report once everything loaded.
PROBE_HEAD = """<script>window.__errors = [];
window.addEventListener('error', function (e) { window.__errors.push('error: ' + (e.message || e.target.src)); }, true);
(function () { var orig = console.error; console.error = function () {
  window.__errors.push('console.error: ' + Array.prototype.join.call(arguments, ' ')); orig.apply(console, arguments); };
})();</script>"""
PROBE_TAIL = """<script>window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var broken = imgs.filter(function (im) { return !(im.complete && im.naturalWidth > 0); }).map(function (im) { return im.alt; });
  var svgs = Array.prototype.slice.call(document.querySelectorAll('svg'));
  var empty = svgs.filter(function (s) { var r = s.getBoundingClientRect(); return !(r.width > 0 && r.height > 0); }).length;
  var box = document.getElementById('viewgraph');
  var status = {images: imgs.length, broken: broken, errors: window.__errors, svgs: svgs.length, empty_svgs: empty,
                edges: document.querySelectorAll('#viewgraph line').length,
                graph_width: box ? box.getBoundingClientRect().width : 0};
  var pre = document.createElement('pre'); pre.id = 'probe'; pre.textContent = JSON.stringify(status);
  document.body.appendChild(pre);
});</script>"""


@pytest.fixture(scope="module")
def sara_run(synthetic_scene, tmp_path_factory) -> Path:
    images, gt = synthetic_scene
    out = tmp_path_factory.mktemp("report") / "out"
    run(make_config("sift-offline"), images, out, gt_dir=gt, progress=False)
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
    assert "force-directed layout" in text and "only the SARA pair source scores pairs" in text and "No model was built" in text
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
    s = data.scores
    more = [e for e in range(len(s.pairs)) if s.num_inliers_all[e] > s.num_inliers[e]]
    assert more and f"{s.num_inliers[more[0]]} inliers ({s.num_inliers_all[more[0]]} of all matches)" in text


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
    first = {p for p, r in zip(data.scores.pairs, data.scores.role) if r in ("tree", "loop", "anchor", "weak", "rescue")}
    added = [p for p in data.pairs if p not in first]
    assert added  # the synthetic run adds pairs for weak views (and may run the pose-guided round)
    for stage, role in (("support", "support"), ("pose_guided", "pose-guided")):
        listed = {tuple(sorted(p)) for p in (records.done_info(sara_run, stage) or {}).get("pairs", [])}
        assert all(roles[p] == role for p in listed)
    assert {roles[p] for p in added} <= {"support", "pose-guided", "repair"}
    assert "support" in {roles[p] for p in added}
    text = write_report(sara_run, sara_run / "roles.html").read_text(encoding="utf-8")
    assert 'data-role="support"' in text
