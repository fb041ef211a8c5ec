"""Stage `map`: pycolmap's incremental (or global) mapper into `sparse/0`, `sparse/1`, ...

Components are numbered by decreasing size, so `sparse/0` is always the largest model, the one
that 3DGS, nerfstudio and COLMAP's GUI open by default.

The new models are built in `.sara/sparse.partial` and swapped in only when there is at least one:
a run that finds no model keeps the previous `sparse/` and raises NoResultError with the reason.
A finished stage is trusted only while `sparse/` holds what it wrote; a model changed since (edited
in COLMAP's GUI, or damaged) is never overwritten on resume: DamagedOutputError says what to do.
"""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from tqdm import tqdm

from . import colmap, map_retries
from .colmap import refine as colmap_refine
from .colmap.stepwise import Checkpoint
from .config import MapConfig
from .io import DamagedOutputError, NoResultError, fingerprint, records, without_added_later
from .map_schedule import ba_direct_max_images, ba_global_growth, ba_global_refinements
from .model_files import colmap_models, model_digest, recover, swap_in  # noqa: F401 (the stage's model folders)

logger = logging.getLogger(__name__)

STAGE = "map"
PARTIAL = "sparse.partial"
CHECKPOINT = "map-checkpoint"


def run(conf: MapConfig, db_path: Path, images_root: Path, out_dir: Path, *, seed: int = 0,
        upstream_key: str = "", progress: bool = True, min_num_inliers: int = 15,
        commit: Callable[[], None] | None = None, overwrite: bool = False, input_model: Path | None = None,
        starved: bool = False) -> Path:
    """Map the matched database into `out_dir/sparse/N`; returns `sparse/` (component sizes and the
    time taken go into the stage record). With `input_model` (incremental mapper only) the mapper
    continues from that model instead of starting from scratch.

    `commit`, when given, runs once the new model exists (or the current one is up to date), just
    before it is swapped in: the pipeline moves the matches it was built from into place there.
    `starved`: the features starved and a camera is a guess (`pipeline.advice.starved`); with
    `conf.hold_distortion_starved` a first mapping holds the distortion from the start. So does
    one of fisheye cameras (their distortion starts as given: 0, the equidistant lens, without
    camera_params); the rounds' refinements refine it once the model is whole.
    """
    out_dir = Path(out_dir)
    sparse = out_dir / "sparse"
    key = state_key(conf, seed, upstream_key)
    if not overwrite and records.is_done(out_dir, STAGE, key) and _model_intact(out_dir, sparse) \
            and not (input_model is not None and _names_gone(sparse, db_path)):
        logger.info("map: model up to date, skipping")
        if commit is not None:
            commit()
        return sparse
    previous = records.read_record(out_dir, STAGE)
    # the incremental mapper continues its own models, and those it built for a contradicted global one
    extend = input_model is not None and "incremental" in (conf.mapper, _mapped_by(previous))
    earlier = ((previous or {}).get("info") or {}) if extend else {}
    fisheye = not extend and conf.refine_distortion and bool(colmap.fisheye_cameras(db_path))
    held = bool(earlier.get("distortion_held")) if extend else \
        (starved and conf.hold_distortion_starved and conf.refine_distortion) or fisheye
    if held and not extend:
        logger.warning("map: the lens distortion is held while mapping: %s", "a fisheye model's four distortion "
                       "terms, fitted to a first model of few views, bent the lens (fountain-P11 through a fisheye: 7 "
                       "of 11 views; held, 11)" if fisheye else "few keypoints per image and a guessed camera do not "
                       "pin it down (map.hold_distortion_starved)")
    conf = replace(conf, refine_distortion=conf.refine_distortion and not held,  # as the model continued was mapped
                   two_view_points=conf.two_view_points or bool(earlier.get("two_view_points")))
    records.mark_started(out_dir, STAGE, key)
    checkpoint = Checkpoint(out_dir / ".sara" / CHECKPOINT, key, conf.checkpoint_minutes * 60) \
        if conf.checkpoint_minutes > 0 and not extend else None
    if checkpoint is not None and overwrite:
        checkpoint.remove()
    earlier_s = checkpoint.elapsed_s() if checkpoint is not None else 0.0  # mapped before a kill, resumed now
    tmp = out_dir / ".sara" / PARTIAL
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    checked: dict[str, Any] = {}  # a continued model against its pairs
    try:
        if extend:
            recs, num_images, elapsed, checked = _continued(conf, db_path, images_root, tmp, seed, progress,
                                                            input_model, min_num_inliers)
        else:
            recs, num_images, elapsed = _map(conf, db_path, images_root, tmp, seed, progress,
                                             min_num_inliers=min_num_inliers, checkpoint=checkpoint)
        sizes = recs.write_by_size(tmp)
        if not sizes:
            kept = "; the previous model in sparse/ is kept" if colmap_models(sparse) else ""
            reason = no_model_reason(db_path, conf, min_num_inliers)
            raise NoResultError(f"map: no model could be built: {reason}{kept}")
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        records.restore(out_dir, STAGE, previous)
        if checkpoint is not None and isinstance(exc, NoResultError):
            checkpoint.remove()  # else kept: the same run resumes from it
        raise
    if commit is not None:
        commit()
    swap_in(tmp, sparse)
    info = {"time_s": elapsed + earlier_s, "num_components": len(sizes), "component_sizes": sizes,
            "num_registered": sizes[0], "num_images": num_images, "forward_start": recs.forward_start,
            "two_view_points": conf.two_view_points or recs.two_view_points,
            "continued": extend, "mapper": recs.mapper or conf.mapper, "distortion_held": held or recs.distortion_held}
    info.update(_first_model_check(recs, previous if info["continued"] else None), **checked)
    records.mark_done(out_dir, STAGE, key, info, outputs={"sparse": model_digest(sparse)})
    if checkpoint is not None:
        checkpoint.remove()
    if len(sizes) > 1:
        logger.warning("map: the scene split into %d models of %s images", len(sizes), sizes)
    return sparse


def _mapped_by(record: dict[str, Any] | None) -> str | None:
    """The mapper that built the model of a map stage's record (None for records before it was kept)."""
    return ((record or {}).get("info") or {}).get("mapper")


#: what the record says of the first mapping's check (`map_retries.agreeing`); a continued model keeps it
FIRST_MODEL_KEYS = ("seed", "remaps", "mended", "first_model_pairs_checked", "first_model_pairs_contradicted")


def _first_model_check(recs: colmap.MappedModels, previous: dict[str, Any] | None) -> dict[str, Any]:
    """The seed that built the first model, the mappings under other seeds, and its pairs checked and
    contradicting it: from this mapping, or for a continued model from the record it continued."""
    if recs.agreement_check is not None:
        return {"seed": recs.seed, "remaps": recs.remaps, "mended": recs.mended,
                "first_model_pairs_checked": recs.agreement_check.checked,
                "first_model_pairs_contradicted": len(recs.agreement_check.contradicted)}
    earlier = (previous or {}).get("info") or {}
    return {k: earlier[k] for k in FIRST_MODEL_KEYS if k in earlier}


def _map(conf: MapConfig, db_path: Path, images_root: Path, tmp: Path, seed: int,
         progress: bool, input_model: Path | None = None, *, min_num_inliers: int = 15,
         checkpoint: Checkpoint | None = None) -> tuple[colmap.MappedModels, int, float]:
    """COLMAP's mapper into `tmp` (continuing from `input_model` when given, incremental only). Each
    step-by-step mapping from scratch keeps its models in a checkpoint and resumes from them: the first
    in `checkpoint`, a retry from a forward pair, a remap under another seed and the incremental mapping
    behind a contradicted global model in checkpoints derived from it."""
    num_images = len(colmap.database_images(db_path))
    colmap.set_seed(seed)
    tic = time.perf_counter()
    if conf.mapper == "incremental":
        recs = _incremental(conf, db_path, images_root, tmp, seed, progress, num_images, input_model,
                            checkpoint=checkpoint)
        if input_model is None:
            recs = map_retries.set_right(_attempts(conf, db_path, images_root, tmp, seed, progress, num_images,
                                                   min_num_inliers, checkpoint), recs)
    elif conf.mapper == "global":
        recs = _global(conf, db_path, images_root, tmp, seed, progress, min_num_inliers, checkpoint)
    else:
        raise ValueError(f"unknown mapper {conf.mapper!r}; choose incremental or global")
    return recs, num_images, time.perf_counter() - tic


def _global(conf: MapConfig, db_path: Path, images_root: Path, tmp: Path, seed: int, progress: bool,
            min_num_inliers: int, checkpoint: Checkpoint | None = None) -> colmap.MappedModels:
    """COLMAP's global mapper, its largest model checked against its own verified pairs; when they
    contradict it (`map_retries.contradicted`) and `map.contradicted_remaps` allows, or when it built
    no model, the incremental mapper maps the scene too and the better model is kept
    (`map_retries.better`). On a sparse graph the global mapper glues stretches that few pairs join
    at wrong rotations, where the incremental one splits the scene (200-image synthetic street,
    SARA's pairs: 126 of 455 pairs off by over 10 degrees, none wrong)."""
    recs = colmap.global_mapping(db_path, images_root, tmp, seed=seed, num_threads=conf.num_threads)
    recs.seed, recs.agreement_check = seed, recs.agreement(db_path, min_num_inliers)
    if recs.largest == 0:
        logger.warning("map: the global mapper built no model: mapping with the incremental mapper (and its "
                       "retries: a forward start, the points seen in two views only)")
    elif not map_retries.contradicted(recs.agreement_check) or conf.contradicted_remaps == 0:
        return recs
    else:
        logger.warning("map: %d of the %d verified pairs between the views of the global mapper's largest model "
                       "contradict it: mapping with the incremental mapper as well and keeping the model its pairs "
                       "agree with", len(recs.agreement_check.contradicted), recs.agreement_check.checked)
    (tmp / "incremental").mkdir()
    again, _, _ = _map(replace(conf, mapper="incremental"), db_path, images_root, tmp / "incremental", seed,
                       progress, min_num_inliers=min_num_inliers,
                       checkpoint=checkpoint.derived("incremental") if checkpoint else None)
    again.mapper = "incremental"
    return again if map_retries.better(again, again.agreement_check, recs, recs.agreement_check) else recs


def _incremental(conf: MapConfig, db_path: Path, images_root: Path, tmp: Path, seed: int, progress: bool,
                 num_images: int, input_model: Path | None, *, forward_start: bool = False,
                 first_image: str | None = None, checkpoint: Checkpoint | None = None) -> colmap.MappedModels:
    with tqdm(total=num_images, desc="map (incremental)", unit="img", disable=not progress) as bar:
        return colmap.incremental_mapping(
            db_path, images_root, tmp, seed=seed, min_model_size=conf.min_model_size,
            abs_pose_min_num_inliers=conf.abs_pose_min_num_inliers,
            abs_pose_min_inlier_ratio=conf.abs_pose_min_inlier_ratio, num_threads=conf.num_threads,
            on_next_image=lambda: bar.update(), input_path=input_model, forward_start=forward_start,
            ba_global_ratio=ba_global_growth(conf, num_images),
            ba_global_refinements=ba_global_refinements(conf, num_images),
            direct_solver_up_to=ba_direct_max_images(conf, num_images), first_image=first_image,
            checkpoint=checkpoint, refine_extra_params=conf.refine_distortion, two_view_points=conf.two_view_points)


def _attempts(conf: MapConfig, db_path: Path, images_root: Path, tmp: Path, seed: int, progress: bool,
              num_images: int, min_num_inliers: int, checkpoint: Checkpoint | None) -> map_retries.Attempts:
    """The ways of mapping again after the first mapping (`map_retries`): this stage's own."""
    def incremental(conf: MapConfig, folder: Path, seed: int, *, forward_start: bool = False,
                    first_image: str | None = None, checkpoint: Checkpoint | None = None) -> colmap.MappedModels:
        return _incremental(conf, db_path, images_root, folder, seed, progress, num_images, None,
                            forward_start=forward_start, first_image=first_image, checkpoint=checkpoint)

    def extend(conf: MapConfig, folder: Path, model: Path) -> colmap.MappedModels:
        return _extend(conf, db_path, images_root, folder, seed, progress, model, min_num_inliers)[0]

    return map_retries.Attempts(conf, db_path, tmp, seed, min_num_inliers, checkpoint, incremental, extend)


def _continued(conf: MapConfig, db_path: Path, images_root: Path, tmp: Path, seed: int, progress: bool,
               input_model: Path, min_num_inliers: int) -> tuple[colmap.MappedModels, int, float, dict[str, Any]]:
    """`input_model` continued (`_extend`), then checked against its pairs and mended at its seam where
    they contradict it (`map_retries.continued`); with what the record says of that check."""
    tic = time.perf_counter()
    recs, num_images, _ = _extend(conf, db_path, images_root, tmp, seed, progress, input_model, min_num_inliers)
    recs, checked = map_retries.continued(_attempts(conf, db_path, images_root, tmp, seed, progress, num_images,
                                                    min_num_inliers, None), recs)
    recs.mapper = "incremental"
    return recs, num_images, time.perf_counter() - tic, checked


def _extend(conf: MapConfig, db_path: Path, images_root: Path, tmp: Path, seed: int, progress: bool,
            input_model: Path, min_num_inliers: int) -> tuple[colmap.MappedModels, int, float]:
    """Continue from `input_model`: the mapper registers the views it lacks, then bundle-adjusts.

    The model is first re-triangulated with the new matches (poses fixed): continuing from it as
    written, the mapper found too few 3D points on the features the left-out views share with it
    (templeSparseRing: 13 of 16 views kept; 16 after re-triangulating, in 0.2 s against 0.7 s
    for mapping anew). The database is not mapped again from scratch where continuing left views
    out: in the 12 such mappings logged (lab/notes/ACCURACY.md 15.2, lab/notes/SCALE.md, CAPTURES.md
    11) none registered more views than the continued model, and each cost a whole mapping (62 s
    of a 1,000-image world's 65 s repair round). The rounds' own rules decide what to do next.
    """
    tic = time.perf_counter()
    (tmp / "extended").mkdir()
    start = tmp / "input"
    colmap_refine.triangulate_new_matches(input_model, db_path, images_root, start, num_threads=conf.num_threads,
                                          seed=seed)
    before = len(colmap.registered_images(start))
    recs, num_images, _ = _map(replace(conf, mapper="incremental"), db_path, images_root, tmp / "extended", seed,
                               progress, start)
    reachable = max(colmap.verified_graph(db_path, min_num_inliers)[2], default=0)
    if recs.largest < reachable:
        logger.info("map: continuing from the model of %d views registered %d of the %d views joined by verified "
                    "pairs", before, recs.largest, reachable)
    return recs, num_images, time.perf_counter() - tic


def no_model_reason(db_path: Path, conf: MapConfig, min_num_inliers: int) -> str:
    """Why the mapper found no model, from the verified pairs of the database."""
    num_pairs, num_images, _, most_inliers = colmap.verified_graph(db_path, min_num_inliers)
    if num_pairs == 0:
        return (f"no image pair has {min_num_inliers} or more verified matches (match.min_num_inliers): "
                "the images do not overlap, or the pairs are wrong")
    need_inliers, need_angle = colmap.mapper_init_requirements()
    linked = f"{num_images} images linked by {num_pairs} verified pairs"
    if conf.mapper == "incremental" and most_inliers < need_inliers:
        return (f"the mapper found no pair of views to start from among the {linked}: the best pair has "
                f"{most_inliers} inlier matches and COLMAP's mapper needs {need_inliers} to start a model")
    if conf.mapper == "incremental":
        fisheye = ("; with a fisheye camera model COLMAP measures that angle with the lens's focal length, and a "
                   "straight drive through a fisheye model gave no start where the default camera model "
                   "(SIMPLE_RADIAL) mapped it whole" if colmap.fisheye_cameras(db_path) else "")
        return (f"the mapper found no pair of views to start from among the {linked} (the best has {most_inliers} "
                f"inlier matches): COLMAP's mapper also needs {need_angle:g} degrees of triangulation angle between "
                "them (a start from views that moved forward, and points seen in two views only, were tried too), and "
                f"these views are too close together, turn on the spot, or see a flat scene, or something that "
                f"moves with the camera fills them (a hand, a car's bonnet: leave it out with --masks){fisheye}")
    return f"the global mapper found no model among the {linked}"


def adopt(out_dir: Path, info: dict[str, Any], *, key: str | None = None) -> None:
    """Make `sparse/` as it is now the map stage's output, although the mapper did not write it (a
    round refined or extended the model of the current matches): a re-run then keeps it instead of
    mapping again, and `sparse/` changed by anyone else is still noticed. `key`: the matches it is
    the model of (`state_key`); None keeps the recorded one."""
    recorded = records.read_record(out_dir, STAGE) or {}
    records.mark_done(out_dir, STAGE, key if key is not None else recorded.get("key", ""), info,
                      outputs={"sparse": model_digest(Path(out_dir) / "sparse")})


def _names_gone(sparse: Path, db_path: Path) -> bool:
    """Whether the main model poses images under names the database no longer has: an update that
    only renamed images leaves the matches as they were (the stage's key holds), not the names."""
    return not colmap.registered_images(sparse / "0") <= set(colmap.database_images(db_path))


def _model_intact(out_dir: Path, sparse: Path) -> bool:
    """Whether `sparse/` still holds the models the stage wrote. Missing: False (map again).
    Changed: DamagedOutputError, never overwritten (a person may have edited it)."""
    if not sparse.exists():
        return False
    recorded = records.recorded_outputs(out_dir, STAGE).get("sparse")
    if recorded is None or recorded == model_digest(sparse):
        return True
    raise DamagedOutputError(
        f"{sparse} was changed after the map stage wrote it (edited, or damaged); move it away or delete it "
        "to map again, or keep it and use another output folder")


#: settings added after runs were made: left out of the key at these values, so that a finished
#: model is not mapped again after an upgrade for a setting it could not have had
ADDED_LATER: dict[str, Any] = {"ba_global_growth": 0.0, "ba_global_refinements": 0, "ba_direct_max_images": 0,
                               "contradicted_remaps": 2, "refine_distortion": True, "mend_seam": True,
                               "two_view_points": False}


#: settings that do not change the model: how often a long mapping keeps its models so far
NOT_IN_KEY = ("checkpoint_minutes",)


def state_key(conf: MapConfig, seed: int, upstream_key: str) -> str:
    values = {k: v for k, v in conf.__dict__.items() if k not in NOT_IN_KEY}
    return fingerprint({"conf": without_added_later(values, ADDED_LATER), "seed": seed, "upstream": upstream_key})
