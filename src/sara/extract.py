"""Stage `extract`: local features of every image into `features-<backend>.h5` (hloc's layout) and
the COLMAP database (images, cameras, keypoints), for any backend of `sara.features`."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from tqdm import tqdm

from . import colmap, masks, overlay
from .cameras import GROUPED_MODES, camera_sharing, share_per_group
from .config import ExtractConfig
from .execute import Beside, Executor, SerialExecutor, for_device, single_threaded_torch_in_worker
from .features import Keypoints, LocalFeatures, features_file_name, make_backend
from .features.sift import ColmapSift, DatabaseToH5, not_extracted
from .io import DamagedOutputError, OutputStateError, atomic_path, ensure_free_space, fingerprint, records
from .io import images as image_files
from .io.h5 import H5_ERRORS, Features, features_digest, has_features, write_features
from .io.images import ImageSet, set_aside
from .scoring import focal

logger = logging.getLogger(__name__)

STAGE = "extract"
DB_NAME = "database.db"


class OutputMismatchError(OutputStateError, ValueError):
    """An output folder holds results made from other inputs or settings."""


#: settings added after outputs existed, with their defaults: at that default they stay out of the
#: key, so features extracted by an earlier sara are still used (not refused as "other settings")
_LATER_SETTINGS = {"estimate_focal": True, "mask_path": ""}


#: digests of the images' bytes, kept between runs (see `sara.io.images.content_digests`)
DIGESTS_NAME = "image-digests.json"


def settings_of(conf: ExtractConfig) -> dict:
    """The extraction settings that key the features (those added later drop out at their default)."""
    settings = {k: v for k, v in conf.__dict__.items() if not (k in _LATER_SETTINGS and v == _LATER_SETTINGS[k])}
    return {**settings, "masks": masks.masks_key(conf.mask_path)} if conf.mask_path else settings


def stage_key(images: ImageSet, conf: ExtractConfig, out_dir: Path, *, progress: bool = True
              ) -> tuple[str, dict[str, str] | None, Callable[[], None], Callable[[set[str]], str]]:
    """(the stage key: the images' names and contents and the settings, the digest of each image
    (None when an earlier sara's key still holds), a function that saves the images' digests for
    the next run: to call once the key is accepted, a function that gives the key without some
    images: those the stage sets aside).

    Features made by an earlier sara, keyed by the images' sizes and modification times, keep
    that key while those are unchanged.
    """
    settings = settings_of(conf)
    cache = out_dir / ".sara" / DIGESTS_NAME
    found: list = []

    def digests() -> tuple[dict[str, str], dict[str, list] | None]:
        found[:] = found or [image_files.content_digests(images, cache, progress=progress)]
        return found[0]

    def key_without(aside: set[str]) -> str:
        return fingerprint({"images": [[n, digests()[0][n]] for n in images.names if n not in aside], "conf": settings})

    record = records.read_record(out_dir, STAGE)
    if record is not None and record.get("key") == fingerprint({"images": images.fingerprint_data(), "conf": settings}):
        return record["key"], None, lambda: None, key_without
    return key_without(set()), digests()[0], lambda: image_files.save_digests(cache, digests()[1]), key_without


def key_as_recorded(record: dict | None, key: str, key_without: Callable[[set[str]], str]) -> str:
    """The finished stage's key when the images differ from its own only by images it set aside
    (a file that vanished during extraction and is gone now, or is back): those stay set aside."""
    if record is None or record.get("done") is not True or record.get("key") == key:
        return key
    info = record.get("info", {})
    aside = set(info.get("skipped") or {})
    if aside and info.get("usable_key") and key_without(aside) == info["usable_key"]:
        return record["key"]
    return key


def _check_existing_database(db_path: Path, images: ImageSet) -> bool:
    """True when the database can be resumed; False when it must be made anew."""
    in_db = colmap.database_images(db_path)
    unknown = sorted(set(in_db) - set(images.names))
    if unknown:
        raise OutputMismatchError(
            f"{db_path.parent} holds a database made from another image set ({len(unknown)} images not in "
            f"this folder, e.g. {unknown[0]!r}); use another output folder or --overwrite"
        )
    return len(in_db) == len(images.names)


def run(conf: ExtractConfig, images: ImageSet, out_dir: Path, *, executor: Executor | None = None,
        overwrite: bool = False, progress: bool = True, camera_groups: dict[str, str] | None = None) -> Path:
    """Local features of every image; returns the path of `features-<backend>.h5`.

    The COLMAP database receives the images, their cameras and the keypoints. Resumes an
    interrupted run: images already done are not extracted again. Images that the extractor's own
    decoder cannot read (COLMAP's reader for SIFT: a format it does not know under an image
    extension, a file gone since the scan) are set aside, each with one warning, and listed in the
    stage record (`usable` applies that list on every later run). A finished stage is trusted only
    while the features file and the database still hold what it wrote. `camera_groups` (frame ->
    the video it came from) gives the frames of each video one camera (`camera_sharing`).
    """
    out_dir = Path(out_dir)
    db_path, h5_path = out_dir / DB_NAME, out_dir / features_file_name(conf)
    key, digests, save_digests_, key_without = stage_key(images, conf, out_dir, progress=progress)
    key = key_as_recorded(records.read_record(out_dir, STAGE), key, key_without)
    tic = time.perf_counter()
    if not overwrite and records.is_done(out_dir, STAGE, key) and _outputs_intact(out_dir, db_path, h5_path):
        logger.info("extract: features up to date, skipping")
        save_digests_()
        usable(images, out_dir, warn=True)  # the images it set aside, one warning each as when it ran
        return h5_path
    backend = make_backend(conf)  # loads weights: a missing file fails here, before any work
    record = records.read_record(out_dir, STAGE)
    if overwrite or (record is not None and record.get("key") != key):
        if record is not None and record.get("key") != key and not overwrite and db_path.exists():
            raise OutputMismatchError(
                f"{out_dir} holds features made from other images or other extraction settings; "
                "use another output folder or --overwrite to redo them"
            )
        colmap.remove_database(db_path)
        h5_path.unlink(missing_ok=True)
        (out_dir / ".sara" / overlay.CELLS_NAME).unlink(missing_ok=True)  # found in features made before
        _partial(h5_path).unlink(missing_ok=True)
    save_digests_()
    records.mark_started(out_dir, STAGE, key)
    camera_mode, groups = camera_sharing(images, conf, camera_groups)
    importing = "per_image" if camera_mode in GROUPED_MODES else camera_mode  # then shared per group below
    # where one camera's intrinsics hold for every image, those of another size cannot be theirs
    one = "--camera-mode single" if camera_mode == "single" else "extract.camera_params" if conf.camera_params else ""
    odd = image_files.other_sizes(images, one) if one else {}
    images = set_aside(images, odd)
    wants_focal = conf.estimate_focal and camera_mode in ("single", "per_video", "per_sequence") and \
        not conf.camera_params
    if hasattr(backend, "extract_to_database"):  # the focal check's pairs fitted during the extraction
        counts, failed, fundamentals = _extract_sift(backend, db_path, h5_path, images, importing, wants_focal,
                                                     progress, groups)
        set_aside(images, failed)  # one warning each
        estimate_with = None if fundamentals is None else (
            lambda group, names: partial(focal.estimate, fundamentals.get(group, [])))
    else:
        if db_path.exists() and not _check_existing_database(db_path, images):
            colmap.remove_database(db_path)  # images were being imported when the run stopped: importing is cheap
        if not db_path.exists():
            _new_database(db_path, images, conf, importing)
        counts, failed = extract_to_h5(backend, conf, images, h5_path, executor, progress)
        kept = set_aside(images, failed).names
        import_keypoints(db_path, h5_path, kept)
        estimate_with = _from_features(h5_path) if wants_focal else None
    info = summarize(counts)
    if masked := masks.apply(conf.mask_path, db_path, h5_path, images):
        info["masked_keypoints"] = masked
    info["static_keypoints"] = overlay.remove_static(db_path, h5_path, images, out_dir / ".sara")
    if info["static_keypoints"]["num_keypoints"] and estimate_with is not None:  # fitted with an overlay's matches
        estimate_with = _from_features(h5_path)
    if groups is not None:
        shared = share_per_group(db_path, images, groups)
        if estimate_with is not None:  # frames of videos: photos' groups have EXIF focal lengths
            info["focal_per_video"] = _focal_per_video(db_path, estimate_with, shared)
    elif estimate_with is not None:
        info["focal"] = focal.check_prior(db_path, estimate_with("", [n for n in images.names if n not in failed]))
    priors = colmap.camera_priors(db_path)  # camera -> whether EXIF gave its focal length
    info["num_cameras"] = len(priors)
    info["cameras_guessed"] = [sum(not known for known in priors.values()), len(priors)]  # focal length a guess
    failed = {**odd, **failed}
    info.update(camera_mode=camera_mode, backend=conf.backend, features=h5_path.name,
                skipped=failed, time_s=time.perf_counter() - tic,
                settings=settings_of(conf), images=digests, usable_key=key_without(set(failed)))
    records.mark_done(out_dir, STAGE, key, info, outputs=recorded(db_path, h5_path))
    return h5_path


def check_added_videos(conf: ExtractConfig, folder: Path, groups: dict[str, str], added: list[str]) -> dict[str, Any]:
    """The focal check of each video whose frames in `folder`'s database and features file are all
    among `added` (a clip added by an update), as a first run checks every video's camera; video ->
    what it found."""
    if not conf.estimate_focal or conf.camera_params:
        return {}
    db_path, frames = folder / DB_NAME, {}
    for name in sorted(colmap.images_with_keypoints(db_path)):
        frames.setdefault(groups.get(name), []).append(name)
    new = {video: names for video, names in frames.items() if video is not None and set(names) <= set(added)}
    return _focal_per_video(db_path, _from_features(folder / features_file_name(conf)), new)


def _focal_per_video(db_path: Path, estimate_with: Callable[[str, list[str]], Callable],
                     videos: dict[str, list[str]]) -> dict[str, Any]:
    """The focal check of each video's camera on its own frames (`videos`: video -> its frames)."""
    return {video: focal.check_prior(db_path, estimate_with(video, names), names, video)
            for video, names in videos.items()}


def _from_features(h5_path: Path) -> Callable[[str, list[str]], Callable]:
    """The focal check of a group of images from their features in `h5_path` (as they are now)."""
    return lambda group, names: partial(focal.estimate_from_features, h5_path, names)


def _extract_sift(backend: ColmapSift, db_path: Path, h5_path: Path, images: ImageSet, camera_mode: str,
                  wants_focal: bool, progress: bool, groups: dict[str, str] | None = None
                  ) -> tuple[dict[str, int], dict[str, str], dict[str, list] | None]:
    """COLMAP's SIFT into the database, each image decoded once, by COLMAP's reader, which imports
    it too (an image it cannot decode is set aside after, with the reason); the features copied
    into `h5_path` and the focal check's pairs fitted while COLMAP extracts. Returns keypoints per
    image, the images set aside (name -> why), and the focal check's fundamental matrices (None
    when there is nothing to check: not `wants_focal`, or the focal length came with the images), by
    video (`groups`: frame -> its video; "" for all the images without groups)."""
    existing = _resumable_database(db_path, images, camera_mode)
    if not db_path.exists():
        with atomic_path(db_path) as tmp:
            tmp.unlink()
            colmap.create_database(tmp)
    todo = sorted(set(images.names) - colmap.images_with_keypoints(db_path))
    nearby = focal.NearbyFundamentals(images.names, groups=groups) if wants_focal else None
    priors_read = False
    with atomic_path(h5_path) as tmp, h5py.File(tmp, "w") as h5:
        copy = DatabaseToH5(db_path, h5, images.sizes)

        def strongest(name: str) -> Features:
            return copy.read(name, focal.NUM_KEYPOINTS)

        def on_watch() -> None:
            nonlocal nearby, priors_read
            copy.update()
            if nearby is not None and copy.counts and not priors_read:  # the camera exists: once
                priors_read = True
                if any(colmap.camera_priors(db_path).values()):
                    nearby = None  # the focal length came with the images (EXIF): nothing to check
            if nearby is not None:
                nearby.add(strongest, copy.counts)

        if todo:
            ensure_free_space(db_path.parent, _bytes_per_image(backend.conf) * len(todo))
            with Beside(on_watch) as beside:
                backend.extract_to_database(db_path, images, todo, progress=progress, camera_mode=camera_mode,
                                            existing_camera_id=existing, on_watch=beside.poke)
        failed = not_extracted(images, colmap.images_with_keypoints(db_path), todo)
        on_watch()  # what COLMAP wrote after the last look
        kept = [n for n in images.names if n not in failed]
        fundamentals = None if nearby is None else nearby.fundamentals(kept, strongest)
    colmap.number_images_by_name(db_path)  # as they finished, COLMAP's threads numbered them
    return {n: copy.counts[n] for n in kept}, failed, fundamentals


def _resumable_database(db_path: Path, images: ImageSet, camera_mode: str) -> int | None:
    """Check a database left by an earlier SIFT extraction (it holds the images COLMAP had read);
    returns the shared camera that the images still to read must join, if any. One that cannot
    be resumed is removed: images in folders that each have a camera (COLMAP would give a folder
    a second one)."""
    if not db_path.exists():
        return None
    _check_existing_database(db_path, images)
    in_db, cameras = colmap.database_images(db_path), colmap.camera_priors(db_path)
    if camera_mode == "per_folder" and cameras and len(in_db) < len(images.names):
        colmap.remove_database(db_path)
        return None
    return next(iter(cameras)) if camera_mode == "single" and len(cameras) == 1 else None


def usable(images: ImageSet, out_dir: Path, *, warn: bool = False) -> ImageSet:
    """The images of a finished extraction: without those its record lists as unreadable (those
    gone from the folder since, e.g. vanished during extraction, are still listed as skipped)."""
    skipped = records.done_info(out_dir, STAGE).get("skipped", {})
    return set_aside(images, {n: r for n, r in skipped.items() if n in images.sizes or n not in images.skipped},
                     warn=warn)


def recorded(db_path: Path, h5_path: Path) -> dict:
    summary = colmap.database_summary(db_path) or {}
    return {h5_path.name: features_digest(h5_path),
            DB_NAME: {k: summary.get(k) for k in ("num_images", "num_images_with_keypoints", "keypoints_digest")}}


def _outputs_intact(out_dir: Path, db_path: Path, h5_path: Path) -> bool:
    """Whether the files of a finished extraction still hold what it wrote.

    A damaged or changed features file is redone (False, with a warning): it is made again from
    the database (SIFT) or the images. A damaged or changed database cannot be mended without
    redoing the matches too: DamagedOutputError says so.
    """
    if not db_path.exists() or not h5_path.exists():
        return False
    fix = "run again with --overwrite to extract the features again (matching is redone too)"
    try:
        summary = colmap.database_summary(db_path) or {}
    except DamagedOutputError as exc:
        raise DamagedOutputError(f"{exc}; {fix}") from None
    recorded = records.recorded_outputs(out_dir, STAGE)
    now_db = {k: summary.get(k) for k in ("num_images", "num_images_with_keypoints", "keypoints_digest")}
    if DB_NAME in recorded and recorded[DB_NAME] != now_db:
        raise DamagedOutputError(f"{db_path} no longer holds the keypoints that the extract stage wrote "
                                 f"(changed by another program?); {fix}")
    try:
        now_h5 = features_digest(h5_path)
    except DamagedOutputError as exc:
        logger.warning("%s: extracting the features again", exc)
        h5_path.unlink()
        return False
    if h5_path.name in recorded and recorded[h5_path.name] != now_h5:
        logger.warning("%s differs from what the extract stage wrote (changed or damaged): extracting again",
                       h5_path)
        h5_path.unlink()
        return False
    return True


def _new_database(db_path: Path, images: ImageSet, conf: ExtractConfig, camera_mode: str) -> None:
    colmap.remove_database(db_path)
    with atomic_path(db_path) as tmp:
        tmp.unlink()
        colmap.create_database(tmp)
        colmap.import_images(tmp, images.root, images.names, camera_mode=camera_mode,
                             camera_model=conf.camera_model, camera_params=conf.camera_params,
                             default_focal_length_factor=conf.default_focal_length_factor)


def _bytes_per_image(conf: ExtractConfig) -> int:
    """At most what one image adds to the database and the features file, in bytes: the configured
    maximum of features ((2 + 4) float32 keypoint values, 128 descriptor bytes in the database;
    float16 descriptors, keypoints and scores in the HDF5 file). COLMAP aborts the whole process
    when the database cannot grow, so the check before must not underestimate."""
    return conf.max_num_features * (6 * 4 + 128 + 128 * 2 + 3 * 4)


def _partial(h5_path: Path) -> Path:
    return h5_path.with_name(h5_path.name + ".partial")


@dataclass(frozen=True)
class _ExtractJob:
    """Images for a worker: it builds the backend once and returns full-resolution features."""

    conf: ExtractConfig
    root: str
    names: list[str]


_BACKENDS: dict[tuple, LocalFeatures] = {}  # per process


def _backend_key(conf: ExtractConfig) -> tuple:
    return tuple(sorted(conf.__dict__.items()))


def _extract_images(job: _ExtractJob) -> list[Keypoints | str]:
    """Features of each image of the job, or why it could not be read (a file gone or damaged since
    the scan must not stop the whole extraction)."""
    key = _backend_key(job.conf)
    if key not in _BACKENDS:
        single_threaded_torch_in_worker()
        colmap.quiet_signals_in_worker()
        _BACKENDS.clear()
        _BACKENDS[key] = make_backend(job.conf)
    out: list[Keypoints | str] = []
    for name in job.names:
        try:
            pixels, factors = image_files.load_image(Path(job.root) / name, job.conf.max_image_size)
        except FileNotFoundError:
            out.append("the file disappeared during extraction")
            continue
        except (OSError, ValueError, SyntaxError) as exc:  # what Pillow raises on a damaged file
            out.append(f"could not be decoded during extraction ({exc})")
            continue
        found = _BACKENDS[key].extract(pixels)
        out.append(Keypoints(xy=image_files.to_full_resolution(found.xy, factors),
                             scores=np.asarray(found.scores, np.float32), descriptors=np.asarray(found.descriptors)))
    return out


#: images per job of learned extraction: progress and resume granularity
EXTRACT_CHUNK = 8


def extract_to_h5(backend: LocalFeatures, conf: ExtractConfig, images: ImageSet, h5_path: Path,
                   executor: Executor | None, progress: bool) -> tuple[dict[str, int], dict[str, str]]:
    """Run a pixel backend over every image into `h5_path`, resumably (a `.partial` file grows
    chunk by chunk and is renamed when complete). Returns keypoints per image, and the images that
    could not be read (name -> why)."""
    partial = _partial(h5_path)
    try:
        with h5py.File(partial, "a") as h5:
            done = {n for n in images.names if has_features(h5, n)}
    except H5_ERRORS:  # cut short while being written: start over
        partial.unlink(missing_ok=True)
        done = set()
    todo = [n for n in images.names if n not in done]
    chunks = [todo[k:k + EXTRACT_CHUNK] for k in range(0, len(todo), EXTRACT_CHUNK)]
    _BACKENDS[_backend_key(conf)] = backend  # in this process, reuse the one already loaded
    executor = for_device(executor, getattr(backend, "device", "cpu"))
    results = (executor or SerialExecutor()).map(
        _extract_images, [_ExtractJob(conf, str(images.root), chunk) for chunk in chunks])
    failed: dict[str, str] = {}
    with h5py.File(partial, "a") as h5, tqdm(total=len(images.names), initial=len(done),
                                              desc=f"extract {backend.name}", unit="img",
                                              disable=not progress) as bar:
        for chunk, found in zip(chunks, results):
            ready = {name: kp for name, kp in zip(chunk, found) if not isinstance(kp, str)}
            failed.update({name: kp for name, kp in zip(chunk, found) if isinstance(kp, str)})
            # HDF5 crashes on a full disk: make sure the chunk fits before writing it
            ensure_free_space(h5_path.parent, sum(kp.xy.nbytes + kp.descriptors.nbytes + kp.scores.nbytes
                                                  for kp in ready.values()) + 4096 * len(chunk))
            for name, kp in ready.items():
                write_features(h5, name, Features(keypoints=kp.xy, descriptors=kp.descriptors, scores=kp.scores,
                                                  image_size=images.sizes[name]))
            h5.flush()
            bar.update(len(chunk))
        counts = {n: int(h5[n]["keypoints"].shape[0]) for n in images.names if n not in failed}
    partial.replace(h5_path)
    return counts, failed


def import_keypoints(db_path: Path, h5_path: Path, names: list[str]) -> None:
    """Put the keypoints of `h5_path` into the database (COLMAP's pixel convention)."""
    missing = set(names) - colmap.images_with_keypoints(db_path)
    if not missing:
        return
    with h5py.File(h5_path, "r") as h5:
        keypoints = {n: colmap.hloc_to_colmap_keypoints(h5[n]["keypoints"][()]) for n in sorted(missing)}
    colmap.write_keypoints(db_path, keypoints)


def summarize(num_kp: dict[str, int]) -> dict:
    no_features = sorted(n for n, k in num_kp.items() if k == 0)
    for name in no_features:
        logger.warning("no features found in %s (flat or featureless image): it cannot be registered", name)
    counts = np.array(list(num_kp.values()))
    return {
        "num_images": len(num_kp),
        "keypoints_mean": float(counts.mean()) if len(counts) else 0.0,
        "keypoints_min": int(counts.min()) if len(counts) else 0,
        "images_without_features": no_features,
    }
