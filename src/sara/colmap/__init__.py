"""Every call into pycolmap goes through this module, so an API change is mended in one place.

Pixel convention: COLMAP's, where the centre of the top-left pixel is (0.5, 0.5). hloc's HDF5
files use (0, 0) for that centre; `colmap_to_hloc_keypoints` converts.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pycolmap

logger = logging.getLogger(__name__)

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

    Without a folder and not verbose, only COLMAP's errors reach the console.
    """
    logging_ = pycolmap.logging
    if verbose:
        logging_.minloglevel = 0
        logging_.alsologtostderr = True
        return
    logging_.alsologtostderr = False
    logging_.stderrthreshold = 2  # errors still reach the console
    if log_dir is None:
        logging_.minloglevel = 2
        return
    Path(log_dir).mkdir(parents=True, exist_ok=True)
    logging_.minloglevel = 0
    logging_.set_log_destination(logging_.INFO, str(Path(log_dir) / "colmap-"))
    for level in (logging_.WARNING, logging_.ERROR):
        logging_.set_log_destination(level, "")


def set_seed(seed: int) -> None:
    pycolmap.set_random_seed(seed)


@contextlib.contextmanager
def open_database(path: Path) -> Iterator[pycolmap.Database]:
    db = pycolmap.Database.open(str(path))
    try:
        yield db
    finally:
        db.close()


def create_database(path: Path) -> None:
    pycolmap.Database.open(str(path)).close()


def import_images(db_path: Path, image_dir: Path, names: list[str], *, camera_mode: str, camera_model: str,
                  camera_params: str = "", default_focal_length_factor: float = 1.2) -> None:
    """Add images and their cameras to the database (no features yet)."""
    opts = pycolmap.ImageReaderOptions()
    opts.camera_model = camera_model
    opts.camera_params = camera_params
    opts.default_focal_length_factor = default_focal_length_factor
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
    pycolmap.extract_features(
        str(db_path), str(image_dir), image_names=names, reader_options=reader,
        extraction_options=opts, device=pycolmap.Device.cpu,
    )


def database_images(db_path: Path) -> dict[str, int]:
    """name -> image_id of the images in a database."""
    with open_database(db_path) as db:
        return {im.name: im.image_id for im in db.read_all_images()}


def read_sift(db: pycolmap.Database, image_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keypoints (N, 2) float32 COLMAP pixels, scales (N,) float32 px, descriptors (N, 128) uint8."""
    kp = np.asarray(db.read_keypoints(image_id), dtype=np.float32)
    desc = np.asarray(db.read_descriptors(image_id).data)
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
    vopts = pycolmap.TwoViewGeometryOptions()
    vopts.min_num_inliers = min_num_inliers
    pycolmap.match_image_pairs(
        str(db_path), matching_options=mopts,
        pairing_options=pycolmap.ImportedPairingOptions(match_list_path=str(pairs_path)),
        verification_options=vopts, device=pycolmap.Device.cpu,
    )


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
    on_next_image: Callable[[], None] | None = None,
) -> dict[int, pycolmap.Reconstruction]:
    opts = pycolmap.IncrementalPipelineOptions()
    opts.min_model_size = min_model_size
    opts.num_threads = num_threads
    opts.mapper.abs_pose_min_num_inliers = abs_pose_min_num_inliers
    opts.mapper.abs_pose_min_inlier_ratio = abs_pose_min_inlier_ratio
    opts.random_seed = seed
    opts.mapper.random_seed = seed
    opts.triangulation.random_seed = seed
    return pycolmap.incremental_mapping(
        str(db_path), str(image_dir), str(out_dir), options=opts,
        next_image_callback=on_next_image,
    )


def global_mapping(db_path: Path, image_dir: Path, out_dir: Path, *, seed: int, num_threads: int = -1) -> dict:
    opts = pycolmap.GlobalPipelineOptions()
    with contextlib.suppress(AttributeError):
        opts.num_threads = num_threads
    with contextlib.suppress(AttributeError):
        opts.random_seed = seed
    return pycolmap.global_mapping(str(db_path), str(image_dir), str(out_dir), options=opts)


def read_model(path: Path) -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(str(path))


def cameras_by_image(db_path: Path) -> dict[str, pycolmap.Camera]:
    """name -> the pycolmap.Camera (intrinsics as imported: EXIF focal or COLMAP's prior)."""
    with open_database(db_path) as db:
        cams = {c.camera_id: c for c in db.read_all_cameras()}
        return {im.name: cams[im.camera_id] for im in db.read_all_images()}


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
