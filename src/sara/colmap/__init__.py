"""Every call into pycolmap goes through this module, so an API change is mended in one place.

Pixel convention: COLMAP's, where the centre of the top-left pixel is (0.5, 0.5). hloc's HDF5
files use (0, 0) for that centre; `colmap_to_hloc_keypoints` converts.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import PIL.Image  # noqa: F401 - before pycolmap: its bundled zlib otherwise breaks Pillow's PNG writer (heap corruption)
import pycolmap

from ..io import DamagedOutputError, LOW_SPACE_BYTES, disk_full_error, fingerprint, free_bytes

logger = logging.getLogger(__name__)


def _sigterm_without_stack_dump() -> None:
    """pycolmap installs glog's failure handler, which prints a native stack dump on SIGTERM (a
    request to stop, not a crash: schedulers, `timeout` and `docker stop` send it, often to every
    process of the group). Give SIGTERM its default action back, unless Python code set a handler;
    crashes (SIGSEGV, SIGABRT) keep their dump. The `sara` command then installs its own handler."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGTERM) in (
            signal.SIG_DFL, None):
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


_sigterm_without_stack_dump()


class ColmapError(RuntimeError):
    """COLMAP failed for a reason that is not a full disk or a damaged database (see its log)."""


@contextlib.contextmanager
def native_errors(what: str, folder: Path) -> Iterator[None]:
    """Turn pycolmap's RuntimeError into an error that says what happened: OSError(ENOSPC) when the
    disk of `folder` is (nearly) full, else ColmapError naming `what` and COLMAP's log."""
    try:
        yield
    except RuntimeError as exc:
        if isinstance(exc, ColmapError):
            raise
        if free_bytes(folder) < LOW_SPACE_BYTES:
            raise disk_full_error(folder) from None
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ColmapError(f"COLMAP could not {what} ({detail}); its log is in {Path(folder) / 'logs'}") from None


# ---------------------------------------------------------------------------------------------
# Cheap checks: can COLMAP's reader decode an image, what does a database hold
# ---------------------------------------------------------------------------------------------


def image_read_problem(path: Path) -> str | None:
    """Why COLMAP's image reader (the one its SIFT extraction uses) cannot decode a file, or None."""
    try:
        bitmap = pycolmap.Bitmap.read(str(path), as_rgb=False)
    except (RuntimeError, ValueError, OSError) as exc:
        return f"COLMAP's image reader fails on it ({exc})"
    if bitmap is None or bitmap.width <= 0 or bitmap.height <= 0:
        return "COLMAP's image reader cannot decode it (a format COLMAP does not read, whatever its extension)"
    return None


_DB_TABLES = ("images", "keypoints", "descriptors", "matches", "two_view_geometries")


def _sqlite_header_problem(path: Path) -> str | None:
    """A database file shorter than its header says: truncated (None when it looks whole)."""
    import struct

    with open(path, "rb") as f:
        header = f.read(100)
    if len(header) < 100 or not header.startswith(b"SQLite format 3\x00"):
        return "not an SQLite database" if header else "empty file"
    page_size = struct.unpack(">H", header[16:18])[0]
    page_size = 65536 if page_size == 1 else page_size
    num_pages = struct.unpack(">I", header[28:32])[0]
    if header[92:96] == header[24:28] and path.stat().st_size < page_size * num_pages:
        return f"truncated: {path.stat().st_size} of {page_size * num_pages} bytes"
    return None


def _query(db_path: Path, *queries: tuple[str, tuple]) -> list[list[tuple]]:
    """Run read-only SQL on a database with SQLite alone (pycolmap's open writes to the file even
    when only reading, which would change its bytes). Opened read-write when possible, so that a
    write-ahead log is merged and removed on close; read-only in a read-only folder."""
    import sqlite3

    for mode in ("rw", "ro"):
        try:
            con = sqlite3.connect(f"file:{db_path}?mode={mode}", uri=True)
            try:
                return [con.execute(sql, args).fetchall() for sql, args in queries]
            finally:
                con.close()
        except sqlite3.OperationalError as exc:
            if mode == "ro" or not any(w in str(exc) for w in ("readonly", "read-only", "unable to open")):
                raise
    raise AssertionError("unreachable")


def database_summary(db_path: Path) -> dict[str, Any] | None:
    """Counts and digests of a COLMAP database, read with SQLite alone (cheap; None when absent).

    num_images, num_images_with_keypoints, keypoints_digest (names and keypoint counts),
    num_matched_pairs, num_verified_pairs (two-view geometries with inliers), matches_digest
    (every pair's match and inlier counts and geometry type). Raises DamagedOutputError when the
    file is truncated or SQLite finds it malformed.
    """
    import sqlite3

    db_path = Path(db_path)
    if not db_path.is_file():
        return None
    problem = _sqlite_header_problem(db_path)
    if problem is not None:
        raise DamagedOutputError(f"{db_path} is damaged ({problem})")
    try:
        (tables,) = _query(db_path, ("SELECT name FROM sqlite_master WHERE type='table'", ()))
        missing = [t for t in _DB_TABLES if t not in {r[0] for r in tables}]
        if missing:
            raise DamagedOutputError(f"{db_path} is not a COLMAP database (no table {missing[0]})")
        images, keypoints, matches, geometries = _query(
            db_path, ("SELECT image_id, name FROM images ORDER BY image_id", ()),
            ("SELECT image_id, rows FROM keypoints ORDER BY image_id", ()),
            ("SELECT pair_id, rows FROM matches ORDER BY pair_id", ()),
            ("SELECT pair_id, rows, config FROM two_view_geometries ORDER BY pair_id", ()))
    except sqlite3.DatabaseError as exc:
        raise DamagedOutputError(f"{db_path} is damaged ({exc})") from None
    names = dict(images)
    return {
        "num_images": len(images),
        "num_images_with_keypoints": sum(1 for _, rows in keypoints if rows > 0),
        "keypoints_digest": fingerprint([(names.get(i, str(i)), rows) for i, rows in keypoints]),
        "num_matched_pairs": sum(1 for _, rows in matches if rows > 0),
        "num_verified_pairs": sum(1 for _, rows, _ in geometries if rows > 0),
        "matches_digest": fingerprint([matches, geometries]),
    }


def verified_graph(db_path: Path, min_num_inliers: int) -> tuple[int, int, list[int], int]:
    """(pairs with at least `min_num_inliers` verified matches, images they touch, the sizes of the
    connected groups of images they form (largest first), the most inlier matches of one pair):
    why a mapper may find no model."""
    (rows,) = _query(db_path, ("SELECT pair_id, rows FROM two_view_geometries WHERE rows >= ?", (int(min_num_inliers),)))
    parent: dict[int, int] = {}

    def find(i: int) -> int:
        while parent.setdefault(i, i) != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for pair_id, _ in rows:
        i, j = pycolmap.pair_id_to_image_pair(int(pair_id))
        parent[find(int(i))] = find(int(j))
    groups: dict[int, int] = {}
    for i in list(parent):
        groups[find(i)] = groups.get(find(i), 0) + 1
    return len(rows), len(parent), sorted(groups.values(), reverse=True), max((int(r) for _, r in rows), default=0)


def verified_inliers(db_path: Path, min_num_inliers: int) -> dict[tuple[str, str], int]:
    """Verified inlier matches of each pair with at least `min_num_inliers`, keyed by the two image
    names in sorted order (read with SQLite: the file is not touched)."""
    return _counts_by_pair(db_path, "SELECT pair_id, rows FROM two_view_geometries WHERE rows >= ?",
                           (int(min_num_inliers),))


def match_counts(db_path: Path) -> dict[tuple[str, str], int]:
    """Matches (before geometric verification) of each matched pair, keyed by the two image names
    in sorted order (read with SQLite)."""
    return _counts_by_pair(db_path, "SELECT pair_id, rows FROM matches", ())


def _counts_by_pair(db_path: Path, sql: str, args: tuple) -> dict[tuple[str, str], int]:
    """(pair_id, count) rows of `sql` keyed by the pair's two image names in sorted order."""
    (rows, images) = _query(db_path, (sql, args), ("SELECT image_id, name FROM images", ()))
    name = {int(i): n for i, n in images}
    out: dict[tuple[str, str], int] = {}
    for pair_id, count in rows:
        i, j = (int(k) for k in pycolmap.pair_id_to_image_pair(int(pair_id)))
        if i in name and j in name:
            a, b = sorted((name[i], name[j]))
            out[(a, b)] = int(count or 0)
    return out


def mapper_init_requirements() -> tuple[int, float]:
    """(inlier matches, triangulation angle in degrees) that COLMAP's incremental mapper needs
    between two views to start a model."""
    opts = pycolmap.IncrementalPipelineOptions()
    return int(opts.mapper.init_min_num_inliers), float(opts.mapper.init_min_tri_angle)

_CAMERA_MODES = {
    "single": pycolmap.CameraMode.SINGLE,
    "per_image": pycolmap.CameraMode.PER_IMAGE,
    "per_folder": pycolmap.CameraMode.PER_FOLDER,
    "auto": pycolmap.CameraMode.AUTO,
}


def version() -> str:
    return pycolmap.__version__


def colmap_to_hloc_keypoints(xy: np.ndarray) -> np.ndarray:
    """(N, 2) keypoints in COLMAP's convention -> hloc's (pixel centre at integer coordinates)."""
    return np.asarray(xy, dtype=np.float32) - 0.5


def hloc_to_colmap_keypoints(xy: np.ndarray) -> np.ndarray:
    return np.asarray(xy, dtype=np.float32) + 0.5


def send_log_to(log_dir: Path | None, *, verbose: bool = False) -> None:
    """Route COLMAP's own log into `log_dir/colmap-<time>.<pid>` (or to the console when verbose).

    Without a folder and not verbose, only COLMAP's errors reach the console; with a folder, none
    (sara reports a failure in one line that names the log).
    """
    logging_ = pycolmap.logging
    if verbose:
        logging_.minloglevel = 0
        logging_.alsologtostderr = True
        return
    logging_.alsologtostderr = False
    logging_.stderrthreshold = 2  # without a log file, errors still reach the console
    if log_dir is None:
        logging_.minloglevel = 2
        return
    logging_.stderrthreshold = 3  # with one, sara's own one-line error says what failed and names the log
    Path(log_dir).mkdir(parents=True, exist_ok=True)
    logging_.minloglevel = 0
    logging_.set_log_destination(logging_.INFO, str(Path(log_dir) / "colmap-"))
    for level in (logging_.WARNING, logging_.ERROR):
        logging_.set_log_destination(level, "")


def bundle_adjust(rec: pycolmap.Reconstruction, options: pycolmap.BundleAdjustmentOptions | None = None) -> None:
    """COLMAP's global bundle adjustment of `rec` (`pycolmap.bundle_adjustment`) without its console output.

    pycolmap's call switches COLMAP's log to the console (glog's alsologtostderr, minloglevel 0) and
    leaves it so: its report, and every later COLMAP message of the process, then reached the terminal
    even with `--quiet`. Unless the log already goes to the console (`--verbose`), its own report is
    kept off the terminal (it still reaches the log file) and the log settings are put back afterwards.
    """
    import sys

    log = pycolmap.logging
    saved = (log.logtostderr, log.alsologtostderr, log.stderrthreshold, log.minloglevel)
    to_console = saved[0] or saved[1]
    options = options or pycolmap.BundleAdjustmentOptions()
    if to_console:
        pycolmap.bundle_adjustment(rec, options)
        return
    sys.stderr.flush()
    kept = os.dup(2)
    try:
        with open(os.devnull, "wb") as sink:
            os.dup2(sink.fileno(), 2)
        pycolmap.bundle_adjustment(rec, options)
    finally:
        os.dup2(kept, 2)
        os.close(kept)
        log.logtostderr, log.alsologtostderr, log.stderrthreshold, log.minloglevel = saved


def set_seed(seed: int) -> None:
    pycolmap.set_random_seed(seed)


@contextlib.contextmanager
def open_database(path: Path) -> Iterator[pycolmap.Database]:
    with native_errors(f"open the database {path}", Path(path).parent):
        db = pycolmap.Database.open(str(path))
    try:
        yield db
    finally:
        db.close()


def copy_database(src: Path, dst: Path) -> None:
    """Copy a COLMAP database consistently (its WAL included) through SQLite's backup API."""
    import sqlite3

    from ..io import atomic_path

    with atomic_path(dst) as tmp:
        source = sqlite3.connect(f"file:{src}?mode=rw", uri=True)  # rw: its log is merged and removed on close
        target = sqlite3.connect(tmp)
        try:
            source.backup(target)
        finally:
            target.close()
            source.close()


def remove_database(path: Path) -> None:
    """Delete a database with its SQLite write-ahead log and index (`-wal`, `-shm`): a log left by
    a killed run must never be replayed onto a newer file of the same name."""
    for suffix in ("", "-wal", "-shm", "-journal"):
        Path(f"{path}{suffix}").unlink(missing_ok=True)


def replace_database(src: Path, dst: Path) -> None:
    """Move a finished database (closed, so its log is merged) onto `dst`, dropping `dst`'s log."""
    for suffix in ("-wal", "-shm", "-journal"):
        Path(f"{dst}{suffix}").unlink(missing_ok=True)
    os.replace(src, dst)


def quiet_signals_in_worker() -> None:
    """In a worker process of ours: SIGTERM ends it silently (instead of the stack dump of
    pycolmap's native handler) and SIGINT is left to the driver, which stops the pool."""
    import multiprocessing
    import signal

    if multiprocessing.parent_process() is None:
        return
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def create_database(path: Path) -> None:
    with native_errors(f"create the database {path}", Path(path).parent):
        pycolmap.Database.open(str(path)).close()


def import_images(db_path: Path, image_dir: Path, names: list[str], *, camera_mode: str, camera_model: str,
                  camera_params: str = "", default_focal_length_factor: float = 1.2) -> None:
    """Add images and their cameras to the database (no features yet)."""
    opts = pycolmap.ImageReaderOptions()
    opts.camera_model = camera_model
    opts.camera_params = camera_params
    opts.default_focal_length_factor = default_focal_length_factor
    with native_errors("import the images into the database", Path(db_path).parent):
        pycolmap.import_images(
            str(db_path), str(image_dir), camera_mode=_CAMERA_MODES[camera_mode], image_names=names, options=opts
        )


def extract_sift(db_path: Path, image_dir: Path, names: list[str], *, max_image_size: int, max_num_features: int,
                 camera_model: str, camera_params: str = "", num_threads: int = -1) -> None:
    """SIFT (RootSIFT, COLMAP defaults) for images already imported; images with features are skipped."""
    opts = pycolmap.FeatureExtractionOptions()
    opts.max_image_size = max_image_size
    opts.num_threads = num_threads
    opts.sift.max_num_features = max_num_features
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    reader.camera_params = camera_params
    with native_errors("extract SIFT features", Path(db_path).parent):
        pycolmap.extract_features(
            str(db_path), str(image_dir), image_names=names, reader_options=reader,
            extraction_options=opts, device=pycolmap.Device.cpu,
        )


def sift_of_image(image: np.ndarray, *, max_num_features: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """COLMAP's SIFT of one (H, W, 3) or (H, W) uint8 image: as :func:`read_sift`."""
    gray = np.asarray(image, dtype=np.float32)
    if gray.ndim == 3:
        gray = gray @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    opts = pycolmap.SiftExtractionOptions()
    opts.max_num_features = max_num_features
    sift = pycolmap.Sift(opts, device=pycolmap.Device.cpu)
    kp, desc = sift.extract(gray / 255.0)
    kp = np.asarray(kp, dtype=np.float32)
    return _split_keypoints(kp, np.asarray(desc))


def write_keypoints(db_path: Path, keypoints: dict[str, np.ndarray]) -> None:
    """Store (N, 2) float32 keypoints (COLMAP's pixel convention) of images already in the database."""
    with open_database(db_path) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        for name, xy in keypoints.items():
            if db.exists_keypoints(ids[name]):
                continue
            db.write_keypoints(ids[name], np.ascontiguousarray(xy, dtype=np.float32).reshape(-1, 2))


def images_with_keypoints(db_path: Path) -> set[str]:
    """Names of the images that have a keypoints entry (read with SQLite: the file is not touched)."""
    (rows,) = _query(db_path, ("SELECT name FROM images JOIN keypoints USING (image_id)", ()))
    return {name for (name,) in rows}


def database_images(db_path: Path) -> dict[str, int]:
    """name -> image_id of the images in a database (read with SQLite: the file is not touched)."""
    (rows,) = _query(db_path, ("SELECT name, image_id FROM images", ()))
    return {name: int(image_id) for name, image_id in rows}


def read_sift(db: pycolmap.Database, image_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keypoints (N, 2) float32 COLMAP pixels, scales (N,) float32 px, descriptors (N, 128) uint8."""
    kp = np.asarray(db.read_keypoints(image_id), dtype=np.float32)
    desc = np.asarray(db.read_descriptors(image_id).data)
    return _split_keypoints(kp, desc)


def _split_keypoints(kp: np.ndarray, desc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if len(kp) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros((0, 128), np.uint8)
    if kp.shape[1] >= 6:  # affine shape a11 a12 a21 a22: scale = sqrt(|det|)
        scale = np.sqrt(np.abs(kp[:, 2] * kp[:, 5] - kp[:, 3] * kp[:, 4]))
    elif kp.shape[1] >= 3:
        scale = kp[:, 2]
    else:
        scale = np.ones(len(kp), np.float32)
    return kp[:, :2].copy(), scale.astype(np.float32), desc.astype(np.uint8, copy=False)


def match_pairs(db_path: Path, pairs_path: Path, *, max_ratio: float, max_distance: float, cross_check: bool,
                min_num_inliers: int, num_threads: int = -1) -> None:
    """COLMAP's SIFT matching and geometric verification of the pairs in a file.

    Pairs already matched in the database are skipped by COLMAP, so this resumes.
    """
    mopts = pycolmap.FeatureMatchingOptions()
    mopts.num_threads = num_threads
    mopts.sift.max_ratio = max_ratio
    mopts.sift.max_distance = max_distance
    mopts.sift.cross_check = cross_check
    vopts = verification_options(min_num_inliers)
    with native_errors("match the pairs", Path(db_path).parent):
        pycolmap.match_image_pairs(
            str(db_path), matching_options=mopts,
            pairing_options=pycolmap.ImportedPairingOptions(match_list_path=str(pairs_path)),
            verification_options=vopts, device=pycolmap.Device.cpu,
        )


def write_matches(db_path: Path, matches: dict[tuple[str, str], np.ndarray]) -> None:
    """Store (K, 2) index matches of image pairs (by name), replacing unverified ones left by a killed run."""
    with open_database(db_path) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        for (name0, name1), m in matches.items():
            id0, id1 = ids[name0], ids[name1]
            if db.exists_two_view_geometry(id0, id1):
                db.delete_two_view_geometry(id0, id1)
            if db.exists_matches(id0, id1):
                db.delete_matches(id0, id1)
            db.write_matches(id0, id1, np.ascontiguousarray(m, dtype=np.uint32).reshape(-1, 2))


#: the seed of the verification's RANSAC: COLMAP's default (-1) draws from a generator per thread,
#: so a pair's inlier count depended on which thread verified it and what it had done before (two
#: identical runs: 216 against 217, 154 against 156 inliers); with a seed every pair draws the same
VERIFICATION_SEED = 0


def verification_options(min_num_inliers: int) -> pycolmap.TwoViewGeometryOptions:
    """COLMAP's geometric verification settings: its defaults, `min_num_inliers`, a fixed RANSAC seed."""
    opts = pycolmap.TwoViewGeometryOptions()
    opts.min_num_inliers = min_num_inliers
    opts.ransac.random_seed = VERIFICATION_SEED
    return opts


def verify_pairs(db_path: Path, pairs_path: Path, *, min_num_inliers: int) -> None:
    """COLMAP's geometric verification of the stored matches of the pairs in a pairs file."""
    with native_errors("verify the matches", Path(db_path).parent):
        pycolmap.verify_matches(str(db_path), str(pairs_path), options=verification_options(min_num_inliers))


def verified_image_pairs(db: pycolmap.Database) -> list[tuple[int, int, int]]:
    """(image_id0, image_id1, num_inliers) of every pair with a two-view geometry, id0 < id1."""
    pair_ids, num_inliers = db.read_two_view_geometry_num_inliers()
    out = []
    for pair_id, n in zip(pair_ids, num_inliers):
        i, j = sorted(pycolmap.pair_id_to_image_pair(int(pair_id)))
        out.append((int(i), int(j), int(n)))
    return out


def incremental_mapping(
    db_path: Path, image_dir: Path, out_dir: Path, *, seed: int, min_model_size: int,
    abs_pose_min_num_inliers: int, abs_pose_min_inlier_ratio: float, num_threads: int = -1,
    on_next_image: Callable[[], None] | None = None, input_path: Path | None = None,
) -> dict[int, pycolmap.Reconstruction]:
    """COLMAP's incremental mapper; with `input_path` it continues from that model (registers the
    images it lacks, then bundle-adjusts) instead of starting from an empty one."""
    opts = pycolmap.IncrementalPipelineOptions()
    opts.min_model_size = min_model_size
    opts.num_threads = num_threads
    opts.mapper.abs_pose_min_num_inliers = abs_pose_min_num_inliers
    opts.mapper.abs_pose_min_inlier_ratio = abs_pose_min_inlier_ratio
    opts.random_seed = seed
    opts.mapper.random_seed = seed
    opts.triangulation.random_seed = seed
    with native_errors("map the matches (incremental mapper)", Path(out_dir)):
        return pycolmap.incremental_mapping(
            str(db_path), str(image_dir), str(out_dir), options=opts,
            input_path=str(input_path) if input_path is not None else "",
            next_image_callback=on_next_image,
        )


def global_mapping(db_path: Path, image_dir: Path, out_dir: Path, *, seed: int, num_threads: int = -1) -> dict:
    opts = pycolmap.GlobalPipelineOptions()
    with contextlib.suppress(AttributeError):
        opts.num_threads = num_threads
    with contextlib.suppress(AttributeError):
        opts.random_seed = seed
    with native_errors("map the matches (global mapper)", Path(out_dir)):
        return pycolmap.global_mapping(str(db_path), str(image_dir), str(out_dir), options=opts)


def read_model(path: Path) -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(str(path))


def has_model(model_dir: Path) -> bool:
    """Whether a folder holds a COLMAP model (binary or text)."""
    return any((Path(model_dir) / f"{kind}.{ext}").is_file() for kind in ("cameras", "images") for ext in ("bin", "txt"))


def registered_images(model_dir: Path) -> set[str]:
    """Names of the posed images of a model folder (empty when there is no model)."""
    if not has_model(model_dir):
        return set()
    rec = read_model(model_dir)
    return {im.name for im in rec.images.values() if im.has_pose}


def cameras_by_image(db_path: Path) -> dict[str, pycolmap.Camera]:
    """name -> the pycolmap.Camera (intrinsics as imported: EXIF focal or COLMAP's prior)."""
    with open_database(db_path) as db:
        cams = {c.camera_id: c for c in db.read_all_cameras()}
        return {im.name: cams[im.camera_id] for im in db.read_all_images()}


def shared_camera(db_path: Path) -> pycolmap.Camera | None:
    """The database's camera when every image uses one and the same, else None."""
    with open_database(db_path) as db:
        cameras = db.read_all_cameras()
    return cameras[0] if len(cameras) == 1 else None


def set_focal_length(db_path: Path, camera_id: int, focal_px: float) -> None:
    """Replace the focal length of one camera of the database (other parameters kept, still a guess
    for bundle adjustment to refine: `has_prior_focal_length` stays as it was)."""
    with open_database(db_path) as db:
        camera = db.read_camera(camera_id)
        for index in camera.focal_length_idxs():
            camera.params[index] = focal_px
        db.update_camera(camera)


def estimate_fundamental(points0: np.ndarray, points1: np.ndarray, *, max_error_px: float,
                         max_trials: int = 10000, seed: int = 0) -> tuple[np.ndarray, int] | None:
    """COLMAP's LO-RANSAC fundamental matrix of (N, 2) pixel correspondences: (F, number of inliers)
    with x1^T F x0 = 0, or None when it finds none."""
    if len(points0) < 8:
        return None
    options = pycolmap.RANSACOptions()
    options.max_error = max_error_px
    options.max_num_trials = max_trials
    options.random_seed = seed
    result = pycolmap.estimate_fundamental_matrix(np.asarray(points0, dtype=np.float64),
                                                  np.asarray(points1, dtype=np.float64), options)
    if result is None:
        return None
    return np.asarray(result["F"], dtype=np.float64), int(np.sum(result["inlier_mask"]))


def image_to_normalized(camera: pycolmap.Camera, xy_colmap: np.ndarray) -> np.ndarray:
    """(N, 2) pixels in COLMAP's convention -> (N, 2) normalized camera coordinates (undistorted)."""
    if len(xy_colmap) == 0:
        return np.zeros((0, 2))
    return np.asarray(camera.cam_from_img(np.asarray(xy_colmap, dtype=np.float64)), dtype=np.float64)[:, :2]


def mean_focal_px(camera: pycolmap.Camera) -> float:
    return float(np.mean([camera.focal_length_x, camera.focal_length_y]))


# ---------------------------------------------------------------------------------------------
# Vocabulary tree (the `vocabtree` baseline pair source)
# ---------------------------------------------------------------------------------------------


def build_visual_index(descriptors: np.ndarray, path: Path, *, num_words: int, num_iterations: int,
                       seed: int, num_threads: int = -1) -> None:
    """Build a pycolmap visual index (vocabulary tree) from SIFT descriptors and write it to `path`.

    descriptors: (N, 128) uint8 SIFT as COLMAP stores them; cast to float32 unscaled, as COLMAP
    does when it indexes or queries a database image. One clustering round; the same seed and
    input give the same file (pycolmap's global seed drives the clustering).
    """
    data = np.ascontiguousarray(np.asarray(descriptors), dtype=np.float32)
    index = pycolmap.VisualIndex.create(128, 64)
    opts = pycolmap.VisualIndex.BuildOptions()
    opts.num_visual_words = int(num_words)
    opts.num_iterations = int(num_iterations)
    opts.num_rounds = 1
    opts.num_threads = num_threads
    pycolmap.set_random_seed(seed)
    index.build(opts, pycolmap.FeatureDescriptorsFloat(type=pycolmap.FeatureExtractorType.SIFT, data=data))
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    index.write(str(path))


def vocab_tree_retrieval(db_path: Path, tree_path: Path, num_images: int, *,
                         num_threads: int = -1) -> list[tuple[str, str]]:
    """COLMAP's vocabulary-tree retrieval: every database image queries the index of all images.

    Returns (query name, retrieved name) for the `num_images` best-scoring images of each query;
    as in COLMAP's vocab_tree_matcher, the query itself is usually among them.
    """
    opts = pycolmap.VocabTreePairingOptions()
    opts.vocab_tree_path = str(tree_path)
    opts.num_images = int(num_images)
    opts.num_threads = num_threads
    with open_database(db_path) as db:
        names = {im.image_id: im.name for im in db.read_all_images()}
        id_pairs = pycolmap.VocabTreePairGenerator(opts, db).all_pairs()
    return [(names[int(a)], names[int(b)]) for a, b in id_pairs]


# ---------------------------------------------------------------------------------------------
# Models as plain arrays (evaluation): poses are cam_from_world, (R (3, 3), t (3,)) float64
# ---------------------------------------------------------------------------------------------



def read_reconstruction(model_dir: Path) -> pycolmap.Reconstruction:
    """Read a COLMAP model folder (binary or text).

    Raises:
        FileNotFoundError: the folder does not exist or holds no COLMAP model.
    """
    model_dir = Path(model_dir)
    if not model_dir.is_dir():
        raise FileNotFoundError(f"Model folder does not exist: {model_dir}")
    if not has_model(model_dir):
        raise FileNotFoundError(
            f"No COLMAP model in {model_dir}: expected cameras/images/points3D .bin or .txt files"
        )
    try:
        return pycolmap.Reconstruction(model_dir)
    except (ValueError, RuntimeError, LookupError, EOFError) as error:  # missing, cut short, damaged
        raise FileNotFoundError(
            f"Could not read a COLMAP model from {model_dir} (damaged or incomplete: {error})"
        ) from error


def pose_of_image(image: Any) -> tuple[np.ndarray, np.ndarray]:
    """(R_cam_from_world (3, 3), t_cam_from_world (3,)) float64 of a posed pycolmap Image."""
    cam_from_world = image.cam_from_world()  # a method in pycolmap 4.x, not a property
    rotation = np.asarray(cam_from_world.rotation.matrix(), dtype=np.float64)
    translation = np.asarray(cam_from_world.translation, dtype=np.float64).reshape(3)
    return rotation, translation


def poses_of(rec: pycolmap.Reconstruction) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name -> (R_cam_from_world (3, 3), t_cam_from_world (3,)) for every image with a pose."""
    return {image.name: pose_of_image(image) for image in rec.images.values() if image.has_pose}


def _image_reprojection_errors_px(
    rec: pycolmap.Reconstruction, image: Any, point_ids_sorted: np.ndarray, xyz_sorted: np.ndarray
) -> np.ndarray:
    """Reprojection errors (K,) float64 in pixels of the K observations of one posed image.

    Points behind the camera give NaN.
    """
    points2d = image.get_observation_points2D()
    if len(points2d) == 0:
        return np.zeros(0)
    xy_observed = np.array([p.xy for p in points2d], dtype=np.float64).reshape(-1, 2)
    point3d_ids = np.array([p.point3D_id for p in points2d], dtype=np.int64)
    xyz_world = xyz_sorted[np.searchsorted(point_ids_sorted, point3d_ids)]
    rotation, translation = pose_of_image(image)
    xyz_cam = xyz_world @ rotation.T + translation
    xy_projected = np.asarray(rec.cameras[image.camera_id].img_from_cam(xyz_cam), dtype=np.float64)
    return np.linalg.norm(xy_projected.reshape(-1, 2) - xy_observed, axis=1)


def reprojection_errors_px(rec: pycolmap.Reconstruction) -> np.ndarray:
    """Reprojection error of every observation of every 3D point, in pixels.

    Each 3D point is projected with the pose and camera of every image in its track and compared
    with the observed keypoint. Vectorised per image.

    Returns:
        (M,) float64, one entry per observation (M = total track length); NaN where the point
        lies behind the camera.
    """
    if rec.num_points3D() == 0:
        return np.zeros(0)
    point_ids = np.fromiter(rec.points3D.keys(), dtype=np.int64, count=rec.num_points3D())
    xyz = np.array([point.xyz for point in rec.points3D.values()], dtype=np.float64)
    order = np.argsort(point_ids)
    point_ids_sorted, xyz_sorted = point_ids[order], xyz[order]
    errors = [
        _image_reprojection_errors_px(rec, image, point_ids_sorted, xyz_sorted)
        for image in rec.images.values()
        if image.has_pose
    ]
    return np.concatenate(errors) if errors else np.zeros(0)


def load_poses(model_dir: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Poses of the registered images of a COLMAP model (text or binary).

    Returns:
        name -> (R_cam_from_world (3, 3) float64, t_cam_from_world (3,) float64); images
        without a pose are left out.

    Raises:
        FileNotFoundError: the folder does not exist or holds no model.
    """
    return poses_of(read_reconstruction(Path(model_dir)))


def model_structure(rec: pycolmap.Reconstruction) -> tuple[int, int, np.ndarray]:
    """(3D points, observations, reprojection error of every observation in pixels (NaN behind))."""
    return rec.num_points3D(), rec.compute_num_observations(), reprojection_errors_px(rec)


def num_registered(rec: pycolmap.Reconstruction) -> int:
    return int(rec.num_reg_images())


def cameras_and_poses(model_dir: Path) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]]:
    """name -> (K (3, 3), R (3, 3), t (3,), (width, height)) of every posed image of a model (gt models)."""
    rec = read_reconstruction(Path(model_dir))
    out = {}
    for image in rec.images.values():
        if not image.has_pose:
            continue
        cam = rec.cameras[image.camera_id]
        R, t = pose_of_image(image)
        out[image.name] = (np.asarray(cam.calibration_matrix(), dtype=np.float64), R, t, (int(cam.width), int(cam.height)))
    return out


def write_models_by_size(folder: Path, recs: dict[int, pycolmap.Reconstruction]) -> list[int]:
    """Write mapper output as `folder/0, 1, ...`, 0 the largest; returns registered images per model.

    A model whose images are all in a larger one is left out: continuing from an input model, COLMAP's
    mapper can build a new model holding every view and keep the input beside it.
    """
    import shutil

    order, seen = [], set()
    for key, rec in sorted(recs.items(), key=lambda kv: (-kv[1].num_reg_images(), kv[0])):
        names = {im.name for im in rec.images.values() if im.has_pose}
        if names and names <= seen:
            logger.info("map: left out a model of %d views that a larger model holds as well", len(names))
            continue
        seen |= names
        order.append((key, rec))
    for sub in list(Path(folder).iterdir()):
        if sub.is_dir():
            shutil.rmtree(sub)
    sizes = []
    for new_index, (_, rec) in enumerate(order):
        dst = Path(folder) / str(new_index)
        dst.mkdir()
        with native_errors(f"write the model {dst}", Path(folder)):
            rec.write(str(dst))
        sizes.append(int(rec.num_reg_images()))
    return sizes


def synthesize_scene(images_dir: Path, gt_dir: Path, *, num_images: int, num_points: int, width: int,
                     height: int, seed: int) -> None:
    """pycolmap's synthetic scene: rendered PNGs into `images_dir`, the true model (text) into `gt_dir`.

    One PINHOLE camera with focal 1.2 * max(width, height); cameras surround one point cloud.
    """
    pycolmap.set_random_seed(seed)
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs = 1
    opts.num_cameras_per_rig = 1
    opts.num_frames_per_rig = num_images
    opts.num_points3D = num_points
    opts.camera_width, opts.camera_height = width, height
    opts.camera_model_id = pycolmap.CameraModelId.PINHOLE
    focal = 1.2 * max(width, height)
    opts.camera_params = [focal, focal, width / 2, height / 2]
    rec = pycolmap.synthesize_dataset(opts)
    pycolmap.synthesize_images(pycolmap.SyntheticImageOptions(), rec, str(images_dir))
    rec.write_text(str(gt_dir))
