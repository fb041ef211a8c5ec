"""SARA's own configuration sections: the scorer, the pair graph, the pair budget and the rounds.

Each field is written once, with `option(default, rule, doc, advanced=...)` (see `rules`). Most are
the paper's constants and experiment knobs, hence advanced; the pair budget's cap and `densify` are
everyday keys.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

from .rules import ConfigError, choice, flag, ints, option, reals, shares, validate


@dataclass(frozen=True, kw_only=True)
class ScoreConfig:
    """The pre-matching scorer: a cheap two-view geometry per candidate pair."""

    SECTION: ClassVar[str] = "score"

    num_keypoints: int = option(1024, ints(5), "M: keypoints per image (largest scale first) used for mutual NN.")
    num_matches: int = option(50, ints(5), "b: best mutual nearest neighbours kept per pair.")
    ransac_iterations: int = option(32, ints(1), "RANSAC iterations of the two-view geometry.")
    ransac_max_error_px: float = option(2.0, reals(0, low_open=True), "Sampson error threshold, pixels.")
    alpha: float = option(1.0, reals(0), "Exponent of the overlap O in the pair weight w = O^alpha g(P)^beta.")
    beta: float = option(0.5, reals(0), "Exponent of the saturated parallax g(P) in the pair weight w.")
    parallax_saturation_deg: float = option(10.0, reals(0, 180, low_open=True), """The parallax saturates
        here: g(P) = min(P, sat) / sat.""")
    min_overlap: float = option(0.005, reals(0, 1), "tau_O: a candidate with less overlap is rejected.")
    min_parallax_deg: float = option(0.5, reals(0, 180, high_open=True), """tau_P: a candidate with less
        parallax is rejected (degrees).""")
    max_descriptor_ratio: float = option(1.0, reals(0, 1, low_open=True), """Lowe's ratio test on the
        scorer's mutual matches: the b best are taken only among matches whose descriptor distance is at most
        this fraction of the distance to the second-best candidate in either image (1: no test). 0.8 cuts the
        accepted pairs whose pre-match rotation errs by over 30 degrees from 135 to 16 on the six shared
        scenes, but changes the selection (AUC@1 -0.003 to +0.001 on four of them), hence off.""")
    min_inliers: int = option(15, ints(0), """Fewest RANSAC inliers of an accepted candidate: RANSAC on
        unrelated images finds 8-12 of 50 by chance.""")
    tree_overlap: str = option("auto", choice("auto", "all", "best"), """The overlap in the spanning tree's
        weight. "best", the paper's: the b best matches' inliers. "all": the mutual nearest neighbours of all
        M keypoints that fit the RANSAC pose, which does not saturate at b and makes trees of the nearest
        views. "auto": "all" where the images' field of view is known to be wide (EXIF,
        extract.camera_params or a sound estimate from the images; at least
        sara.pairs.sara.field_of_view.WIDE_FIELD_OF_VIEW_DEG) and the views do not move along their optical
        axes (a drive, as the scorer's relative poses show: sara.pairs.sara.field_of_view.FORWARD_AXIAL_COSINE),
        else "best": "all" gains on wide lenses and loses 0.16-0.40 AUC@1 on long-lens crops; moving
        straight ahead its nearest views are the shortest steps. Loops, anchors and weak-view pairs always
        rank by the paper's w.""")

    def __post_init__(self) -> None:
        validate(self)
        if self.min_inliers > self.num_matches:
            raise ConfigError("score.min_inliers", f"score.min_inliers ({self.min_inliers}) must be at most "
                              f"score.num_matches ({self.num_matches}): every candidate pair would be rejected")
        if self.num_matches > self.num_keypoints:
            raise ConfigError("score.num_matches", f"score.num_matches ({self.num_matches}) must be at most "
                              f"score.num_keypoints ({self.num_keypoints})")


@dataclass(frozen=True, kw_only=True)
class SequenceConfig:
    """Ordered captures (video frames, bursts): candidates from a window of neighbouring frames too."""

    SECTION: ClassVar[str] = "sequence"

    mode: str = option("auto", choice("auto", "yes", "no"), """auto: the images are frames of a sequence when
        their names number them (frame_000123.png, IMG_0042.JPG) and their global descriptors agree (most
        nearest neighbours are neighbouring frames, see min_agreement), and the window is used from
        auto_min_frames frames; yes: whenever the names number them, at any length; no: never.""",
        advanced=False)
    window: int = option(5, ints(1), """In a sequence, each frame is also a candidate pair with this many
        following frames, besides its retrieval neighbours (which close the loops).""")
    chain: int = option(1, ints(0), """In a sequence, each frame's best accepted candidates (by weight) among
        the `window` frames after it that the selection left out, this many, are selected too (role chain):
        the chain through time that holds an incremental mapper's geometry between loop closures. On a
        1,000-frame walk the first graph without it held 54% of its verified pairs between frames 9 or more
        apart and mapped to 815 views (AUC@1 0.587); with a chain over the next 8 frames, 995 views in one
        model (0.902, 3 of 4 seeds), where as many pairs by weight alone gave 918 (0.756). End to end, same
        pair cap, one run each: AUC@1 0.920 -> 0.930 at 1,000 frames, 0.908 -> 0.921 at 3,000. 0: none.""")
    min_agreement: float = option(0.5, reals(0, 1), """auto: the share of the images' nearest global
        descriptors that must be neighbouring frames (within `window`) for the names' order to count; in long
        sequences ten times the share a shuffled order reaches, where that is lower (from about 200 frames:
        a walk that passes places twice has nearest neighbours on the other pass).""")

    auto_min_frames: int = option(500, ints(1), """auto: fewest frames of a sequence (all its sequences
        together) for the window to be used. On a 1,000-frame walk the window joined 996 views in one model
        where retrieval alone left 980 in four; on the shared scenes of 11-119 frames it gained nothing and
        cost up to 0.0016 AUC@1 (lab/notes/CAPTURES.md, section 14).""")

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

    SECTION: ClassVar[str] = "graph"

    use_loops: bool = option(True, flag(), "Run multi-scale loop consolidation.")
    use_anchors: bool = option(True, flag(), "Add long-baseline anchors.")
    use_weak: bool = option(True, flag(), "Reinforce weak views.")

    loop_budget_ratio: float = option(0.5, reals(0), """Loop-closing pairs per image (pairs / image). Half a
        pair per image closes a loop for roughly every other tree edge, the main defence against drift.""")
    anchor_budget_ratio: float = option(0.15, reals(0), """Long-baseline anchor pairs per image (pairs /
        image). Few: they are the pairs with the least overlap among the useful ones, kept for triangulation
        angle.""")
    weak_budget_ratio: float = option(0.25, reals(0), """Weak-view pairs per image (pairs / image). Enough for
        every leaf of a tree (about a quarter of the views in a typical capture) to get a second pair.""")

    loop_scale_fractions: tuple[float, float, float] = option((1 / 3, 1 / 3, 1 / 3), shares(3), """Shares of
        the loop budget for short, medium and long loops (unitless, normalised to sum 1). Equal shares: no
        scale of drift is known in advance to dominate.""")
    loop_short_frac: float = option(0.1, reals(0, 1), """Short loops have tree path length
        L <= s1 = max(loop_min_short_len, ceil(loop_short_frac * D)), D the forest's diameter (tree
        edges).""")
    loop_long_frac: float = option(0.3, reals(0, 1), """Long loops have L > s2 = max(s1 + 1,
        ceil(loop_long_frac * D)) (tree edges). The loop score's gain gamma(L) = min(1, log(1 + L) /
        log(1 + s2)) saturates at s2: long loops are ranked by weight alone, shorter ones are
        discounted.""")
    loop_min_short_len: int = option(3, ints(2), """Smallest s1 (tree edges): triangles and quadrilaterals
        always count as short.""")

    anchor_max_per_view: int = option(1, ints(1), """Most anchors touching one view (pairs). One makes the
        anchors a matching, so they spread over 2 * budget distinct views instead of piling onto a few wide
        views.""")

    weak_degree: int = option(1, ints(0), """A view whose degree in the selected graph is at most this
        (pairs) is weak: a leaf of the tree hangs on one pair, and one bad match detaches it.""")
    weak_quantile: float = option(0.2, reals(0, 1), """A view whose median accepted candidate weight is
        strictly below this quantile (0-1) of all views' medians is weak too; 0 disables this criterion.""")
    weak_per_view: int = option(1, ints(1), "Most pairs added per weak view (pairs).")

    reject_inconsistent: bool = option(False, flag(), """Before the spanning tree, reject accepted candidates
        whose pre-match rotation does not close around triangles of other candidates (symmetric or repeated
        structures: `sara.selection.ambiguity`); reason "inconsistent" in scores.csv. It never disconnects the
        candidate graph. Switch it on for photo collections of symmetric or repeated buildings, where a model
        splits or folds. Off by default: on the six shared scenes the selections already avoided the pairs it
        rejects (AUC@1 +0.004 on templeRing, -0.004 on bm-moldGoldCape, within 0.0005 on the others).""")
    max_cycle_error_deg: float = option(20.0, reals(0, 180, low_open=True), """A triangle of candidates fails
        when its rotations compose to more than this angle (degrees). The pre-match rotations use the focal
        length known before mapping, so true triangles err by several degrees.""")
    cycle_min_failed: int = option(2, ints(1), """Fewest failing triangles that can blame a pair (a single
        failing triangle does not say which of its three pairs is wrong).""")

    def __post_init__(self) -> None:
        validate(self)
        if not self.loop_short_frac <= self.loop_long_frac:
            raise ValueError("GraphConfig needs 0 <= loop_short_frac <= loop_long_frac")

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
class BudgetConfig:
    """The one owner of the pair cap: the pairs of all rounds together (selection, support before
    mapping, repair and pose-guided after it)."""

    SECTION: ClassVar[str] = "budget"

    max_pairs_per_image: float = option(4.0, reals(0), """Cap on the pairs of all rounds together (selection,
        repair, pose-guided), per image.""", advanced=False)
    max_pairs_fraction: float = option(0.25, reals(0, 1), """Cap on the pairs of all rounds together, as a
        fraction of the exhaustive N (N - 1) / 2; on small collections it bounds the selection (the spanning
        tree is always kept).""")
    densify: bool = option(False, flag(), """More 3D points (3DGS initialisation): the pose-guided round ranks
        pairs by all predicted covisible points, with its own budget and cap (densify_pairs_per_image).""",
                           advanced=False)
    densify_pairs_per_image: float = option(6.0, reals(0), """With densify: pose-guided pairs per registered
        image (pairs / image); the cap of all rounds is then densify_pairs_per_image + 2 pairs per image and
        60% of the exhaustive pairs (bm-moldGoldCape: 4 per image gave 83% of exhaustive's 3D points, 6 gave
        92%; fountain, 11 images: half of the exhaustive pairs gave 84%, 60% gave 91%).""")

    def __post_init__(self) -> None:
        validate(self)

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

    def total_cap(self, num_images: int) -> int:
        """Most pairs of all rounds together, with or without `densify`."""
        return self.densify_cap(num_images) if self.densify else self.pair_cap(num_images)


@dataclass(frozen=True, kw_only=True)
class RoundsConfig:
    """SARA's rounds around mapping: support before the first model; repair, pose-guided pairs and
    track extension after it. Every round spends from the cap of `BudgetConfig`."""

    SECTION: ClassVar[str] = "rounds"

    repair_rounds: int = option(3, ints(0), """Rounds after the first model (0: none). A round repairs views
        that the model left out although the selected graph joins them (up to repair_pairs_per_view more
        candidates per left-out view), else runs the pose-guided round once: 3 rounds leave room for a repair
        before and after it.""")
    repair_pairs_per_view: int = option(3, ints(1), "Most candidates a repair round adds per left-out view.")
    repair_descriptor_ratio: float = option(0.8, reals(0, 1, low_open=True), """A repair round ranks a
        left-out view's candidates after scoring them again with Lowe's ratio test at this ratio
        (score.max_descriptor_ratio; 1: ranked by the first scores). Across a wide baseline the scorer's b most
        similar matches are mostly wrong, so its pose and inlier counts are noise (7-14 inliers on pairs that a
        full matching verifies with 15-159, 8-16 on pairs it does not); among matches that pass the ratio test
        the pose is found (lab/notes/CAPTURES.md, section 10). The selection too scores the rejected
        candidates of views cut off from its graph's largest part again at this ratio and keeps those it
        accepts. Only runs that leave views out (of the selected graph or of the model) are touched.""")
    max_time_fraction: float = option(0.0, reals(0), """The rounds after the first model may take at most this
        fraction of the first round's match + map time (0, the default: no limit): each round's pairs are cut to
        what its matching may take at the first round's matching rate, and no round starts once the time is
        spent (the last round's mapping may overrun it). Off by default because the pairs then depend on the
        machine's speed and load, and a run no longer repeats; 0.5 kept the rounds within about that share in
        lab/notes/ETA.md. A round that registers no new image and leaves as many models is not repeated. The
        rounds' share of the time is in run.json (stages.rounds).""")
    support_min_view_inliers: int = option(200, ints(0), """Before the first mapping, a view whose verified
        pairs hold fewer inlier matches than this in all gets up to support_pairs_per_view more accepted
        candidates (best weight first), matched before the mapper runs, within half of the room the pair cap
        leaves (`sara.pairs.sara.support`; 0 disables). Views of the shared scenes sum 223 or more (thousands on
        most); on low-texture ones a view's few pairs of a few dozen inliers each leave it unregistered and
        the model splits.""")
    support_pairs_per_view: int = option(3, ints(0), """Most candidates added per weakly supported view before
        the first mapping (0 disables).""")
    fill_before_map_images: int = option(0, ints(0), """From this many images, the round before the first
        mapping also matches the best remaining accepted candidates (by weight) up to the pair cap, which the
        repair and fill rounds after mapping would otherwise add, each after mapping again (0, the default:
        never). Measured on the synthetic street world only, one run each (lab/notes/SCALE.md): 1,000 images,
        the first model 979 views in 4 models instead of 895 in 12, end result the same (979 / 4, AUC@1 0.894
        against 0.892); 3,000 images, the first model 2,962 views in 6 instead of 1,654 in 41, but that
        mapping took 1,052 s instead of 300 and the model folded (AUC@1 0.29 against 0.76, 1,793 s against
        1,100 end to end). Hence off.""")
    pose_guided_pairs_per_image: float = option(1.0, reals(0), """Pairs per registered image that the
        pose-guided round adds after the first model (pairs / image; 0 disables the round): the unmatched
        pairs of registered views with the highest weight w = O^alpha g(P)^beta, overlap and parallax
        predicted by the model. With the model's poses, the gap a sparse selection leaves is a lack of
        constraints, which a few well-chosen pairs per view recover.""")
    pose_guided_min_points: int = option(30, ints(1), """A pair is matched in the pose-guided round only if the
        first model predicts at least this many covisible points (points); fewer rarely pass verification
        (15 inliers). Where the scorer used every keypoint of both views (no more than score.num_keypoints, as
        in low-texture captures) its count of the pair's matches that fit one pose must reach it too: there
        the model's prediction ran ahead of what matching found (two low-texture stand-ins, four namings
        each: 11-26 of a round's 39-42 pairs verified before, 22-34 of 22-34 but one after).""")
    pose_guided_max_view_angle_deg: float = option(45.0, reals(0, 180, low_open=True), """A point counts as
        covisible only if the two views see it from directions at most this far apart (degrees): SIFT seldom
        matches across wider angles.""")
    pose_guided_max_per_view: int = option(2, ints(0), """Most pose-guided pairs that touch one view (pairs; 0:
        no limit): the best pairs are taken in order of weight, skipping a pair once one of its views has this
        many. 2, twice a view's even share at 1 pair per image, spreads the round over the views (raise it
        with pose_guided_pairs_per_image). Against no limit: AUC@1 +0.009 to +0.025 on three stand-in scenes
        and +0.010 on bm-moldGoldCape, -0.001 to -0.005 on three others.""")
    pose_guided_last: bool = option(True, flag(), """When the repairs used up repair_rounds with no round
        refining the model (large captures: each repair round joins more left-out views, so the pose-guided
        round never came), one more round for the pose-guided pairs, refined into the model with its poses
        held (no mapping again). Synthetic walks, one run each (lab/notes/SCALE.md): 1,000
        images AUC@1 / @5 0.927 / 0.979 against 0.911 / 0.976 (identical runs: 0.001 apart), 3,000 images
        0.912 / 0.973 against 0.903 / 0.972; retrieval top-k 0.924 / 0.970 and 0.909 / 0.965. Time
        after extraction at 1,000 images, idle machine: 578 s against 344-363 s (the round itself 169 s;
        retrieval top-k 767 s, run right after). No shared scene reaches the third round.""")
    extend_tracks: bool = option(True, flag(), """When the pose-guided round refines the model (or else, on the
        final model), add to its tracks the keypoints that observe its 3D points without a match saying so,
        then bundle-adjust once more: each view against the points it should see, a keypoint within
        extend_tracks_radius_px of the projection whose descriptor passes COLMAP's SIFT matching tests
        against the track's (`sara.colmap.tracks.extend_tracks`). Longer tracks make a stronger final bundle
        adjustment without matching more pairs.""")
    extend_tracks_radius_px: float = option(1.5, reals(0, low_open=True), """How far from a point's projection a
        keypoint may be to join its track (pixels): 1.0 and 2.0 measured worse on some of the six shared
        scenes.""")
    extend_tracks_scale_quantile: float = option(0.995, reals(0, 1), """Where the keypoints carry their scale
        (SIFT), a keypoint joins a track only if its size in the scene (scale x depth / focal length) is
        within this quantile of the model's own tracks' spread around their median (1.38-1.52x on the six
        shared scenes); 0: not tested. Against no test: AUC@1 +0.004 on bm-moldGoldCape and 0 to +0.0034 on
        the other five; neutral on half-size stand-ins, where 0.98 and 0.99 lose up to 0.006; -0.002 to
        -0.004 on two 25-degree crops.""")
    extend_model: bool = option(True, flag(), """A round after mapping that must map again (views left out of
        the model) continues from the model it has (COLMAP's mapper with an input model) instead of mapping
        everything from scratch.""")

    def __post_init__(self) -> None:
        validate(self)
