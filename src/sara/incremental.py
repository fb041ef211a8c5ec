"""Incremental updates: an output folder whose images were added, removed or changed since its run.

The extract stage keeps the digest of every image it was made from (its record's `images`). When
the image folder no longer matches them and the extraction settings are the same, the update:

1. plans: which images were added, removed or changed (removed, then added under the same name);
   copies the database into `.sara/update/`, and keeps the run's pairs, scores and main model
   there without the images that go (`pairs.txt`, `scores.csv`, `model/`);
2. updates the copy: deletes the images that go (features, matches, geometries), imports and
   extracts only the images that come, and writes the new features file beside it;
3. swaps the copies in and records the extract stage as done for the new images;
4. the later stages then continue from what was kept: the pair source selects again, reusing the
   kept scores (`sara.pairs.Extension`), the match stage matches only the selected pairs not yet
   matched (and drops the earlier ones no longer selected), and the mapper continues from the kept
   model (`start_model`), so only new work is done.

Its ledger (the `update` record) names the phase reached, so a run killed at any moment resumes
with the same command: before the swap the folder's own files are untouched; the swap finishes on
the next run whatever the images are then; afterwards each stage resumes by its own record.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py

from . import colmap, extract, masks, overlay
from .cameras import camera_sharing, may_leave_single, share_per_group
from .colmap.model import write_model
from .config import ExtractConfig
from .execute import Executor
from .features import features_file_name, make_backend
from .features.sift import DatabaseToH5, not_extracted
from .io import atomic_path, records
from .io.h5 import has_features
from .io.images import ImageSet, set_aside
from .io.pairs import Pair, read_pairs, write_pairs
from .io.scores import read_scores_csv, write_scores_csv

logger = logging.getLogger(__name__)

STAGE = "update"
WORK = "update"
PAIRS_NAME, SCORES_NAME, MODEL_NAME = "pairs.txt", "scores.csv", "model"
#: the database as the update left it, before any pair was selected again: the earlier matches of
#: the unchanged images, from which the match stage copies a pair selected again instead of
#: matching it (the match stage removes pairs no longer selected from the database)
MATCHED_NAME = "matched.db"


@dataclass(frozen=True)
class Change:
    """How a collection differs from the one a run was made from (sorted image names); `renamed`:
    old name -> new name of the images whose content is under a new name (neither added nor removed)."""

    added: list[str]
    removed: list[str]
    changed: list[str]
    renamed: dict[str, str] = field(default_factory=dict)

    @property
    def to_drop(self) -> list[str]:
        return sorted(self.removed + self.changed)

    @property
    def to_extract(self) -> list[str]:
        return sorted(self.added + self.changed)

    def counts(self) -> dict[str, int]:
        return {"num_added": len(self.added), "num_removed": len(self.removed), "num_changed": len(self.changed),
                "num_renamed": len(self.renamed)}


def compare(old: dict[str, str], new: dict[str, str], *, across_folders: bool = True) -> Change:
    """The images of `new` (name -> content digest) that `old` lacks, the reverse, those whose content
    differs, and those renamed: a name that came with the content of a name that went (one for one,
    in name order, where several files hold the same bytes). Without `across_folders` an image moved
    to another folder is removed and added (its camera is its folder's)."""
    added, removed = sorted(set(new) - set(old)), sorted(set(old) - set(new))
    gone: dict[tuple[str, str], list[str]] = {}

    def where(name: str, digest: str) -> tuple[str, str]:
        return digest, "" if across_folders else name.rpartition("/")[0]

    for name in removed:
        gone.setdefault(where(name, old[name]), []).append(name)
    renamed = {gone[where(name, new[name])].pop(0): name for name in added if gone.get(where(name, new[name]))}
    return Change(added=[n for n in added if n not in set(renamed.values())],
                  removed=[n for n in removed if n not in renamed],
                  changed=sorted(n for n in set(old) & set(new) if old[n] != new[n]), renamed=renamed)


class SettingsChangedError(extract.OutputMismatchError):
    """The features of an output folder were made with other extraction settings."""


def changed_setting(old: dict[str, Any], new: dict[str, Any]) -> str | None:
    """`extract.NAME (old -> new)` of the first setting that differs, None when all agree."""
    for name in sorted(set(old) | set(new)):
        if old.get(name) != new.get(name):
            return f"extract.{name} ({old.get(name)!r} -> {new.get(name)!r})"
    return None


def _work(out_dir: Path) -> Path:
    return Path(out_dir) / ".sara" / WORK


def ledger(out_dir: Path) -> dict[str, Any]:
    """The update's record: key (the extract key it leads to), phase and counts ({} when none)."""
    record = records.read_record(out_dir, STAGE) or {}
    return {**record.get("info", {}), "key": record.get("key")} if record else {}


def _save(out_dir: Path, key: str, info: dict[str, Any]) -> None:
    records.mark_done(out_dir, STAGE, key, {k: v for k, v in info.items() if k != "key"})


def update_features(conf: ExtractConfig, images: ImageSet, out_dir: Path, *, executor: Executor | None = None,
                    progress: bool = True, camera_groups: dict[str, str] | None = None) -> dict[str, Any] | None:
    """Bring the features of an output folder up to date with `images`, extracting only the images
    added or changed since its run; returns the update's ledger (None: nothing to update here,
    the extract stage decides). Raises SettingsChangedError, naming the setting, when the
    extraction settings differ. `camera_groups` (frame -> its video): the frames of a video added
    to a folder of videos share a camera of their own, as in a first run."""
    out_dir = Path(out_dir)
    if ledger(out_dir).get("phase") == "swap":
        _swap_in(out_dir)  # a run killed while swapping: finish it whatever the images are now
    record = records.read_record(out_dir, extract.STAGE)
    if record is None or record.get("done") is not True or not (out_dir / extract.DB_NAME).exists():
        return None
    key, digests, save_digests, key_without = extract.stage_key(images, conf, out_dir, progress=progress)
    if digests is None or extract.key_as_recorded(record, key, key_without) == record.get("key"):
        # the key holds, or differs only by images the run set aside (gone during extraction): no update
        save_digests()  # the key holds: the extract stage need not read the images again
        if ledger(out_dir).get("phase") == "features":  # images back as they were: the copies are not needed
            discard(out_dir)
        return None
    info = record.get("info", {})
    old_settings, old_digests = info.get("settings"), info.get("images")
    if old_settings is None or old_digests is None:
        return None  # made by an earlier sara: the extract stage refuses, as it did then
    setting = changed_setting(old_settings, extract.settings_of(conf))
    if setting is not None:
        raise SettingsChangedError(f"{out_dir} holds features made with other extraction settings: {setting}; use "
                                   "another output folder or --overwrite to extract them again")
    if not set(old_digests.values()) & set(digests.values()):
        return None  # no image in common, under any name: another collection, which the extract stage refuses
    current = ledger(out_dir)
    if current.get("key") != key or current.get("phase") != "features":
        current = _plan(out_dir, conf, info, digests, key)
    tic = time.perf_counter()
    change = compare(old_digests, digests, across_folders=_across_folders(info))
    grouped = camera_groups if conf.camera_mode == "auto" and camera_groups else None
    mode = info.get("camera_mode")  # a photo joins its phone's camera, a frame its clip's, a new clip gets one
    if grouped is None and (mode in ("per_exif", "per_sequence") or mode == "single" and may_leave_single(
            images, change.to_extract)):  # (cameras are merged, never split)
        mode, grouped = camera_sharing(images, conf)
    extracted, failed = _update_copies(conf, images, out_dir, change, info, executor, progress, grouped)
    focals = extract.check_added_videos(conf, _work(out_dir), grouped, change.to_extract) if camera_groups \
        and grouped else {}  # a clip added: its camera checked as a first run checks each video's
    colmap.copy_database(_work(out_dir) / extract.DB_NAME, _work(out_dir) / MATCHED_NAME)
    new_info = _new_info(out_dir, info, digests, extracted, failed, time.perf_counter() - tic)
    if grouped and not camera_groups:
        new_info["camera_mode"] = mode
    if camera_groups and grouped and len(set(grouped.values())) > 1:
        new_info["camera_mode"] = "per_video"
        new_info["focal_per_video"] = {**(info.get("focal_per_video") or {}), **focals}
    current.update(phase="swap", num_extracted=extracted, extract_time_s=time.perf_counter() - tic,
                   extract_info=new_info)
    _save(out_dir, key, current)
    _swap_in(out_dir)
    save_digests()
    return ledger(out_dir)


def _plan(out_dir: Path, conf: ExtractConfig, info: dict[str, Any], digests: dict[str, str],
          key: str) -> dict[str, Any]:
    """Start an update: copy the database, keep the run's pairs, scores and main model without the
    images that go (those an unfinished earlier update kept, when there is one), write the ledger."""
    work = _work(out_dir)
    pending = ledger(out_dir)
    # an earlier update not finished (images changed again meanwhile): its kept pairs and model go on
    carried = pending.get("phase") in ("features", "extracted") and "paired_images" in pending and work.is_dir()
    paired = pending.get("paired_images") if carried else info["images"]
    change = compare(info["images"], digests, across_folders=_across_folders(info))
    for name in os.listdir(work) if work.is_dir() else []:
        if not (carried and name in (PAIRS_NAME, SCORES_NAME, MODEL_NAME)):
            _remove(work / name)
    work.mkdir(parents=True, exist_ok=True)
    if not carried:
        for name in (PAIRS_NAME, SCORES_NAME):
            if (out_dir / name).is_file():
                shutil.copy2(out_dir / name, work / name)
    main = (work / MODEL_NAME) if carried else (out_dir / "sparse" / "0")
    if colmap.has_model(main) and change.to_drop:
        pruned = work / (MODEL_NAME + ".partial")
        left = colmap.prune_model(main, set(change.to_drop), pruned)
        _remove(work / MODEL_NAME)
        if left >= 2:  # else nothing to continue from: the update maps from the database
            pruned.rename(work / MODEL_NAME)
        else:
            _remove(pruned)
    elif colmap.has_model(main) and not carried:
        shutil.copytree(main, work / MODEL_NAME)
    colmap.copy_database(out_dir / extract.DB_NAME, work / extract.DB_NAME)
    _rename(work, change.renamed)
    paired = {change.renamed.get(name, name): digest for name, digest in paired.items()}
    plan = {"phase": "features", "old_key": info.get("key"), "paired_images": paired, "images": digests,
            **change.counts(), "added": change.added, "removed": change.removed, "changed": change.changed,
            "renamed": change.renamed}
    _save(out_dir, key, plan)
    logger.warning("update: %d images added, %d removed, %d changed, %d renamed since the last run: extracting %d, "
                   "keeping the features, matches and model of the other %d", len(change.added),
                   len(change.removed), len(change.changed), len(change.renamed), len(change.to_extract),
                   len(digests) - len(change.to_extract))
    return ledger(out_dir)


def _across_folders(info: dict[str, Any]) -> bool:
    """Whether an image moved to another folder keeps its features as it is: not where each folder
    has its camera (`camera_mode` per_folder)."""
    return info.get("camera_mode") != "per_folder"


def _rename(work: Path, renamed: dict[str, str]) -> None:
    """The images renamed under their new names in the update's copies of the database, pairs, scores
    and model: their features, matches and poses are kept as they were."""
    if not renamed:
        return
    ids = colmap.image_ids(work / extract.DB_NAME)
    colmap.rename_images(work / extract.DB_NAME, {ids[old]: new for old, new in renamed.items() if old in ids})
    if (work / PAIRS_NAME).is_file():
        pairs = read_pairs(work / PAIRS_NAME)
        write_pairs(work / PAIRS_NAME, [(renamed.get(a, a), renamed.get(b, b)) for a, b in pairs])
    if (work / SCORES_NAME).is_file():
        scores, roles = read_scores_csv(work / SCORES_NAME)
        scores.name0 = [renamed.get(n, n) for n in scores.name0]
        scores.name1 = [renamed.get(n, n) for n in scores.name1]
        write_scores_csv(work / SCORES_NAME, scores, roles)
    if colmap.has_model(work / MODEL_NAME):
        write_model(work / MODEL_NAME, work / (MODEL_NAME + ".renamed"), rename=renamed)
        shutil.rmtree(work / MODEL_NAME)
        (work / (MODEL_NAME + ".renamed")).rename(work / MODEL_NAME)


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


def _update_copies(conf: ExtractConfig, images: ImageSet, out_dir: Path, change: Change, info: dict[str, Any],
                   executor: Executor | None, progress: bool,
                   grouped: dict[str, str] | None = None) -> tuple[int, dict[str, str]]:
    """Delete the images that go from the database copy, import and extract those that come, and
    write the new features file beside it; returns the number of images the update extracts and
    those it set aside (name -> why). With COLMAP's SIFT each new image is decoded once, by the
    extraction's reader, which imports it too, as in a first run (`extract._extract_sift`)."""
    work = _work(out_dir)
    db = work / extract.DB_NAME
    colmap.delete_images(db, change.to_drop)
    backend = make_backend(conf)
    come = ImageSet(images.root, change.to_extract, {n: images.sizes[n] for n in change.to_extract})
    extracted: dict[str, Any] = {}
    if hasattr(backend, "extract_to_database"):
        todo = sorted(set(come.names) - colmap.images_with_keypoints(db))
        if todo:
            camera_mode, existing = _camera_of_new(db, images, todo, info, grouped)
            backend.extract_to_database(db, come, todo, progress=progress, camera_mode=camera_mode,
                                        existing_camera_id=existing)
        failed = not_extracted(come, colmap.images_with_keypoints(db), todo)
    else:
        to_import = [n for n in come.names if n not in colmap.database_images(db)]
        if to_import:  # an empty list would make pycolmap import every image of the folder
            camera_mode, existing = _camera_of_new(db, images, to_import, info, grouped)
            colmap.import_images(db, images.root, to_import, camera_mode=camera_mode, camera_model=conf.camera_model,
                                 camera_params=conf.camera_params, existing_camera_id=existing,
                                 default_focal_length_factor=conf.default_focal_length_factor)
        added_h5 = work / "added.h5"
        if not added_h5.exists():  # else extracted before a kill: `extract_to_h5` renames it when complete
            extract.extract_to_h5(backend, conf, come, added_h5, executor, progress)
        with h5py.File(added_h5, "r") as h5:
            done = sorted(n for n in come.names if has_features(h5, n))
        failed = {n: "not extracted (unreadable)" for n in come.names if n not in done}
        extracted = {"path": added_h5, "names": done}
        extract.import_keypoints(db, added_h5, done)
    set_aside(come, failed)  # one warning each
    if grouped:  # the new images' groups, those of kept images too: the camera of a group's oldest image
        share_per_group(db, images, grouped)
    _write_features(out_dir, conf, images, change, extracted)
    masks.apply(conf.mask_path, db, work / features_file_name(conf), come)
    if (out_dir / ".sara" / overlay.CELLS_NAME).exists():  # the overlay the first run found: out of these too
        overlay.remove_static(db, work / features_file_name(conf), come, out_dir / ".sara")
    return len(come.names) - len(failed), failed  # over every attempt: a killed update resumed counts them once


def _camera_of_new(db: Path, images: ImageSet, names: list[str], info: dict[str, Any],
                   grouped: dict[str, str] | None = None) -> tuple[str, int | None]:
    """(camera mode, existing camera id) for the new images: the run's shared camera when it has
    one and they have its size, else a camera each (or per folder, as the run did; frames of a new
    video, `grouped`: a camera each, then one per video)."""
    mode = "per_image" if grouped else info.get("camera_mode", "per_image")
    shared = colmap.shared_camera(db) if mode == "single" else None
    if shared is not None and all(images.sizes[n] == (shared.width, shared.height) for n in names):
        return "single", shared.camera_id
    # pycolmap makes a camera per image in `per_image` mode even when given the shared one
    return ("per_folder" if mode == "per_folder" else "per_image"), None


def _write_features(out_dir: Path, conf: ExtractConfig, images: ImageSet, change: Change,
                    extracted: dict[str, Any]) -> None:
    """The new features file in `.sara/update/`: the kept images' groups copied from the folder's
    file, the new images' from the database copy (SIFT) or from the new images' own file."""
    work, name = _work(out_dir), features_file_name(conf)
    db = work / extract.DB_NAME
    with_keypoints = colmap.images_with_keypoints(db)
    keep = with_keypoints - set(change.to_extract)
    was = {new_name: old_name for old_name, new_name in change.renamed.items()}
    with atomic_path(work / name) as tmp, h5py.File(tmp, "w") as new, h5py.File(out_dir / name, "r") as old:
        for image in sorted(keep):
            _copy_group(old, new, image, was.get(image, image))
        if extracted:
            with h5py.File(extracted["path"], "r") as added:
                for image in extracted["names"]:
                    _copy_group(added, new, image)
            return
        DatabaseToH5(db, new, {image: images.sizes[image] for image in with_keypoints - keep}).update()


def _copy_group(src: h5py.File, dst: h5py.File, name: str, src_name: str | None = None) -> None:
    """Copy the group of image `name` (a path with `/` for images in subfolders), from `src_name`
    when it was under another name."""
    parent = name.rpartition("/")[0]
    src.copy(src[src_name or name], dst.require_group(parent) if parent else dst, name=name.rpartition("/")[2])


def _new_info(out_dir: Path, info: dict[str, Any], digests: dict[str, str], extracted: int, failed: dict[str, str],
              elapsed: float) -> dict[str, Any]:
    """The extract stage's record after the update: its counts over all images now, and the images
    set aside with the reason (`failed`: the update's, with those of the run before it)."""
    work = _work(out_dir)
    with h5py.File(work / info.get("features", "features-sift.h5"), "r") as h5:
        names = [n for n in digests if n in h5]
        counts = {n: int(h5[n]["keypoints"].shape[0]) for n in names}
    skipped = {n: why for n, why in {**info.get("skipped", {}), **failed}.items() if n in digests and n not in counts}
    skipped.update({n: "not extracted (unreadable)" for n in digests if n not in counts and n not in skipped})
    return {**info, **extract.summarize(counts), "skipped": skipped, "images": digests, "time_s": elapsed,
            "num_extracted": extracted, "num_cameras": len(colmap.camera_priors(work / extract.DB_NAME))}


def _swap_in(out_dir: Path) -> None:
    """Move the updated features file and database into place, then record the extract stage as
    done for the new images (each step done again safely after a kill)."""
    work, current = _work(out_dir), ledger(out_dir)
    info = current["extract_info"]
    h5_name = info.get("features", "features-sift.h5")
    if (work / h5_name).exists():
        os.replace(work / h5_name, out_dir / h5_name)
    if (work / extract.DB_NAME).exists():
        colmap.replace_database(work / extract.DB_NAME, out_dir / extract.DB_NAME)
    db, h5 = out_dir / extract.DB_NAME, out_dir / h5_name
    records.mark_done(out_dir, extract.STAGE, current["key"], info, outputs=extract.recorded(db, h5))
    (work / "added.h5").unlink(missing_ok=True)
    current["phase"] = "extracted"
    _save(out_dir, current["key"], current)
    logger.info("update: %d images extracted in %.1f s", current.get("num_extracted", 0),
                current.get("extract_time_s", 0.0))


def pending(out_dir: Path, extract_key: str) -> dict[str, Any] | None:
    """The ledger of an update whose features are in place for `extract_key` and whose later
    stages have not finished yet (None when there is none)."""
    current = ledger(out_dir)
    if current.get("phase") != "extracted" or current.get("key") != extract_key:
        return None
    return current


def renamed_only(update: dict[str, Any] | None) -> bool:
    """Whether a pending update only renamed images (none added, removed or changed)."""
    return bool(update and update.get("num_renamed")) and not any(
        update.get(k) for k in ("num_added", "num_removed", "num_changed"))


def kept_pairs(out_dir: Path, update: dict[str, Any]) -> tuple[list[Pair], list[str], Path | None]:
    """(the pairs of the run between images kept unchanged, the images that need pairs, the run's
    scores file or None) of a pending update."""
    work, paired, now = _work(out_dir), update["paired_images"], update["images"]
    kept = {n for n, digest in now.items() if paired.get(n) == digest}
    pairs = read_pairs(work / PAIRS_NAME) if (work / PAIRS_NAME).is_file() else []
    scores = work / SCORES_NAME if (work / SCORES_NAME).is_file() else None
    return [p for p in pairs if p[0] in kept and p[1] in kept], sorted(set(now) - kept), scores


def earlier_matches(out_dir: Path, extract_key: str) -> Path | None:
    """The earlier matches of a pending update (`MATCHED_NAME`; None when there is none)."""
    path = _work(out_dir) / MATCHED_NAME
    return path if pending(out_dir, extract_key) is not None and path.is_file() else None


def start_model(out_dir: Path, extract_key: str) -> Path | None:
    """The kept main model a pending update's mapping continues from (None: map from the database)."""
    update = pending(out_dir, extract_key)
    model = _work(out_dir) / MODEL_NAME
    return model if update is not None and colmap.has_model(model) else None


def record_stage(out_dir: Path, name: str, info: dict[str, Any]) -> None:
    """Note what a later stage of a pending update did (its counts go into run.json)."""
    current = ledger(out_dir)
    if current.get("phase") == "extracted":
        current[name] = info
        _save(out_dir, current["key"], current)


def finish(out_dir: Path, extract_key: str, summary: dict[str, Any]) -> dict[str, Any] | None:
    """Close a pending update once its model is in place: the ledger keeps the counts, the kept
    pairs and model are deleted. Returns the counts for run.json (None when no update ran)."""
    current = pending(out_dir, extract_key)
    if current is None:
        done = ledger(out_dir)
        return done.get("summary") if done.get("phase") == "done" and done.get("key") == extract_key else None
    report = {**{k: current.get(k, 0) for k in ("num_added", "num_removed", "num_changed", "num_renamed",
                                                   "num_extracted")},
              **summary, "added": current.get("added", []), "removed": current.get("removed", []),
              "changed": current.get("changed", []), "renamed": current.get("renamed", {})}
    _save(out_dir, extract_key, {"phase": "done", "summary": report})
    shutil.rmtree(_work(out_dir), ignore_errors=True)
    logger.warning("update: %d added, %d removed, %d changed, %d renamed; %d images extracted, %d pairs scored, %d "
                   "pairs matched (%d earlier pairs kept, %d dropped)", report["num_added"], report["num_removed"],
                   report["num_changed"], report["num_renamed"], report["num_extracted"],
                   report.get("num_pairs_scored", 0),
                   report.get("num_pairs_matched", 0), report.get("num_pairs_kept", 0),
                   report.get("num_pairs_dropped", 0))
    return report


def discard(out_dir: Path) -> None:
    """Forget any update (`--overwrite` redoes everything)."""
    records.clear(out_dir, STAGE)
    shutil.rmtree(_work(out_dir), ignore_errors=True)
