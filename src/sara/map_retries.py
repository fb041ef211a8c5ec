"""The first incremental mapping set right before the rounds: mapped again with the lens distortion
held, or from a forward pair, when its largest model could not grow, or with the points seen in two
views only when nothing was built (two photos); mended at its seam, or mapped
again under other seeds, when its own verified pairs contradict it. Each keeps the better model
(`better`). The map stage (`sara.mapping`) passes in its own ways of mapping (`Attempts`)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

from . import colmap
from .colmap.stepwise import Checkpoint
from .config import MapConfig

logger = logging.getLogger(__name__)

#: a first model holding less than this share of the views that verified pairs join is a start
#: that could not grow: the mapper is tried again from a forward pair
FORWARD_RETRY_SHARE = 0.5

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


@dataclass(frozen=True)
class Attempts:
    """What the mappings after the first share. `incremental(conf, folder, seed, forward_start=,
    first_image=, checkpoint=)` maps the database from scratch into `folder`; `extend(conf, folder,
    model)` continues `model` (the map stage's `_incremental` and `_extend`)."""

    conf: MapConfig
    db_path: Path
    tmp: Path
    seed: int
    min_num_inliers: int
    checkpoint: Checkpoint | None
    incremental: Callable[..., colmap.MappedModels]
    extend: Callable[[MapConfig, Path, Path], colmap.MappedModels]
    #: `reachable`'s answer once read; shared by the copies `replace` makes (the database does not
    #: change while the first mapping is set right)
    reachable_views: list[int] = field(default_factory=list, repr=False, compare=False)

    def derived(self, name: str, *extra: str) -> Checkpoint | None:
        return self.checkpoint.derived(name, *extra) if self.checkpoint is not None else None

    def agreement(self, recs: colmap.MappedModels) -> colmap.Agreement:
        return recs.agreement(self.db_path, self.min_num_inliers)

    def reachable(self) -> int:
        """The most views that verified pairs join (the database is read once)."""
        if not self.reachable_views:
            self.reachable_views.append(max(colmap.verified_graph(self.db_path, self.min_num_inliers)[2], default=0))
        return self.reachable_views[0]


def set_right(tries: Attempts, first: colmap.MappedModels) -> colmap.MappedModels:
    """The first mapping, or the better one mapped after it: with the distortion held, from a forward
    pair, then mended or mapped again under other seeds where its pairs contradict it."""
    recs = distortion_held(tries, first)
    conf = tries.conf
    tries = replace(tries, conf=replace(conf, refine_distortion=conf.refine_distortion and not recs.distortion_held))
    recs = two_view_points(tries, forward_start(tries, recs))
    tries = replace(tries, conf=replace(tries.conf, two_view_points=tries.conf.two_view_points or recs.two_view_points))
    return agreeing(tries, recs)


def distortion_held(tries: Attempts, first: colmap.MappedModels) -> colmap.MappedModels:
    """Map again with the cameras' distortion held, when it was refined and the first model holds less
    than `FORWARD_RETRY_SHARE` of the views joined by verified pairs; keeps the mapping whose largest
    model holds more views (`better`), and the retries and continuations after it hold it too. Before
    the forward retry: where holding the distortion lets the model grow, that mapping is saved.

    Where few points pin the lens down, the adjustments can bend it to make up for a wrong guess of
    the camera: on a low-texture stand-in (211 keypoints per image, its principal point 9 px off the
    centre) the radial term ran to -0.7 to -1.6 in every piece and the first models held 7-16 of 47
    views; held, all 47 in one model under each of four namings (lab/notes/CAPTURES.md, 23-24)."""
    if not tries.conf.refine_distortion or first.largest == 0:
        return first
    reachable = tries.reachable()
    if first.largest >= FORWARD_RETRY_SHARE * reachable:
        return first
    logger.info("map: the first model holds %d of the %d views joined by verified pairs: mapping again with the "
                "lens distortion held (map.refine_distortion)", first.largest, reachable)
    folder = tries.tmp / "distortion-held"
    folder.mkdir()
    again = tries.incremental(replace(tries.conf, refine_distortion=False), folder, tries.seed,
                              checkpoint=tries.derived(folder.name))
    again.distortion_held = True
    if not better(again, tries.agreement(again), first, tries.agreement(first)):
        return first
    logger.warning("map: with the lens distortion held the largest model holds %d views (refined: %d); kept, "
                   "and held in the rounds' mappings too", again.largest, first.largest)
    return again


def forward_start(tries: Attempts, first: colmap.MappedModels) -> colmap.MappedModels:
    """Map again with a start from views that moved along their viewing direction allowed, when
    the first mapping built no model, or a largest model of less than `FORWARD_RETRY_SHARE` of the
    views joined by verified pairs; keeps the result whose largest model holds more views.

    A camera driving or walking straight ahead gives COLMAP no start it accepts (every pair moved
    forward), or only one between two views where the path turns, from which the model often
    cannot grow (kitti-seq1 on SARA's pairs: 2, 5 and 51 of 51 views under seeds 0, 1 and 2)."""
    if first.largest > 0:
        reachable = tries.reachable()
        if first.largest >= FORWARD_RETRY_SHARE * reachable:
            return first
        logger.info("map: the first model holds %d of the %d views joined by verified pairs: mapping again from a "
                    "forward pair", first.largest, reachable)
    else:
        logger.info("map: COLMAP found no pair of views to start from that moved sideways enough; the camera "
                    "moves along its viewing direction (driving, walking ahead): starting from a forward pair")
    retry_dir = tries.tmp / "forward" if first.largest > 0 else tries.tmp
    retry_dir.mkdir(exist_ok=True)
    again = tries.incremental(tries.conf, retry_dir, tries.seed, forward_start=True,
                              checkpoint=tries.derived("forward"))
    if again.largest <= first.largest:
        return first
    again.forward_start, again.distortion_held = True, first.distortion_held
    return again


def two_view_points(tries: Attempts, first: colmap.MappedModels) -> colmap.MappedModels:
    """Map again with the points seen in two views only, from a forward pair allowed, when no model
    was built so far (the forward retry included); keeps that mapping when it builds one.

    COLMAP triangulates only points whose matches join three views or more (ignore_two_view_tracks),
    so two photos never make a model however well they overlap (two views of fountain-P11: none,
    4,696 inlier matches; with these points both views and 4,696 points). Where a third view joins
    the points, nothing changes: this runs only where nothing else built a model."""
    if first.largest > 0 or tries.conf.two_view_points:
        return first
    logger.info("map: no model could be built from the points seen in three views or more: mapping again with "
                "those seen in two views only (map.two_view_points)")
    folder = tries.tmp / "two-view"
    folder.mkdir()
    again = tries.incremental(replace(tries.conf, two_view_points=True), folder, tries.seed, forward_start=True,
                              checkpoint=tries.derived(folder.name))
    if again.largest == 0:
        return first
    logger.warning("map: with the points seen in two views only, the largest model holds %d views", again.largest)
    again.two_view_points, again.forward_start, again.distortion_held = True, True, first.distortion_held
    return again


def agreeing(tries: Attempts, first: colmap.MappedModels) -> colmap.MappedModels:
    """Mend the first mapping's largest model at its seam (`mended`, if `map.mend_seam`) when its own
    verified pairs contradict it (`contradicted`), then map again, at most `map.contradicted_remaps`
    times, while the best so far is contradicted: under the next seed, on `REMAP_THREADS` threads,
    the first model started from the view in most of the contradicting pairs; keeps the best. When a
    mapping (or the mend) is contradicted by exactly the pairs that contradicted the one before it, the
    fault is in those pairs' matches, not in how the mapper built the model, and no more mappings
    follow (dtu-scan24 under exhaustive matching: the same 12 pairs under seeds 0 and 1, CAPTURES.md 15).

    The incremental mapper can bend a model where the views pass a place twice: the pairs that
    would close the loop never join a track, so nothing in the mapper sees them (lab/notes/SCALE.md)."""
    seed = tries.seed
    best, best_check = first, tries.agreement(first)
    best.seed, remaps, check, same = seed, 0, best_check, False
    earlier = check  # the check of the model mapped last before the next one
    if contradicted(best_check) and tries.conf.mend_seam:
        best, best_check, mend = mended(tries, first, check)
        if same := mend is not None and set(mend.contradicted) == set(check.contradicted):
            logger.warning("map: the same %d pairs contradict the mended model: the fault is in those pairs, not in "
                           "how the mapper built the model; no mapping again", len(check.contradicted))
    while not same and contradicted(best_check) and remaps < tries.conf.contradicted_remaps:
        remaps += 1
        start = check.most_contradicted_view()  # the last model's: a model no pair contradicts ends the loop
        logger.warning("map: %d of the %d verified pairs between the views of the largest model contradict it "
                       "(their matches lie more than %.0f px off its epipolar lines): mapping again under seed %d, "
                       "starting from %s", len(check.contradicted), check.checked, colmap.CONTRADICTION_PX,
                       seed + remaps, start)
        folder = tries.tmp / f"seed-{seed + remaps}"
        folder.mkdir()
        colmap.set_seed(seed + remaps)
        again = tries.incremental(replace(tries.conf, num_threads=REMAP_THREADS), folder, seed + remaps,
                                  forward_start=first.forward_start, first_image=start,
                                  checkpoint=tries.derived(folder.name, f"{start}"))
        again.forward_start, again.seed = first.forward_start, seed + remaps
        again.distortion_held = first.distortion_held
        check = tries.agreement(again)
        logger.warning("map: under seed %d the largest model holds %d views, %d of %d pairs contradict it",
                       seed + remaps, again.largest, len(check.contradicted), check.checked)
        if better(again, check, best, best_check):
            best, best_check = again, check
        if set(check.contradicted) == set(earlier.contradicted):
            logger.warning("map: the same %d pairs contradict the model under seed %d: the fault is in those "
                           "pairs, not in how the mapper built the model; no more mappings", len(check.contradicted),
                           seed + remaps)
            break
        earlier = check
    best.agreement_check, best.remaps = best_check, remaps
    return best


def mended(tries: Attempts, first: colmap.MappedModels, check: colmap.Agreement,
           ) -> tuple[colmap.MappedModels, colmap.Agreement, colmap.Agreement | None]:
    """(the first model or, where better, it cut at its seam and continued, its check, the continued one's)."""
    folder = tries.tmp / "mend"
    cut = colmap.cut_at_seam(first, check, tries.db_path, folder / "cut", min_num_inliers=tries.min_num_inliers)
    if cut is None:
        return first, check, None
    logger.warning("map: %d of the %d verified pairs between the views of the largest model contradict it: taking out "
                   "the %d views up to %d pairs from them (and %d cut off with them) and continuing the %d others",
                   len(check.contradicted), check.checked, cut.taken_out, colmap.SEAM_HOPS, cut.dropped, cut.kept)
    try:
        recs = tries.extend(tries.conf, folder, folder / "cut")
    except colmap.ColmapError as exc:  # the first model stays, and the remaps follow as without the mend
        logger.warning("map: continuing the cut model failed (%s): keeping the first model", exc)
        return first, check, None
    recs.forward_start, recs.distortion_held = first.forward_start, first.distortion_held
    recs.seed, recs.mended, again = tries.seed, True, tries.agreement(recs)
    logger.warning("map: continued, the largest model holds %d views (%d before), %d of %d pairs contradict it",
                   recs.largest, first.largest, len(again.contradicted), again.checked)
    return (recs, again, again) if better(recs, again, first, check) else (first, check, again)


def continued(tries: Attempts, recs: colmap.MappedModels) -> tuple[colmap.MappedModels, dict[str, int | bool]]:
    """A continued model (a round's mapping) checked against its verified pairs, the round's new ones
    included, and mended at its seam where they contradict it (`map.mend_seam`); never mapped again from
    scratch (a round that could not register its views leaves them to the next). Returns the model
    kept and what the map stage's record says of it.

    A continuation registers views next to a model that agreed with its pairs; a new pair that closes
    a loop across a stretch placed wrong shows the bend as it does in a first model, and a round that
    glues a view at the wrong place bends its neighbourhood."""
    check = tries.agreement(recs)
    info: dict[str, int | bool] = {"continued_pairs_checked": check.checked,
                                   "continued_pairs_contradicted": len(check.contradicted)}
    if not contradicted(check):
        return recs, info
    if not tries.conf.mend_seam:
        logger.warning("map: %d of the %d verified pairs between the views of the continued model contradict it "
                       "(map.mend_seam is off: kept as it is)", len(check.contradicted), check.checked)
        return recs, info
    kept, kept_check, _ = mended(tries, recs, check)
    if kept is not recs:
        info.update(continued_mended=True, continued_pairs_contradicted=len(kept_check.contradicted))
    return kept, info


def contradicted(check: colmap.Agreement) -> bool:
    return check.share > CONTRADICTED_SHARE or len(check.contradicted) >= CONTRADICTED_PAIRS


def better(new: colmap.MappedModels, new_check: colmap.Agreement, old: colmap.MappedModels,
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
        sound = not contradicted(check) and model.largest >= other.largest - len(seam)
        return model.largest > 0, sound, model.largest, -len(check.contradicted)

    return rank(new, new_check, old, old_check) > rank(old, old_check, new, new_check)
