"""`sara demo`: an offline self-test that needs nothing but the installed package.

Synthesises a scene with known poses, reconstructs it with SARA's pairs and with exhaustive pairs
through the same matching and mapping, evaluates both against the truth and prints the table. It
writes SARA's `report.html`, as `sara run` does, so the demo shows the page a real run leaves.
"""

from __future__ import annotations

from pathlib import Path

from .config import make_config
from .pipeline import run, share_features
from .report.html import write_report
from .synthetic import make_scene
from .tables import markdown_table

METHODS = ("sara", "exhaustive")
ROWS = (
    ("images registered", lambda r: f"{r.metrics['num_registered']}/{r.metrics['num_images_gt']}"),
    ("models", lambda r: str(r.metrics["num_components"])),
    ("pairs matched", lambda r: str(r.stages["pairs"]["num_pairs"])),
    ("pair selection (s)", lambda r: f"{r.stages['pairs']['time_s']:.2f}"),
    ("matching (s)", lambda r: f"{r.stages['match']['time_s']:.2f}"),
    ("AUC@5", lambda r: f"{r.metrics['auc']['5']:.3f}"),
    ("rotation error (deg, median)", lambda r: _fmt(r.metrics["rel_rotation_error_median_deg"])),
    ("3D points", lambda r: str(r.metrics["num_points3d"])),
)


def _fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.3f}"


def run_demo(out_dir: Path, *, num_images: int = 24, progress: bool = True) -> str:
    """Run the demo, write `out_dir/sara/report.html` and return the comparison table (Markdown)
    followed by where the model and the report are."""
    out_dir = Path(out_dir)
    images, gt = make_scene(out_dir / "scene", num_images=num_images)
    features = out_dir / "features"
    run(make_config("sift-offline"), images, features, progress=progress, stop_after="extract")
    reports = {}
    for method in METHODS:  # the same features for both: only the pairs differ
        conf = make_config("sift-offline", {"pairs.method": method})
        share_features(features, out_dir / method)
        reports[method] = run(conf, images, out_dir / method, gt_dir=gt, progress=progress)
    report_html = write_report(out_dir / "sara")
    table = markdown_table(["", *METHODS], [[label, *(get(reports[m]) for m in METHODS)] for label, get in ROWS])
    lines = [f"sara demo: synthetic scene of {num_images} images ({out_dir})", "", table, "",
             f"Model: {out_dir / 'sara' / 'sparse' / '0'}  (run record: {out_dir / 'sara' / 'report.md'})",
             f"Report: {report_html}  (open it in a browser: why these pairs, what came of them)"]
    return "\n".join(lines)
