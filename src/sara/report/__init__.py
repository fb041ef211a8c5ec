"""What a run folder says about its pairs and its model, gathered for `report.html`.

`load_run(out_dir)` reads whatever the run left (every file is optional except that at least one
of `run.json`, `pairs.txt` or `database.db` must be there) into `RunData`:

- `run.json`: configuration (thresholds), per-stage times and counts, the image folder;
- `database.db`: every image of the run and the verified pairs with their inlier counts;
- `pairs.txt`: the pairs that were matched; `scores.csv` (SARA only): every candidate pair with
  overlap O, parallax P (deg), weight w, inliers, accepted, reason and role;
- `sparse/0` (the largest model) and the sizes of all models; `metrics.json` (with `--gt`).

The page itself is written by `sara.report.html.write_report(out_dir)`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .. import colmap
from ..colmap import model
from ..export import recorded_images_root
from ..io import read_json, records
from ..io.pairs import Pair, read_pairs
from ..io.scores import read_scores_csv
from ..pipeline.rounds import ROUNDS_STAGE

SELECTED_ROLES = ("tree", "loop", "anchor", "weak", "rescue", "chain")
#: SARA's pairs matched after the first round: for weakly matched views before mapping, the
#: pose-guided round, repairs of views left out of the model, and the fill round after a repair
#: that left them out
ADDED_ROLES = ("support", "pose-guided", "repair", "fill")
ALL_ROLES = SELECTED_ROLES + ADDED_ROLES + ("selected", "unselected", "rejected")


@dataclass(frozen=True)
class Scores:
    """The columns of `scores.csv`, one row per candidate pair (arrays of equal length)."""

    pairs: list[Pair]
    num_inliers: np.ndarray  # (E,) int64, among the b best matches
    overlap: np.ndarray  # (E,) float64, O
    parallax_deg: np.ndarray  # (E,) float64, P
    weight: np.ndarray  # (E,) float64, w
    accepted: np.ndarray  # (E,) bool
    reason: list[str]  # "" when accepted
    role: list[str]  # tree | loop | anchor | weak | rescue | unselected | rejected
    num_inliers_all: np.ndarray | None = None  # (E,) int64, among all mutual matches
    num_matches: np.ndarray | None = None  # (E,) int64, b: the best mutual matches the pre-match kept


@dataclass
class RunData:
    out_dir: Path
    run: dict[str, Any] = field(default_factory=dict)
    names: list[str] = field(default_factory=list)  # every image of the run, sorted
    pairs: list[Pair] = field(default_factory=list)  # matched pairs (pairs.txt)
    verified: dict[Pair, int] = field(default_factory=dict)  # verified pair -> inlier matches
    scores: Scores | None = None
    model: model.ModelData | None = None  # sparse/0
    model_sizes: list[int] = field(default_factory=list)  # registered images per model
    metrics: dict[str, Any] | None = None
    images_root: Path | None = None
    added: dict[Pair, str] = field(default_factory=dict)  # SARA: pair matched after the first round -> role
    agreement: colmap.Agreement | None = None  # model 0 against the verified pairs between its views

    @property
    def config(self) -> dict[str, Any]:
        return self.run.get("config", {})

    @property
    def stages(self) -> dict[str, Any]:
        return self.run.get("stages", {})

    @property
    def method(self) -> str:
        return str(self.stages.get("pairs", {}).get("method") or self.config.get("pairs", {}).get("method", "?"))

    @property
    def num_exhaustive(self) -> int:
        n = len(self.names)
        return n * (n - 1) // 2

    def edge_roles(self) -> dict[Pair, str]:
        """Role of every pair to draw: the scored candidates' roles; matched pairs outside them are,
        in a SARA run, `support` (for weakly matched views, before mapping), `pose-guided` or
        `repair` (views left out of the model), and `selected` in any other run."""
        roles: dict[Pair, str] = {}
        if self.scores is not None:
            roles.update(zip(self.scores.pairs, self.scores.role))
        for pair in self.pairs:
            if roles.get(pair) not in SELECTED_ROLES:
                roles[pair] = self.added.get(pair, "repair") if self.scores is not None else "selected"
        return roles


def read_scores(path: Path) -> Scores:
    """`scores.csv` (read by `sara.io.scores`) with each pair in canonical order and a role for every row."""
    table, roles = read_scores_csv(path)
    roles = roles or [""] * len(table)
    return Scores(
        pairs=[_canonical(a, b) for a, b in zip(table.name0, table.name1)],
        num_inliers=table.num_inliers, overlap=table.overlap, parallax_deg=table.parallax_deg,
        weight=table.weight, accepted=table.accepted, reason=[r.strip() for r in table.reason],
        role=[r.strip() or ("unselected" if a else "rejected") for r, a in zip(roles, table.accepted)],
        num_inliers_all=table.num_inliers_all, num_matches=table.num_matches,
    )


def _canonical(a: str, b: str) -> Pair:
    return (a, b) if a < b else (b, a)


def load_run(out_dir: Path) -> RunData:
    """Everything a run folder holds for its report (see the module docstring)."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise FileNotFoundError(f"output folder not found: {out_dir}")
    found = [name for name in ("run.json", "pairs.txt", "database.db") if (out_dir / name).exists()]
    if not found:
        raise FileNotFoundError(f"{out_dir} holds no sara run (no run.json, pairs.txt or database.db)")
    data = RunData(out_dir)
    if (out_dir / "run.json").exists():
        data.run = read_json(out_dir / "run.json")
    if (out_dir / "database.db").exists():
        data.names, data.verified = model.database_pairs(out_dir / "database.db")
    if (out_dir / "pairs.txt").exists():
        data.pairs = read_pairs(out_dir / "pairs.txt", known_names=data.names or None)
    if (out_dir / "scores.csv").exists():
        data.scores = read_scores(out_dir / "scores.csv")
    models = model.find_models(out_dir / "sparse")
    if models:
        data.model = model.read_model(models[0])
        data.model_sizes = [len(data.model.names)] + [len(colmap.registered_images(m)) for m in models[1:]]
        if (out_dir / "database.db").exists():
            data.agreement = colmap.model_agreement(models[0], out_dir / "database.db")
    _load_metrics(data)
    data.added = _added_roles(out_dir)
    data.names = sorted(set(data.names) | _names_in(data))
    data.images_root = _images_root(data)
    return data


#: where runs of sara 0.1 listed the pairs added after the first round (before the rounds' ledger)
_LEGACY_RECORDS = {"support": "support", "pose-guided": "pose_guided"}


def _added_roles(out_dir: Path) -> dict[Pair, str]:
    """Pairs the rounds' ledger lists as added after the first selection, with their role (for a
    run of sara 0.1, the records its rounds kept; pairs they do not list are repairs)."""
    record = records.read_record(out_dir, ROUNDS_STAGE) or {}
    if record.get("done") is True and "added" in record.get("info", {}):
        added = record["info"]["added"]
    else:
        added = {role: (records.done_info(out_dir, stage) or {}).get("pairs", [])
                 for role, stage in _LEGACY_RECORDS.items()}
    out: dict[Pair, str] = {}
    for role, pairs in added.items():
        for pair in pairs:
            if isinstance(pair, (list, tuple)) and len(pair) == 2:
                out[_canonical(str(pair[0]), str(pair[1]))] = str(role)
    return out


def _names_in(data: RunData) -> set[str]:
    names = {n for pair in data.pairs for n in pair}
    if data.scores is not None:
        names |= {n for pair in data.scores.pairs for n in pair}
    if data.model is not None:
        names |= set(data.model.names)
    return names


def _load_metrics(data: RunData) -> None:
    path = data.out_dir / "metrics.json"
    if path.exists():
        data.metrics = read_json(path)
    elif data.run.get("metrics"):
        data.metrics = data.run["metrics"]


def _images_root(data: RunData) -> Path | None:
    try:
        root = recorded_images_root(data.out_dir)
    except (FileNotFoundError, KeyError):
        return None
    return root if root.is_dir() else None
