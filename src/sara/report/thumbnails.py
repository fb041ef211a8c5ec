"""The "Views and pairs" section: thumbnails of the weakest views and of example pairs with their scores.

Captions lead with the numbers that tell pairs apart. The overlap O counts the RANSAC inliers among
the b best matches, so on a well-textured scene most selected pairs have all b of them inliers and
share O = b / sqrt(N0 N1); with a parallax above the saturation angle they share w too. The inliers
among all mutual matches, the parallax and the verified matches of the full matching still differ.
"""

from __future__ import annotations

import base64
import io
import logging
from collections import Counter
from pathlib import Path

import numpy as np

from ..io.pairs import Pair
from . import SELECTED_ROLES, RunData, Scores
from .markup import esc, section

logger = logging.getLogger(__name__)

THUMB_PX = 200
NUM_WEAKEST_VIEWS = 5
NUM_EXAMPLE_PAIRS = 4


class Thumbnails:
    """Base64 JPEG thumbnails of the run's images, made once each."""

    def __init__(self, root: Path | None, max_px: int = THUMB_PX):
        self.root, self.max_px = root, max_px
        self._cache: dict[str, str | None] = {}

    def __call__(self, name: str) -> str | None:
        if name not in self._cache:
            self._cache[name] = self._make(name)
        return self._cache[name]

    def _make(self, name: str) -> str | None:
        if self.root is None or not (self.root / name).is_file():
            return None
        from PIL import Image

        try:
            with Image.open(self.root / name) as im:
                im.draft("RGB", (self.max_px * 2, self.max_px * 2))
                rgb = im.convert("RGB")
                rgb.thumbnail((self.max_px, self.max_px))
                buf = io.BytesIO()
                rgb.save(buf, format="JPEG", quality=72)
        except OSError as err:
            logger.warning("report: no thumbnail of %s (%s)", name, err)
            return None
        return "data:image/jpeg;base64," + base64.b64encode(buf.getvalue()).decode("ascii")

    def img(self, name: str) -> str:
        uri = self(name)
        if uri is None:
            return f"<div class=\"noimg\">{esc(name)}</div>"
        return f"<img src=\"{uri}\" alt=\"{esc(name)}\" title=\"{esc(name)}\">"


def weakest_views(data: RunData, count: int = NUM_WEAKEST_VIEWS) -> list[tuple[str, str]]:
    """(name, why) of the views most at risk: left out of the model, then fewest 3D points (or matched pairs)."""
    roles = data.edge_roles()
    degree = Counter(n for p, r in roles.items() if r not in ("unselected", "rejected") for n in p)
    if data.model is not None:
        obs = dict(zip(data.model.names, data.model.num_observations.tolist()))
        left_out = [(n, "not registered") for n in data.names if n not in obs]
        weak = sorted(obs, key=lambda n: (obs[n], n))
        ranked = left_out + [(n, f"{obs[n]} 3D points") for n in weak]
    else:
        ranked = [(n, "") for n in sorted(data.names, key=lambda n: (degree[n], n))]
    return [(n, ", ".join(x for x in (why, f"{degree[n]} matched pairs") if x)) for n, why in ranked[:count]]


def example_pairs(data: RunData, count: int = NUM_EXAMPLE_PAIRS) -> tuple[list[int], list[int]]:
    """Rows of `scores.csv` to show: selected (the best of each role, then the weakest) and rejected
    (the most overlapping of each reason first).

    Selected pairs rank by w, then by the inliers among all mutual matches: w ties wherever O is
    capped at the b best matches, and the name order alone would then pick the examples.
    """
    s = data.scores
    if s is None:
        return [], []
    order = np.lexsort((-_inliers_all(s), -s.weight))  # stable: w first, then all-match inliers
    selected = [e for e in order if s.role[e] in SELECTED_ROLES]
    chosen: list[int] = []
    for role in SELECTED_ROLES:
        chosen += [e for e in selected if s.role[e] == role and e not in chosen][:1]
    if selected and selected[-1] not in chosen:
        chosen.append(selected[-1])
    chosen += [e for e in selected if e not in chosen]
    rejected = [e for e in np.argsort(-s.overlap, kind="stable") if s.role[e] == "rejected"]
    first: list[int] = []
    for reason in dict.fromkeys(s.reason[e] for e in rejected):
        first.append(next(e for e in rejected if s.reason[e] == reason))
    first += [e for e in rejected if e not in first]
    return [int(e) for e in chosen[:count]], [int(e) for e in first[:count]]


def _inliers_all(s: Scores) -> np.ndarray:
    """(E,) the inliers among all mutual matches (those among the b best in files that lack them)."""
    return s.num_inliers if s.num_inliers_all is None else np.maximum(s.num_inliers_all, s.num_inliers)


def degrees(value: float) -> str:
    """An angle for a caption; a parallax the scorer did not measure says so."""
    return f"{value:.2f}\u00b0" if np.isfinite(value) else "not measured"


def pair_caption(s: Scores, e: int, verified: dict[Pair, int]) -> str:
    """The caption of row `e` of `s`: what tells the pair apart first (the inliers among all mutual
    matches, the parallax, the verified matches of the full matching), then O and w and whether O
    is at its cap (every one of the b best matches an inlier), then the names."""
    a, b = s.pairs[e]
    label = s.role[e] if s.accepted[e] else f"rejected: {s.reason[e] or 'not accepted'}"
    first = [f"<b>{esc(label)}</b>", f"{int(_inliers_all(s)[e]):,} inliers among all mutual matches",
             f"parallax P={degrees(s.parallax_deg[e])}"]
    if (a, b) in verified:
        first.append(f"{verified[(a, b)]:,} verified matches")
    if s.num_matches is None:
        best = f"{s.num_inliers[e]} inliers among the best matches"
    else:
        capped = 0 < s.num_matches[e] <= s.num_inliers[e]
        best = f"{s.num_inliers[e]} of the {s.num_matches[e]} best matches"
        best += ", all inliers: the cap" if capped else ""
    second = f"O={s.overlap[e]:.4f} ({best}) &middot; w={s.weight[e]:.4f}"
    return f"{' &middot; '.join(first)}<br>{second}<br>{esc(a)} &ndash; {esc(b)}"


def _shown_note(shown: int, total: int, what: str, how: str) -> str:
    return f"<p class=\"note\">{shown} of {total} {what} shown ({how}).</p>"


def _pairs_html(s: Scores, verified: dict[Pair, int], thumbs: Thumbnails, rows: list[int]) -> str:
    cards = [f"<figure class=\"pair\"><div>{thumbs.img(s.pairs[e][0])}{thumbs.img(s.pairs[e][1])}</div>"
             f"<figcaption>{pair_caption(s, e, verified)}</figcaption></figure>" for e in rows]
    return f"<div class=\"pairs\">{''.join(cards)}</div>"


def thumbnails_section(data: RunData, thumbs: Thumbnails) -> str:
    """Weakest views, then example selected and rejected pairs, each saying how many of how many it shows."""
    views = weakest_views(data)
    how = "left out of the model first, then fewest 3D points" if data.model is not None else "fewest matched pairs"
    body = "<h3>Weakest views</h3>" + _shown_note(len(views), len(data.names), "views", how)
    body += "<div class=\"thumbs\">" + "".join(
        f"<figure>{thumbs.img(n)}<figcaption><b>{esc(n)}</b><br>{esc(why)}</figcaption></figure>"
        for n, why in views) + "</div>"
    s = data.scores
    if s is not None:
        selected, rejected = example_pairs(data)
        num_selected = sum(r in SELECTED_ROLES for r in s.role)
        num_rejected = sum(r == "rejected" for r in s.role)
        added = len(set(data.pairs) - {p for p, r in zip(s.pairs, s.role) if r in SELECTED_ROLES})
        how = "the best of each role, then the weakest, by w and then the inliers among all mutual matches"
        if added:
            how += f"; {added} more pairs were matched after the first round, drawn in the view graph"
        if selected:
            body += "<h3>Selected pairs</h3>" + _shown_note(len(selected), num_selected, "selected pairs", how)
            body += _pairs_html(s, data.verified, thumbs, selected)
        if rejected:
            body += "<h3>Rejected candidates</h3>" + _shown_note(
                len(rejected), num_rejected, "rejected candidates", "the most overlapping of each reason first")
            body += _pairs_html(s, data.verified, thumbs, rejected)
    note = "" if data.images_root is not None else "The image folder recorded in run.json is not here: no thumbnails."
    return section("Views and pairs", body, note)
