"""`report.html`: one self-contained page that shows why the pairs were chosen and what came of them.

Opens without a network: inline CSS, inline SVG figures, thumbnails as base64 JPEG, a few lines of
inline JavaScript (legend toggles). The CSS and JavaScript are files of the package
(`sara/report/assets/`), read once and written into every page. Sections, each present when the run
has the data for it:

1. summary cards; 2. the view graph over the reconstructed camera positions seen from above (a
force-directed layout when there is no model), edges coloured by role, rejected candidates faint;
3. a top-down plot of the cameras and the coloured 3D points; 4. pairs against exhaustive matching;
5. histograms of overlap O, parallax P, RANSAC inliers and weight w with the scorer's thresholds;
6. thumbnails of the weakest views and of selected and rejected pairs, captioned with the numbers
that tell them apart; 7. time per stage; 8. the reconstruction; 9. the evaluation against ground
truth (`metrics.json`); 10. the advice the run gave (low texture, guessed cameras, an update);
11. the commands to run next (export the model, rebuild the page).

`sara.report.sections` writes sections 1-5 and 7-11, `sara.report.thumbnails` section 6, and
`sara.report.svg` draws the figures.
"""

from __future__ import annotations

import logging
from functools import cache
from importlib import resources
from pathlib import Path

from ..io import write_text_atomic
from . import RunData, load_run, sections
from .markup import esc
from .thumbnails import Thumbnails, thumbnails_section

logger = logging.getLogger(__name__)

REPORT_NAME = "report.html"
#: the page's style sheet and script, package data beside this module
ASSETS = ("report.css", "report.js")


def write_report(out_dir: Path, dest: Path | None = None) -> Path:
    """Write `out_dir/report.html` (or `dest`) for the run in `out_dir`; returns its path.

    Works for every pair source (SARA's scores are optional) and for runs without a model.
    """
    data = load_run(Path(out_dir))
    dest = Path(dest) if dest is not None else Path(out_dir) / REPORT_NAME
    write_text_atomic(dest, render(data))
    logger.info("report: %s", dest)
    return dest


@cache
def asset(name: str) -> str:
    """The text of one of :data:`ASSETS`, read from the installed package (a wheel ships them)."""
    if name not in ASSETS:
        raise ValueError(f"unknown report asset {name!r}; the assets are {', '.join(ASSETS)}")
    return resources.files(__package__).joinpath("assets", name).read_text(encoding="utf-8")


def render(data: RunData) -> str:
    """The whole page as one HTML string."""
    thumbs = Thumbnails(data.images_root)
    figures = f"<div class=\"row\">{sections.view_graph(data)}{sections.top_down(data)}</div>"
    tables = f"<div class=\"row\">{sections.reconstruction(data)}{sections.evaluation(data)}</div>"
    parts = [sections.summary(data), figures, sections.pairs_against_exhaustive(data), sections.scores(data),
             thumbnails_section(data, thumbs), sections.timing(data), tables, sections.advice(data),
             sections.next_steps(data)]
    title = f"sara report: {data.out_dir.resolve().name}"
    body = "".join(s for s in parts if s)
    return (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
            f"<title>{esc(title)}</title><style>\n{asset('report.css')}</style></head><body>"
            f"<h1>{esc(title)}</h1><p class=\"sub\">{esc(str(data.out_dir.resolve()))} &middot; pair source "
            f"<b>{esc(data.method)}</b>{_versions(data)}</p>{body}<script>\n{asset('report.js')}</script></body></html>\n")


def _versions(data: RunData) -> str:
    """The sara version and those of the libraries run.json records, for the page's subtitle."""
    versions = data.run.get("versions", {})
    parts = [f"sara {data.run['sara_version']}"] if data.run.get("sara_version") else []
    parts += [f"{k} {v}" for k, v in versions.items() if k != "python"]
    return (" &middot; " + esc(", ".join(parts))) if parts else ""
