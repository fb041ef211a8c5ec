"""Configuration: one frozen dataclass per stage, nested in `PipelineConfig`.

The CLI takes a preset name plus `stage.field=value` overrides; the resolved configuration is
written to `run.json` in the output folder. Unknown keys are errors that list the valid ones.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True, kw_only=True)
class ImagesConfig:
    recursive: bool = False  # look for images in sub-folders too (names keep the sub-path)
    # EXIF orientation tags: "ignore" uses the stored pixels, as COLMAP, 3DGS and nerfstudio's COLMAP
    # loaders do; "apply" writes upright copies to <out>/images_upright and reconstructs from those
    exif_orientation: str = "ignore"

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class ExtractConfig:
    """Local features: COLMAP's SIFT (RootSIFT, COLMAP's defaults) or a learned backend."""

    backend: str = "sift"  # local-feature backend, see `sara.features.BACKENDS`
    max_num_features: int = 8192  # keypoints kept per image at most
    max_image_size: int = 3200  # px; larger images are downscaled for extraction, keypoints mapped back
    device: str = "auto"  # learned backends: auto | cpu | cuda
    weights: str = ""  # learned backends: a local weights file (else found as `sara weights` lists)
    camera_model: str = "SIMPLE_RADIAL"
    # auto: one shared camera when all images have the same size and the same EXIF camera (make, model,
    # focal; or no EXIF at all), else one per image (photos from different phones)
    camera_mode: str = "auto"  # auto | single | per_image | per_folder
    camera_params: str = ""  # known intrinsics, e.g. "fx,fy,cx,cy" for PINHOLE; empty = EXIF or prior
    default_focal_length_factor: float = 1.2  # COLMAP's prior: focal = factor * max(width, height)
    # one shared camera without EXIF focal or camera_params: estimate its focal length from pairs of
    # neighbouring images and use it where it is >= 2.5x the prior (long lenses; `sara.scoring.focal`)
    estimate_focal: bool = True
    num_threads: int = -1

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class RetrievalConfig:
    """Global descriptors and the cosine kNN that proposes candidate pairs."""

    descriptor: str = "vlad"  # vlad | bow | dinov2 | aliked-gem (learned: local weights, `sara weights`)
    num_neighbors: int = 20  # k: nearest neighbours kept per image (the union is symmetric)
    codebook_size: int = 64  # VLAD visual words, learned from the collection itself
    features_per_image: int = 1000  # RootSIFT descriptors per image used for VLAD (largest scale first)
    weights: str = ""  # local weights file for learned descriptors (dinov2, aliked-gem)
    device: str = "auto"  # learned descriptors: auto | cpu | cuda
    image_size: int = 448  # learned descriptors: longer image side in pixels
    widen_neighbors: int = 80
    """SARA only: when the selected graph falls apart, the views outside its largest component get
    more candidates, from this many nearest neighbours (then four times as many if still apart;
    each round at most as many new candidates as were scored before it; 0: off)."""

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class ScoreConfig:
    """The pre-matching scorer: a cheap two-view geometry per candidate pair."""

    num_keypoints: int = 1024  # M: keypoints per image (largest scale first) used for mutual NN
    num_matches: int = 50  # b: best mutual nearest neighbours kept per pair
    ransac_iterations: int = 32
    ransac_max_error_px: float = 2.0  # Sampson error threshold
    alpha: float = 1.0  # exponent of the overlap in w
    beta: float = 0.5  # exponent of the saturated parallax in w
    parallax_saturation_deg: float = 10.0  # g(P) = min(P, sat) / sat
    min_overlap: float = 0.005  # tau_O
    min_parallax_deg: float = 0.5  # tau_P
    min_inliers: int = 15  # RANSAC on unrelated images finds 8-12 of 50 by chance
    # the overlap in the spanning tree's weight: "best", the paper's (the b best matches' inliers),
    # "all": the mutual nearest neighbours of all M keypoints that fit the RANSAC pose, which does
    # not saturate at b and makes trees of the nearest views, or "auto": "all" where the images'
    # field of view is known to be wide (EXIF, extract.camera_params or a sound estimate from the
    # images; at least sara.pairs.sara_source.WIDE_FIELD_OF_VIEW_DEG), else "best". "all" gains on
    # wide lenses (the Strecha scenes at full to quarter size, internet-photo stand-ins) and loses
    # 0.16-0.40 AUC@1 on long-lens crops and 0.004 on bm-moldGoldCape (docs/ACCURACY.md 16, 19).
    # Loops, anchors and weak-view pairs always rank by the paper's w
    tree_overlap: str = "auto"

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class PairsConfig:
    """Which pair source feeds matching, and the options of the baseline sources."""

    method: str = "sara"  # sara | exhaustive | sequential | vocabtree | retrieval | <path to pairs.txt>
    sequential_overlap: int = 10
    sequential_quadratic: bool = False
    sequential_loop_detection: bool = False  # add retrieval neighbours (vlad) every loop_period images
    sequential_loop_period: int = 10
    sequential_loop_neighbors: int = 5
    vocab_tree_path: str = ""  # a saved pycolmap visual index; built from this collection when empty
    vocab_num_images: int = 30  # top-k of the vocabulary tree retrieval
    vocab_num_words: int = 4096
    # SARA only: rounds after the first model (0: none). A round repairs views that the model left
    # out although the selected graph joins them (up to repair_pairs_per_view more candidates per
    # left-out view), else runs the pose-guided round once (graph.pose_guided_*): 3 rounds leave room
    # for a repair before and after it (docs/ACCURACY.md)
    repair_rounds: int = 3
    repair_pairs_per_view: int = 3
    # SARA only, before the first mapping: a view whose verified pairs hold fewer inlier matches
    # than min_view_inliers in all gets up to support_pairs_per_view more accepted candidates (best
    # weight first), matched before the mapper runs, within half of the room the pair cap leaves
    # (`sara.pairs.support`; 0 disables). Views of the shared scenes sum 223 or more (thousands on
    # most); on low-texture ones a view's few pairs of a few dozen inliers each leave it
    # unregistered and the model splits (docs/ACCURACY.md, section 14)
    min_view_inliers: int = 200
    support_pairs_per_view: int = 3

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class MatchConfig:
    """Full matching of the selected pairs and COLMAP's geometric verification of the matches."""

    backend: str = "auto"  # matcher, see `sara.matchers.BACKENDS`; auto: the usual one for the features
    device: str = "auto"  # learned matchers: auto | cpu | cuda
    weights: str = ""  # learned matchers: a local weights file
    max_ratio: float = 0.8
    max_distance: float = 0.7
    cross_check: bool = True
    min_num_inliers: int = 15
    num_threads: int = -1
    chunk_size: int = 128  # pairs per matcher call: progress granularity and resume points

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class MapConfig:
    mapper: str = "incremental"  # incremental | global
    min_model_size: int = 3
    # Registration of a new image (PnP): COLMAP's defaults are 30 inliers and a 0.25 ratio; lower
    # values pose wide-baseline views that COLMAP leaves out (templeSparseRing: 16/16 instead of 13/16).
    abs_pose_min_num_inliers: int = 15
    abs_pose_min_inlier_ratio: float = 0.1
    num_threads: int = -1
    extend_model: bool = True
    """A round after mapping that must map again (views left out of the model) continues from the
    model it has (COLMAP's mapper with an input model) instead of mapping everything from scratch."""

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class GraphConfig:
    """Budgets and thresholds of the pair-graph stage.

    Budgets are ``ceil(ratio * num_images)`` pairs per augmentation; a ratio of 0 or a
    ``use_*`` flag set to False disables that augmentation (for ablations).
    With the defaults the selection has about ``(N - 1) + 0.9 N = 1.9 N`` pairs, a mean
    degree near 4: the tree gives connectivity, the rest gives redundancy.
    """

    use_loops: bool = True
    """Run multi-scale loop consolidation."""
    use_anchors: bool = True
    """Add long-baseline anchors."""
    use_weak: bool = True
    """Reinforce weak views."""

    loop_budget_ratio: float = 0.5
    """Loop-closing pairs per image (pairs / image). Half a pair per image closes a loop
    for roughly every other tree edge, the main defence against drift."""
    anchor_budget_ratio: float = 0.15
    """Long-baseline anchor pairs per image (pairs / image). Few: they are the pairs with
    the least overlap among the useful ones, kept for triangulation angle."""
    weak_budget_ratio: float = 0.25
    """Weak-view pairs per image (pairs / image). Enough for every leaf of a tree
    (about a quarter of the views in a typical capture) to get a second pair."""

    loop_scale_fractions: tuple[float, float, float] = (1 / 3, 1 / 3, 1 / 3)
    """Shares of the loop budget for short, medium and long loops (unitless, normalised
    to sum 1). Equal shares: no scale of drift is known in advance to dominate."""
    loop_short_frac: float = 0.1
    """Short loops have tree path length ``L <= s1 = max(loop_min_short_len,
    ceil(loop_short_frac * D))``, ``D`` the forest's diameter (tree edges)."""
    loop_long_frac: float = 0.3
    """Long loops have ``L > s2 = max(s1 + 1, ceil(loop_long_frac * D))`` (tree edges).
    The loop score's gain ``gamma(L) = min(1, log(1 + L) / log(1 + s2))`` saturates at
    ``s2``: long loops are ranked by weight alone, shorter ones are discounted."""
    loop_min_short_len: int = 3
    """Smallest ``s1`` (tree edges): triangles and quadrilaterals always count as short."""

    anchor_max_per_view: int = 1
    """Most anchors touching one view (pairs). One makes the anchors a matching, so they
    spread over ``2 * budget`` distinct views instead of piling onto a few wide views."""

    weak_degree: int = 1
    """A view whose degree in the selected graph is at most this (pairs) is weak: a
    leaf of the tree hangs on one pair, and one bad match detaches it."""
    weak_quantile: float = 0.2
    """A view whose median accepted candidate weight is strictly below this quantile
    (0-1) of all views' medians is weak too; 0 disables this criterion."""
    weak_per_view: int = 1
    """Most pairs added per weak view (pairs)."""

    pose_guided_pairs_per_image: float = 1.0
    """Pairs per registered image that SARA's pose-guided round adds after the first model
    (pairs / image; 0 disables the round): the unmatched pairs of registered views with the highest
    weight w = O^alpha g(P)^beta, overlap and parallax predicted by the model (docs/ACCURACY.md)."""
    pose_guided_min_points: int = 30
    """A pair is matched in the pose-guided round only if the first model predicts at least this
    many covisible points (points); fewer rarely pass verification (15 inliers)."""
    pose_guided_max_view_angle_deg: float = 45.0
    """A point counts as covisible only if the two views see it from directions at most this far
    apart (degrees): SIFT seldom matches across wider angles."""
    pose_guided_max_per_view: int = 2
    """Most pose-guided pairs that touch one view (pairs; 0: no limit): the best pairs are taken in
    order of weight, skipping a pair once one of its views has this many. 2, twice a view's even
    share at 1 pair per image, spreads the round over the views (raise it with
    `pose_guided_pairs_per_image`). Measured against no limit (docs/ACCURACY.md 13.2): AUC@1
    +0.009 to +0.025 on three stand-ins nobody tuned for and +0.010 on bm-moldGoldCape (above
    exhaustive's), -0.005 on templeRing, -0.003 on castle and -0.001 on Herz-Jesus."""
    extend_tracks: bool = True
    """When the pose-guided round refines the model (or else, on the final model), add to its
    tracks the keypoints that observe its 3D points without a match saying so, then bundle-adjust
    once more: each view against the points it should see, a keypoint within
    `extend_tracks_radius_px` of the projection whose descriptor passes COLMAP's SIFT matching
    tests against the track's (`sara.colmap.refine.extend_tracks`). Longer tracks for the final
    bundle adjustment without matching more pairs (docs/ACCURACY.md, sections 12 and 12.8)."""
    extend_tracks_radius_px: float = 1.5
    """How far from a point's projection a keypoint may be to join its track (pixels): 1.0 and 2.0
    measured worse on some of the six shared scenes (docs/ACCURACY.md, section 12)."""
    extend_tracks_scale_quantile: float = 0.995
    """Where the keypoints carry their scale (SIFT), a keypoint joins a track only if its size in
    the scene (scale x depth / focal length) is within this quantile of the model's own tracks'
    spread around their median (1.38-1.52x on the six shared scenes). 0: not tested. Measured
    against no test (docs/ACCURACY.md 20): AUC@1 +0.004 on bm-moldGoldCape, now above exhaustive's,
    and 0 to +0.0034 on the other five; neutral on half-size stand-ins, where 0.98 and 0.99 lose
    up to 0.006; -0.002 to -0.004 on two 25-degree crops."""
    max_pairs_per_image: float = 4.0
    """Cap on the pairs of all rounds together (selection, repair, pose-guided), per image."""
    max_pairs_fraction: float = 0.25
    """Cap on the pairs of all rounds together, as a fraction of the exhaustive N (N - 1) / 2; on
    small collections it bounds the selection (the spanning tree is always kept)."""
    densify: bool = False
    """More 3D points (3DGS initialisation): the pose-guided round ranks pairs by all predicted
    covisible points, with its own budget and cap (`densify_pairs_per_image`)."""
    densify_pairs_per_image: float = 6.0
    """With `densify`: pose-guided pairs per registered image (pairs / image); the cap of all
    rounds is then ``densify_pairs_per_image + 2`` pairs per image and 60% of the exhaustive pairs
    (bm-moldGoldCape: 4 per image gave 83% of exhaustive's 3D points, 6 gave 92%; fountain, 11
    images: half of the exhaustive pairs gave 84%, 60% gave 91%)."""

    def pair_cap(self, num_images: int) -> int:
        """Most pairs of all rounds together for ``num_images`` images (at least a spanning tree)."""
        exhaustive = num_images * (num_images - 1) // 2
        cap = min(math.floor(self.max_pairs_per_image * num_images + 1e-9),
                  math.floor(self.max_pairs_fraction * exhaustive + 1e-9))
        return max(cap, num_images - 1)

    def densify_cap(self, num_images: int) -> int:
        """Most pairs of all rounds together with `densify`."""
        exhaustive = num_images * (num_images - 1) // 2
        return max(min(math.floor((self.densify_pairs_per_image + 2) * num_images + 1e-9), (3 * exhaustive) // 5),
                   num_images - 1)

    def __post_init__(self) -> None:
        validate(self)
        for name in ("loop_budget_ratio", "anchor_budget_ratio", "weak_budget_ratio"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"GraphConfig.{name} must be >= 0, got {getattr(self, name)}")
        fractions = np.asarray(self.loop_scale_fractions, dtype=np.float64)
        if fractions.shape != (3,) or np.any(fractions < 0) or not fractions.sum() > 0:
            raise ValueError(
                "GraphConfig.loop_scale_fractions must be three non-negative numbers "
                f"with a positive sum, got {self.loop_scale_fractions}"
            )
        if not 0 <= self.loop_short_frac <= self.loop_long_frac:
            raise ValueError("GraphConfig needs 0 <= loop_short_frac <= loop_long_frac")
        if self.loop_min_short_len < 2:
            raise ValueError("GraphConfig.loop_min_short_len must be >= 2")
        if self.anchor_max_per_view < 1 or self.weak_per_view < 1:
            raise ValueError("GraphConfig.anchor_max_per_view and weak_per_view must be >= 1")
        if self.weak_degree < 0 or not 0 <= self.weak_quantile <= 1:
            raise ValueError("GraphConfig needs weak_degree >= 0 and 0 <= weak_quantile <= 1")

    def budgets(self, num_images: int) -> dict[str, int]:
        """Pairs each augmentation may add for ``num_images`` images (0 when disabled)."""
        ratios = {
            "loop": self.loop_budget_ratio if self.use_loops else 0.0,
            "anchor": self.anchor_budget_ratio if self.use_anchors else 0.0,
            "weak": self.weak_budget_ratio if self.use_weak else 0.0,
        }
        # The small slack keeps e.g. 0.15 * 20 = 3.0000000000000004 from becoming 4.
        return {k: max(0, math.ceil(r * num_images - 1e-9)) for k, r in ratios.items()}


@dataclass(frozen=True, kw_only=True)
class ExecuteConfig:
    """Where the work runs. Results never depend on these settings, so no output is keyed on them."""

    executor: str = "auto"  # auto (serial for 1 worker, else processes) | serial | processes | ray
    workers: int = 0  # parallel workers; 0: one per CPU core
    ray_address: str = ""  # with executor=ray: a cluster address or "auto"; empty starts a local one
    shard_size: int = 512  # most pairs per shard of parallel scoring (4 shards per worker down to 64 pairs;
    # fewer than two shards: scored in-process)

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class PipelineConfig:
    images: ImagesConfig = field(default_factory=ImagesConfig)
    extract: ExtractConfig = field(default_factory=ExtractConfig)
    pairs: PairsConfig = field(default_factory=PairsConfig)
    retrieval: RetrievalConfig = field(default_factory=RetrievalConfig)
    score: ScoreConfig = field(default_factory=ScoreConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    match: MatchConfig = field(default_factory=MatchConfig)
    map: MapConfig = field(default_factory=MapConfig)
    execute: ExecuteConfig = field(default_factory=ExecuteConfig)
    seed: int = 0

    def __post_init__(self) -> None:
        validate(self)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# ---------------------------------------------------------------------------------------------
# Valid values: checked when a config is made (so a bad `-s key=value` or flag fails at once,
# naming the option and its valid range)
# ---------------------------------------------------------------------------------------------


class ConfigError(ValueError):
    """An option has a value outside its valid range; `option` is its dotted name."""

    def __init__(self, option: str, message: str) -> None:
        super().__init__(message)
        self.option = option


#: COLMAP's camera models (pycolmap.CameraModelId, less INVALID)
CAMERA_MODELS = (
    "SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL", "RADIAL_FISHEYE",
    "OPENCV", "OPENCV_FISHEYE", "FULL_OPENCV", "FOV", "THIN_PRISM_FISHEYE", "RAD_TAN_THIN_PRISM_FISHEYE",
    "SIMPLE_DIVISION", "DIVISION", "SIMPLE_FISHEYE", "FISHEYE", "EUCM", "EQUIRECTANGULAR",
)
MAX_SEED = 2**31 - 1


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _is_real(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def _ints(low: int, high: int | None = None) -> tuple[Any, str]:
    text = f"an integer >= {low}" if high is None else f"an integer from {low} to {high}"
    return (lambda v: _is_int(v) and v >= low and (high is None or v <= high)), text


def _reals(low: float, high: float | None = None, *, low_open: bool = False, high_open: bool = False) -> tuple[Any, str]:
    def ok(v: Any) -> bool:
        if not _is_real(v) or not math.isfinite(v):
            return False
        above = v > low if low_open else v >= low
        below = high is None or (v < high if high_open else v <= high)
        return above and below

    if high is None:
        text = f"a finite number {'>' if low_open else '>='} {low:g}"
    else:
        text = f"a number in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
    return ok, text


def _choice(*options: str) -> tuple[Any, str]:
    return (lambda v: v in options), "one of " + ", ".join(options)


def _name() -> tuple[Any, str]:
    return (lambda v: isinstance(v, str) and v.strip() != "" and v == v.strip()), "a name (not empty)"


def _text() -> tuple[Any, str]:
    return (lambda v: isinstance(v, str)), "a string"


def _flag() -> tuple[Any, str]:
    return (lambda v: isinstance(v, (bool, np.bool_))), "true or false"


def _device() -> tuple[Any, str]:
    import re

    return (lambda v: isinstance(v, str) and re.fullmatch(r"auto|cpu|mps|cuda(:\d+)?", v) is not None,
            "auto, cpu, cuda, cuda:N or mps")


def _numbers_list() -> tuple[Any, str]:
    def ok(v: Any) -> bool:
        if not isinstance(v, str):
            return False
        if not v.strip():
            return True
        try:
            return all(math.isfinite(float(x)) for x in v.split(","))
        except ValueError:
            return False

    return ok, "empty or comma-separated numbers, e.g. 1200,1200,512,384"


_THREADS = _ints(-1)  # COLMAP: -1 (or 0) uses every core

#: section.field -> (check, description of the valid values); every field of every section has one
RULES: dict[str, tuple[Any, str]] = {
    "images.recursive": _flag(),
    "images.exif_orientation": _choice("ignore", "apply"),
    "extract.backend": _name(),
    "extract.max_num_features": _ints(1),
    "extract.max_image_size": _ints(32),
    "extract.device": _device(),
    "extract.weights": _text(),
    "extract.camera_model": _choice(*CAMERA_MODELS),
    "extract.camera_mode": _choice("auto", "single", "per_image", "per_folder"),
    "extract.camera_params": _numbers_list(),
    "extract.default_focal_length_factor": _reals(0, 100, low_open=True),
    "extract.estimate_focal": _flag(),
    "extract.num_threads": _THREADS,
    "retrieval.descriptor": _name(),
    "retrieval.num_neighbors": _ints(1),
    "retrieval.codebook_size": _ints(1),
    "retrieval.features_per_image": _ints(1),
    "retrieval.weights": _text(),
    "retrieval.device": _device(),
    "retrieval.image_size": _ints(32),
    "retrieval.widen_neighbors": _ints(0),
    "score.num_keypoints": _ints(5),
    "score.num_matches": _ints(5),
    "score.ransac_iterations": _ints(1),
    "score.ransac_max_error_px": _reals(0, low_open=True),
    "score.alpha": _reals(0),
    "score.beta": _reals(0),
    "score.parallax_saturation_deg": _reals(0, 180, low_open=True),
    "score.min_overlap": _reals(0, 1),
    "score.min_parallax_deg": _reals(0, 180, high_open=True),
    "score.min_inliers": _ints(0),
    "score.tree_overlap": _choice("auto", "all", "best"),
    "pairs.method": _name(),
    "pairs.sequential_overlap": _ints(1),
    "pairs.sequential_quadratic": _flag(),
    "pairs.sequential_loop_detection": _flag(),
    "pairs.sequential_loop_period": _ints(1),
    "pairs.sequential_loop_neighbors": _ints(1),
    "pairs.vocab_tree_path": _text(),
    "pairs.vocab_num_images": _ints(1),
    "pairs.vocab_num_words": _ints(2),
    "pairs.repair_rounds": _ints(0),
    "pairs.repair_pairs_per_view": _ints(1),
    "pairs.min_view_inliers": _ints(0),
    "pairs.support_pairs_per_view": _ints(0),
    "match.backend": _name(),
    "match.device": _device(),
    "match.weights": _text(),
    "match.max_ratio": _reals(0, 1, low_open=True),
    "match.max_distance": _reals(0, low_open=True),
    "match.cross_check": _flag(),
    "match.min_num_inliers": _ints(1),
    "match.num_threads": _THREADS,
    "match.chunk_size": _ints(1),
    "map.mapper": _choice("incremental", "global"),
    "map.min_model_size": _ints(2),
    "map.abs_pose_min_num_inliers": _ints(3),
    "map.abs_pose_min_inlier_ratio": _reals(0, 1, low_open=True),
    "map.num_threads": _THREADS,
    "map.extend_model": _flag(),
    "graph.use_loops": _flag(),
    "graph.use_anchors": _flag(),
    "graph.use_weak": _flag(),
    "graph.loop_budget_ratio": _reals(0),
    "graph.anchor_budget_ratio": _reals(0),
    "graph.weak_budget_ratio": _reals(0),
    "graph.loop_short_frac": _reals(0, 1),
    "graph.loop_long_frac": _reals(0, 1),
    "graph.loop_min_short_len": _ints(2),
    "graph.anchor_max_per_view": _ints(1),
    "graph.weak_degree": _ints(0),
    "graph.weak_quantile": _reals(0, 1),
    "graph.weak_per_view": _ints(1),
    "graph.pose_guided_pairs_per_image": _reals(0),
    "graph.pose_guided_min_points": _ints(1),
    "graph.pose_guided_max_view_angle_deg": _reals(0, 180, low_open=True),
    "graph.pose_guided_max_per_view": _ints(0),
    "graph.extend_tracks": _flag(),
    "graph.extend_tracks_radius_px": _reals(0, low_open=True),
    "graph.extend_tracks_scale_quantile": _reals(0, 1),
    "graph.max_pairs_per_image": _reals(0),
    "graph.max_pairs_fraction": _reals(0, 1),
    "graph.densify": _flag(),
    "graph.densify_pairs_per_image": _reals(0),
    "execute.executor": _choice("auto", "serial", "processes", "ray"),
    "execute.workers": _ints(0),
    "execute.ray_address": _text(),
    "execute.shard_size": _ints(1),
    "seed": _ints(0, MAX_SEED),
}

#: the section name of each config class in `PipelineConfig`
SECTIONS = {
    "ImagesConfig": "images", "ExtractConfig": "extract", "RetrievalConfig": "retrieval", "ScoreConfig": "score",
    "PairsConfig": "pairs", "MatchConfig": "match", "MapConfig": "map", "GraphConfig": "graph",
    "ExecuteConfig": "execute", "PipelineConfig": "",
}


def validate(conf: Any) -> None:
    """Raise ConfigError for the first field of a config section outside its valid range."""
    section = SECTIONS.get(type(conf).__name__, type(conf).__name__)
    for f in dataclasses.fields(conf):
        value = getattr(conf, f.name)
        if dataclasses.is_dataclass(value):
            continue
        option = f"{section}.{f.name}" if section else f.name
        rule = RULES.get(option)
        if rule is not None and not rule[0](value):
            raise ConfigError(option, f"{option} must be {rule[1]}, got {value!r}")
    _cross_checks(conf, section)


def _cross_checks(conf: Any, section: str) -> None:
    if section == "score" and conf.min_inliers > conf.num_matches:
        raise ConfigError("score.min_inliers", f"score.min_inliers ({conf.min_inliers}) must be at most "
                          f"score.num_matches ({conf.num_matches}): every candidate pair would be rejected")
    if section == "score" and conf.num_matches > conf.num_keypoints:
        raise ConfigError("score.num_matches", f"score.num_matches ({conf.num_matches}) must be at most "
                          f"score.num_keypoints ({conf.num_keypoints})")


#: What the learned presets share. A LightGlue pair costs 3-10x a SIFT pair on a CPU, so their pair
#: budget is 2.5 N for all rounds (SIFT: 4 N) and the pose-guided round adds half a pair per view
#: (SIFT: one): measured on bm-moldGoldCape in docs/BENCHMARKS.md ("The learned presets' budget").
_LEARNED: dict[str, Any] = {"extract.max_num_features": 2048, "extract.max_image_size": 1024,
                            "graph.max_pairs_per_image": 2.5, "graph.pose_guided_pairs_per_image": 0.5}

PRESETS: dict[str, dict[str, Any]] = {
    "sift-offline": {},
    # Faster preview on large collections: fewer SIFT features, smaller images.
    "sift-fast": {"extract.max_num_features": 4096, "extract.max_image_size": 1600},
    # The paper's setting: learned features and LightGlue (`pip install 'sara[learned]'` and the weights;
    # `sara weights` says where each file is looked for). 1024 px and 2048 keypoints, as measured in
    # docs/BENCHMARKS.md; the licence of each weight file is listed by `sara weights`.
    "aliked-lightglue": {"extract.backend": "aliked-n16", **_LEARNED, "match.backend": "lightglue"},
    "disk-lightglue": {"extract.backend": "disk", **_LEARNED, "match.backend": "lightglue"},
    "xfeat-lighterglue": {"extract.backend": "xfeat", **_LEARNED, "match.backend": "lighterglue"},
}


def _parse_value(raw: str, typ: Any, key: str) -> Any:
    if isinstance(typ, str) and typ.startswith("tuple["):  # "0.5,0.25,0.25" or "(0.5, 0.25, 0.25)"
        item = typ[len("tuple["):].split(",")[0].strip().rstrip("]")
        parts = [p for p in raw.strip().strip("()[]").split(",") if p.strip()]
        return tuple(_parse_value(p.strip(), item, key) for p in parts)
    if isinstance(typ, str):
        typ = {"int": int, "float": float, "bool": bool, "str": str}.get(typ, str)
    origin = typing.get_origin(typ)
    if origin in (typing.Union, types.UnionType):
        typ = next(t for t in typing.get_args(typ) if t is not type(None))
    try:
        if typ is bool:
            low = raw.strip().lower()
            if low in ("1", "true", "yes", "on"):
                return True
            if low in ("0", "false", "no", "off"):
                return False
            raise ValueError(raw)
        if typ in (int, float, str):
            return typ(raw)
    except ValueError:
        raise ValueError(f"bad value for {key}: {raw!r} is not a {typ.__name__}") from None
    return raw


def apply_overrides(conf: Any, overrides: dict[str, Any], prefix: str = "") -> Any:
    """Return a copy of a (nested) config dataclass with `a.b=value` overrides applied.

    Values may be strings (from the command line; parsed by the field's type) or typed values.
    """
    fields = {f.name: f for f in dataclasses.fields(conf)}
    nested: dict[str, dict[str, Any]] = {}
    direct: dict[str, Any] = {}
    for key, value in overrides.items():
        head, _, rest = key.partition(".")
        if head not in fields:
            valid = ", ".join(prefix + n for n in fields)
            raise ValueError(f"unknown option {prefix + key!r}; valid options here: {valid}")
        current = getattr(conf, head)
        if rest:
            if not dataclasses.is_dataclass(current):
                raise ValueError(f"option {prefix + head!r} has no sub-options")
            nested.setdefault(head, {})[rest] = value
        elif dataclasses.is_dataclass(current):
            valid = ", ".join(f"{prefix}{head}.{f.name}" for f in dataclasses.fields(current))
            raise ValueError(f"{prefix + head!r} is a group of options: set one of {valid}")
        else:
            direct[head] = _parse_value(value, fields[head].type, prefix + key) if isinstance(value, str) else value
    for head, sub in nested.items():
        direct[head] = apply_overrides(getattr(conf, head), sub, prefix=f"{prefix}{head}.")
    return dataclasses.replace(conf, **direct)


def parse_override_args(args: list[str]) -> dict[str, str]:
    """`['a.b=1', 'c=x']` -> {'a.b': '1', 'c': 'x'}."""
    out = {}
    for arg in args:
        key, sep, value = arg.partition("=")
        if not sep or not key:
            raise ValueError(f"bad option {arg!r}: write it as key=value, e.g. retrieval.num_neighbors=20")
        out[key.strip()] = value.strip()
    return out


def make_config(preset: str = "sift-offline", overrides: dict[str, Any] | None = None) -> PipelineConfig:
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of: {', '.join(PRESETS)}")
    conf = apply_overrides(PipelineConfig(), dict(PRESETS[preset]))
    return apply_overrides(conf, overrides or {})


def config_from_dict(data: dict[str, Any]) -> PipelineConfig:
    """Rebuild a PipelineConfig from `to_dict()` output (e.g. run.json)."""
    flat: dict[str, Any] = {}

    def walk(d: dict[str, Any], prefix: str) -> None:
        for k, v in d.items():
            if isinstance(v, dict):
                walk(v, f"{prefix}{k}.")
            else:
                flat[prefix + k] = v

    walk(data, "")
    return apply_overrides(PipelineConfig(), flat)
