"""hloc interop: SARA pairs from hloc's own feature files, and a COLMAP model from hloc's matches.

hloc (cvg/Hierarchical-Localization) stores, and these functions read and write, its layouts:

- local features (`hloc/extract_features.py`): one HDF5 group per image name holding
  `keypoints` (N, 2) in pixels with the centre of the top-left pixel at (0, 0), `descriptors`
  (D, N), `scores` (N,) (`keypoint_scores` for DISK and ALIKED) and `image_size` (2,) = (width,
  height) of the original image; float16 with `as_half` (hloc's default);
- global descriptors (`hloc/extract_features.py` with a global model, read by
  `hloc/pairs_from_retrieval.py`): one group per image holding `global_descriptor` (D,);
- pairs (`hloc/utils/parsers.py` `parse_retrieval`): text, `name0 name1` per line, split at
  whitespace, so names must not contain spaces;
- matches (`hloc/match_features.py`, read by `hloc/utils/io.py` `get_matches`): one group per pair
  named `names_to_pair(name0, name1)` (each name with '/' replaced by '-', joined by '/'; older
  files join by '_'), holding `matches0` (N0,) int (-1: unmatched) and `matching_scores0` (N0,).

With hloc installed, the SARA pairs replace `pairs_from_exhaustive` or `pairs_from_retrieval`::

    pairs = sara.hloc.select_pairs(outputs / "feats-superpoint-n4096-r1024.h5", outputs / "pairs-sara.txt")
    matches = match_features.main(matcher_conf, pairs, features=feature_conf["output"], export_dir=outputs)
    model_dir = sara.hloc.reconstruct(images, features, matches, pairs, outputs / "sfm")

SARA's pre-matching scorer needs intrinsics; hloc's files hold only image sizes, so a database with
COLMAP's prior (focal = `extract.default_focal_length_factor` * the longer side, centred principal
point) is made for the selection, as COLMAP itself does for an image without EXIF focal length.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from pathlib import Path

import h5py
import numpy as np
from tqdm import tqdm

from . import colmap, mapping
from .colmap import model
from .config import PipelineConfig, make_config
from .io import atomic_path, fingerprint
from .io.h5 import Features, list_names, write_features
from .io.pairs import Pair, read_pairs, write_pairs
from .pairs import PairContext, get_source

logger = logging.getLogger(__name__)

LEGACY_GLOBAL_NAME = "global-sara.h5"  # hloc layout of a sara 0.1 global.h5
_SCORE_KEYS = ("scores", "keypoint_scores")


def read_hloc_features(h5: h5py.File, name: str) -> Features:
    """One image of an open hloc feature file, as float32 `Features` (descriptors (N, D)).

    Images without keypoint scores get equal scores (their order is kept).
    """
    if name not in h5 or "keypoints" not in h5[name]:
        raise ValueError(f"image {name!r} has no keypoints in {h5.filename}")
    grp = h5[name]
    kp = np.asarray(grp["keypoints"][()], dtype=np.float32).reshape(-1, 2)
    desc = np.asarray(grp["descriptors"][()], dtype=np.float32)
    if desc.ndim != 2 or len(kp) not in desc.shape:
        raise ValueError(f"{h5.filename}:{name}: descriptors of shape {desc.shape} for {len(kp)} keypoints")
    if desc.shape[1] == len(kp):  # hloc's (D, N)
        desc = desc.T
    key = next((k for k in _SCORE_KEYS if k in grp), None)
    scores = np.asarray(grp[key][()], np.float32) if key else np.linspace(1, 0, len(kp), dtype=np.float32)
    size = tuple(int(v) for v in grp["image_size"][()])
    return Features(kp, np.ascontiguousarray(desc), scores.reshape(-1), size)  # type: ignore[arg-type]


def copy_for_sara(features: Path, names: Sequence[str], dest: Path, *, top_k: int | None,
                  progress: bool = True) -> dict[str, tuple[int, int]]:
    """The `top_k` best-scored features of each image into a sara feature file; returns name -> (w, h)."""
    sizes = {}
    with h5py.File(features, "r") as src, atomic_path(dest) as tmp, h5py.File(tmp, "w") as out:
        for name in tqdm(names, desc="read hloc features", unit="img", disable=not progress):
            feats = read_hloc_features(src, name)
            if top_k is not None and len(feats.scores) > top_k:
                keep = np.sort(np.argsort(-feats.scores, kind="stable")[:top_k])
                feats = Features(feats.keypoints[keep], feats.descriptors[keep], feats.scores[keep], feats.image_size)
            write_features(out, name, feats)
            sizes[name] = feats.image_size
    return sizes


def select_pairs(features: Path, pairs_path: Path, *, names: Sequence[str] | None = None,
                 conf: PipelineConfig | None = None, work_dir: Path | None = None,
                 image_dir: Path | None = None, progress: bool = True) -> Path:
    """SARA pairs of the images of an hloc feature file, written as an hloc pairs file; returns its path.

    features: hloc local features (SuperPoint, DISK, ALIKED, SIFT, ...: any descriptor size).
    names: the images to pair (default: every image in `features`).
    conf: sara's configuration (default preset `sift-offline`); its retrieval, score and graph
        sections apply, `extract.camera_model` and `extract.default_focal_length_factor` give the prior.
    work_dir: where SARA writes `scores.csv`, its global descriptors (in hloc's layout, see
        `global_descriptors`) and a temporary database (default: `<pairs stem>-sara/` beside the pairs).
    """
    features, pairs_path = Path(features), Path(pairs_path)
    if not features.is_file():
        raise FileNotFoundError(f"hloc feature file not found: {features}")
    names = sorted(names) if names is not None else list_names(features)
    _check_names(names, features)
    conf = conf or make_config("sift-offline")
    work = Path(work_dir) if work_dir is not None else pairs_path.parent / f"{pairs_path.stem}-sara"
    (work / ".sara").mkdir(parents=True, exist_ok=True)  # the records folder a pipeline run would have made
    local = work / "features.h5"
    sizes = copy_for_sara(features, names, local, top_k=_top_k(conf), progress=progress)
    db_path = work / "cameras.db"
    model.database_from_sizes(db_path, sizes, camera_model=conf.extract.camera_model,
                              focal_length_factor=conf.extract.default_focal_length_factor)
    ctx = PairContext(names=list(names), images_root=Path(image_dir) if image_dir else features.parent,
                      features_path=local, db_path=db_path, out_dir=work, conf=conf, progress=progress)
    result = get_source("sara")(ctx)
    write_pairs(pairs_path, result.pairs)
    exhaustive = len(names) * (len(names) - 1) // 2
    logger.info("sara: %d pairs of %d images (%.1f%% of exhaustive) -> %s", len(result.pairs), len(names),
                100 * len(result.pairs) / max(exhaustive, 1), pairs_path)
    global_path = global_descriptors(work)
    if global_path is not None:
        logger.info("sara: global descriptors in hloc's layout -> %s", global_path)
    return pairs_path


def _check_names(names: Sequence[str], features: Path) -> None:
    if len(names) < 2:
        raise ValueError(f"{features} holds {len(names)} image(s): pairs need at least two")
    spaced = [n for n in names if any(c.isspace() for c in n)]
    if spaced:
        raise ValueError(f"image name {spaced[0]!r} contains whitespace: hloc's pairs files cannot hold it")


def _top_k(conf: PipelineConfig) -> int | None:
    wanted = [conf.score.num_keypoints, conf.retrieval.features_per_image]
    return None if min(wanted) <= 0 else max(wanted)


# ---------------------------------------------------------------------------------------------
# Global descriptors
# ---------------------------------------------------------------------------------------------


def global_descriptors(work_dir: Path) -> Path | None:
    """SARA's global descriptors in `work_dir` in hloc's layout (`global-<descriptor>.h5`), if any.

    A `global.h5` of sara 0.1 (rows layout) is converted to `global-sara.h5`.
    """
    work_dir = Path(work_dir)
    found = sorted(work_dir.glob("global-*.h5"))
    legacy = work_dir / "global.h5"
    if legacy.exists() and (not found or legacy.stat().st_mtime_ns > found[0].stat().st_mtime_ns):
        return write_hloc_global(work_dir / LEGACY_GLOBAL_NAME, *read_any_global(legacy))
    return found[0] if found else None


def read_any_global(path: Path) -> tuple[list[str], np.ndarray]:
    """Names and (N, D) float32 global descriptors from sara's `global.h5` or an hloc global file."""
    with h5py.File(path, "r") as h5:
        if "names" in h5 and "descriptors" in h5:  # sara's rows layout
            names = [n.decode() if isinstance(n, bytes) else str(n) for n in h5["names"][()]]
            return names, np.asarray(h5["descriptors"][()], dtype=np.float32)
    names: list[str] = []

    def visit(key: str, obj: object) -> None:
        if isinstance(obj, h5py.Group) and "global_descriptor" in obj:
            names.append(key)

    with h5py.File(path, "r") as h5:
        h5.visititems(visit)
        names.sort()
        desc = [np.asarray(h5[n]["global_descriptor"][()], dtype=np.float32).reshape(-1) for n in names]
    return names, np.stack(desc) if desc else np.zeros((0, 0), np.float32)


def write_hloc_global(path: Path, names: Sequence[str], desc: np.ndarray) -> Path:
    """Global descriptors in hloc's layout: one group per image with `global_descriptor` (D,) float32."""
    with atomic_path(Path(path)) as tmp, h5py.File(tmp, "w") as h5:
        for name, row in zip(names, np.asarray(desc, dtype=np.float32)):
            h5.create_group(name).create_dataset("global_descriptor", data=row)
    return Path(path)


# ---------------------------------------------------------------------------------------------
# hloc matches -> COLMAP database -> model
# ---------------------------------------------------------------------------------------------


def names_to_pair(name0: str, name1: str, separator: str = "/") -> str:
    """hloc's key of a pair in a matches file."""
    return separator.join((name0.replace("/", "-"), name1.replace("/", "-")))


def read_hloc_matches(h5: h5py.File, name0: str, name1: str, *, min_score: float | None = None) -> np.ndarray:
    """(K, 2) int64 keypoint indices (into image 0, image 1) of a pair in an open hloc matches file."""
    for separator in ("/", "_"):
        for a, b, flip in ((name0, name1, False), (name1, name0, True)):
            key = names_to_pair(a, b, separator)
            if key in h5:
                grp = h5[key]
                matches0 = np.asarray(grp["matches0"][()], dtype=np.int64)
                idx = np.flatnonzero(matches0 > -1)
                if min_score is not None and "matching_scores0" in grp:
                    idx = idx[np.asarray(grp["matching_scores0"][()], dtype=np.float32)[idx] > min_score]
                pairs = np.stack([idx, matches0[idx]], axis=1)
                return pairs[:, ::-1].copy() if flip else pairs
    raise ValueError(f"pair ({name0}, {name1}) is not in {h5.filename}: matched with another pairs file?")


def _pair_matches(matches: Path, pairs: list[Pair], min_score: float | None,
                  progress: bool) -> Iterator[tuple[Pair, np.ndarray]]:
    with h5py.File(matches, "r") as h5:
        for name0, name1 in tqdm(pairs, desc="import hloc matches", unit="pair", disable=not progress):
            yield (name0, name1), read_hloc_matches(h5, name0, name1, min_score=min_score)


def reconstruct(image_dir: Path, features: Path, matches: Path, pairs_path: Path, out_dir: Path, *,
                conf: PipelineConfig | None = None, camera_mode: str = "auto",
                min_match_score: float | None = None, progress: bool = True) -> Path:
    """COLMAP model from hloc features and matches, with sara's verification and mapping settings.

    Imports the images (EXIF focal or COLMAP's prior), the keypoints and the matches of the pairs
    into `out_dir/database.db`, runs COLMAP's geometric verification and sara's mapping stage into
    `out_dir/sparse/0`, `1`, ... (largest first). Returns `out_dir/sparse/0`; RuntimeError when no
    model could be built.
    """
    image_dir, features, matches, out_dir = Path(image_dir), Path(features), Path(matches), Path(out_dir)
    for path in (image_dir, features, matches, Path(pairs_path)):
        if not path.exists():
            raise FileNotFoundError(f"not found: {path}")
    conf = conf or make_config("sift-offline")
    names = list_names(features)
    pairs = read_pairs(Path(pairs_path), known_names=names)
    out_dir.mkdir(parents=True, exist_ok=True)
    db_path = out_dir / "database.db"
    db_path.unlink(missing_ok=True)
    colmap.create_database(db_path)
    colmap.import_images(db_path, image_dir, names, camera_mode=camera_mode, camera_model=conf.extract.camera_model,
                         default_focal_length_factor=conf.extract.default_focal_length_factor)
    with h5py.File(features, "r") as h5:
        keypoints = {n: colmap.hloc_to_colmap_keypoints(read_hloc_features(h5, n).keypoints) for n in names}
    colmap.write_keypoints(db_path, keypoints)
    colmap.write_matches(db_path, dict(_pair_matches(matches, pairs, min_match_score, progress)))
    # COLMAP reads the pairs as sara read them (a byte-order mark or a score column would mislead it)
    clean = write_pairs(out_dir / ".pairs-verified.txt", pairs)
    try:
        colmap.verify_pairs(db_path, clean, min_num_inliers=conf.match.min_num_inliers)
    finally:
        clean.unlink(missing_ok=True)
    num_verified = len(model.database_pairs(db_path)[1])
    logger.info("hloc import: %d images, %d pairs, %d verified", len(names), len(pairs), num_verified)
    key = fingerprint({"files": [_stat(p) for p in (features, matches, Path(pairs_path))], "mode": camera_mode,
                       "min_score": min_match_score})
    mapping.run(conf.map, db_path, image_dir, out_dir, seed=conf.seed, upstream_key=key, progress=progress)
    models = model.find_models(out_dir / "sparse")
    if not models:
        raise RuntimeError(f"no model could be built from {len(pairs)} pairs ({num_verified} verified)")
    return models[0]


def _stat(path: Path) -> list:
    stat = path.stat()
    return [str(path.resolve()), stat.st_size, stat.st_mtime_ns]
