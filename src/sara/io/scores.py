"""`scores.csv`: one row per scored candidate pair, every component of its score and its role.

Columns: name0, name1, num_matches, num_inliers, num_inliers_all, overlap, parallax_deg, weight,
accepted, reason, role, rotvec_x, rotvec_y, rotvec_z, direction_x, direction_y, direction_z. Floats are
written with full precision (repr), so a file read back gives the same arrays. Files written before
num_inliers_all existed are read with it equal to num_inliers; files written before the rotation or
direction columns, with NaN rotations or directions.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import atomic_path


@dataclass(eq=False)
class PairScores:
    """Scores of P pairs, one entry per pair in the order scored.

    Attributes:
        name0, name1: image names, P each.
        num_matches: (P,) int64 mutual nearest neighbours used (at most ``num_matches``).
        num_inliers: (P,) int64 RANSAC inliers (among the b best matches).
        num_inliers_all: (P,) int64 mutual nearest neighbours of all keypoints that fit the RANSAC
            pose (>= num_inliers where a pose was found); num_inliers when not given.
        overlap: (P,) float64 ``num_inliers / sqrt(N0 N1)``.
        parallax_deg: (P,) float64 median triangulation angle, degrees; NaN where not measured
            (the pair failed a test before the parallax one).
        weight: (P,) float64 ``w``; 0 where the parallax was not measured.
        accepted: (P,) bool.
        reason: P strings, why it was rejected (see sara.scoring.REASONS), "" when accepted.
        rotvec: (P, 3) float64 the scorer's relative rotation ``cam1_from_cam0`` of each pair as a
            rotation vector (axis times angle, radians); NaN where RANSAC found no pose or it was not
            recorded (files of earlier versions).
        direction: (P, 3) float64 the same pose's translation as a unit vector (camera 0's centre seen
            from camera 1); NaN where there is none or it was not recorded.
    """

    name0: list[str]
    name1: list[str]
    num_matches: np.ndarray
    num_inliers: np.ndarray
    overlap: np.ndarray
    parallax_deg: np.ndarray
    weight: np.ndarray
    accepted: np.ndarray
    reason: list[str]
    num_inliers_all: np.ndarray | None = None
    rotvec: np.ndarray | None = None
    direction: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.num_inliers_all is None:
            self.num_inliers_all = np.array(self.num_inliers, dtype=np.int64, copy=True)
        if self.rotvec is None:
            self.rotvec = np.full((len(self.name0), 3), np.nan)
        self.rotvec = np.asarray(self.rotvec, dtype=np.float64).reshape(len(self.name0), 3)
        if self.direction is None:
            self.direction = np.full((len(self.name0), 3), np.nan)
        self.direction = np.asarray(self.direction, dtype=np.float64).reshape(len(self.name0), 3)

    def __len__(self) -> int:
        return len(self.name0)

    @classmethod
    def from_scores(cls, pairs: Sequence[tuple[str, str]], scores: Sequence[Any]) -> PairScores:
        def column(name: str, dtype: Any) -> np.ndarray:
            return np.array([getattr(s, name) for s in scores], dtype=dtype).reshape(len(scores))

        return cls(
            name0=[p[0] for p in pairs], name1=[p[1] for p in pairs],
            num_matches=column("num_matches", np.int64), num_inliers=column("num_inliers", np.int64),
            overlap=column("overlap", np.float64), parallax_deg=column("parallax_deg", np.float64),
            weight=column("weight", np.float64), accepted=column("accepted", bool),
            reason=[s.reason for s in scores], num_inliers_all=column("num_inliers_all", np.int64),
            rotvec=np.array([s.rotvec for s in scores], dtype=np.float64).reshape(len(scores), 3),
            direction=np.array([s.direction for s in scores], dtype=np.float64).reshape(len(scores), 3),
        )


CSV_COLUMNS = (
    "name0", "name1", "num_matches", "num_inliers", "num_inliers_all", "overlap", "parallax_deg", "weight",
    "accepted", "reason", "role", "rotvec_x", "rotvec_y", "rotvec_z", "direction_x", "direction_y", "direction_z",
)
ROTVEC_COLUMNS = ("rotvec_x", "rotvec_y", "rotvec_z")
DIRECTION_COLUMNS = ("direction_x", "direction_y", "direction_z")
#: columns a scores file may lack (written by an earlier version)
OPTIONAL_COLUMNS = ("num_inliers_all", *ROTVEC_COLUMNS, *DIRECTION_COLUMNS)


_ARRAY_FIELDS = ("num_matches", "num_inliers", "num_inliers_all", "overlap", "parallax_deg", "weight", "accepted",
                 "rotvec", "direction")


def concat_scores(first: PairScores, second: PairScores) -> PairScores:
    """The scores of `first`'s pairs followed by `second`'s."""
    return PairScores(
        name0=first.name0 + second.name0, name1=first.name1 + second.name1,
        **{name: np.concatenate([getattr(first, name), getattr(second, name)]) for name in _ARRAY_FIELDS},
        reason=first.reason + second.reason,
    )


def take_scores(scores: PairScores, rows: Sequence[int]) -> PairScores:
    """The scores of `scores`' pairs at `rows`, in that order."""
    pick = np.asarray(rows, dtype=np.int64).reshape(-1)
    return PairScores(name0=[scores.name0[k] for k in pick], name1=[scores.name1[k] for k in pick],
                      **{name: getattr(scores, name)[pick] for name in _ARRAY_FIELDS},
                      reason=[scores.reason[k] for k in pick])


def write_scores_csv(path: Path, scores: PairScores, roles: Sequence[str] | None = None) -> Path:
    """Write one row per pair (columns :data:`CSV_COLUMNS`) atomically; returns ``path``.

    ``roles`` gives each pair's role in the selection (e.g. "tree", "loop", "rejected");
    the column is empty without it. Floats are written with full precision.
    """
    if roles is not None and len(roles) != len(scores):
        raise ValueError(f"{len(roles)} roles for {len(scores)} pairs")
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="", encoding="utf-8") as f:
            writer = csv.writer(f)
            writer.writerow(CSV_COLUMNS)
            for k in range(len(scores)):
                writer.writerow([
                    scores.name0[k], scores.name1[k],
                    int(scores.num_matches[k]), int(scores.num_inliers[k]), int(scores.num_inliers_all[k]),
                    repr(float(scores.overlap[k])), repr(float(scores.parallax_deg[k])),
                    repr(float(scores.weight[k])), "true" if scores.accepted[k] else "false",
                    scores.reason[k], roles[k] if roles is not None else "",
                    *(repr(float(v)) for v in scores.rotvec[k]),
                    *(repr(float(v)) for v in scores.direction[k]),
                ])
    return path


def _column(rows: list[dict[str, str]], key: str, convert: Any, path: Path) -> list[Any]:
    out = []
    for k, row in enumerate(rows):
        try:
            out.append(convert(row[key]))
        except (TypeError, ValueError):
            raise ValueError(f"{path}, line {k + 2}: bad {key} {row[key]!r}") from None
    return out


def _parse_bool(text: str) -> bool:
    low = text.strip().lower()
    if low in ("true", "1"):
        return True
    if low in ("false", "0"):
        return False
    raise ValueError(text)


def read_scores_csv(path: Path) -> tuple[PairScores, list[str] | None]:
    """Read a file of :func:`write_scores_csv`; roles are None when that column is empty."""
    path = Path(path)
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        fields = reader.fieldnames or []
        missing = [c for c in CSV_COLUMNS if c not in fields and c not in OPTIONAL_COLUMNS]
        if missing:
            raise ValueError(f"{path} is not a scores file: columns {missing} are missing")
        rows = list(reader)

    def column(key: str, convert: Any, dtype: Any) -> np.ndarray:
        return np.array(_column(rows, key, convert, path), dtype=dtype).reshape(len(rows))

    scores = PairScores(
        name0=[r["name0"] for r in rows], name1=[r["name1"] for r in rows],
        num_matches=column("num_matches", int, np.int64),
        num_inliers=column("num_inliers", int, np.int64),
        num_inliers_all=column("num_inliers_all", int, np.int64) if "num_inliers_all" in fields else None,
        overlap=column("overlap", float, np.float64),
        parallax_deg=column("parallax_deg", float, np.float64),
        weight=column("weight", float, np.float64),
        accepted=column("accepted", _parse_bool, bool),
        reason=[r["reason"] for r in rows],
        rotvec=(np.stack([column(c, float, np.float64) for c in ROTVEC_COLUMNS], axis=1)
                if all(c in fields for c in ROTVEC_COLUMNS) else None),
        direction=(np.stack([column(c, float, np.float64) for c in DIRECTION_COLUMNS], axis=1)
                   if all(c in fields for c in DIRECTION_COLUMNS) else None),
    )
    roles = [r["role"] for r in rows]
    return scores, (roles if any(roles) else None)


def older_columns(path: Path) -> list[str]:
    """The columns of OPTIONAL_COLUMNS that a scores file lacks: it was written by an older release,
    before the selection used them (empty: a file of this release)."""
    with open(path, newline="", encoding="utf-8") as f:
        fields = next(csv.reader(f), [])
    return [c for c in OPTIONAL_COLUMNS if c not in fields]
