"""Compare estimated COLMAP models with a ground-truth model (the metrics are in `metrics.py`).

An estimate is a list of model folders, one per connected component (``sparse/0``, ``sparse/1``,
...). Metrics that need one model use the largest component (most registered images).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .. import colmap
from ..io import write_json_atomic
from ..tables import format_number, text_table
from .ground_truth import load_ground_truth, match_names
from .metrics import (
    DEFAULT_THRESHOLDS_DEG,
    absolute_metrics,
    failure_metrics,
    median_or_none,
    relative_metrics,
)

logger = logging.getLogger(__name__)


def _structure_metrics(model: colmap.ModelSummary) -> dict[str, Any]:
    """3D point count, mean track length and reprojection errors of one reconstruction."""
    num_points, num_observations, errors = model.num_points3d, model.num_observations, model.reprojection_errors_px
    finite = np.isfinite(errors)
    if not np.all(finite):
        logger.warning("%d of %d observations lie behind their camera; left out of the "
                       "reprojection errors", int(np.sum(~finite)), errors.size)
    errors = errors[finite]
    return {
        "num_points3d": int(num_points),
        "mean_track_length": (
            float(num_observations / num_points) if num_points else None
        ),
        "reproj_error_mean_px": float(np.mean(errors)) if errors.size else None,
        "reproj_error_median_px": median_or_none(errors),
    }


def _read_components(model_dirs: Sequence[Path]) -> list[colmap.ModelSummary]:
    """Read every model folder that exists; missing or empty ones are skipped with a warning."""
    recs = []
    for model_dir in model_dirs:
        try:
            recs.append(colmap.read_summary(Path(model_dir)))
        except FileNotFoundError as error:
            logger.warning("Skipping estimated model: %s", error)
    return recs


def gt_image_names(gt_dir: Path, names: Sequence[str]) -> set[str]:
    """Which of `names` the ground truth at `gt_dir` poses (a COLMAP model or a transforms.json,
    its names matched as `ground_truth.match_names` does; FileNotFoundError when it holds none)."""
    return set(match_names(load_ground_truth(Path(gt_dir)), names)) & set(names)


def evaluate_models(model_dirs: list[Path] | Path, gt_dir: Path, *,
                    thresholds_deg: Sequence[float] = DEFAULT_THRESHOLDS_DEG,
                    require_model: bool = False) -> dict[str, Any]:
    """Evaluate the components of an estimated reconstruction against the ground truth.

    Args:
        model_dirs: estimated COLMAP model folders (one per component), or one folder. Missing
            folders are skipped; with none left the estimate is scored as a complete failure.
        gt_dir: the ground truth: a COLMAP model folder (poses of all images) or a transforms.json
            (`ground_truth`).
        thresholds_deg: thresholds of the pose AUC, in degrees.

    Returns:
        A JSON-serialisable dict. Pose metrics use the largest component (most registered
        images): ``num_registered`` / ``registered_pct`` (gt images registered in it),
        ``num_registered_any`` (in any component), ``num_components``, ``num_images_est``
        (registered images of the largest component, gt or not), relative pose error medians
        in degrees over co-registered pairs, ``auc`` {threshold: AUC of max(rot, trans) error
        over all gt pairs}, ``abs_rotation_error_median_deg`` and ``position_error_median_pct``
        (after a similarity alignment of camera centres; None with fewer than 3 images) and
        the structure statistics ``num_points3d``, ``mean_track_length``,
        ``reproj_error_mean_px``, ``reproj_error_median_px``. Missing values are None.

    Raises:
        FileNotFoundError: the ground-truth folder does not exist or holds no model; with
            `require_model`, no estimated model with registered images could be read (else that
            is scored as a failure).
        ValueError: the estimate and the ground truth share no image name (another scene).
    """
    if isinstance(model_dirs, (str, os.PathLike)):
        model_dirs = [Path(model_dirs)]
    gt = load_ground_truth(Path(gt_dir))
    metrics = failure_metrics(len(gt), thresholds_deg)
    recs = [rec for rec in _read_components(model_dirs) if rec.num_registered > 0]
    if not recs:
        if require_model:
            where = ", ".join(str(d) for d in model_dirs) or "the given folder"
            raise FileNotFoundError(f"no readable COLMAP model with registered images in {where}")
        logger.warning("No estimated model with registered images: scored as a failure")
        return metrics
    names = set().union(*(rec.poses.keys() for rec in recs))
    gt = match_names(gt, names)
    if not names & gt.keys():
        raise ValueError(f"the model and the ground truth {gt_dir} share no image name (model: e.g. "
                         f"{sorted(names)[0]!r}; ground truth: e.g. {sorted(gt)[0]!r}): is it the ground truth "
                         "of another scene?")
    largest = max(recs, key=lambda rec: (rec.num_registered, rec.num_points3d))
    est = largest.poses
    registered_any = names & gt.keys()
    num_registered = len(est.keys() & gt.keys())
    metrics.update({
        "num_registered": num_registered,
        "registered_pct": 100.0 * num_registered / len(gt) if gt else 0.0,
        "num_registered_any": len(registered_any),
        "num_components": len(recs),
        "num_images_est": len(est),
    })
    metrics.update(relative_metrics(est, gt, thresholds_deg))
    metrics.update(absolute_metrics(est, gt))
    metrics.update(_structure_metrics(largest))
    return metrics


# ----------------------------------------------------------------------------------------------
# Presentation and runner


def format_table(metrics: dict) -> str:
    """Render metrics as a two-column text table; nested dicts become ``auc@<key>`` rows."""
    rows = []
    for key, value in metrics.items():
        if isinstance(value, dict):
            rows.extend((f"{key}@{sub}", format_number(v)) for sub, v in value.items())
        else:
            rows.append((key, format_number(value)))
    return text_table(("metric", "value"), rows)


def find_model_dirs(model_root: Path) -> list[Path]:
    """Component folders under ``model_root``.

    ``model_root`` is either one model folder (holding cameras.bin or cameras.txt) or a folder
    of components (``sparse/0``, ``sparse/1``, ...). Returns [] when it does not exist.
    """
    model_root = Path(model_root)
    if colmap.has_model(model_root):
        return [model_root]
    if not model_root.is_dir():
        return []
    subdirs = [p for p in model_root.iterdir() if p.is_dir() and colmap.has_model(p)]
    numbered = sorted((p for p in subdirs if p.name.isdigit()), key=lambda p: int(p.name))
    return numbered + sorted(p for p in subdirs if not p.name.isdigit())


def evaluate(model_root: Path, gt_dir: Path, out_path: Path | None = None, *,
             require_model: bool = False) -> dict:
    """Evaluate every component under ``model_root`` against ``gt_dir``.

    Writes the metrics as JSON to ``out_path`` (atomically) when given, and returns them.
    A missing ``model_root`` evaluates as a failed reconstruction, or with ``require_model``
    (`sara evaluate`) raises FileNotFoundError.
    """
    model_dirs = find_model_dirs(Path(model_root))
    if require_model and not model_dirs:
        state = "does not exist" if not Path(model_root).exists() else "holds no COLMAP model"
        raise FileNotFoundError(f"{model_root} {state}: give a model folder (cameras, images, points3D), its "
                                "sparse/ folder or a sara output folder")
    logger.debug(
        "Evaluating %d component(s) under %s against %s", len(model_dirs), model_root, gt_dir
    )
    metrics = evaluate_models(model_dirs, Path(gt_dir), require_model=require_model)
    if out_path is not None:
        write_json_atomic(Path(out_path), metrics)
        logger.debug("Wrote metrics to %s", out_path)
    logger.debug("Evaluation of %s:\n%s", model_root, format_table(metrics))
    return metrics
