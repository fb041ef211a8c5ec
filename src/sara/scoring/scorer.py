"""The pre-matching scorer: a cheap two-view geometry per candidate pair.

For a pair of images, the scorer

1. matches the top-M keypoints of each image (largest scale first) by mutual nearest neighbours
   of their L2-normalised descriptors and keeps the best ``num_matches`` by similarity (with
   ``max_descriptor_ratio`` < 1, only among those that pass Lowe's ratio test);
2. runs a short, seeded 5-point RANSAC for the essential matrix (poselib) on those matches;
3. triangulates the inliers (midpoint method) with the recovered relative pose and takes the
   parallax ``P`` as the median triangulation angle of the points in front of both cameras;
   but ``P = 0`` when a pure rotation (allowing for a wrong focal length) fits the inliers about
   as well as the essential matrix: then the 5-point pose is degenerate and its baseline spurious.

The triangulation angle is the angle at the 3D point between the rays to the two camera centres,
so the relative rotation does not count: a pure rotation or a near-duplicate pair has ``P ~ 0``.
From the inlier count and ``P`` come the overlap ``O = num_inliers / sqrt(N_i N_j)`` and the
weight ``w = O^alpha * g(P)^beta``, ``g(P) = min(P, sat) / sat``.

The b best matches bound that inlier count: on well-textured scenes most overlapping pairs have all
b of them inliers, so their weights tie, and a spanning tree of ``w`` is decided by the order of the
pairs (by name). The scorer therefore also counts ``num_inliers_all``: the mutual nearest neighbours
among *all* M keypoints that fit the pose RANSAC found (the same error threshold). It does not
saturate, and it ranks pairs by how many matches a full matching verifies better than
``num_inliers`` does. The spanning tree can use it
(`ScoreConfig.tree_overlap`; by default only where the field of view is known to be wide: trees of
the most overlapping pairs have short baselines, which long lenses pay for).

Frames: ``R, t`` is ``cam1_from_cam0`` (``x_cam1 = R x_cam0 + t``); normalised camera
coordinates are ``(x / z, y / z)`` of the point in the camera frame (undistorted).
"""

from __future__ import annotations

import logging
import math
import tempfile
import time
from collections import OrderedDict
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from .. import colmap
from ..config import ScoreConfig
from ..descriptors import descriptor_distance_ratios, l2_normalize, mutual_matches_from_similarity
from ..execute import Executor, SerialExecutor
from ..io.h5 import FeatureCache, Features
from ..io.scores import PairScores
from ..rotations import rotvec_from_matrix
from .twoview import RelativePose, estimate_relative_pose, inlier_parallax_deg, sampson_errors

if TYPE_CHECKING:
    from .journal import ScoreJournal

logger = logging.getLogger(__name__)

#: Why a pair is rejected, in the order the conditions are checked ("" when accepted).
REASONS = ("no_model", "few_inliers", "low_overlap", "low_parallax")


# ----------------------------------------------------------------------------------------
# One pair
# ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ViewFeatures:
    """What the scorer needs of one image (its top-M keypoints).

    Attributes:
        descriptors: (M, D) uint8 or float, as stored; normalised when matched.
        points_norm: (M, 2) float64 normalised, undistorted camera coordinates.
        focal_px: mean focal length in pixels (converts the pixel threshold).
        unit: the descriptors are already `l2_normalize`d (float32), as a `ViewStore` gives them.
    """

    descriptors: np.ndarray
    points_norm: np.ndarray
    focal_px: float
    unit: bool = False

    def __post_init__(self) -> None:
        if len(self.descriptors) != len(self.points_norm):
            raise ValueError(
                f"{len(self.descriptors)} descriptors but {len(self.points_norm)} keypoints"
            )

    @property
    def num_keypoints(self) -> int:
        return len(self.points_norm)

    @classmethod
    def from_features(cls, feats: Features, camera: Any) -> ViewFeatures:
        """From hloc-convention features and the image's pycolmap camera."""
        xy = colmap.hloc_to_colmap_keypoints(feats.keypoints)
        return cls(
            descriptors=np.asarray(feats.descriptors),
            points_norm=colmap.image_to_normalized(camera, xy),
            focal_px=colmap.mean_focal_px(camera),
        )


@dataclass(frozen=True)
class PairScore:
    """The score of one pair; see :func:`score_pair`."""

    num_matches: int
    num_inliers: int
    overlap: float
    parallax_deg: float  # NaN when not measured: the pair failed an earlier test
    weight: float  # 0 when the parallax was not measured
    accepted: bool
    reason: str  # one of REASONS, "" when accepted
    num_inliers_all: int = 0  # mutual nearest neighbours of all M keypoints that fit the pose
    rotvec: tuple[float, float, float] = (math.nan, math.nan, math.nan)  # cam1_from_cam0, radians
    direction: tuple[float, float, float] = (math.nan, math.nan, math.nan)  # unit t of cam1_from_cam0


def pair_weight(overlap: float, parallax_deg: float, conf: ScoreConfig) -> float:
    """``w = O^alpha * g(P)^beta`` with ``g(P) = min(P, sat) / sat``."""
    saturated = min(max(parallax_deg, 0.0), conf.parallax_saturation_deg) / conf.parallax_saturation_deg
    return float(max(overlap, 0.0) ** conf.alpha * saturated**conf.beta)


def tree_weights(scores: PairScores, conf: ScoreConfig) -> np.ndarray:
    """(P,) float64: the weight the spanning tree maximises, ``scores.weight`` but for the overlap.

    With ``conf.tree_overlap == "all"`` the overlap counts ``num_inliers_all`` instead of the b best
    matches' inliers (`score_pair`), so pairs whose b best matches are all inliers no longer tie:
    w scaled by ``(num_inliers_all / num_inliers)^alpha``. Rejected pairs keep weight 0.
    """
    weight = np.asarray(scores.weight, dtype=np.float64)
    if conf.tree_overlap == "best":
        return weight
    if conf.tree_overlap != "all":  # "auto" is resolved by the pair source (it needs the cameras)
        raise ValueError(f"tree_overlap must be 'best' or 'all' here, got {conf.tree_overlap!r}")
    inliers = np.maximum(scores.num_inliers, 1)
    return weight * (np.maximum(scores.num_inliers_all, inliers) / inliers) ** conf.alpha


def rejection_reason(
    found_model: bool, num_inliers: int, overlap: float, parallax_deg: float, conf: ScoreConfig
) -> str:
    """The first failed condition of :data:`REASONS`, or "" when the pair is accepted."""
    if not found_model:
        return "no_model"
    if num_inliers < conf.min_inliers:
        return "few_inliers"
    if overlap < conf.min_overlap:
        return "low_overlap"
    if parallax_deg < conf.min_parallax_deg:
        return "low_parallax"
    return ""


def score_pair(view0: ViewFeatures, view1: ViewFeatures, conf: ScoreConfig, *, seed: int = 0) -> PairScore:
    """Score one pair: mutual NN, short RANSAC, parallax, overlap, weight.

    ``num_inliers`` counts the RANSAC inliers among the b best matches; ``num_inliers_all`` the
    mutual nearest neighbours of all M keypoints within the same error of that pose (at least
    ``num_inliers``; 0 without a pose); ``parallax_deg`` is :func:`inlier_parallax_deg`;
    ``overlap`` is ``num_inliers / sqrt(N0 * N1)`` with N the keypoints used (at most M per image);
    ``rotvec`` the RANSAC pose's rotation (NaN without a pose): cycles of them test the pairs'
    consistency (`sara.selection.ambiguity`); ``direction`` its translation as a unit vector, camera
    0's centre seen from camera 1 (along the optical axis when the camera moves straight ahead).
    A pair that fails a test before the parallax one (no model, too few inliers, too little
    overlap) is not triangulated: nothing uses its parallax, which is NaN ("not measured"), and its
    weight is 0. On low-texture scenes most candidates fail so, and the parallax test was 40% of
    a pair's cost. The same views, settings and seed always give the same score.
    """
    similarity = _unit(view0) @ _unit(view1).T
    every, _ = mutual_matches_from_similarity(similarity)
    best = every
    if conf.max_descriptor_ratio < 1.0:  # the b best among the matches distinct in both images
        best = every[descriptor_distance_ratios(similarity, every) <= conf.max_descriptor_ratio]
    matches = best[: conf.num_matches]  # the best b, most similar first
    x0, x1 = view0.points_norm[matches[:, 0]], view1.points_norm[matches[:, 1]]
    max_error = conf.ransac_max_error_px * 2.0 / (view0.focal_px + view1.focal_px)
    pose = estimate_relative_pose(x0, x1, max_error=max_error, iterations=conf.ransac_iterations, seed=seed)
    num_inliers = 0 if pose is None else int(pose.inliers.sum())
    num_inliers_all = 0 if pose is None else max(num_inliers, int(np.count_nonzero(
        sampson_errors(pose.R, pose.t, view0.points_norm[every[:, 0]], view1.points_norm[every[:, 1]]) <= max_error
    )))
    denom = math.sqrt(view0.num_keypoints * view1.num_keypoints)
    overlap = num_inliers / denom if denom > 0 else 0.0
    reason = rejection_reason(pose is not None, num_inliers, overlap, math.inf, conf)
    if reason:
        parallax_deg, weight = math.nan, 0.0
    else:
        parallax_deg = inlier_parallax_deg(
            pose, x0[pose.inliers], x1[pose.inliers], max_error=max_error,
            iterations=conf.ransac_iterations, seed=seed,
        )
        reason = rejection_reason(True, num_inliers, overlap, parallax_deg, conf)
        weight = pair_weight(overlap, parallax_deg, conf)
    return PairScore(
        num_matches=len(matches), num_inliers=num_inliers, overlap=overlap, parallax_deg=parallax_deg,
        weight=weight, accepted=reason == "", reason=reason, num_inliers_all=num_inliers_all,
        **_pose_vectors(pose),
    )


def _unit(view: ViewFeatures) -> np.ndarray:
    """(M, D) float32 unit descriptors (a `ViewStore`'s views are normalised once, not per pair)."""
    if view.descriptors.ndim != 2:
        raise ValueError(f"descriptors must be (N, D), got shape {view.descriptors.shape}")
    return view.descriptors if view.unit else l2_normalize(view.descriptors, axis=1)


def _pose_vectors(pose: RelativePose | None) -> dict[str, tuple[float, ...]]:
    """A relative pose's rotation (axis times angle, radians) and translation as a unit vector
    (`PairScore.rotvec`, `.direction`); NaN without a pose."""
    if pose is None:
        return {"rotvec": (math.nan,) * 3, "direction": (math.nan,) * 3}
    t = np.asarray(pose.t, dtype=np.float64)
    return {"rotvec": tuple(float(v) for v in rotvec_from_matrix(pose.R)),
            "direction": tuple(float(v) for v in t / max(float(np.linalg.norm(t)), 1e-300))}


# ----------------------------------------------------------------------------------------
# Many pairs
# ----------------------------------------------------------------------------------------


def load_views(
    names: Iterable[str], features_path: Path, db_path: Path, num_keypoints: int, *, progress: bool = True
) -> dict[str, ViewFeatures]:
    """The top-``num_keypoints`` features of each image, normalised with its database camera."""
    names = sorted(set(names))
    return dict(zip(names, _views_of(names, features_path, db_path, num_keypoints, progress)))


class ViewStore:
    """Every image's scorer input (top-M descriptors, normalised points, focal) in memory-mapped
    arrays, written in one pass over the features file: worker processes share the pages, and
    memory grows with the images scored, never with the pairs.

    Files in `folder`: descriptors (N, M, D), points (N, M, 2) float64, counts (N,), focal (N,).
    The unit descriptors of the last `UNIT_CACHE_VIEWS` views asked for are kept in memory: a view
    is in many pairs, and normalising its descriptors for each took a seventh of the scoring time.
    """

    UNIT_CACHE_VIEWS = 64

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self.descriptors = np.load(self.folder / "descriptors.npy", mmap_mode="r")
        self.points = np.load(self.folder / "points.npy", mmap_mode="r")
        self.counts = np.load(self.folder / "counts.npy")
        self.focal = np.load(self.folder / "focal.npy")
        self._unit: OrderedDict[int, np.ndarray] = OrderedDict()

    def view(self, index: int) -> ViewFeatures:
        n = int(self.counts[index])
        unit = self._unit.get(index)
        if unit is None:
            unit = self._unit[index] = l2_normalize(np.asarray(self.descriptors[index, :n]), axis=1)
            if len(self._unit) > self.UNIT_CACHE_VIEWS:
                self._unit.popitem(last=False)
        else:
            self._unit.move_to_end(index)
        return ViewFeatures(descriptors=unit, points_norm=np.asarray(self.points[index, :n]),
                            focal_px=float(self.focal[index]), unit=True)

    @classmethod
    def write(cls, folder: Path, names: Sequence[str], features_path: Path, db_path: Path, num_keypoints: int, *,
              progress: bool = True) -> ViewStore:
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        num = len(names)
        counts, focal = np.zeros(num, np.int64), np.zeros(num, np.float64)
        desc = points = None
        for i, view in enumerate(_views_of(names, features_path, db_path, num_keypoints, progress)):
            if desc is None:  # the first view gives the descriptors' size and type
                shape = (num, num_keypoints, view.descriptors.shape[1])
                desc = np.lib.format.open_memmap(folder / "descriptors.npy", "w+", view.descriptors.dtype, shape)
                points = np.lib.format.open_memmap(folder / "points.npy", "w+", np.float64, (num, num_keypoints, 2))
            n = view.num_keypoints
            desc[i, :n], points[i, :n], counts[i], focal[i] = view.descriptors, view.points_norm, n, view.focal_px
        if desc is None:
            np.save(folder / "descriptors.npy", np.zeros((0, num_keypoints, 0), np.uint8))
            np.save(folder / "points.npy", np.zeros((0, num_keypoints, 2)))
        else:
            desc.flush()
            points.flush()
        del desc, points
        np.save(folder / "counts.npy", counts)
        np.save(folder / "focal.npy", focal)
        return cls(folder)


def _views_of(names: Sequence[str], features_path: Path, db_path: Path, num_keypoints: int,
              progress: bool) -> Iterator[ViewFeatures]:
    """ViewFeatures of `names` in order, reading the features file once."""
    cameras = colmap.cameras_by_image(Path(db_path))
    missing = [n for n in names if n not in cameras]
    if missing:
        raise ValueError(
            f"{len(missing)} images are not in the database {db_path} (e.g. {missing[0]!r}); "
            "score pairs with the database the features were extracted into"
        )
    with FeatureCache(Path(features_path), capacity=1, top_k=num_keypoints) as reader:
        for name in tqdm(names, desc="load features", unit="img", disable=not progress):
            try:
                feats = reader.get(name)
            except KeyError as err:
                raise ValueError(f"image {name!r} has no features in {features_path}") from err
            yield ViewFeatures.from_features(feats, cameras[name])


@dataclass(frozen=True)
class _Shard:
    """Pairs to score, as row indices into a ViewStore; what a worker receives."""

    store: str
    index0: np.ndarray
    index1: np.ndarray
    conf: ScoreConfig
    seed: int


_OPEN_STORES: dict[str, ViewStore] = {}  # per process: a worker opens a store once


def _score_shard(shard: _Shard) -> list[PairScore]:
    store = _OPEN_STORES.get(shard.store)
    if store is None:
        _OPEN_STORES.clear()
        store = _OPEN_STORES[shard.store] = ViewStore(Path(shard.store))
    with threadpool_limits(1):  # small matrix products: threaded BLAS costs 3x here (measured)
        return [score_pair(store.view(int(a)), store.view(int(b)), shard.conf, seed=shard.seed)
                for a, b in zip(shard.index0, shard.index1)]


#: most pairs per shard of parallel scoring
SHARD_PAIRS = 512
#: fewest pairs per shard: fewer pairs than two such shards are scored in this process, where
#: starting worker processes would cost about what they save (measured: 120 pairs, 0.5 s either way)
MIN_SHARD_PAIRS = 64
#: shards per worker at least (when the shards stay above MIN_SHARD_PAIRS): with as many shards as
#: workers, one worker's last shard finishes alone (bm-moldGoldCape, 1,356 pairs in shards of 512
#: on 2 workers: 3.8 s; in shards of 339: 3.3 s)
SHARDS_PER_WORKER = 4


def shard_pairs(num_pairs: int, workers: int, most: int = SHARD_PAIRS) -> int:
    """Pairs per shard: at most `most`, few enough that each worker gets SHARDS_PER_WORKER shards,
    and at least MIN_SHARD_PAIRS (or `most`, when that is smaller)."""
    even = math.ceil(num_pairs / max(1, SHARDS_PER_WORKER * workers))
    return max(min(MIN_SHARD_PAIRS, most), min(most, even))


def score_pairs(
    pairs: Sequence[tuple[str, str]],
    features_path: Path,
    db_path: Path,
    conf: ScoreConfig,
    *,
    executor: Executor | None = None,
    shard_size: int = SHARD_PAIRS,
    work_dir: Path | None = None,
    progress: bool = True,
    seed: int = 0,
    journal: ScoreJournal | None = None,
) -> PairScores:
    """Score candidate pairs, in shards over `executor` (default: this process).

    Each image's top-M features are read once into a memory-mapped `ViewStore` in `work_dir`
    (a temporary folder by default, removed at the end). A pair's score depends only on its two
    views, the settings and the seed, so results are the same for any executor and worker count.

    Args:
        pairs: (name0, name1) image names; both must have features and a database camera.
        features_path: features file (hloc layout, keypoints in hloc's pixel convention).
        db_path: the COLMAP database with the images' cameras (EXIF focal or COLMAP's prior).
        conf: scorer settings.
        executor: where the shards run (`sara.execute`); None: serially, here.
        shard_size: most pairs per shard (see `shard_pairs`); fewer pairs than two shards are
            scored in this process.
        work_dir: where the view store goes (its own sub-folder, removed afterwards).
        progress: show progress bars.
        seed: RANSAC seed, the same for every pair: a pair's score does not depend on the others.
        journal: where each shard's scores are kept as it comes back; pairs found there are not
            scored again (a selection stopped part-way, `scoring.journal`).
    Returns:
        The scores, in the order of ``pairs``.
    """
    pairs = [(str(a), str(b)) for a, b in pairs]
    same = [a for a, b in pairs if a == b]
    if same:
        raise ValueError(f"a pair of an image with itself: {same[0]!r}")
    if shard_size < 1:
        raise ValueError(f"execute.shard_size must be at least 1, got {shard_size}")
    kept = journal.scored(conf, seed) if journal is not None else {}
    todo = [p for p in pairs if p not in kept]
    if len(todo) < len(pairs):
        logger.info("score: %d of the %d pairs were scored by an earlier selection on these features (or one "
                    "that stopped); scoring the other %d", len(pairs) - len(todo), len(pairs), len(todo))
    names = sorted({n for p in todo for n in p})
    row = {n: i for i, n in enumerate(names)}
    index0 = np.array([row[a] for a, _ in todo], dtype=np.int64)
    index1 = np.array([row[b] for _, b in todo], dtype=np.int64)
    if executor is not None:
        shard_size = shard_pairs(len(todo), executor.workers, shard_size)
    if executor is None or len(todo) < 2 * shard_size:
        executor = SerialExecutor()
    if work_dir is not None:
        Path(work_dir).mkdir(parents=True, exist_ok=True)
    results: list[PairScore] = []
    with tempfile.TemporaryDirectory(prefix="score-views-", dir=work_dir) as tmp:
        store = ViewStore.write(Path(tmp), names, features_path, db_path, conf.num_keypoints, progress=progress)
        start = time.perf_counter()
        shards = [_Shard(str(store.folder), index0[k:k + shard_size], index1[k:k + shard_size], conf, seed)
                  for k in range(0, len(todo), shard_size)]
        with tqdm(total=len(todo), desc=f"score pairs ({executor.workers} worker(s))", unit="pair",
                  disable=not progress) as bar:
            for part in executor.map(_score_shard, shards):
                if journal is not None:
                    journal.add(conf, seed, todo[len(results):len(results) + len(part)], part)
                results += part
                bar.update(len(part))
        _OPEN_STORES.clear()
        del store
    fresh = iter(results)
    scores = PairScores.from_scores(pairs, [kept[p] if p in kept else next(fresh) for p in pairs])
    _log_summary(scores, len(todo), time.perf_counter() - start)
    return scores


def _log_summary(scores: PairScores, num_scored: int, elapsed_s: float) -> None:
    count = len(scores)
    if count == 0:
        logger.info("score: no pairs")
        return
    rejected = {r: scores.reason.count(r) for r in REASONS if r in scores.reason}
    logger.info(
        "score: %d pairs (%d scored in %.1f s, %.2f ms per pair); %d accepted, rejected: %s",
        count, num_scored, elapsed_s, 1e3 * elapsed_s / max(1, num_scored), int(scores.accepted.sum()),
        rejected or "none",
    )
