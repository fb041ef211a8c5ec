"""The focal length of a shared camera, from the images, where nothing else gives it.

Without EXIF or known intrinsics COLMAP starts from a prior of 1.2 x the larger image side (a field
of view of about 45 degrees). For a long lens that prior is several times too short (a 11-degree
field of view: 4x), the pre-matching scorer's essential matrices and triangulation angles are then
wrong, and the mapper's first models split.

For the true focal length f, the essential matrix E = K^T F K of a pair has two equal non-zero
singular values. Over a log-spaced grid of f (principal point at the image centre, no distortion),
the cost of a pair is (s1 - s2) / s1 with s1 >= s2 the two largest singular values of K^T F K, and the
estimate is the f where the median cost over pairs is smallest.

Measured on the shared scenes: within 1% of the true focal
length on the three Strecha scenes, 1,930-3,064 px against 2,563 px on bm-moldGoldCape (depending
on the pairs and RANSAC settings), and 1.9-2.8x the prior on quarter-size centre crops of two
Strecha scenes (true: 3x). On a turntable capture
(Middlebury's temples: every optical axis through the object) the problem is degenerate and the
estimate falls to a fraction of the true value, and it always falls *below* the prior there. Hence
sara replaces the prior only when the estimate is longer than it by at least `LONGER_THAN_PRIOR`.

Whether an estimate can be trusted at all shows in the shape of the cost curve
(`FocalEstimate.sound`): on a general capture the cost rises steeply below the estimate and most
pairs, taken alone, put their own best focal length near it; on the turntables the curve is flat
below the estimate and the pairs disagree. A sound estimate gives the field of view, which decides
what kind of spanning tree the selection builds (`sara.pairs.sara.field_of_view`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Container
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from .. import colmap
from ..descriptors import mutual_nearest_neighbours
from ..io.h5 import FeatureCache, Features

logger = logging.getLogger(__name__)

#: focal lengths tried, as multiples of the larger image side
GRID = np.geomspace(0.25, 8.0, 61)
#: pairs of images close in name order that are tried (consecutive frames first)
MAX_PAIRS = 40
#: a pair counts when its fundamental matrix has at least this many inliers
MIN_INLIERS = 40
#: an estimate needs at least this many such pairs
MIN_PAIRS = 8
#: the prior is replaced only by an estimate at least this many times longer: the estimate spreads
#: by +-30% with the pairs used on a narrow field of view, and a moderately better start did not pay
#: (bm-moldGoldCape, estimate 2.1x the prior: AUC@1 0.9251 against 0.9295 from the prior)
LONGER_THAN_PRIOR = 2.5
#: a sound estimate: the median cost at focal / SHARPNESS_STEP is at least MIN_SHARPNESS times that at
#: the estimate (the Strecha scenes at full, half and quarter size: 2.5-15; the turntables of Middlebury 1.1-1.2) ...
SHARPNESS_STEP = 1.5
MIN_SHARPNESS = 2.0
#: ... and at least MIN_AGREEMENT of the pairs have their own best focal length within AGREEMENT_STEP
#: of it (Strecha: 0.63-1.0; turntables 0.2-0.3)
AGREEMENT_STEP = 1.25
MIN_AGREEMENT = 0.5
#: a pair whose two epipoles lie within this share of the larger image side from the centre is left
#: out (kitti-seq1's 40 pairs: at most 0.026; the Strecha scenes, their quarter-size centre crops
#: included: at least 0.5): it gave a flat cost curve whose minimum, 9,808 px on one decoding of
#: those frames against a true 707 px, replaced the prior
AXIS_EPIPOLE = 0.2
#: features per image used (the strongest)
NUM_KEYPOINTS = 2048
#: matches per pair kept (the most similar mutual nearest neighbours)
NUM_MATCHES = 512
#: RANSAC threshold of the fundamental matrices, pixels, and its most trials
MAX_ERROR_PX = 1.5
MAX_TRIALS = 2000


@dataclass(frozen=True)
class FocalEstimate:
    focal_px: float
    num_pairs: int  # pairs with a fundamental matrix of MIN_INLIERS or more
    cost: float  # median cost at the estimate
    cost_at_prior: float  # median cost at the prior it is compared with
    sharpness: float = 0.0  # median cost at focal_px / SHARPNESS_STEP over the cost at the estimate
    agreement: float = 0.0  # share of pairs whose own best focal length is within AGREEMENT_STEP of it

    @property
    def sound(self) -> bool:
        """Whether the cost curve pins the estimate down (not the flat curve of a degenerate capture)."""
        return self.sharpness >= MIN_SHARPNESS and self.agreement >= MIN_AGREEMENT

    def replaces(self, prior_px: float) -> bool:
        """Whether this estimate should replace COLMAP's prior of `prior_px`: only when much longer.

        A sound estimate shorter than the prior (Strecha's 1,368 px against a prior of 1,843 px, the
        truth 1,380) is not applied: with it, SARA's AUC@1 fell on four of seven Strecha scenes and
        stand-ins and exhaustive matching's moved both ways. It still tells the
        field of view (`field_of_view_deg`).
        """
        return self.focal_px >= LONGER_THAN_PRIOR * prior_px


def field_of_view_deg(focal_px: float, width: int, height: int) -> float:
    """The angle the larger image side spans at this focal length (pinhole, degrees)."""
    return float(np.degrees(2.0 * np.arctan(max(width, height) / (2.0 * focal_px))))


def nearby_pairs(names: list[str], max_pairs: int = MAX_PAIRS) -> list[tuple[str, str]]:
    """Pairs one and two apart in name order (frames of a capture), at most `max_pairs`, spread evenly."""
    pairs = [(names[k], names[k + step]) for step in (1, 2) for k in range(len(names) - step)]
    if len(pairs) <= max_pairs:
        return pairs
    keep = np.unique(np.linspace(0, len(pairs) - 1, max_pairs).round().astype(int))
    return [pairs[k] for k in keep]


def focal_costs(fundamentals: list[np.ndarray], focals: np.ndarray, principal: tuple[float, float]) -> np.ndarray:
    """(len(focals), len(fundamentals)) cost (s1 - s2) / s1 of K^T F K for each focal length and pair."""
    F = np.stack(fundamentals)  # (P, 3, 3)
    K = np.zeros((len(focals), 1, 3, 3))
    K[:, 0, 0, 0] = K[:, 0, 1, 1] = focals
    K[:, 0, :2, 2] = principal
    K[:, 0, 2, 2] = 1.0
    s = np.linalg.svd(np.swapaxes(K, -1, -2) @ F @ K, compute_uv=False)  # (len(focals), P, 3), decreasing
    return (s[..., 0] - s[..., 1]) / np.maximum(s[..., 0], 1e-300)


def moves_along_the_axis(F: np.ndarray, width: int, height: int) -> bool:
    """Whether both epipoles of F lie within `AXIS_EPIPOLE` of the image centre: the camera moved
    (nearly) along its optical axis. Such a pair tells no focal length: K^T F K keeps two equal
    singular values at every focal length (frames of a car driving straight ahead)."""
    centre, side = np.array([width / 2.0, height / 2.0]), max(width, height)
    for M in (F, F.T):
        e = np.linalg.svd(M)[2][-1]
        if abs(e[2]) < 1e-12 or np.linalg.norm(e[:2] / e[2] - centre) > AXIS_EPIPOLE * side:
            return False
    return True


def estimate(fundamentals: list[np.ndarray], width: int, height: int, prior_px: float) -> FocalEstimate | None:
    """The focal length whose essential matrices are most consistent, or None with too few pairs
    (those of a camera moving along its optical axis do not count)."""
    fundamentals = [F for F in fundamentals if not moves_along_the_axis(F, width, height)]
    if len(fundamentals) < MIN_PAIRS:
        return None
    side = max(width, height)
    grid = GRID * side
    costs = focal_costs(fundamentals, grid, (width / 2.0, height / 2.0))  # (len(grid), pairs)
    median = np.median(costs, axis=1)
    best = int(np.argmin(median))
    found = float(grid[best])
    at_prior, below = (float(np.median(c)) for c in focal_costs(
        fundamentals, np.array([prior_px, found / SHARPNESS_STEP]), (width / 2.0, height / 2.0)))
    own = grid[np.argmin(costs, axis=0)]
    agreement = float(np.mean(np.abs(np.log(own / found)) <= np.log(AGREEMENT_STEP)))
    return FocalEstimate(found, len(fundamentals), float(median[best]), at_prior,
                         sharpness=below / max(float(median[best]), 1e-300), agreement=agreement)


def pair_fundamental(fa: Features, fb: Features, *, seed: int = 0) -> np.ndarray | None:
    """The fundamental matrix of two images' strongest features (mutual nearest neighbours), or None
    with fewer than `MIN_INLIERS` inliers."""
    matches = mutual_nearest_neighbours(fa.descriptors, fb.descriptors, NUM_MATCHES)[0]
    found = colmap.estimate_fundamental(fa.keypoints[matches[:, 0]], fb.keypoints[matches[:, 1]],
                                        max_error_px=MAX_ERROR_PX, max_trials=MAX_TRIALS, seed=seed)
    return found[0] if found is not None and found[1] >= MIN_INLIERS else None


class NearbyFundamentals:
    """The fundamental matrices of the `nearby_pairs` of a capture (of each video's frames apart,
    `groups`: name -> its video), fitted as the features of their images arrive: the SIFT
    extraction fits them while COLMAP is still extracting (`add` from its watch), so that the focal
    check costs next to nothing after it."""

    def __init__(self, names: list[str], *, seed: int = 0, groups: dict[str, str] | None = None) -> None:
        self.groups = groups or {}
        self.pairs, self.seed = self._nearby(names), seed
        self.found: dict[tuple[str, str], np.ndarray | None] = {}

    def _nearby(self, names: list[str]) -> list[tuple[str, str]]:
        return [pair for group in self._split(names).values() for pair in nearby_pairs(group)]

    def _split(self, names: list[str]) -> dict[str, list[str]]:
        by_group: dict[str, list[str]] = {}
        for name in names:
            by_group.setdefault(self.groups.get(name, ""), []).append(name)
        return by_group

    def add(self, read: Callable[[str], Features], ready: Container[str]) -> None:
        """Fit the pairs not fitted yet whose two images are `ready` (`read` gives their features,
        the strongest `NUM_KEYPOINTS` first). On one thread: beside COLMAP's extraction, which keeps
        every core busy, threaded BLAS and RANSAC only spin (twice the CPU time, measured), and the
        matches do not change with the machine's number of cores."""
        held: dict[str, Features] = {}
        with threadpool_limits(1):
            for a, b in self.pairs:
                if (a, b) in self.found or a not in ready or b not in ready:
                    continue
                fa, fb = (held[n] if n in held else held.setdefault(n, read(n)) for n in (a, b))
                self.found[(a, b)] = pair_fundamental(fa, fb, seed=self.seed)

    def fundamentals(self, names: list[str], read: Callable[[str], Features]) -> dict[str, list[np.ndarray]]:
        """Group ("" without groups) -> the matrices of the nearby pairs of its images among `names`
        (the images in the end: those set aside during extraction change the pairs), fitting those
        still missing."""
        self.pairs = self._nearby(names)
        self.add(read, set(names))
        return {group: [F for F in (self.found[pair] for pair in nearby_pairs(members)) if F is not None]
                for group, members in self._split(names).items()}


def estimate_from_features(features_path: Path, names: list[str], width: int, height: int,
                           prior_px: float, *, seed: int = 0) -> FocalEstimate | None:
    """Match pairs near in name order (mutual nearest neighbours of the strongest features), fit a
    fundamental matrix to each, and estimate the shared focal length from them."""
    with FeatureCache(features_path, top_k=NUM_KEYPOINTS, capacity=8) as cache:
        fundamentals = NearbyFundamentals(names, seed=seed).fundamentals(names, cache.get).get("", [])
    return estimate(fundamentals, width, height, prior_px)


def check_prior(db_path: Path, estimate_with: Callable[[int, int, float], FocalEstimate | None],
                names: list[str] | None = None, label: str = "") -> dict | None:
    """Replace COLMAP's focal prior of the shared camera (of the images `names`: the frames of one
    video) by an estimate from the images where that is clearly longer (`estimate_with(width,
    height, prior)`: `estimate` or `estimate_from_features`); what was found goes into the extract
    stage's record; `label` names the video in the messages."""
    camera = colmap.shared_camera(db_path, names)
    of = f" of {label}" if label else ""
    if camera is None or camera.has_prior_focal_length or camera.is_fisheye():  # EXIF gave it; or not a pinhole
        return None
    prior = float(camera.mean_focal_length())
    found = estimate_with(camera.width, camera.height, prior)
    if found is None:
        logger.info("focal length%s: too few pairs of neighbouring images that tell it (a camera moving straight "
                    "ahead tells none) to check COLMAP's prior (%.0f px)", of, prior)
        return {"prior_px": prior, "estimated_px": None, "applied": False}
    applied = found.replaces(prior)
    if applied:
        colmap.set_focal_length(db_path, camera.camera_id, found.focal_px)
        logger.warning("focal length%s: the images say %.0f px (%.1f-degree field of view), %.2fx COLMAP's prior "
                       "of %.0f px; starting from %.0f px (give extract.camera_params if you know it)", of,
                       found.focal_px, field_of_view_deg(found.focal_px, camera.width, camera.height),
                       found.focal_px / prior, prior, found.focal_px)
    else:
        logger.info("focal length%s: estimate %.0f px, prior %.0f px kept", of, found.focal_px, prior)
    return {"prior_px": prior, "estimated_px": found.focal_px, "applied": applied, "num_pairs": found.num_pairs,
            "cost": found.cost, "cost_at_prior": found.cost_at_prior, "sharpness": found.sharpness,
            "agreement": found.agreement, "sound": found.sound}
