"""Ambiguity rejection: candidate pairs whose relative rotations do not close around cycles.

Symmetric and repeated structures (two identical facades, the four sides of a tower) give
candidate pairs with plenty of inliers and a wrong relative pose. Alone such a pair looks as good as
any; against its neighbours it does not fit. The scorer estimates each accepted pair's rotation
``R_ij = cam_j_from_cam_i``; around a triangle ``i -> j -> k -> i`` of accepted candidates the true
rotations compose to the identity, so the angle of ``R_ik^T R_jk R_ij`` (the triangle's *closure
error*) measures how wrong its three rotations are together.

A failing triangle (closure error above ``max_error_deg``) says that one of its three pairs is
wrong, not which. It points at one when the other two are *vouched for*: each closes some other
triangle. (Like the loop tests of 1DSfM and of loop-constraint disambiguation, the pairs check each
other; no pair is trusted on its own.) A pair is rejected when

- at least ``min_failed`` of its failing triangles point at it, and
- most of its triangles fail (more than half: a wrong pair closes a triangle only by chance, a true
  pair closes every triangle whose other two pairs are true).

Pairs are rejected one at a time, the most blamed first (then the largest share of failing
triangles, then the lowest weight), and the triangles of a rejected pair stop counting: a pair that
vouched for others only through it no longer does. Pairs in no triangle are never tested, hence
kept; so are the pairs of a view whose every pair disagrees with the others (nothing says which).

The check never disconnects the accepted graph, and so never leaves a view without a pair: a
triangle that crosses a cut of the graph holds exactly two of the pairs across it, so when all of
them but one are rejected, every triangle of the last one holds a rejected pair and has stopped
counting; nothing can blame it. (`tests/test_ambiguity.py` checks this on random graphs.)

The scorer's rotations come from the focal length known before mapping (EXIF or COLMAP's prior,
often 1.3-2x off), so true pairs' rotations err by several degrees; the threshold is set above that
(see ``GraphConfig.max_cycle_error_deg``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..config import GraphConfig
from ..io.scores import PairScores
from ..rotations import angle_between_deg, matrix_from_rotvec
from .spanning import _check_graph

logger = logging.getLogger(__name__)

#: the rejection reason of a pair that fails its rotation cycles (scores.csv's "reason")
INCONSISTENT = "inconsistent"


@dataclass(frozen=True)
class CycleCheck:
    """The outcome of :func:`inconsistent_pairs`.

    Attributes:
        rejected: (R,) int64 indices into ``edges`` of the rejected pairs, in the order rejected.
        triangles: (T, 3) int64 edge indices ``(ij, jk, ik)`` of the triangles of tested pairs.
        closure_error_deg: (T,) float64 each triangle's closure error, degrees.
        failed: (E,) int64 failing triangles of each pair (all triangles, before any rejection).
        in_triangles: (E,) int64 triangles of each pair.
    """

    rejected: np.ndarray
    triangles: np.ndarray
    closure_error_deg: np.ndarray
    failed: np.ndarray
    in_triangles: np.ndarray

    def stats(self) -> dict[str, int]:
        """Counts for a log line or a record."""
        return {"triangles": len(self.triangles), "failed_triangles": int(self.failed.sum() // 3),
                "rejected": len(self.rejected)}


def triangles_of(num_images: int, edges: np.ndarray, tested: np.ndarray) -> np.ndarray:
    """(T, 3) int64 edge indices ``(ij, jk, ik)`` of the triangles ``i < j < k`` whose three pairs
    are all `tested`; edges: (E, 2) int64 ``i < j``, unique; tested: (E,) bool. Sorted by ``(i, j, k)``."""
    edges = _check_graph(num_images, edges)
    index = {(int(a), int(b)): e for e, (a, b) in enumerate(edges) if tested[e]}
    higher: list[set[int]] = [set() for _ in range(num_images)]  # neighbours with a larger index
    for a, b in index:
        higher[a].add(b)
    out = []
    for (i, j), ij in sorted(index.items()):
        for k in sorted(higher[i] & higher[j]):
            out.append((ij, index[(j, k)], index[(i, k)]))
    return np.array(out, dtype=np.int64).reshape(-1, 3)


def closure_errors_deg(rotvec: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(T,) float64 angle of ``R_ik^T R_jk R_ij`` (degrees) for triangles ``(ij, jk, ik)``;
    rotvec: (E, 3) rotation vectors of ``cam_j_from_cam_i`` of each pair ``(i, j)``, ``i < j``."""
    if len(triangles) == 0:
        return np.zeros(0)
    rot = matrix_from_rotvec(np.asarray(rotvec, dtype=np.float64)[triangles.reshape(-1)])
    ij, jk, ik = rot[0::3], rot[1::3], rot[2::3]
    return angle_between_deg(ik, jk @ ij)


def inconsistent_pairs(
    num_images: int,
    edges: np.ndarray,
    rotvec: np.ndarray,
    accepted: np.ndarray,
    weight: np.ndarray,
    *,
    max_error_deg: float,
    min_failed: int = 2,
) -> CycleCheck:
    """The accepted pairs whose rotations fail their triangles (see the module's docstring).

    Args:
        num_images: N.
        edges: (E, 2) int64 candidate pairs ``i < j``, unique.
        rotvec: (E, 3) float64 rotation vectors of ``cam_j_from_cam_i``; NaN where unknown (untested).
        accepted: (E,) bool; only accepted pairs are tested.
        weight: (E,) float64 pair weight: of two pairs blamed alike, the weaker is rejected first.
        max_error_deg: a triangle fails above this closure error (degrees).
        min_failed: fewest failing triangles that can blame a pair.
    Returns:
        A :class:`CycleCheck`; the same input always gives the same output.
    """
    edges = _check_graph(num_images, edges)
    rotvec = np.asarray(rotvec, dtype=np.float64).reshape(len(edges), 3)
    accepted = np.asarray(accepted, dtype=bool).reshape(len(edges))
    weight = np.asarray(weight, dtype=np.float64).reshape(len(edges))
    tested = accepted & np.all(np.isfinite(rotvec), axis=1)
    triangles = triangles_of(num_images, edges, tested)
    errors = closure_errors_deg(rotvec, triangles)
    fails = errors > max_error_deg
    in_triangles = np.bincount(triangles.reshape(-1), minlength=len(edges)).astype(np.int64)
    failed = np.bincount(triangles[fails].reshape(-1), minlength=len(edges)).astype(np.int64)
    rejected = _reject_greedily(triangles, fails, weight, min_failed)
    return CycleCheck(rejected=np.array(rejected, dtype=np.int64).reshape(-1), triangles=triangles,
                      closure_error_deg=errors, failed=failed, in_triangles=in_triangles)


def _blame(triangles: np.ndarray, fails: np.ndarray, alive: np.ndarray, num_edges: int) -> tuple[np.ndarray, ...]:
    """Per pair, over the `alive` triangles: (triangles, failing ones, failing ones that blame it).

    A pair is vouched for when it closes at least one triangle; a failing triangle blames one of its
    pairs when the other two are vouched for (then it is the one that does not fit)."""
    vouched = np.bincount(triangles[alive & ~fails].reshape(-1), minlength=num_edges) > 0
    failing = triangles[alive & fails]
    v = vouched[failing]
    blames = np.stack([v[:, 1] & v[:, 2], v[:, 0] & v[:, 2], v[:, 0] & v[:, 1]], axis=1)
    total = np.bincount(triangles[alive].reshape(-1), minlength=num_edges)
    failed = np.bincount(failing.reshape(-1), minlength=num_edges)
    return total, failed, np.bincount(failing[blames], minlength=num_edges)


def _reject_greedily(triangles: np.ndarray, fails: np.ndarray, weight: np.ndarray, min_failed: int) -> list[int]:
    """Blamed pairs, most blamed first; each rejection removes its triangles from the counts."""
    alive = np.ones(len(triangles), dtype=bool)
    out: list[int] = []
    while True:
        total, failed, blamed = _blame(triangles, fails, alive, len(weight))
        candidates = np.flatnonzero((blamed >= min_failed) & (2 * failed > total))
        if len(candidates) == 0:
            return out
        share = failed[candidates] / total[candidates]
        order = np.lexsort((candidates, weight[candidates], -share, -blamed[candidates]))
        worst = int(candidates[order[0]])
        out.append(worst)
        alive &= ~np.any(triangles == worst, axis=1)


def mark_inconsistent(num_images: int, edges: np.ndarray, scores: PairScores, conf: GraphConfig) -> CycleCheck | None:
    """Run :func:`inconsistent_pairs` on `scores` and mark the rejected pairs in place: not
    accepted, reason :data:`INCONSISTENT` (weights kept). Pairs marked by an earlier call are tested
    again, so a caller may call it after adding candidates. None when ``conf.reject_inconsistent`` is off.
    """
    if not conf.reject_inconsistent:
        return None
    earlier = np.array([r == INCONSISTENT for r in scores.reason], dtype=bool)
    accepted = scores.accepted | earlier
    check = inconsistent_pairs(num_images, edges, scores.rotvec, accepted, scores.weight,
                               max_error_deg=conf.max_cycle_error_deg, min_failed=conf.cycle_min_failed)
    rejected = np.zeros(len(edges), dtype=bool)
    rejected[check.rejected] = True
    scores.accepted[:] = accepted & ~rejected
    scores.reason[:] = [INCONSISTENT if rejected[e] else ("" if earlier[e] else r) for e, r in enumerate(scores.reason)]
    for e in check.rejected:
        logger.debug("pair %s %s rejected: %d of its %d rotation triangles fail", scores.name0[e], scores.name1[e],
                     check.failed[e], check.in_triangles[e])
    logger.info("rotation cycles: %d triangles of accepted pairs, %d fail (above %g deg); %d pairs rejected as "
                "inconsistent", len(check.triangles), check.stats()["failed_triangles"], conf.max_cycle_error_deg,
                len(check.rejected))
    return check
