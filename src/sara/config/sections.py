"""The configuration sections of the stages every pair source shares: one frozen dataclass each.

Each field is written once, with `option(default, rule, doc, advanced=...)`: its default, its valid
values, whether it is an everyday key, and what it does. SARA's own sections (scorer, graph, pair
budget, rounds) are in `sara_sections`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from .rules import (
    CAMERA_MODELS,
    choice,
    device,
    flag,
    growth,
    ints,
    name,
    numbers_list,
    option,
    reals,
    text,
    threads,
    validate,
)


@dataclass(frozen=True, kw_only=True)
class ImagesConfig:
    """Which images of the folder make the collection, and how they are read."""

    SECTION: ClassVar[str] = "images"

    recursive: bool = option(False, flag(), "Look for images in sub-folders too (names keep the sub-path).",
                             advanced=False)
    exif_orientation: str = option("ignore", choice("ignore", "apply"), """EXIF orientation tags: "ignore" uses
        the stored pixels, as COLMAP, 3DGS and nerfstudio's COLMAP loaders do; "apply" writes upright copies
        to <out>/images_upright and reconstructs from those.""")

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class ExtractConfig:
    """Local features: COLMAP's SIFT (RootSIFT, COLMAP's defaults) or a learned backend."""

    SECTION: ClassVar[str] = "extract"

    backend: str = option("sift", name(), "Local-feature backend, see `sara.features.BACKENDS`.", advanced=False)
    max_num_features: int = option(8192, ints(1), "Keypoints kept per image at most.", advanced=False)
    max_image_size: int = option(3200, ints(32), """Longer image side in pixels; larger images are downscaled
        for extraction and their keypoints mapped back.""")
    device: str = option("auto", device(), "Learned backends: auto, cpu or cuda.")
    weights: str = option("", text(), """Learned backends: a local weights file (else found where
        `sara weights` lists).""")
    camera_model: str = option("SIMPLE_RADIAL", choice(*CAMERA_MODELS), "COLMAP camera model of the images.")
    camera_mode: str = option("auto", choice("auto", "single", "per_image", "per_folder"), """How images share
        cameras. auto: one shared camera when all images have the same size and the same EXIF camera (make,
        model, focal; or no EXIF at all), one per video for the frames of a folder of videos, one per numbered
        sequence of frames without EXIF (clip0_0001.png, ...: names differing by a frame number, split where the
        frame size changes; also clips of one size, which another lens or a zoom may have filmed), one per phone
        (EXIF make, model and focal lengths, and size: a phone held upright is another camera) when some
        photos share one, else one per image (photos from different phones).""",
                              advanced=False)
    camera_params: str = option("", numbers_list(), """Known intrinsics, e.g. "fx,fy,cx,cy" for PINHOLE; empty:
        from EXIF or the prior.""", advanced=False)
    default_focal_length_factor: float = option(1.2, reals(0, 100, low_open=True), """COLMAP's focal length
        prior: focal = factor * max(width, height).""")
    estimate_focal: bool = option(True, flag(), """With one shared camera (or one per video) and neither an
        EXIF focal length nor camera_params: estimate its focal length from pairs of neighbouring images and use
        it where it is at least 2.5x the prior (long lenses; `sara.scoring.focal`).""")
    num_threads: int = option(-1, threads(), "COLMAP's extraction threads; -1: every core.")
    mask_path: str = option("", text(), """A folder of masks (--masks): keypoints on a mask's black pixels
        are left out (an operator's hand, a car's bonnet, people walking through, the sky). A mask is an
        image of its image's shape, DIR/<image name>.png as COLMAP names it, DIR/<name without extension>.png
        as nerfstudio does, or under the image's own name; an image without one is used whole (`sara.masks`). One
        mask image instead of a folder masks every image (a car's bonnet, a mount).""")

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class RetrievalConfig:
    """Global descriptors and the cosine kNN that proposes candidate pairs."""

    SECTION: ClassVar[str] = "retrieval"

    descriptor: str = option("vlad", name(), """Global descriptor: vlad, bow, dinov2 or aliked-gem (the
        learned ones need local weights, see `sara weights`).""", advanced=False)
    num_neighbors: int = option(20, ints(1), """k: nearest neighbours kept per image (the union is
        symmetric).""", advanced=False)
    codebook_size: int = option(64, ints(1), "VLAD visual words, learned from the collection itself.")
    features_per_image: int = option(1000, ints(1), """RootSIFT descriptors per image used for VLAD (largest
        scale first).""")
    weights: str = option("", text(), "Local weights file for learned descriptors (dinov2, aliked-gem).")
    device: str = option("auto", device(), "Learned descriptors: auto, cpu or cuda.")
    image_size: int = option(448, ints(32), "Learned descriptors: longer image side in pixels.")
    widen_neighbors: int = option(80, ints(0), """SARA only: when the selected graph falls apart, the views
        outside its largest component get more candidates, from this many nearest neighbours (then four
        times as many if still apart; each round at most as many new candidates as were scored before it;
        0: off).""")

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class PairsConfig:
    """Which pair source feeds matching."""

    SECTION: ClassVar[str] = "pairs"

    method: str = option("sara", name(), """Pair source: sara, exhaustive, sequential, vocabtree, retrieval,
        or the path of a pairs.txt file.""", advanced=False)

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class SequentialConfig:
    """The `sequential` pair source: each image with the next ones in name order (video frames)."""

    SECTION: ClassVar[str] = "sequential"

    overlap: int = option(10, ints(1), "Each image is paired with this many following images.")
    quadratic: bool = option(False, flag(), """Pair each image with the images 1, 2, 4, 8, ... places on
        (overlap of them) instead, as pycolmap's quadratic overlap.""")
    loop_detection: bool = option(False, flag(), """Add retrieval neighbours (global descriptors) of every
        loop_period-th image, to close loops the sequence misses.""")
    loop_period: int = option(10, ints(1), "With loop_detection: every this many images is a loop query.")
    loop_neighbors: int = option(5, ints(1), "With loop_detection: retrieval neighbours paired per query.")

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class VocabTreeConfig:
    """The `vocabtree` pair source: COLMAP's vocabulary-tree retrieval."""

    SECTION: ClassVar[str] = "vocab_tree"

    path: str = option("", text(), """A saved pycolmap visual index; when empty one is built from this
        collection's own SIFT descriptors.""")
    num_images: int = option(30, ints(1), "Top-k of the vocabulary tree retrieval, per query image.")
    num_words: int = option(4096, ints(2), "Visual words of a tree built from the collection.")

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class MatchConfig:
    """Full matching of the selected pairs and COLMAP's geometric verification of the matches."""

    SECTION: ClassVar[str] = "match"

    backend: str = option("auto", name(), """Matcher, see `sara.matchers.BACKENDS`; auto: the usual one for
        the features.""")
    device: str = option("auto", device(), "Learned matchers: auto, cpu or cuda.")
    weights: str = option("", text(), "Learned matchers: a local weights file.")
    max_ratio: float = option(0.8, reals(0, 1, low_open=True), "Lowe's ratio test of SIFT matching.")
    max_distance: float = option(0.7, reals(0, low_open=True), "Largest descriptor distance of a SIFT match.")
    cross_check: bool = option(True, flag(), "Keep only mutual nearest neighbours.")
    min_num_inliers: int = option(15, ints(1), "Fewest inliers of a verified pair.")
    num_threads: int = option(-1, threads(), "COLMAP's matching threads; -1: every core.")
    chunk_size: int = option(128, ints(1), "Pairs per matcher call: progress granularity and resume points.")

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class MapConfig:
    """COLMAP's mapper, run on the verified matches."""

    SECTION: ClassVar[str] = "map"

    mapper: str = option("incremental", choice("incremental", "global"), "COLMAP's mapper.", advanced=False)
    min_model_size: int = option(3, ints(2), "Fewest registered images of a model that is kept.")
    abs_pose_min_num_inliers: int = option(15, ints(3), """Registration of a new image (PnP): fewest
        inliers. COLMAP's default is 30; lower values pose wide-baseline views that COLMAP leaves out
        (templeSparseRing: 16 of 16 views instead of 13).""")
    abs_pose_min_inlier_ratio: float = option(0.1, reals(0, 1, low_open=True), """Registration of a new image
        (PnP): smallest inlier ratio (COLMAP's default: 0.25).""")
    num_threads: int = option(-1, threads(), "COLMAP's mapping threads; -1: every core.")
    refine_distortion: bool = option(True, flag(), """Incremental mapper: refine the cameras' distortion
        (COLMAP's ba_refine_extra_params) while mapping. false holds it at its start (0 without
        calibration), in the rounds' refinements too, where few points pin it down: on a low-texture
        stand-in whose principal point is 9 px off the centre the refined radial term ran to -0.7 to
        -1.6, and its first models broke into pieces (7-26 of 47 views in the largest, SARA's pairs
        and exhaustive matching's alike); held, every mapping of the same databases kept all 47 views
        in one model. true: a first model that
        holds under half the views the verified pairs join is mapped again with it held, and that
        mapping is kept (and its continuations hold it) when its largest model holds more views.""")
    hold_distortion_starved: bool = option(True, flag(), """Incremental mapper: where SIFT starved (under 500
        keypoints per image on average) and a camera's focal length is a guess (no EXIF, no camera_params),
        hold the distortion from the first mapping on, as the retry above holds it, and refine it in the
        rounds' refinements. Few weak matches do not pin it down: on two low-texture stand-ins (122 and
        211 keypoints per image) the refined radial term ran to -0.8 to -1.6 on images without any, and
        first models holding over half the views (no retry) stayed split.""")
    two_view_points: bool = option(False, flag(), """Incremental mapper: also triangulate points seen in
        two views only (COLMAP ignores them: ignore_two_view_tracks). With only two photos every point is
        seen in two, so COLMAP builds no model of them. false: where no model could be built otherwise,
        the mapper maps once more with them (two photos of a facade: 2 of 2 views, 4,696 points).""")
    contradicted_remaps: int = option(2, ints(0), """Incremental mapper: when more than 0.5% of the verified
        pairs between the first model's views, or at least 20 of them, contradict it (their matches lie
        over 4 px off its epipolar lines: a model bent where the views pass a place twice), map again at
        most this many times, under the next seed and starting from the view in most contradicting pairs,
        and keep the model its pairs agree with, else the largest; stop early when a mapping is contradicted
        by the same pairs as the one before it (the pairs are wrong, not the model). Global mapper: a model
        so contradicted is mapped again by the incremental mapper and the better one kept. 0: never.""")
    mend_seam: bool = option(True, flag(), """Incremental mapper: before mapping a contradicted first model
        again, take out the views of the contradicting pairs and every view up to two verified pairs
        from them, and continue the rest, which registers them again; kept, and no remap follows, when
        its pairs then agree with it and it holds as many views less the seam's. Tried only where the
        cut keeps at least half the model (a seam in a large model, not a small scene bent as a whole):
        at 10,000 images it mended a first model in minutes where a remap takes hours. A round's
        continued model that its pairs contradict is mended the same way (never mapped again).""")
    ba_global_growth: float = option(0.0, growth(), """Incremental mapper: adjust the whole model each time
        its registered views or points grew by this factor (COLMAP's ba_global_frames_ratio and
        ba_global_points_ratio, 1.1). 0: by size, COLMAP's 1.1 for scenes of fewer than 500 images
        and 1.4 from 500 (the same models in less time on the 1,000-image synthetic world).""")
    ba_global_refinements: int = option(0, ints(0), """Incremental mapper: most rounds of re-triangulation
        and adjustment in each global bundle adjustment (COLMAP's ba_global_max_refinements, 5).
        0: by size, COLMAP's 5 for scenes of fewer than 500 images and 1 from 500.""")
    ba_direct_max_images: int = option(0, ints(0), """Incremental mapper: largest model whose global bundle
        adjustments use Ceres' direct sparse solver (COLMAP switches to an iterative one above 1,000,
        many times slower). 0: by size, COLMAP's own mapping loop for scenes of fewer than 1,000
        images, from 1,000 sara drives the mapper step by step with the direct solver up to 20,000. A
        value set by hand always uses that loop; under 1,000 it keeps COLMAP's limit.""")
    checkpoint_minutes: float = option(10.0, reals(0), """Incremental mapper, step-by-step mapping (scenes of
        1,000 images or more, or ba_direct_max_images set): write the models so far at most this often (after
        a global adjustment) to .sara/map-checkpoint (a mapping done again, under another seed or from another
        start, to .sara/map-checkpoint-*), so that a run killed during a long mapping resumes from them instead
        of mapping again from the start. 0: never.""")

    def __post_init__(self) -> None:
        validate(self)


@dataclass(frozen=True, kw_only=True)
class ExecuteConfig:
    """Where the work runs. Results never depend on these settings, so no output is keyed on them."""

    SECTION: ClassVar[str] = "execute"

    executor: str = option("auto", choice("auto", "serial", "processes", "ray"), """auto: serial for one
        worker, else processes.""")
    workers: int = option(0, ints(0), "Parallel workers; 0: one per CPU core.", advanced=False)
    ray_address: str = option("", text(), """With executor=ray: a cluster address or "auto"; empty starts a
        local one.""")
    shard_size: int = option(512, ints(1), """Most pairs per shard of parallel scoring (4 shards per worker
        down to 64 pairs; fewer than two shards: scored in-process).""")

    def __post_init__(self) -> None:
        validate(self)
