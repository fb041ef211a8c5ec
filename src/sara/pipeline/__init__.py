"""The pipeline: images -> features -> pairs -> matches -> sparse model (-> evaluation), resumable.

Files are the contract between stages; each stage reads what the one before wrote:

    features-<backend>.h5, database.db   extract (the database: images, cameras, keypoints)
    pairs.txt (+ the source's files:     pairs (SARA: scores.csv and global descriptors)
      scores.csv, global-<descr>.h5)
    database.db                          match (matches and verified two-view geometries)
    sparse/0, sparse/1, ...              map (0 is the largest model)
    metrics.json                         with a ground truth
    run.json, report.md                  configuration, versions, per-stage times and counts
    logs/                                COLMAP's own log

A pair source with rounds (SARA) adds pairs around mapping (`rounds.py`); `pairs.txt` and the
run record then say what was really matched.

Nothing lost, nothing silently wrong:

- every option and name is checked before any work (`preflight`), so a bad option never touches
  the output folder;
- a stage trusts its record only while its outputs still hold what it wrote (`sara.io.records`):
  derived files (features, scores) that are damaged are made again; files a person may have
  edited (`pairs.txt`, `sparse/`) are never overwritten on resume, and a damaged database stops
  the run, each with a message that names the file and the fix;
- new pairs, matches and models are built beside the old ones (`.sara/`) and swapped in only when
  complete; a run that produces nothing (no pairs, no verified pair, no model) raises NoResultError
  and keeps the previous `pairs.txt`, matches, `sparse/`, `run.json` and `report.md`;
- `run.json` and `report.md` are written when a run finishes (and `run.json` once when a folder's
  first run has its features, so that `sara map OUT` finds the images);
- files left by killed runs are removed when a run starts and ends (`sara.io.clean_temporaries`).
"""

from __future__ import annotations

from .pairs_stage import PAIRS_NAME, pair_context, pairs_key
from .pairs_stage import run as select_pairs
from .record import RunReport, render_report, versions
from .run import map_model, match_pairs, preflight, recover, run
from .single import load_run, map_only, match_only, share_features

__all__ = ["PAIRS_NAME", "RunReport", "load_run", "map_model", "map_only", "match_only", "match_pairs",
           "pair_context", "pairs_key", "preflight", "recover", "render_report", "run", "select_pairs",
           "share_features", "versions"]
