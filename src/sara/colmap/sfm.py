"""Structure from motion: COLMAP's incremental and global mappers, its bundle adjustment, and the
mapper's output written as numbered model folders."""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pycolmap

from . import stepwise
from .consistency import Agreement, agreement
from .database_queries import database_images, verified_inliers
from .edit import prune_model
from .native import native_errors

logger = logging.getLogger(__name__)


def mapper_init_requirements() -> tuple[int, float]:
    """(inlier matches, triangulation angle in degrees) that COLMAP's incremental mapper needs
    between two views to start a model."""
    opts = pycolmap.IncrementalPipelineOptions()
    return int(opts.mapper.init_min_num_inliers), float(opts.mapper.init_min_tri_angle)


@dataclass
class MappedModels:
    """The models of one mapping, kept inside the adapter: how many views each registered, and
    writing them out (`write_models_by_size`)."""

    reconstructions: dict[int, pycolmap.Reconstruction]
    forward_start: bool = False  # the mapper started from a pair that moved along the viewing direction
    two_view_points: bool = False  # mapped with the points seen in two views only (`ignore_two_view_tracks` off)
    seed: int | None = None  # the random seed of the mapping that built them
    agreement_check: Agreement | None = None  # the largest model against its pairs, where checked
    remaps: int = 0  # mappings under other seeds because the first model was contradicted
    mapper: str | None = None  # set where another mapper than the one asked for built them
    distortion_held: bool = False  # mapped with the cameras' distortion held (`refine_extra_params` False)
    mended: bool = False  # a contradicted first model cut at its seam and continued (`mend`)

    def agreement(self, db_path: Path, min_num_inliers: int) -> Agreement:
        """How the largest model agrees with the verified pairs between its views (`consistency`)."""
        if not self.reconstructions:
            return Agreement(0)
        largest = max(self.reconstructions.values(), key=lambda rec: rec.num_reg_images())
        return agreement(largest, db_path, min_num_inliers=min_num_inliers)

    @property
    def largest(self) -> int:
        """Views registered in the largest model (0 when there is none)."""
        return max((rec.num_reg_images() for rec in self.reconstructions.values()), default=0)

    def write_by_size(self, folder: Path) -> list[int]:
        return write_models_by_size(folder, self.reconstructions)


def incremental_mapping(
    db_path: Path, image_dir: Path, out_dir: Path, *, seed: int, min_model_size: int,
    abs_pose_min_num_inliers: int, abs_pose_min_inlier_ratio: float, num_threads: int = -1,
    on_next_image: Callable[[], None] | None = None, input_path: Path | None = None,
    forward_start: bool = False, ba_global_ratio: float | None = None, ba_global_refinements: int | None = None,
    direct_solver_up_to: int | None = None, first_image: str | None = None,
    checkpoint: stepwise.Checkpoint | None = None, refine_extra_params: bool = True, two_view_points: bool = False,
) -> MappedModels:
    """COLMAP's incremental mapper; with `input_path` it continues from that model (registers the
    images it lacks, then bundle-adjusts) instead of starting from an empty one.

    `forward_start` lets the mapper start from a pair of views that moved along the viewing
    direction: COLMAP refuses such a start (`init_max_forward_motion`, 0.95 of the baseline along
    the optical axis), so a camera driving or walking straight ahead never starts a model.
    `ba_global_ratio`: adjust the whole model each time its views or points grew by this factor
    (COLMAP's `ba_global_frames_ratio` and `ba_global_points_ratio`; None keeps COLMAP's 1.1).
    `ba_global_refinements`: the most rounds of re-triangulation and adjustment in each global
    adjustment (COLMAP's `ba_global_max_refinements`; None keeps its 5).
    `direct_solver_up_to`: the mapping is driven step by step (`stepwise`) so that its global
    adjustments use Ceres' direct sparse solver up to this many images (None: COLMAP's pipeline,
    iterative above 1,000).
    `first_image`: the first model starts from this image (by name) and the partner the mapper picks
    for it; the mapping is then driven step by step (direct solver as COLMAP sets it unless
    `direct_solver_up_to` says more).
    `checkpoint`: where the step-by-step mapping keeps its models so far and resumes from them
    (`stepwise.Checkpoint`; COLMAP's own loop has none).
    `refine_extra_params`: the adjustments refine the cameras' distortion (COLMAP's default); False
    holds it where it starts.
    `two_view_points`: also triangulate the points seen in two views only (COLMAP ignores them).
    """
    opts = pycolmap.IncrementalPipelineOptions()
    if forward_start:
        opts.mapper.init_max_forward_motion = 1.0
    if ba_global_ratio is not None:
        opts.ba_global_frames_ratio = opts.ba_global_points_ratio = ba_global_ratio
    if ba_global_refinements is not None:
        opts.ba_global_max_refinements = ba_global_refinements
    opts.min_model_size = min_model_size
    opts.ba_refine_extra_params = refine_extra_params
    opts.triangulation.ignore_two_view_tracks = not two_view_points
    opts.num_threads = num_threads
    opts.mapper.abs_pose_min_num_inliers = abs_pose_min_num_inliers
    opts.mapper.abs_pose_min_inlier_ratio = abs_pose_min_inlier_ratio
    opts.random_seed = seed
    opts.mapper.random_seed = seed
    opts.triangulation.random_seed = seed
    with native_errors("map the matches (incremental mapper)", Path(out_dir)), \
            _mappable_start(Path(db_path), input_path, opts.min_num_matches, Path(out_dir)) as input_path:
        if direct_solver_up_to is not None or first_image is not None:
            first_id = None if first_image is None else database_images(Path(db_path))[first_image]
            return MappedModels(stepwise.incremental_mapping(
                Path(db_path), Path(image_dir), Path(out_dir), opts, direct_up_to=direct_solver_up_to or 0,
                on_next_image=on_next_image, input_path=input_path, first_image_id=first_id, checkpoint=checkpoint))
        return MappedModels(pycolmap.incremental_mapping(
            str(db_path), str(image_dir), str(out_dir), options=opts,
            input_path=str(input_path) if input_path is not None else "",
            next_image_callback=on_next_image,
        ))


@contextlib.contextmanager
def _mappable_start(db_path: Path, input_path: Path | None, min_num_matches: int, out_dir: Path):
    """The model to continue from: `input_path`, or a copy of it without the views that the mapper
    cannot hold, those left with no verified pair of `min_num_matches` inliers in the database (their
    pairs went with images removed by an update, or were not selected again). COLMAP leaves such a
    view out of what it loads from the database, and continuing a model that holds it fails on a
    lookup by its id (IndexError: unordered_map::at). None (map from scratch) when fewer than two
    views stay; the copy, inside `out_dir` (which a killed mapping's next start clears), is deleted
    on exit."""
    if input_path is None:
        yield None
        return
    linked = {name for pair in verified_inliers(db_path, min_num_matches) for name in pair}
    rec = pycolmap.Reconstruction(str(input_path))
    lost = {image.name for image in rec.images.values() if image.has_pose and image.name not in linked}
    if not lost:
        yield input_path
        return
    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".start-", dir=out_dir) as tmp:
        left = prune_model(Path(input_path), lost, Path(tmp))
        logger.warning("map: %d of the %d views of the model continued have no verified pair left (%s): "
                       "left out of it%s", len(lost), rec.num_reg_images(), ", ".join(sorted(lost)[:3]) +
                       (", ..." if len(lost) > 3 else ""), "" if left >= 2 else "; too few views stay: mapped anew")
        yield Path(tmp) if left >= 2 else None


def global_mapping(db_path: Path, image_dir: Path, out_dir: Path, *, seed: int,
                   num_threads: int = -1) -> MappedModels:
    """COLMAP's global mapper (GLOMAP); the settings this pycolmap lacks are left at its defaults."""
    opts = pycolmap.GlobalPipelineOptions()
    with contextlib.suppress(AttributeError):
        opts.num_threads = num_threads
    with contextlib.suppress(AttributeError):
        opts.random_seed = seed
    with native_errors("map the matches (global mapper)", Path(out_dir)):
        return MappedModels(pycolmap.global_mapping(str(db_path), str(image_dir), str(out_dir), options=opts))


def bundle_adjust(rec: pycolmap.Reconstruction, options: pycolmap.BundleAdjustmentOptions | None = None) -> None:
    """COLMAP's global bundle adjustment of `rec` (`pycolmap.bundle_adjustment`) without its console output.

    pycolmap's call switches COLMAP's log to the console (glog's alsologtostderr, minloglevel 0) and
    leaves it so: its report, and every later COLMAP message of the process, then reached the terminal
    even with `--quiet`. Unless the log already goes to the console (`--verbose`), its own report is
    kept off the terminal (it still reaches the log file) and the log settings are put back afterwards.
    Ceres' direct sparse solver is allowed up to `stepwise.DIRECT_SOLVER_MAX_IMAGES` images (COLMAP:
    1,000, then an iterative solver many times slower on large models).
    """
    import sys

    log = pycolmap.logging
    saved = (log.logtostderr, log.alsologtostderr, log.stderrthreshold, log.minloglevel)
    to_console = saved[0] or saved[1]
    options = options or pycolmap.BundleAdjustmentOptions()
    options.ceres.max_num_images_direct_sparse_cpu_solver = max(
        options.ceres.max_num_images_direct_sparse_cpu_solver, stepwise.DIRECT_SOLVER_MAX_IMAGES)
    if to_console:
        pycolmap.bundle_adjustment(rec, options)
        return
    sys.stderr.flush()
    kept = os.dup(2)
    try:
        with open(os.devnull, "wb") as sink:
            os.dup2(sink.fileno(), 2)
        pycolmap.bundle_adjustment(rec, options)
    finally:
        os.dup2(kept, 2)
        os.close(kept)
        log.logtostderr, log.alsologtostderr, log.stderrthreshold, log.minloglevel = saved


def write_models_by_size(folder: Path, recs: dict[int, pycolmap.Reconstruction]) -> list[int]:
    """Write mapper output as `folder/0, 1, ...`, 0 the largest; returns registered images per model.

    A model whose images are all in a larger one is left out: continuing from an input model, COLMAP's
    mapper can build a new model holding every view and keep the input beside it.
    """
    import shutil

    order, seen = [], set()
    for key, rec in sorted(recs.items(), key=lambda kv: (-kv[1].num_reg_images(), kv[0])):
        names = {im.name for im in rec.images.values() if im.has_pose}
        if names and names <= seen:
            logger.info("map: left out a model of %d views that a larger model holds as well", len(names))
            continue
        seen |= names
        order.append((key, rec))
    for sub in list(Path(folder).iterdir()):
        if sub.is_dir():
            shutil.rmtree(sub)
    sizes = []
    for new_index, (_, rec) in enumerate(order):
        dst = Path(folder) / str(new_index)
        dst.mkdir()
        with native_errors(f"write the model {dst}", Path(folder)):
            rec.write(str(dst))
        sizes.append(int(rec.num_reg_images()))
    return sizes
