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
import math
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .. import colmap, eta, extract, mapping, match
from ..config import PipelineConfig
from ..io import NoResultError, file_digest, fingerprint, link_or_copy, read_json, records, write_json_atomic
from ..io.pairs import Pair, read_pairs, write_pairs
from ..pairs import PairContext, Round, Rounds

logger = logging.getLogger(__name__)

PAIRS_NAME = "pairs.txt"
#: the ledger of the rounds of the current selection
ROUNDS_STAGE = "rounds"
#: the last step on the final model, once per model
FINISH_STAGE = "finish"
#: the pairs of a round, until its model replaces the previous one
STAGED_PAIRS = "pairs.next.txt"
#: where a round keeps the model it started from (hard links) until its own mapping is known to hold
#: no fewer views in the main model
BEFORE_ROUND = "sparse.before-round"
#: the map stage's record of that model, beside it (a run killed after the round's mapping replaced
#: the model and before it was compared puts it back on the next run: `restore_interrupted`)
BEFORE_RECORD = "sparse.before-round.json"


@dataclass
class RoundsRun:
    """What the rounds of one run need: the source's rounds, its context and the selection's key."""

    rounds: Rounds
    ctx: PairContext
    conf: PipelineConfig
    out_dir: Path
    selection_key: str
    progress: bool = True
    #: earlier matches to take pairs from (`match.run`'s `reserve`)
    reserve: Path | None = None

    @property
    def staged(self) -> Path:
        return self.out_dir / ".sara" / STAGED_PAIRS

    def match(self, pairs_path: Path) -> Path:
        """Match `pairs_path` beside the current database; returns the database holding the matches."""
        return match.run(self.conf.match, pairs_path, self.out_dir / extract.DB_NAME, self.out_dir,
                         features_path=self.ctx.features_path, features_backend=self.conf.extract.backend,
                         executor=self.ctx.executor, progress=self.progress, beside=True, reserve=self.reserve)


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
    other staged pairs are dropped; a round's mapping that was killed leaves the map stage as
    `restore_interrupted` says (call it holding the output folder's lock)."""
    staged = out_dir / ".sara" / STAGED_PAIRS
    if staged.exists():
        record = records.read_record(out_dir, ROUNDS_STAGE) or {}
        if record.get("info", {}).get("pairs_digest") == file_digest(staged):
            os.replace(staged, out_dir / PAIRS_NAME)
        else:
            staged.unlink()
    restore_interrupted(out_dir)


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
    match_estimate_s: float = 0.0


def before_mapping(run: RoundsRun, work: Path) -> tuple[Path, Staged | None]:
    """Let the source add pairs once the first ones are matched (in `work`), and match them.

    Returns the database to map and the staged round (None when nothing was added)."""
    info = ledger(run.out_dir, run.selection_key)
    if "first_match_time_s" not in info:  # the match stage's figures of the first pairs, before any round
        first = records.done_info(run.out_dir, match.STAGE)
        info.update(first_match_time_s=first.get("time_s", 0.0),
                    first_match_estimate_s=first.get("estimate_s", first.get("time_s", 0.0)),
                    first_match_rate_pairs_per_s=first.get("rate_pairs_per_s", 0.0))
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
    done = record.get("info", {}) if matched_now else {}
    return work, Staged(added, done.get("time_s", 0.0), done.get("estimate_s", done.get("time_s", 0.0)))


def commit_staged(run: RoundsRun, staged: Staged) -> None:
    """The pairs matched before mapping become `pairs.txt` (called as the model is swapped in)."""
    before = ledger(run.out_dir, run.selection_key).get("before_mapping", {})
    _commit_pairs(run, staged.added, {"before_mapping": {
        "num_pairs": before.get("num_pairs", 0) + len(staged.added.pairs),
        "match_time_s": before.get("match_time_s", 0.0) + staged.match_time_s,
        "match_estimate_s": before.get("match_estimate_s", 0.0) + staged.match_estimate_s}})


# ---------------------------------------------------------------------------------------------
# After mapping
# ---------------------------------------------------------------------------------------------


def after_mapping(run: RoundsRun) -> dict[str, Any] | None:
    """Let the source look at the model and ask for more pairs; match them, then refine or map again.

    Up to `rounds.repair_rounds` rounds, within their time budget (`time_budget`): each round's
    pairs are cut to what its matching may take at the first round's rate, and no round starts
    once the budget is spent. A round that registered no new image and left as many models is not
    repeated (its role asked for again ends the rounds). A round whose mapping fails keeps the
    previous round's pairs, matches and model. Then the source's last step on the final model.
    Returns the ledger (None when no round and no last step ran)."""
    if run.conf.rounds.repair_rounds <= 0:
        return None
    out_dir = run.out_dir
    info = ledger(out_dir, run.selection_key)
    if "first_map_time_s" not in info:  # the map stage's time of the first model, before any round
        info["first_map_time_s"] = records.done_info(out_dir, mapping.STAGE).get("time_s", 0.0)
        info.update(rounds=0, pairs_added=0, time_s=0.0, match_time_s=0.0, match_estimate_s=0.0, map_time_s=0.0,
                    refined_rounds=0, history=[])
        _save(run, info)
    while info["rounds"] < run.conf.rounds.repair_rounds and _one_round(run, info):
        info = ledger(out_dir, run.selection_key)
    info = ledger(out_dir, run.selection_key)
    if _last_round_due(run, info):
        _one_round(run, info, last=True)
        info = ledger(out_dir, run.selection_key)
    finished = _finish(run, refined=info.get("refined_rounds", 0) > 0)
    if finished is not None:
        info.update(extension=finished, time_s=info["time_s"] + finished["time_s"],
                    map_time_s=info["map_time_s"] + finished["time_s"])
        _save(run, info)
    return info if info.get("rounds") or info.get("extension") else None


def time_budget(conf: PipelineConfig, info: dict[str, Any]) -> eta.TimeBudget:
    """The rounds' time budget from the ledger: `rounds.max_time_fraction` of the first round's
    match + map time, less what the rounds after mapping took so far."""
    return eta.TimeBudget(conf.rounds.max_time_fraction, info.get("first_match_time_s", 0.0),
                          info.get("first_map_time_s", 0.0), spent_s=info.get("time_s", 0.0),
                          rate_pairs_per_s=info.get("first_match_rate_pairs_per_s", 0.0))


def _last_round_due(run: RoundsRun, info: dict[str, Any]) -> bool:
    """Whether the repairs used up `rounds.repair_rounds` with no round refining the model
    (`rounds.pose_guided_last`): then one more round (once: it makes the count one more), in which
    the source may only refine."""
    return (run.conf.rounds.pose_guided_last and info["rounds"] == run.conf.rounds.repair_rounds
            and "stopped" not in info and not info.get("refined_rounds", 0))


def _one_round(run: RoundsRun, info: dict[str, Any], *, last: bool = False) -> bool:
    """One round after mapping; False when there is none to run (the ledger says why in `stopped`).
    `last`: the round after the repairs' (`_last_round_due`), for pairs that refine the model."""
    out_dir = run.out_dir
    budget = time_budget(run.conf, info)
    limit = budget.pairs_that_fit()
    total_s = None if math.isinf(budget.total_s) else budget.total_s
    if limit == 0:
        logger.info("rounds: %s of their time budget of %s taken (rounds.max_time_fraction of the first round's "
                    "match and map time), too little left to match a pair: no more rounds",
                    eta.format_duration(budget.spent_s), eta.format_duration(budget.total_s))
        return _stop(run, "time budget spent", total_s)
    tic = time.perf_counter()
    pairs = read_pairs(out_dir / PAIRS_NAME, known_names=run.ctx.names)
    run.ctx.max_round_pairs, run.ctx.last_round = limit, last
    try:
        added = run.rounds.after_mapping(run.ctx, pairs, out_dir / "sparse" / "0")
    finally:
        run.ctx.max_round_pairs, run.ctx.last_round = None, False
    if added is None or not added.pairs:
        return _stop(run, "nothing more to add", total_s)
    if added.role in info.get("unproductive_roles", []):
        logger.info("rounds: the last %s round registered no new image and left as many models: not repeating it",
                    added.role)
        return _stop(run, "a round without gain asked for again", total_s)
    added = _within(added, pairs, limit)
    if not added.pairs:
        return _stop(run, "nothing more to add", total_s)
    state = _model_state(out_dir)
    write_pairs(run.staged, pairs + added.pairs)
    try:
        work = run.match(run.staged)
        matched = records.done_info(out_dir, match.STAGE)
        done = {"rounds": info["rounds"] + 1, "pairs_added": info["pairs_added"] + len(added.pairs),
                "match_time_s": info["match_time_s"] + matched.get("time_s", 0.0),
                "match_estimate_s": info.get("match_estimate_s", 0.0)
                + matched.get("estimate_s", matched.get("time_s", 0.0))}
        refined = _refine(run, added, work, done)
        map_s = refined["time_s"] if refined is not None else _map_again(run, added, work, done)
    except NoResultError as exc:
        logger.warning("the %d pairs added after mapping gave no better model (%s): keeping the model as it "
                       "was", len(added.pairs), exc)
        colmap.remove_database(out_dir / ".sara" / match.NEXT_DB_NAME)
        run.staged.unlink(missing_ok=True)
        return _stop(run, "a round gave no better model", total_s)
    info = ledger(out_dir, run.selection_key)
    after = _model_state(out_dir)
    gained = after[0] > state[0] or after[1] < state[1]
    round_s = time.perf_counter() - tic
    mapped = records.done_info(out_dir, mapping.STAGE) if refined is None else {}
    if "kept_after_round" in mapped:  # the round's model was dropped: the record is the earlier model's
        mapped = {}
    info.setdefault("history", []).append({
        "role": added.role, "num_pairs": len(added.pairs), "pair_limit": limit,
        "match_time_s": matched.get("time_s", 0.0), "map_time_s": map_s, "time_s": round_s,
        "registered": [state[0], after[0]], "num_models": [state[1], after[1]], "gain": gained,
        # the round's continued model against its pairs (`map_retries.continued`)
        **{k: mapped[k] for k in ("continued_pairs_contradicted", "continued_mended") if k in mapped}})
    if not gained:
        info["unproductive_roles"] = sorted(set(info.get("unproductive_roles", [])) | {added.role})
    info.update(time_s=info["time_s"] + round_s, map_time_s=info["map_time_s"] + map_s,
                refined_rounds=info["refined_rounds"] + (refined is not None), time_budget_s=total_s)
    _save(run, info)
    return True


def _stop(run: RoundsRun, why: str, time_budget_s: float | None) -> bool:
    """No more rounds, and why (in the ledger)."""
    info = ledger(run.out_dir, run.selection_key)
    info.update(stopped=why, time_budget_s=time_budget_s)
    _save(run, info)
    return False


def _within(added: Round, matched: list[Pair], limit: int | None) -> Round:
    """The round's pairs that are not matched yet, the first `limit` of them (None: all)."""
    done = {tuple(sorted(p)) for p in matched}
    fresh = [p for p in added.pairs if tuple(sorted(p)) not in done]
    if limit is not None and len(fresh) > limit:
        logger.info("rounds: %d of the %s round's %d pairs fit in the time left", limit, added.role, len(fresh))
        fresh = fresh[:limit]
    return Round(fresh, added.role)


def _model_state(out_dir: Path) -> tuple[int, int]:
    """(images registered in the main model, number of models), as the map stage recorded them."""
    mapped = records.done_info(out_dir, mapping.STAGE)
    return int(mapped.get("num_registered", 0)), int(mapped.get("num_components", 0))


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
    # whether the mapper may continue this model (the incremental one's) is the map stage's call
    extend = conf.rounds.extend_model and colmap.has_model(main)
    before = out_dir / ".sara" / BEFORE_ROUND
    previous = records.read_record(out_dir, mapping.STAGE)
    _linked_copy(out_dir / "sparse", before)
    if before.is_dir():
        matches = fingerprint(match.matches_digest(out_dir / extract.DB_NAME))
        write_json_atomic(out_dir / ".sara" / BEFORE_RECORD, {"previous": previous, "matches": matches})
    try:
        mapping.run(conf.map, work, run.ctx.images_root, out_dir, seed=conf.seed,
                    upstream_key=fingerprint(match.matches_digest(work)), progress=run.progress,
                    min_num_inliers=conf.match.min_num_inliers, commit=commit, input_model=main if extend else None)
        map_s = records.done_info(out_dir, mapping.STAGE).get("time_s", 0.0)
        _keep_the_larger(out_dir, before, previous)
    finally:
        (out_dir / ".sara" / BEFORE_RECORD).unlink(missing_ok=True)
        shutil.rmtree(before, ignore_errors=True)
    return map_s


def _linked_copy(sparse: Path, dest: Path) -> None:
    """`sparse` as it is now, in `dest`: hard links (the mapper writes new files, never into old
    ones), copies where links cannot be made; nothing when there is no `sparse`."""
    shutil.rmtree(dest, ignore_errors=True)
    if sparse.is_dir():
        shutil.copytree(sparse, dest, copy_function=link_or_copy)


def restore_interrupted(out_dir: Path) -> None:
    """A round's starting model left behind by a run killed during the round's mapping, then
    dropped. Killed once the mapping was recorded: the larger of the two models stays
    (`_keep_the_larger`). Killed inside the mapping: before the round's matches were committed,
    the map stage's record goes back to what it was (the model is untouched until then); after,
    the starting model is put back as the model of those matches, as a mapping that failed keeps it.
    Run by `recover`, before any stage: left "started", the map stage's record would have the map
    stage map everything again."""
    before, saved = out_dir / ".sara" / BEFORE_ROUND, out_dir / ".sara" / BEFORE_RECORD
    if saved.is_file() and before.is_dir():
        logger.info("a round's mapping was interrupted: checking the model it left against the one it started from")
        kept = read_json(saved)
        now = records.read_record(out_dir, mapping.STAGE) or {}
        if now.get("done") is True:
            _keep_the_larger(out_dir, before, kept["previous"])
        elif fingerprint(match.matches_digest(out_dir / extract.DB_NAME)) == kept["matches"]:
            records.restore(out_dir, mapping.STAGE, kept["previous"])
        elif colmap.has_model(before / "0"):
            mapping.swap_in(before, out_dir / "sparse")
            mapping.adopt(out_dir, ((kept["previous"] or {}).get("info") or {}), key=now.get("key", ""))
    saved.unlink(missing_ok=True)
    shutil.rmtree(before, ignore_errors=True)


def _keep_the_larger(out_dir: Path, before: Path, previous: dict[str, Any] | None) -> None:
    """Put the round's starting model (`before`, its map record `previous`) back when the round's
    mapping holds fewer views in its main model: a round adds pairs to register views, and a
    continuation that lost some (a 47-view low-texture stand-in: 25 views, then 16 after a second
    repair) must not end the run with less than it had. It stays the map stage's model of the
    matches now committed (the round's), so a re-run keeps it."""
    had = int(((previous or {}).get("info") or {}).get("num_registered", 0))
    now = records.read_record(out_dir, mapping.STAGE) or {}
    holds = int((now.get("info") or {}).get("num_registered", 0))
    if holds >= had or not colmap.has_model(before / "0"):
        return
    logger.warning("the round's mapping holds %d views in its main model, fewer than the %d of the model it started "
                   "from: keeping that model", holds, had)
    mapping.swap_in(before, out_dir / "sparse")
    mapping.adopt(out_dir, {**previous["info"], "kept_after_round": holds}, key=now.get("key", ""))


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
