"""The rounds a pair source runs around mapping (`sara.pairs.Rounds`), driven without knowing the source.

Before the first mapping a source may add pairs once the first ones are matched; after it, up to
`rounds.repair_rounds` rounds add pairs, which are matched and then either refined into the model
by the source or mapped again; a last step may improve the final model. Every round's pairs are
matched beside the current database and swapped in with the model they led to: a round that
fails keeps the previous pairs, matches and model.

The rounds keep their own record, the ledger (`ROUNDS_STAGE`): each round's pairs and role, its
match and map times, and the digest of `pairs.txt` as the rounds left it (it then lists every
pair matched). The records of the pairs, match and map stages stay what those stages wrote; a
model refined or extended here becomes the map stage's output through `mapping.adopt`.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .. import colmap, extract, mapping, match
from ..config import PipelineConfig
from ..io import NoResultError, file_digest, fingerprint, records
from ..io.pairs import read_pairs, write_pairs
from ..pairs import PairContext, Round, Rounds

logger = logging.getLogger(__name__)

PAIRS_NAME = "pairs.txt"
#: the ledger of the rounds of the current selection
ROUNDS_STAGE = "rounds"
#: the last step on the final model, once per model
FINISH_STAGE = "finish"
#: the pairs of a round, until its model replaces the previous one
STAGED_PAIRS = "pairs.next.txt"


@dataclass
class RoundsRun:
    """What the rounds of one run need: the source's rounds, its context and the selection's key."""

    rounds: Rounds
    ctx: PairContext
    conf: PipelineConfig
    out_dir: Path
    selection_key: str
    progress: bool = True

    @property
    def staged(self) -> Path:
        return self.out_dir / ".sara" / STAGED_PAIRS

    def match(self, pairs_path: Path) -> Path:
        """Match `pairs_path` beside the current database; returns the database holding the matches."""
        return match.run(self.conf.match, pairs_path, self.out_dir / extract.DB_NAME, self.out_dir,
                         features_path=self.ctx.features_path, features_backend=self.conf.extract.backend,
                         executor=self.ctx.executor, progress=self.progress, beside=True)


# ---------------------------------------------------------------------------------------------
# The ledger
# ---------------------------------------------------------------------------------------------


def ledger(out_dir: Path, selection_key: str) -> dict[str, Any]:
    """The rounds' record of this selection (empty when none ran for it)."""
    record = records.read_record(out_dir, ROUNDS_STAGE) or {}
    if record.get("done") is not True or record.get("key") != selection_key:
        return {}
    return dict(record.get("info", {}))


def _save(run: RoundsRun, info: dict[str, Any]) -> None:
    records.mark_done(run.out_dir, ROUNDS_STAGE, run.selection_key, info)


def pairs_digest(out_dir: Path, selection_key: str) -> dict[str, Any] | None:
    """The digest of `pairs.txt` as the rounds of this selection left it (None: they never wrote it)."""
    return ledger(out_dir, selection_key).get("pairs_digest")


def _commit_pairs(run: RoundsRun, added: Round, extra: dict[str, Any]) -> None:
    """The round's pairs become `pairs.txt`: the ledger first (a run killed in between finishes the
    move in `recover`), then the file."""
    info = ledger(run.out_dir, run.selection_key)
    roles = info.setdefault("added", {})
    pairs = {tuple(p) for p in roles.get(added.role, [])} | {tuple(p) for p in added.pairs}
    roles[added.role] = [list(p) for p in sorted(pairs)]
    info.update(extra, pairs_digest=file_digest(run.staged))
    _save(run, info)
    os.replace(run.staged, run.out_dir / PAIRS_NAME)


def recover(out_dir: Path) -> None:
    """A round's pairs whose ledger was written before a run was killed become `pairs.txt`; any
    other staged pairs are dropped (call it holding the output folder's lock)."""
    staged = out_dir / ".sara" / STAGED_PAIRS
    if not staged.exists():
        return
    record = records.read_record(out_dir, ROUNDS_STAGE) or {}
    if record.get("info", {}).get("pairs_digest") == file_digest(staged):
        os.replace(staged, out_dir / PAIRS_NAME)
    else:
        staged.unlink()


def clear(out_dir: Path) -> None:
    """A new selection: the rounds of the previous one no longer apply."""
    records.clear(out_dir, ROUNDS_STAGE)


# ---------------------------------------------------------------------------------------------
# Before the first mapping
# ---------------------------------------------------------------------------------------------


@dataclass
class Staged:
    """Pairs matched before the first mapping, not yet in `pairs.txt` (they move in with the model)."""

    added: Round
    match_time_s: float


def before_mapping(run: RoundsRun, work: Path) -> tuple[Path, Staged | None]:
    """Let the source add pairs once the first ones are matched (in `work`), and match them.

    Returns the database to map and the staged round (None when nothing was added)."""
    info = ledger(run.out_dir, run.selection_key)
    if "first_match_time_s" not in info:  # the match stage's time of the first pairs, before any round
        info["first_match_time_s"] = records.done_info(run.out_dir, match.STAGE).get("time_s", 0.0)
        _save(run, info)
    pairs = read_pairs(run.out_dir / PAIRS_NAME, known_names=run.ctx.names)
    added = run.rounds.before_mapping(run.ctx, pairs, work)
    if added is None or not added.pairs:
        return work, None
    first = records.read_record(run.out_dir, match.STAGE) or {}
    write_pairs(run.staged, pairs + added.pairs)
    work = run.match(run.staged)
    record = records.read_record(run.out_dir, match.STAGE) or {}
    matched_now = record.get("key") != first.get("key") and first.get("done") is True
    elapsed = record.get("info", {}).get("time_s", 0.0) if matched_now else 0.0
    return work, Staged(added, elapsed)


def commit_staged(run: RoundsRun, staged: Staged) -> None:
    """The pairs matched before mapping become `pairs.txt` (called as the model is swapped in)."""
    before = ledger(run.out_dir, run.selection_key).get("before_mapping", {})
    _commit_pairs(run, staged.added, {"before_mapping": {
        "num_pairs": before.get("num_pairs", 0) + len(staged.added.pairs),
        "match_time_s": before.get("match_time_s", 0.0) + staged.match_time_s}})


# ---------------------------------------------------------------------------------------------
# After mapping
# ---------------------------------------------------------------------------------------------


def after_mapping(run: RoundsRun) -> dict[str, Any] | None:
    """Let the source look at the model and ask for more pairs; match them, then refine or map again.

    Up to `rounds.repair_rounds` rounds; a round whose mapping fails keeps the previous round's
    pairs, matches and model. Then the source's last step on the final model. Returns the ledger
    (None when no round and no last step ran)."""
    if run.conf.rounds.repair_rounds <= 0:
        return None
    out_dir = run.out_dir
    info = ledger(out_dir, run.selection_key)
    if "first_map_time_s" not in info:  # the map stage's time of the first model, before any round
        info["first_map_time_s"] = records.done_info(out_dir, mapping.STAGE).get("time_s", 0.0)
        info.update(rounds=0, pairs_added=0, time_s=0.0, match_time_s=0.0, map_time_s=0.0, refined_rounds=0)
        _save(run, info)
    while info["rounds"] < run.conf.rounds.repair_rounds:
        pairs = read_pairs(out_dir / PAIRS_NAME, known_names=run.ctx.names)
        added = run.rounds.after_mapping(run.ctx, pairs, out_dir / "sparse" / "0")
        if added is None or not added.pairs:
            break
        tic = time.perf_counter()
        write_pairs(run.staged, pairs + added.pairs)
        try:
            work = run.match(run.staged)
            match_s = records.done_info(out_dir, match.STAGE).get("time_s", 0.0)
            done = {"rounds": info["rounds"] + 1, "pairs_added": info["pairs_added"] + len(added.pairs),
                    "match_time_s": info["match_time_s"] + match_s}
            refined = _refine(run, added, work, done)
            map_s = refined["time_s"] if refined is not None else _map_again(run, added, work, done)
        except NoResultError as exc:
            logger.warning("the %d pairs added after mapping gave no better model (%s): keeping the model as it "
                           "was", len(added.pairs), exc)
            colmap.remove_database(out_dir / ".sara" / match.NEXT_DB_NAME)
            run.staged.unlink(missing_ok=True)
            break
        info = ledger(out_dir, run.selection_key)
        info.update(time_s=info["time_s"] + time.perf_counter() - tic, map_time_s=info["map_time_s"] + map_s,
                    refined_rounds=info["refined_rounds"] + (refined is not None))
        _save(run, info)
    finished = _finish(run, refined=info.get("refined_rounds", 0) > 0)
    if finished is not None:
        info = ledger(out_dir, run.selection_key)
        info.update(extension=finished, time_s=info["time_s"] + finished["time_s"],
                    map_time_s=info["map_time_s"] + finished["time_s"])
        _save(run, info)
    return info if info.get("rounds") or info.get("extension") else None


def _copy_other_models(sparse: Path, new: Path) -> None:
    """Into `new`, whose main model (0) replaces `sparse/0`: the other components as they are."""
    for other in sorted(sparse.iterdir()):
        if other.is_dir() and other.name != "0":
            shutil.copytree(other, new / other.name)


def _refine(run: RoundsRun, added: Round, work: Path, done: dict[str, Any]) -> dict[str, Any] | None:
    """The source refines the main model with the round's matches (poses held, re-triangulated,
    adjusted) instead of mapping again; None when it declines this round."""
    out_dir, sparse = run.out_dir, run.out_dir / "sparse"
    tmp = out_dir / ".sara" / "sparse.refined"
    shutil.rmtree(tmp, ignore_errors=True)
    result = run.rounds.refine(run.ctx, added, work, sparse / "0", tmp / "0")
    if result is None:
        shutil.rmtree(tmp, ignore_errors=True)
        return None
    _copy_other_models(sparse, tmp)
    match.commit(work, out_dir / extract.DB_NAME, out_dir)
    _commit_pairs(run, added, done)
    mapping.swap_in(tmp, sparse)
    # the refined model is the model of the committed matches: a re-run keeps it
    key = mapping.state_key(run.conf.map, run.conf.seed,
                            fingerprint(match.matches_digest(out_dir / extract.DB_NAME)))
    mapping.adopt(out_dir, {**records.done_info(out_dir, mapping.STAGE), "refined": True,
                            "time_s": result["time_s"]}, key=key)
    return result


def _map_again(run: RoundsRun, added: Round, work: Path, done: dict[str, Any]) -> float:
    """Map the round's matches (continuing from the main model where the mapper can); when that
    gives a model, the round's database and pairs replace the previous ones just before it does.
    Returns the mapping time."""
    out_dir = run.out_dir

    def commit() -> None:
        match.commit(work, out_dir / extract.DB_NAME, out_dir)
        _commit_pairs(run, added, done)

    main = out_dir / "sparse" / "0"
    conf = run.conf
    extend = conf.rounds.extend_model and conf.map.mapper == "incremental" and colmap.has_model(main)
    mapping.run(conf.map, work, run.ctx.images_root, out_dir, seed=conf.seed,
                upstream_key=fingerprint(match.matches_digest(work)), progress=run.progress,
                min_num_inliers=conf.match.min_num_inliers, commit=commit, input_model=main if extend else None)
    return records.done_info(out_dir, mapping.STAGE).get("time_s", 0.0)


def _finish(run: RoundsRun, *, refined: bool) -> dict[str, Any] | None:
    """The source's last word on the final model (SARA: extend its tracks when no refinement did);
    once per model: a model it already finished is left as it is."""
    out_dir, sparse = run.out_dir, run.out_dir / "sparse"
    done = records.done_info(out_dir, FINISH_STAGE)
    if done and done.get("model") == mapping.model_digest(sparse):
        return None
    tmp = out_dir / ".sara" / "sparse.finished"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        result = run.rounds.finish(run.ctx, sparse / "0", tmp / "0", refined=refined)
    except (OSError, ValueError, KeyError, RuntimeError) as exc:  # an improvement only: the model stays
        logger.warning("the last step on the final model failed (%s): keeping the model as it is", exc)
        result = None
    if result is None:
        shutil.rmtree(tmp, ignore_errors=True)
        return None
    _copy_other_models(sparse, tmp)
    mapping.swap_in(tmp, sparse)
    mapping.adopt(out_dir, records.done_info(out_dir, mapping.STAGE))
    records.mark_done(out_dir, FINISH_STAGE, "", {**result, "model": mapping.model_digest(sparse)})
    return result
