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

from . import colmap
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
        commit: Callable[[], None] | None = None, overwrite: bool = False, input_model: Path | None = None) -> Path:
    """Map the matched database into `out_dir/sparse/N`; returns `sparse/` (component sizes and the
    time taken go into the stage record). With `input_model` (incremental mapper only) the mapper
    continues from that model instead of starting from scratch.

    `commit`, when given, runs once the new model exists (or the current one is up to date), just
    before it is swapped in: the pipeline moves the matches it was built from into place there.
    """
    out_dir = Path(out_dir)
    sparse = out_dir / "sparse"
    key = state_key(conf, seed, upstream_key)
    if not overwrite and records.is_done(out_dir, STAGE, key) and _model_intact(out_dir, sparse):
        logger.info("map: model up to date, skipping")
        if commit is not None:
            commit()
        return sparse
    previous = records.read_record(out_dir, STAGE)
    # the incremental mapper continues its own models, and those it built for a contradicted global one
    extend = input_model is not None and "incremental" in (conf.mapper, _mapped_by(previous))
    held = extend and bool(((previous or {}).get("info") or {}).get("distortion_held"))
    conf = replace(conf, refine_distortion=conf.refine_distortion and not held)  # as the model continued was mapped
    records.mark_started(out_dir, STAGE, key)
    checkpoint = Checkpoint(out_dir / ".sara" / CHECKPOINT, key, conf.checkpoint_minutes * 60) \
        if conf.checkpoint_minutes > 0 and not extend else None
    if checkpoint is not None and overwrite:
        checkpoint.remove()
    earlier_s = checkpoint.elapsed_s() if checkpoint is not None else 0.0  # mapped before a kill, resumed now
    tmp = out_dir / ".sara" / PARTIAL
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        if extend:
            recs, num_images, elapsed = _extend(conf, db_path, images_root, tmp, seed, progress, input_model,
                                                min_num_inliers)
            recs.mapper = "incremental"
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
            "continued": extend, "mapper": recs.mapper or conf.mapper, "distortion_held": held or recs.distortion_held}
    info.update(_first_model_check(recs, previous if info["continued"] else None))
    records.mark_done(out_dir, STAGE, key, info, outputs={"sparse": model_digest(sparse)})
    if checkpoint is not None:
        checkpoint.remove()
    if len(sizes) > 1:
        logger.warning("map: the scene split into %d models of %s images", len(sizes), sizes)
    return sparse


def _mapped_by(record: dict[str, Any] | None) -> str | None:
    """The mapper that built the model of a map stage's record (None for records before it was kept)."""
    return ((record or {}).get("info") or {}).get("mapper")


#: what the record says of the first mapping's check (`_agreeing`); a continued model keeps it
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
            recs = _distortion_held(conf, db_path, images_root, tmp, seed, progress, num_images, recs,
                                    min_num_inliers, checkpoint)
            conf = replace(conf, refine_distortion=conf.refine_distortion and not recs.distortion_held)
            recs = _forward_start(conf, db_path, images_root, tmp, seed, progress, num_images, recs,
                                  min_num_inliers, checkpoint)
            recs = _agreeing(conf, db_path, images_root, tmp, seed, progress, num_images, recs, min_num_inliers,
                             checkpoint)
    elif conf.mapper == "global":
        recs = _global(conf, db_path, images_root, tmp, seed, progress, min_num_inliers, checkpoint)
    else:
        raise ValueError(f"unknown mapper {conf.mapper!r}; choose incremental or global")
    return recs, num_images, time.perf_counter() - tic


def _global(conf: MapConfig, db_path: Path, images_root: Path, tmp: Path, seed: int, progress: bool,
            min_num_inliers: int, checkpoint: Checkpoint | None = None) -> colmap.MappedModels:
    """COLMAP's global mapper, its largest model checked against its own verified pairs; when they
    contradict it (`_contradicted`) and `map.contradicted_remaps` allows, the incremental mapper maps
    the scene too and the better model is kept (`_better`). On a sparse graph the global mapper glues
    stretches that few pairs join at wrong rotations, where the incremental one splits the scene
    (200-image synthetic street, SARA's pairs: 126 of 455 pairs off by over 10 degrees, none wrong)."""
    recs = colmap.global_mapping(db_path, images_root, tmp, seed=seed, num_threads=conf.num_threads)
    recs.seed, recs.agreement_check = seed, recs.agreement(db_path, min_num_inliers)
    if not _contradicted(recs.agreement_check) or conf.contradicted_remaps == 0:
        return recs
    logger.warning("map: %d of the %d verified pairs between the views of the global mapper's largest model "
                   "contradict it: mapping with the incremental mapper as well and keeping the model its pairs "
                   "agree with", len(recs.agreement_check.contradicted), recs.agreement_check.checked)
    (tmp / "incremental").mkdir()
    again, _, _ = _map(replace(conf, mapper="incremental"), db_path, images_root, tmp / "incremental", seed,
                       progress, min_num_inliers=min_num_inliers,
                       checkpoint=checkpoint.derived("incremental") if checkpoint else None)
    again.mapper = "incremental"
    return again if _better(again, again.agreement_check, recs, recs.agreement_check) else recs


def _distortion_held(conf: MapConfig, db_path: Path, images_root: Path, tmp: Path, seed: int, progress: bool,
                     num_images: int, first: colmap.MappedModels, min_num_inliers: int,
                     checkpoint: Checkpoint | None = None) -> colmap.MappedModels:
    """Map again with the cameras' distortion held, when it was refined and the first model holds less
    than `FORWARD_RETRY_SHARE` of the views joined by verified pairs; keeps the mapping whose largest
    model holds more views (`_better`), and the retries and continuations after it hold it too. Before
    the forward retry: where holding the distortion lets the model grow, that mapping is saved.

    Where few points pin the lens down, the adjustments can bend it to make up for a wrong guess of
    the camera: on a low-texture stand-in (211 keypoints per image, its principal point 9 px off the
    centre) the radial term ran to -0.7 to -1.6 in every piece and the first models held 7-16 of 47
    views; held, all 47 in one model under each of four namings (lab/notes/CAPTURES.md, 23-24)."""
    if not conf.refine_distortion or first.largest == 0:
        return first
    reachable = max(colmap.verified_graph(db_path, min_num_inliers)[2], default=0)
    if first.largest >= FORWARD_RETRY_SHARE * reachable:
        return first
    logger.info("map: the first model holds %d of the %d views joined by verified pairs: mapping again with the "
                "lens distortion held (map.refine_distortion)", first.largest, reachable)
    folder = tmp / "distortion-held"
    folder.mkdir()
    again = _incremental(replace(conf, refine_distortion=False), db_path, images_root, folder, seed, progress,
                         num_images, None, checkpoint=checkpoint.derived(folder.name) if checkpoint else None)
    again.distortion_held = True
    if not _better(again, again.agreement(db_path, min_num_inliers), first, first.agreement(db_path, min_num_inliers)):
        return first
    logger.warning("map: with the lens distortion held the largest model holds %d views (refined: %d); kept, "
                   "and held in the rounds' mappings too", again.largest, first.largest)
    return again


#: a first model holding less than this share of the views that verified pairs join is a start
#: that could not grow: the mapper is tried again from a forward pair
FORWARD_RETRY_SHARE = 0.5


def _forward_start(conf: MapConfig, db_path: Path, images_root: Path, tmp: Path, seed: int, progress: bool,
                   num_images: int, first: colmap.MappedModels, min_num_inliers: int,
                   checkpoint: Checkpoint | None = None) -> colmap.MappedModels:
    """Map again with a start from views that moved along their viewing direction allowed, when
    the first mapping built no model, or a largest model of less than `FORWARD_RETRY_SHARE` of the
    views joined by verified pairs; keeps the result whose largest model holds more views.

    A camera driving or walking straight ahead gives COLMAP no start it accepts (every pair moved
    forward), or only one between two views where the path turns, from which the model often
    cannot grow (kitti-seq1 on SARA's pairs: 2, 5 and 51 of 51 views under seeds 0, 1 and 2)."""
    if first.largest > 0:
        reachable = max(colmap.verified_graph(db_path, min_num_inliers)[2], default=0)
        if first.largest >= FORWARD_RETRY_SHARE * reachable:
            return first
        logger.info("map: the first model holds %d of the %d views joined by verified pairs: mapping again from a "
                    "forward pair", first.largest, reachable)
    else:
        logger.info("map: COLMAP found no pair of views to start from that moved sideways enough; the camera "
                    "moves along its viewing direction (driving, walking ahead): starting from a forward pair")
    retry_dir = tmp / "forward" if first.largest > 0 else tmp
    retry_dir.mkdir(exist_ok=True)
    again = _incremental(conf, db_path, images_root, retry_dir, seed, progress, num_images, None, forward_start=True,
                         checkpoint=checkpoint.derived("forward") if checkpoint else None)
    if again.largest <= first.largest:
        return first
    again.forward_start, again.distortion_held = True, first.distortion_held
    return again


#: a first model contradicted by more than this share of the verified pairs between its views
#: (`colmap.consistency`) is mapped again under another random seed. On the 1,000-image synthetic
#: street two bent first models had 1.9% and 3.2%, good ones from the same matches none.
CONTRADICTED_SHARE = 0.005
#: ... or by this many, whatever their share: a bend contradicts the pairs that close the loop across
#: its seam, as many in a large model as in a small one (bent: 37-76 pairs, 45 of 15,577 at 3,000
#: images, 76 of 21,795 at 10,000; good: 0-2, and 12 wrong pairs on dtu-scan24; lab/notes/SCALE.md)
CONTRADICTED_PAIRS = 20


#: threads of a mapping done again because the first model was contradicted. With one thread the
#: mapper's result depends on its seed alone: on the 1,000-image synthetic street's first graph six
#: seeds gave six good models single-threaded (0 of 2,052 pairs contradicting), where with both cores
#: of the idle machine seeds 0 and 1 gave bent ones and the same seed under load a good one; on the
#: idle 2-core machine seed 0 took 118 s on one thread, 144 s (bent) on two (lab/notes/SCALE.md)
REMAP_THREADS = 1


def _agreeing(conf: MapConfig, db_path: Path, images_root: Path, tmp: Path, seed: int, progress: bool,
              num_images: int, first: colmap.MappedModels, min_num_inliers: int,
              checkpoint: Checkpoint | None = None) -> colmap.MappedModels:
    """Mend the first mapping's largest model at its seam (`_mended`, if `map.mend_seam`) when its own
    verified pairs contradict it (`_contradicted`), then map again, at most `map.contradicted_remaps`
    times, while the best so far is contradicted: under the next seed, on `REMAP_THREADS` threads,
    the first model started from the view in most of the contradicting pairs; keeps the best. When a
    mapping (or the mend) is contradicted by exactly the pairs that contradicted the one before it, the
    fault is in those pairs' matches, not in how the mapper built the model, and no more mappings
    follow (dtu-scan24 under exhaustive matching: the same 12 pairs under seeds 0 and 1, CAPTURES.md 15).

    The incremental mapper can bend a model where the views pass a place twice: the pairs that
    would close the loop never join a track, so nothing in the mapper sees them (lab/notes/SCALE.md)."""
    best, best_check = first, first.agreement(db_path, min_num_inliers)
    best.seed, remaps, check, same = seed, 0, best_check, False
    earlier = check  # the check of the model mapped last before the next one
    if _contradicted(best_check) and conf.mend_seam:
        best, best_check, mend = _mended(conf, db_path, images_root, tmp, seed, progress, first, check, min_num_inliers)
        if same := mend is not None and set(mend.contradicted) == set(check.contradicted):
            logger.warning("map: the same %d pairs contradict the mended model: the fault is in those pairs, not in "
                           "how the mapper built the model; no mapping again", len(check.contradicted))
    while not same and _contradicted(best_check) and remaps < conf.contradicted_remaps:
        remaps += 1
        start = check.most_contradicted_view()  # the last model's: a model no pair contradicts ends the loop
        logger.warning("map: %d of the %d verified pairs between the views of the largest model contradict it "
                       "(their matches lie more than %.0f px off its epipolar lines): mapping again under seed %d, "
                       "starting from %s", len(check.contradicted), check.checked, colmap.CONTRADICTION_PX,
                       seed + remaps, start)
        folder = tmp / f"seed-{seed + remaps}"
        folder.mkdir()
        colmap.set_seed(seed + remaps)
        again = _incremental(replace(conf, num_threads=REMAP_THREADS), db_path, images_root, folder, seed + remaps,
                             progress, num_images, None, forward_start=first.forward_start, first_image=start,
                             checkpoint=checkpoint.derived(folder.name, f"{start}") if checkpoint else None)
        again.forward_start, again.seed = first.forward_start, seed + remaps
        again.distortion_held = first.distortion_held
        check = again.agreement(db_path, min_num_inliers)
        logger.warning("map: under seed %d the largest model holds %d views, %d of %d pairs contradict it",
                       seed + remaps, again.largest, len(check.contradicted), check.checked)
        if _better(again, check, best, best_check):
            best, best_check = again, check
        if set(check.contradicted) == set(earlier.contradicted):
            logger.warning("map: the same %d pairs contradict the model under seed %d: the fault is in those "
                           "pairs, not in how the mapper built the model; no more mappings", len(check.contradicted),
                           seed + remaps)
            break
        earlier = check
    best.agreement_check, best.remaps = best_check, remaps
    return best


def _mended(conf: MapConfig, db_path: Path, images_root: Path, tmp: Path, seed: int, progress: bool,
            first: colmap.MappedModels, check: colmap.Agreement, min_num_inliers: int,
            ) -> tuple[colmap.MappedModels, colmap.Agreement, colmap.Agreement | None]:
    """(the first model or, where better, it cut at its seam and continued, its check, the continued one's)."""
    cut = colmap.cut_at_seam(first, check, db_path, tmp / "mend" / "cut", min_num_inliers=min_num_inliers)
    if cut is None:
        return first, check, None
    logger.warning("map: %d of the %d verified pairs between the views of the largest model contradict it: taking out "
                   "the %d views up to %d pairs from them (and %d cut off with them) and continuing the %d others",
                   len(check.contradicted), check.checked, cut.taken_out, colmap.SEAM_HOPS, cut.dropped, cut.kept)
    try:
        mended, _, _ = _extend(conf, db_path, images_root, tmp / "mend", seed, progress, tmp / "mend" / "cut",
                               min_num_inliers)
    except colmap.ColmapError as exc:  # the first model stays, and the remaps follow as without the mend
        logger.warning("map: continuing the cut model failed (%s): keeping the first model", exc)
        return first, check, None
    mended.forward_start, mended.distortion_held = first.forward_start, first.distortion_held
    mended.seed, mended.mended, again = seed, True, mended.agreement(db_path, min_num_inliers)
    logger.warning("map: continued, the largest model holds %d views (%d before), %d of %d pairs contradict it",
                   mended.largest, first.largest, len(again.contradicted), again.checked)
    return (mended, again, again) if _better(mended, again, first, check) else (first, check, again)


def _contradicted(check: colmap.Agreement) -> bool:
    return check.share > CONTRADICTED_SHARE or len(check.contradicted) >= CONTRADICTED_PAIRS


def _better(new: colmap.MappedModels, new_check: colmap.Agreement, old: colmap.MappedModels,
            old_check: colmap.Agreement) -> bool:
    """Any model beats none; a model its pairs do not contradict beats one they do, when it holds as
    many views less the other's seam (the views of the pairs contradicting it, which a mapping that
    mends the bend may rightly leave out); then more views; then fewer contradictions.

    A remap that breaks the scene into pieces is not a mended bend: at 10,000 images a bent model of
    9,350 views was mapped again into pieces whose largest, 3,167 views, no pair contradicted; keeping
    it would have left the rounds 6,800 views to register again (lab/notes/SCALE.md)."""
    def rank(model: colmap.MappedModels, check: colmap.Agreement, other: colmap.MappedModels,
             other_check: colmap.Agreement) -> tuple[bool, bool, int, int]:
        seam = {view for pair in other_check.contradicted for view in pair}
        sound = not _contradicted(check) and model.largest >= other.largest - len(seam)
        return model.largest > 0, sound, model.largest, -len(check.contradicted)

    return rank(new, new_check, old, old_check) > rank(old, old_check, new, new_check)


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
            checkpoint=checkpoint, refine_extra_params=conf.refine_distortion)


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
        return (f"the mapper found no pair of views to start from among the {linked} (the best has {most_inliers} "
                f"inlier matches): COLMAP's mapper also needs {need_angle:g} degrees of triangulation angle between "
                "them (a start from views that moved forward was tried too), and these views are too close together, "
                "turn on the spot, or see a flat scene")
    return f"the global mapper found no model among the {linked}"


def adopt(out_dir: Path, info: dict[str, Any], *, key: str | None = None) -> None:
    """Make `sparse/` as it is now the map stage's output, although the mapper did not write it (a
    round refined or extended the model of the current matches): a re-run then keeps it instead of
    mapping again, and `sparse/` changed by anyone else is still noticed. `key`: the matches it is
    the model of (`state_key`); None keeps the recorded one."""
    recorded = records.read_record(out_dir, STAGE) or {}
    records.mark_done(out_dir, STAGE, key if key is not None else recorded.get("key", ""), info,
                      outputs={"sparse": model_digest(Path(out_dir) / "sparse")})


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
                               "contradicted_remaps": 2, "refine_distortion": True, "mend_seam": True}


#: settings that do not change the model: how often a long mapping keeps its models so far
NOT_IN_KEY = ("checkpoint_minutes",)


def state_key(conf: MapConfig, seed: int, upstream_key: str) -> str:
    values = {k: v for k, v in conf.__dict__.items() if k not in NOT_IN_KEY}
    return fingerprint({"conf": without_added_later(values, ADDED_LATER), "seed": seed, "upstream": upstream_key})
