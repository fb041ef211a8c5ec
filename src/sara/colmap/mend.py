"""Cutting a model at its seam, so that the mapper can register the views there again.

A first model that its own verified pairs contradict (`consistency`) is not always bent as a whole:
at 10,000 images SARA's first model of a synthetic street was within 0.6 units of the truth (643
across) everywhere but in two stretches of about 150 frames where the street passes a place again,
glued there 8-60 units off. Taking out only the views of the contradicting pairs does not help: the
rest of each stretch still holds it in place, and continuing the model puts the views back where
they were. Taken out with every view up to two verified pairs away from them, the stretches go out
whole, and continuing the rest registers them again from both sides: 0 of 26,170 pairs
contradicting, AUC@1 0.823 -> 0.855 in 5-9 minutes, where mapping all 10,000 views again on one
thread took about 90 (lab/notes/SCALE.md, "Mending the seam by cutting it out").
"""

from __future__ import annotations

from collections.abc import Set
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from .consistency import Agreement
from .database import open_pycolmap_database
from .sfm import MappedModels

#: the views taken out are those of the contradicting pairs and every view up to this many verified
#: pairs away from them (10,000-image street: none away left the stretches in place; one and two
#: mended them alike, as on a bent 1,000-image model; two leaves room for a wider stretch)
SEAM_HOPS = 2
#: a cut keeping less of the model than this share is no local mend: the model is mapped again instead
MIN_KEPT_SHARE = 0.5


@dataclass(frozen=True)
class Cut:
    """What `cut_at_seam` took out of a model and kept."""

    taken_out: int  # views around the seam
    dropped: int  # views of smaller parts that no longer shared a 3D point with the largest
    kept: int  # views of the model written


def cut_at_seam(models: MappedModels, check: Agreement, db_path: Path, out: Path, *, min_num_inliers: int,
                hops: int = SEAM_HOPS) -> Cut | None:
    """Write to `out` the largest model of `models` without the views around the pairs of `check` that
    contradict it (those views and every view up to `hops` verified pairs of at least
    `min_num_inliers` inliers away), keeping only the largest part of the rest that shares 3D points.
    None (nothing written) when there is no contradicting pair or the part kept holds under
    `MIN_KEPT_SHARE` of the model's views."""
    seam = {view for pair in check.contradicted for view in pair}
    if not seam or not models.reconstructions:
        return None
    rec = pycolmap.Reconstruction(max(models.reconstructions.values(), key=lambda r: r.num_reg_images()))
    posed = {img.name: image_id for image_id, img in rec.images.items() if img.has_pose}
    around = _neighbourhood(seam & posed.keys(), _neighbours(db_path, posed.keys(), min_num_inliers), hops)
    for frame_id in {rec.image(posed[name]).frame_id for name in around}:  # a rig's images share a frame
        rec.deregister_frame(frame_id)
    parts = _parts(rec)
    kept = parts[0] if parts else set()
    if len(kept) < MIN_KEPT_SHARE * len(posed):
        return None
    for frame_id in {rec.image(image_id).frame_id for part in parts[1:] for image_id in part}:
        rec.deregister_frame(frame_id)
    out.mkdir(parents=True, exist_ok=True)
    rec.write(str(out))
    return Cut(len(around), len(posed) - len(around) - len(kept), len(kept))


def _neighbours(db_path: Path, names: Set[str], min_num_inliers: int) -> dict[str, set[str]]:
    """Name -> the names it shares a verified pair with (at least `min_num_inliers` inliers), among `names`."""
    out: dict[str, set[str]] = {}
    with open_pycolmap_database(db_path) as db:
        by_id = {img.image_id: img.name for img in db.read_all_images()}
        pair_ids, num_inliers = db.read_two_view_geometry_num_inliers()
    for pair_id, n in zip(pair_ids, num_inliers):
        a, b = (by_id[int(i)] for i in pycolmap.pair_id_to_image_pair(int(pair_id)))
        if n >= min_num_inliers and a in names and b in names:
            out.setdefault(a, set()).add(b)
            out.setdefault(b, set()).add(a)
    return out


def _neighbourhood(seam: set[str], neighbours: dict[str, set[str]], hops: int) -> set[str]:
    """`seam` and every name up to `hops` steps of `neighbours` away from it."""
    out, front = set(seam), set(seam)
    for _ in range(hops):
        front = {n for view in front for n in neighbours.get(view, ())} - out
        out |= front
    return out


def _parts(rec: pycolmap.Reconstruction) -> list[set[int]]:
    """The registered images of `rec` grouped by the 3D points they share, largest first."""
    parent = {image_id: image_id for image_id, img in rec.images.items() if img.has_pose}

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for point in rec.points3D.values():
        seen = np.unique([el.image_id for el in point.track.elements])
        first = root(int(seen[0]))
        for other in seen[1:]:
            parent[root(int(other))] = first
    groups: dict[int, set[int]] = {}
    for image_id in parent:
        groups.setdefault(root(image_id), set()).add(image_id)
    return sorted(groups.values(), key=len, reverse=True)
