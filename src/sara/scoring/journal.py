"""The scores of candidate pairs kept on disk, so that no selection on the same features scores a
pair twice.

Scoring is most of the selection at scale (83% of its CPU at 10,000 images, where the selection
took 9-18 minutes on two cores: lab/notes/SCALE.md), and the pairs stage writes nothing until it
ends. The journal holds the scores of each shard as it comes back, under the settings and seed that
made them; a pair's score depends only on its two views, those settings and the seed, so a score
read back is the score the pair would get again. A selection stopped part-way therefore scores only
the pairs it had not finished, and one run again with other graph, budget or candidate settings only
the candidates it had never scored. The journal belongs to one set of views (`key`: the extract
stage's key, which covers the features and cameras): opened for other views it starts empty.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ..config import ScoreConfig
from ..io import fingerprint
from .scorer import PairScore

logger = logging.getLogger(__name__)

KEY_FILE = "key"


@dataclass(frozen=True)
class ScoreJournal:
    """Scored pairs in `folder`, for the inputs `key` names."""

    folder: Path
    key: str

    def open(self) -> ScoreJournal:
        """Keep what the folder holds for this key; a journal of other inputs is cleared."""
        try:
            same = (self.folder / KEY_FILE).read_text(encoding="utf-8") == self.key
        except OSError:
            same = False
        if not same:
            self.remove()
            self.folder.mkdir(parents=True)
            (self.folder / KEY_FILE).write_text(self.key, encoding="utf-8")
        return self

    def scored(self, conf: ScoreConfig, seed: int) -> dict[tuple[str, str], PairScore]:
        """The pairs scored so far under `conf` and `seed`; a file cut short by the stop is skipped."""
        found: dict[tuple[str, str], PairScore] = {}
        for path in sorted(self.folder.glob(f"{_settings(conf, seed)}-*.json")):
            try:
                rows = json.loads(path.read_text(encoding="utf-8"))
                found.update({(a, b): score for a, b, *fields in rows if (score := _score(fields)) is not None})
            except (OSError, ValueError, TypeError):
                logger.debug("score journal: %s does not read, its pairs are scored again", path)
        return found

    def add(self, conf: ScoreConfig, seed: int, pairs: Sequence[tuple[str, str]], scores: Sequence[PairScore]) -> None:
        """Keep the scores of `pairs` (one shard), written whole or not at all."""
        rows = [[a, b, int(s.num_matches), int(s.num_inliers), float(s.overlap), float(s.parallax_deg),
                 float(s.weight), bool(s.accepted), str(s.reason), int(s.num_inliers_all),
                 [float(x) for x in s.rotvec], [float(x) for x in s.direction]]
                for (a, b), s in zip(pairs, scores, strict=True)]
        path = self.folder / f"{_settings(conf, seed)}-{uuid.uuid4().hex}.json"
        partial = path.with_suffix(".part")
        partial.write_text(json.dumps(rows), encoding="utf-8")
        os.replace(partial, path)

    def remove(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)


def _score(fields: list) -> PairScore | None:
    """A journal row's score (after the names): the plain fields, then the rotation and the
    direction as lists. None for a row of an older release, written before the direction was kept:
    the selection reads it (the spanning tree's rule for views moving straight ahead), so the pair
    is scored again."""
    vectors = [tuple(f) for f in fields if isinstance(f, list)]
    if len(vectors) < 2:
        return None
    plain = [f for f in fields if not isinstance(f, list)]
    return PairScore(*plain, rotvec=vectors[0], direction=vectors[1])


def _settings(conf: ScoreConfig, seed: int) -> str:
    return fingerprint({"score": conf.__dict__, "seed": seed})
