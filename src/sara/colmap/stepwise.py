"""COLMAP's incremental mapping driven one step at a time, for scenes too large for its own loop.

COLMAP's incremental mapper adjusts the whole model now and then; above 1,000 registered images
Ceres switches that adjustment from its direct sparse solver to an iterative one, and pycolmap's
pipeline offers no setting for the switch. On the 3,000-image synthetic world one such adjustment
took 3-19 minutes past 1,000 views, most of the mapping; on a converged 992-view model the iterative
solver took 103.5 s where the direct one took 6.8 s for the same result (lab/notes/SCALE.md).

`incremental_mapping` here runs the same steps as COLMAP's pipeline through pycolmap's
`IncrementalMapper` (first pair, next images registered from 3D points or else from 2D matches
alone, triangulation, local refinement, global refinement by growth, several models, the two
relaxations of the first pair's thresholds), with two changes: its global adjustments may use the
direct sparse solver up to `direct_up_to` images, and a model given to continue from (a repair
round's) is grown on a lighter schedule (`_Run.model`). Each model's time by step is logged.

A `Checkpoint` writes the models so far every few minutes (after a global adjustment) and once
the mapping ends; a mapping of the same key killed before its stage finished resumes from them:
the models that were done stay as they are and the one that was growing grows on.
"""

from __future__ import annotations

import contextlib
import copy
import glob
import json
import logging
import os
import shutil
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import pycolmap

logger = logging.getLogger(__name__)

#: sara's own adjustments, and its step-by-step mapping by default, use Ceres' direct sparse solver up
#: to this many images (COLMAP: 1,000). On a converged 9,300-view model of the 10,000-image synthetic
#: world one global adjustment took 74.7 s with it and did not end in 900 s with the iterative solver;
#: the first mapping of that world, with the limit at 5,000, did not end in 90 minutes, and with it
#: above the world's size ended in 81 (lab/notes/SCALE.md). Not measured past 10,000 views.
DIRECT_SOLVER_MAX_IMAGES = 20000
#: COLMAP gives up on a first pair whose model stays under min_model_size after this many failed trials
MIN_INITIAL_REG_TRIALS = 30
#: rounds of local adjustment and re-triangulation after each view registered into a model being
#: continued (COLMAP: `ba_local_max_refinements`, 2). A first mapping keeps COLMAP's two: with one, the
#: first mapping of the 3,000-image world split into models of at most 1,050 views instead of 1,633
#: (one run each, lab/notes/SCALE.md)
CONTINUED_LOCAL_REFINEMENTS = 1


@dataclass(frozen=True)
class Checkpoint:
    """Where a mapping keeps its models so far (`folder`), for which inputs (`key`), and how often
    it writes them (at most every `every_s` seconds, after a global adjustment)."""

    folder: Path
    key: str
    every_s: float

    def save(self, manager: pycolmap.ReconstructionManager, current: int | None, elapsed_s: float = 0.0) -> None:
        """Write every model of `manager` (`current`: the one growing; None: the mapping ended) and the
        seconds the mapping has taken so far, over every run of it; the folder is replaced only once
        the new one is complete."""
        new, old = self.folder.with_name(self.folder.name + ".next"), self.folder.with_name(self.folder.name + ".old")
        shutil.rmtree(new, ignore_errors=True)
        new.mkdir(parents=True)
        views = []
        for idx in range(manager.size()):
            (new / str(idx)).mkdir()
            manager.get(idx).write(str(new / str(idx)))
            views.append(manager.get(idx).num_reg_frames())
        (new / "checkpoint.json").write_text(json.dumps({"key": self.key, "current": current, "views": views,
                                                         "elapsed_s": round(elapsed_s, 3)}))
        shutil.rmtree(old, ignore_errors=True)
        if self.folder.exists():
            os.replace(self.folder, old)
        os.replace(new, self.folder)
        shutil.rmtree(old, ignore_errors=True)

    def restore(self, manager: pycolmap.ReconstructionManager) -> dict[str, Any] | None:
        """Read the models of a checkpoint of this key into `manager` (empty); returns its record
        (`current`, `views`), or None when there is none (or one of other inputs)."""
        for folder in (self.folder, self.folder.with_name(self.folder.name + ".old")):
            try:
                record = json.loads((folder / "checkpoint.json").read_text())
                if record.get("key") == self.key:
                    for idx in range(len(record["views"])):
                        manager.read(str(folder / str(idx)))
                    if [manager.get(i).num_reg_frames() for i in range(manager.size())] != record["views"]:
                        raise ValueError("the models differ from the record")
                    return record
            except (OSError, ValueError, RuntimeError, KeyError, TypeError, IndexError):  # damaged: not used
                manager.clear()
        return None

    def elapsed_s(self) -> float:
        """Seconds of mapping held by this checkpoint and those derived from it (the mappings of these
        inputs that a killed run did): what the map stage of the run that resumes them adds to its own."""
        total = 0.0
        for folder in [self.folder, *self.folder.parent.glob(glob.escape(self.folder.name) + "-*")]:
            if folder.suffix in (".next", ".old"):
                continue
            try:
                record = json.loads((folder / "checkpoint.json").read_text())
                total += float(record.get("elapsed_s", 0.0)) if str(record.get("key")).startswith(self.key) else 0.0
            except (OSError, ValueError, TypeError, AttributeError):  # damaged or none: nothing to add
                continue
        return total

    def derived(self, label: str, detail: str = "") -> Checkpoint:
        """The checkpoint of another mapping of the same inputs (a remap under another seed, a retry
        from another start): its own folder beside this one, named by `label`; `detail` (what that
        mapping starts from) goes into its key only."""
        return replace(self, folder=self.folder.with_name(f"{self.folder.name}-{label}"),
                       key=f"{self.key}/{label}/{detail}")

    def remove(self) -> None:
        """Remove this checkpoint and every one derived from it."""
        name = self.folder.name
        for folder in self.folder.parent.glob(glob.escape(name) + "*"):
            if folder.name in (name, name + ".next", name + ".old") or folder.name.startswith(name + "-"):
                shutil.rmtree(folder, ignore_errors=True)


def incremental_mapping(db_path: Path, image_dir: Path, out_dir: Path, opts: pycolmap.IncrementalPipelineOptions,
                        *, direct_up_to: int, on_next_image: Callable[[], None] | None = None,
                        input_path: Path | None = None, first_image_id: int | None = None,
                        checkpoint: Checkpoint | None = None) -> dict[int, pycolmap.Reconstruction]:
    """Map `db_path` as `pycolmap.incremental_mapping` does, the global adjustments allowed Ceres'
    direct sparse solver up to `direct_up_to` images; each model is written to `out_dir/<index>`.
    With `first_image_id` the first model starts from that image and the partner COLMAP picks for
    it (the later models as COLMAP starts them; COLMAP's own `init_image_id1` would hold every model
    to that image, so the views it cannot reach got no model). With `checkpoint` (and no
    `input_path`) the models so far are kept there, and a mapping that finds them goes on from them."""
    cache_options = pycolmap.DatabaseCacheOptions()
    cache_options.min_num_matches = opts.min_num_matches
    cache_options.ignore_watermarks = opts.ignore_watermarks
    with pycolmap.Database.open(str(db_path)) as database:
        cache = pycolmap.DatabaseCache.create(database, cache_options)
    manager = pycolmap.ReconstructionManager()
    if input_path is not None:
        manager.read(str(input_path))
        checkpoint = None
    resumed = checkpoint.restore(manager) if checkpoint is not None else None
    if resumed is not None:
        logger.warning("map: resuming the mapping from its checkpoint: %d models of %s views%s", len(resumed["views"]),
                       resumed["views"], "" if resumed["current"] is None else ", the last one growing")
        first_image_id = None
    run = _Run(opts, cache, manager, direct_up_to, on_next_image, first_image_id, checkpoint,
               started=time.monotonic() - float((resumed or {}).get("elapsed_s", 0.0)))
    if cache.num_images() > 0 and (resumed is None or resumed["current"] is not None):
        run.all(resumed)
        if checkpoint is not None:
            checkpoint.save(manager, None, time.monotonic() - run.started)
    models = {}
    for idx in range(manager.size()):
        rec = manager.get(idx)
        if opts.extract_colors:
            rec.extract_colors_for_all_images(str(image_dir))
        (Path(out_dir) / str(idx)).mkdir(parents=True, exist_ok=True)
        rec.write(str(Path(out_dir) / str(idx)))
        models[idx] = rec
    return models


class _Run:
    """One mapping: COLMAP's `IncrementalPipeline::Run`, `Reconstruct` and `ReconstructSubModel`."""

    def __init__(self, opts: pycolmap.IncrementalPipelineOptions, cache: pycolmap.DatabaseCache,
                 manager: pycolmap.ReconstructionManager, direct_up_to: int,
                 on_next_image: Callable[[], None] | None, first_image_id: int | None = None,
                 checkpoint: Checkpoint | None = None, started: float | None = None) -> None:
        self.opts, self.cache, self.manager, self.on_next_image = opts, cache, manager, on_next_image
        self.checkpoint, self.saved_at, self.current = checkpoint, time.monotonic(), 0
        self.started = time.monotonic() if started is None else started  # of the mapping, earlier runs included
        self.pipeline = pycolmap.IncrementalPipeline(opts, cache, manager)
        self.first_pipeline = None  # starts the first new model from a given image, then is dropped
        if first_image_id is not None:
            first = copy.copy(opts)
            first.init_image_id1, first.init_image_id2 = first_image_id, -1
            self.first_pipeline = pycolmap.IncrementalPipeline(first, cache, manager)
        self.global_ba = opts.get_global_bundle_adjustment()
        self.global_ba.ceres.max_num_images_direct_sparse_cpu_solver = max(
            direct_up_to, self.global_ba.ceres.max_num_images_direct_sparse_cpu_solver)
        self.local_ba = opts.get_local_bundle_adjustment()
        self.triangulation = opts.get_triangulation()
        fallback = [False, True] if opts.structure_less_registration_fallback else [False]
        self.kinds = [True] if opts.structure_less_registration_only else fallback
        self.spent_s: Counter[str] = Counter()  # wall seconds of the current model by step, for the log

    def all(self, resumed: dict[str, Any] | None = None) -> None:
        """With `resumed` (a checkpoint's record, its models in the manager): the finished models are
        the mapper's again as they were, and the growing one grows on as a first mapping's would."""
        num_images = self.cache.num_images()
        mapper_options = self.opts.get_mapper()
        mapper = pycolmap.IncrementalMapper(self.cache)
        if resumed is None:
            self.models(mapper, mapper_options, cont=self.manager.size() > 0)
        else:
            for idx in range(self.manager.size()):
                if idx != resumed["current"]:  # their views count as registered, as when they were built
                    mapper.begin_reconstruction(self.manager.get(idx))
                    mapper.end_reconstruction(False)
            self.models(mapper, mapper_options, cont=True, growing=resumed["current"])
        for _ in range(2):  # COLMAP relaxes the first pair's inliers, then its angle, and tries again
            for relax in (_halve_inliers, _halve_angle):
                if mapper.num_total_reg_images() == num_images:
                    return
                relax(mapper_options)
                mapper.reset_initialization_stats()
                self.models(mapper, mapper_options, cont=False)

    def models(self, mapper: pycolmap.IncrementalMapper, mapper_options: pycolmap.IncrementalMapperOptions,
               *, cont: bool, growing: int | None = None) -> None:
        """New models until the views run out; with `cont` the first trial continues model 0 (a
        repair's model), or model `growing` of a resumed mapping."""
        status = pycolmap.IncrementalPipelineStatus
        for trial in range(self.opts.init_num_trials):
            idx = (growing or 0) if cont and trial == 0 else self.manager.add()
            self.current, rec = idx, self.manager.get(idx)
            result = self.model(mapper, mapper_options, rec, resumed=growing is not None and trial == 0)
            if result == status.NO_INITIAL_PAIR:
                mapper.end_reconstruction(True)
                self.manager.delete(idx)
                return
            if result != status.SUCCESS:  # a bad first pair: try another
                mapper.end_reconstruction(True)
                self.manager.delete(idx)
                continue
            total = mapper.num_total_reg_images()
            min_size = min(0.8 * self.cache.num_images(), self.opts.min_model_size)
            if (self.opts.multiple_models and self.manager.size() > 1 and rec.num_reg_frames() < min_size) \
                    or rec.num_reg_frames() == 0:
                mapper.end_reconstruction(True)
                self.manager.delete(idx)
            else:
                rec.update_point_3d_errors()
                mapper.end_reconstruction(False)
                pycolmap.align_reconstruction_to_orig_rig_scales(self.cache.rigs, rec)
            if not self.opts.multiple_models or self.manager.size() >= self.opts.max_num_models \
                    or total >= self.cache.num_images() - 1:
                return

    def model(self, mapper: pycolmap.IncrementalMapper, mapper_options: pycolmap.IncrementalMapperOptions,
              rec: pycolmap.Reconstruction, *, resumed: bool = False) -> pycolmap.IncrementalPipelineStatus:
        """Grow `rec` (from a first pair when empty) until no view registers.

        A model given to continue from is already adjusted as a whole, and the views added to it
        sit at its edges: each is adjusted locally once instead of twice, and the whole model only
        when it grew by COLMAP's ratio or its registrations end (`grown`), once: COLMAP adjusts the
        whole model when registration stalls and again after its loop unless a growth adjustment was
        the last, so a stalled model was adjusted twice on the same views (9,878 views of the
        10,000-image world: 314 s, then 295 s). Continuing a 2,353-view
        model of the 3,000-image synthetic world by 600 views took 153 s instead of 302 s (local
        adjustments 95 s against 168 s, global 51 s against 128 s) for the same views and AUC@1
        to 0.0001 (lab/notes/SCALE.md). A model `resumed` from a checkpoint grows as it did before."""
        status = pycolmap.IncrementalPipelineStatus
        mapper.begin_reconstruction(rec)
        continued = rec.num_reg_frames() > 0 and not resumed
        if rec.num_reg_frames() == 0:
            start = self.start(mapper, mapper_options, rec)
            if start != status.SUCCESS:
                return start
        ba_frames, ba_points = rec.num_reg_frames(), rec.num_points3D()
        local_rounds = min(self.opts.ba_local_max_refinements, CONTINUED_LOCAL_REFINEMENTS) if continued \
            else self.opts.ba_local_max_refinements
        self.spent_s.clear()
        registered = previous = True
        while registered or previous:
            previous, registered = registered, False
            image_id = -1
            with self.timed("registration"):
                for structure_less in self.kinds:  # from 3D points first, then (less reliable) from 2D matches alone
                    image_id, registered = self.register_next(mapper, mapper_options, rec, structure_less)
                    if registered:
                        break
            if registered:
                with self.timed("triangulation"):
                    for data_id in rec.image(image_id).frame.image_ids:
                        mapper.triangulate_image(self.triangulation, data_id.id)
                with self.timed("local adjustment"):
                    mapper.iterative_local_refinement(local_rounds, self.opts.ba_local_max_refinement_change,
                                                      mapper_options, self.local_ba, self.triangulation, image_id)
                if self.grown(rec, ba_frames, ba_points) if continued \
                        else self.pipeline.check_run_global_refinement(rec, ba_frames, ba_points):
                    self.refine(mapper, mapper_options)
                    ba_frames, ba_points = rec.num_reg_frames(), rec.num_points3D()
                if self.on_next_image is not None:
                    self.on_next_image()
            if mapper.num_shared_reg_images() >= self.opts.max_model_overlap:
                break
            if not registered and previous:
                self.refine(mapper, mapper_options)
                if continued:  # the adjustment after the loop would repeat this one on the same views
                    ba_frames, ba_points = rec.num_reg_frames(), rec.num_points3D()
        if rec.num_reg_frames() > 0 and rec.num_reg_frames() != ba_frames and rec.num_points3D() != ba_points:
            self.refine(mapper, mapper_options)
        logger.info("map: model of %d views (%s): %s", rec.num_reg_frames(),
                    "continued" if continued else "resumed" if resumed else "new",
                    ", ".join(f"{step} {seconds:.1f} s" for step, seconds in self.spent_s.items()))
        return status.SUCCESS

    def start(self, mapper: pycolmap.IncrementalMapper, mapper_options: pycolmap.IncrementalMapperOptions,
              rec: pycolmap.Reconstruction) -> pycolmap.IncrementalPipelineStatus:
        """The first pair of a new model: from the given first image once, else as COLMAP picks it."""
        if self.first_pipeline is not None:
            pipeline, self.first_pipeline = self.first_pipeline, None
            start = pipeline.initialize_reconstruction(mapper, mapper_options, rec)
            if start != pycolmap.IncrementalPipelineStatus.NO_INITIAL_PAIR:
                return start
        return self.pipeline.initialize_reconstruction(mapper, mapper_options, rec)

    def grown(self, rec: pycolmap.Reconstruction, ba_frames: int, ba_points: int) -> bool:
        """COLMAP's growth test for a global adjustment without its every-500-views and
        every-250,000-points terms: a model being continued is adjusted when it grew by the ratio,
        and once its registrations end (`model`)."""
        return rec.num_reg_frames() >= self.opts.ba_global_frames_ratio * ba_frames \
            or rec.num_points3D() >= self.opts.ba_global_points_ratio * ba_points

    def register_next(self, mapper: pycolmap.IncrementalMapper, mapper_options: pycolmap.IncrementalMapperOptions,
                      rec: pycolmap.Reconstruction, structure_less: bool) -> tuple[int, bool]:
        """Try the mapper's next candidates in its order until one registers: (its id, True), else (-1, False)."""
        register = mapper.register_next_structure_less_image if structure_less else mapper.register_next_image
        for trial, image_id in enumerate(mapper.find_next_images(mapper_options, structure_less)):
            if register(mapper_options, image_id):
                return image_id, True
            if trial >= MIN_INITIAL_REG_TRIALS and rec.num_reg_images() < self.opts.min_model_size:
                break  # this first pair does not grow: COLMAP gives it up
        return -1, False

    @contextlib.contextmanager
    def timed(self, step: str) -> Iterator[None]:
        """Add the wall seconds of the block to `step` in the current model's `spent_s`."""
        tic = time.perf_counter()
        try:
            yield
        finally:
            self.spent_s[step] += time.perf_counter() - tic

    def refine(self, mapper: pycolmap.IncrementalMapper, mapper_options: pycolmap.IncrementalMapperOptions) -> None:
        before_s = self.spent_s["global adjustment"]
        with self.timed("global adjustment"):
            mapper.iterative_global_refinement(self.opts.ba_global_max_refinements,
                                               self.opts.ba_global_max_refinement_change, mapper_options,
                                               self.global_ba, self.triangulation, True)
            mapper.filter_frames(mapper_options)
        logger.info("map: global adjustment of %d views in %.1f s", mapper.reconstruction.num_reg_frames(),
                    self.spent_s["global adjustment"] - before_s)
        if self.checkpoint is not None and time.monotonic() - self.saved_at >= self.checkpoint.every_s:
            with self.timed("checkpoint"):
                self.checkpoint.save(self.manager, self.current, time.monotonic() - self.started)
            self.saved_at = time.monotonic()


def _halve_inliers(options: pycolmap.IncrementalMapperOptions) -> None:
    options.init_min_num_inliers = options.init_min_num_inliers // 2


def _halve_angle(options: pycolmap.IncrementalMapperOptions) -> None:
    options.init_min_tri_angle = options.init_min_tri_angle / 2
