"""Stage `pairs`: the configured pair source (or a pairs file) -> `pairs.txt`.

The source writes its own files (scores, global descriptors, caches) into `.sara/pairs.next/`;
they and `pairs.txt` replace the previous ones only when it selected at least one pair (else
NoResultError, and the previous pairs, matches and model stay). The stage is keyed by the
features and by the configuration sections the source declares it depends on.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from pathlib import Path
from typing import Any

from .. import extract, incremental
from ..config import PipelineConfig
from ..execute import Executor
from ..io import DamagedOutputError, NoResultError, file_digest, fingerprint, records, without_added_later
from ..io.images import ImageSet
from ..io.pairs import read_pairs, write_pairs
from ..pairs import SOURCES, Extension, PairContext, PairSource, get_source
from ..scoring import ScoreJournal
from . import rounds

logger = logging.getLogger(__name__)

STAGE = "pairs"
PAIRS_NAME = rounds.PAIRS_NAME
STAGING = "pairs.next"
#: the candidate pairs' scores (`sara.scoring.ScoreJournal`), written as they come back and kept for
#: these features: a selection stopped part-way, or run again with other graph, budget or candidate
#: settings, scores only the pairs it finds no score of; cleared with other features and on overwrite
SCORE_JOURNAL = "score-journal"
#: outputs of the pairs stage whose digests the record keeps (caches check themselves)
_TRACKED_PAIR_FILES = (PAIRS_NAME, "scores.csv")


def pair_source_file(method: str) -> Path | None:
    """None for a named pair source; the path for a pairs file (FileNotFoundError when neither)."""
    if method in SOURCES:
        return None
    path = Path(method)
    if path.is_dir():
        raise IsADirectoryError(f"--pairs {method}: a folder, not a pairs file ('name0 name1' per line) "
                                f"nor a pair source ({', '.join(SOURCES)})")
    if not path.is_file():
        raise FileNotFoundError(f"--pairs {method}: not a pair source ({', '.join(SOURCES)}) and no such pairs file")
    return path


def source_sections(conf: PipelineConfig) -> tuple[str, ...]:
    """The configuration sections the configured pair source depends on (a pairs file: "pairs")."""
    method = conf.pairs.method
    return get_source(method).sections(conf) if method in SOURCES else ("pairs",)


#: settings added after runs were made: left out of the key at these values, so that a finished
#: run is not redone for a setting it could not have had (it keeps what it found)
ADDED_LATER: dict[str, dict[str, Any]] = {"rounds": {"repair_descriptor_ratio": 0.8, "pose_guided_last": True},
                                           "sequence": {"chain": 1}}


def _keyed(section: str, values: dict[str, Any]) -> dict[str, Any]:
    return without_added_later(values, ADDED_LATER.get(section, {}))


def pairs_key(conf: PipelineConfig, extract_key: str, source_file: Path | None) -> str:
    data: dict[str, Any] = {"extract": extract_key, "seed": conf.seed}
    data.update({section: _keyed(section, getattr(conf, section).__dict__) for section in source_sections(conf)})
    if source_file is not None:
        data["file"] = source_file.read_text(encoding="utf-8", errors="replace")
    return fingerprint(data)


def current_key(conf: PipelineConfig, out_dir: Path) -> str:
    """The key of the pairs stage for this configuration and the features in `out_dir`."""
    extract_key = (records.read_record(out_dir, extract.STAGE) or {}).get("key", "")
    return pairs_key(conf, extract_key, pair_source_file(conf.pairs.method))


def pair_context(conf: PipelineConfig, images: ImageSet, features_path: Path, out_dir: Path, *,
                 executor: Executor | None = None, progress: bool = True, work_dir: Path | None = None,
                 score_journal: ScoreJournal | None = None) -> PairContext:
    focal_estimate = records.done_info(out_dir, extract.STAGE).get("focal")  # the extract stage's result
    return PairContext(names=images.names, images_root=images.root, features_path=features_path,
                       db_path=out_dir / extract.DB_NAME, out_dir=work_dir or out_dir, conf=conf, progress=progress,
                       executor=executor, focal_estimate=focal_estimate, score_journal=score_journal)


def run(conf: PipelineConfig, images: ImageSet, features_path: Path, out_dir: Path, *,
        executor: Executor | None = None, overwrite: bool = False, progress: bool = True) -> Path:
    """Write `pairs.txt` from the configured source; returns its path."""
    method = conf.pairs.method
    source_file = pair_source_file(method)
    extract_key = (records.read_record(out_dir, extract.STAGE) or {}).get("key", "")
    key = pairs_key(conf, extract_key, source_file)
    pairs_path = out_dir / PAIRS_NAME
    if not overwrite and records.is_done(out_dir, STAGE, key) and pairs_intact(out_dir, key):
        logger.info("pairs: %s up to date, skipping", pairs_path)
        return pairs_path
    tic = time.perf_counter()
    staging = out_dir / ".sara" / STAGING
    journal = ScoreJournal(out_dir / ".sara" / SCORE_JOURNAL, _scores_key(extract_key, features_path))
    if overwrite:
        journal.remove()
    source = get_source(method) if source_file is None else None
    if source is not None:
        _keep_caches(source, staging, journal.open().folder)  # those a killed selection left
    shutil.rmtree(staging, ignore_errors=True)
    try:
        if source is None:
            pairs = read_pairs(source_file, known_names=images.names)
            info: dict[str, Any] = {"source": str(source_file)}
            why_empty = ""
        else:
            _seed_caches(source, (out_dir, journal.folder), staging)
            ctx = pair_context(conf, images, features_path, out_dir, executor=executor, progress=progress,
                               work_dir=staging, score_journal=journal)
            extension = _extension(source, out_dir)
            result = source.extend(ctx, extension) if extension is not None else source(ctx)
            pairs, info, why_empty = result.pairs, {**result.info, "timings_s": result.timings_s}, result.why_empty
        if not pairs:
            raise NoResultError(_no_pairs_reason(method, source_file, why_empty, len(images.names), out_dir))
        produced = _swap_in_pair_files(staging, out_dir, key)
    finally:
        if source is not None and journal.folder.is_dir():  # stopped: its caches are kept
            _keep_caches(source, staging, journal.folder)
        shutil.rmtree(staging, ignore_errors=True)
    write_pairs(pairs_path, pairs)
    n = len(images.names)
    exhaustive = n * (n - 1) // 2
    info.update(method=method, num_pairs=len(pairs), num_selected=len(pairs), time_s=time.perf_counter() - tic,
                num_exhaustive_pairs=exhaustive, fraction_of_exhaustive=len(pairs) / max(1, exhaustive))
    outputs = {name: file_digest(out_dir / name) for name in [PAIRS_NAME, *produced] if name in _TRACKED_PAIR_FILES}
    records.mark_done(out_dir, STAGE, key, info, outputs=outputs)
    if source is not None:  # the caches a stopped selection handed on are in the output folder now
        _drop_caches(source, journal.folder)
    return pairs_path


def _scores_key(extract_key: str, features_path: Path) -> str:
    """What a candidate's score depends on besides the score settings and the seed (which name the
    journal's files): the features and cameras, i.e. the extract stage's key; where no extract stage
    recorded them (features made elsewhere), the features file's name, size and time."""
    if extract_key:
        return extract_key
    try:
        stat = Path(features_path).stat()
    except OSError:  # no features: nothing will be scored
        return fingerprint({"features": str(features_path)})
    return fingerprint({"features": Path(features_path).name, "size": stat.st_size, "mtime_ns": stat.st_mtime_ns})


def _extension(source: PairSource, out_dir: Path) -> Extension | None:
    """The earlier selection to extend, when an incremental update awaits its pairs and the source
    can extend one (None: select all pairs)."""
    update = incremental.pending(out_dir, (records.read_record(out_dir, extract.STAGE) or {}).get("key", ""))
    if source.extend is None or update is None:
        return None
    kept, new_names, scores_path = incremental.kept_pairs(out_dir, update)
    renamed = incremental.renamed_only(update)
    return Extension(kept, new_names, scores_path, renamed) if kept or scores_path is not None else None


def _seed_caches(source: PairSource, folders: tuple[Path, ...], staging: Path) -> None:
    """Copy the source's caches of earlier selections into the staging folder (it reuses them): from
    each of `folders` in turn, a later one's file replacing an earlier one's of the same name."""
    staging.mkdir(parents=True, exist_ok=True)
    for folder in folders:
        for pattern in source.caches:
            for path in folder.glob(pattern):
                if path.is_file():
                    shutil.copy2(path, staging / path.name)


def _keep_caches(source: PairSource, staging: Path, journal: Path) -> None:
    """Move the caches a stopped selection left in `staging` into the score journal's folder: the
    selection run again reuses them (each cache checks its own inputs, as `retrieval.run` does)."""
    for pattern in source.caches if staging.is_dir() else ():
        for path in staging.glob(pattern):
            if path.is_file():
                os.replace(path, journal / path.name)


def _drop_caches(source: PairSource, journal: Path) -> None:
    for pattern in source.caches:
        for path in journal.glob(pattern):
            path.unlink(missing_ok=True)


def _swap_in_pair_files(staging: Path, out_dir: Path, key: str) -> list[str]:
    """Move what the source wrote into the output folder; returns the file names."""
    records.mark_started(out_dir, STAGE, key)
    rounds.clear(out_dir)
    produced = []
    if staging.is_dir():
        for path in sorted(staging.iterdir()):
            if path.is_file():
                os.replace(path, out_dir / path.name)
                produced.append(path.name)
    return produced


def _no_pairs_reason(method: str, source_file: Path | None, why_empty: str, num_images: int, out_dir: Path) -> str:
    kept = " (the previous pairs, matches and model are kept)" if (out_dir / PAIRS_NAME).exists() else ""
    if source_file is not None:
        return f"{source_file} lists no pairs: nothing to match{kept}"
    if num_images < 2:
        return f"only {num_images} usable image: a reconstruction needs at least 2{kept}"
    extracted = records.read_record(out_dir, extract.STAGE) or {}
    featureless = (extracted.get("info") or {}).get("images_without_features") or []
    if num_images - len(featureless) < 2:
        return (f"{len(featureless)} of {num_images} images have no features (flat or featureless): a "
                f"reconstruction needs at least 2 with features{kept}")
    return f"{why_empty or f'the {method} pair source selected no pairs'}{kept}"


def pairs_intact(out_dir: Path, key: str) -> bool:
    """Whether the pairs stage's files still hold what it (or the rounds after it) wrote.

    `pairs.txt` missing: select again (False). Changed (edited, emptied or cut short): never
    overwritten, DamagedOutputError says what to do. `scores.csv` changed or damaged: made again
    (False, with a warning).
    """
    pairs_path = out_dir / PAIRS_NAME
    if not pairs_path.exists():
        return False
    recorded = records.recorded_outputs(out_dir, STAGE)
    expected = rounds.pairs_digest(out_dir, key) or recorded.get(PAIRS_NAME)
    if expected is not None and expected != file_digest(pairs_path):
        raise DamagedOutputError(
            f"{pairs_path} was changed after the pairs stage wrote it (edited, emptied or cut short); delete it to "
            f"select the pairs again, or match your own pairs with `sara match {out_dir} --pairs FILE`")
    for name in _TRACKED_PAIR_FILES[1:]:
        if name in recorded and recorded[name] != file_digest(out_dir / name):
            logger.warning("%s differs from what the pairs stage wrote (changed, damaged or missing): selecting "
                           "the pairs again", out_dir / name)
            return False
    return True
