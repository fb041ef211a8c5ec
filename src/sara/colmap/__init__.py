"""Every call into pycolmap goes through this package, so an API change is mended in one place.

Its modules follow COLMAP's objects: `native` (errors, signals, log, seed), `database` (the file,
images, cameras, keypoints, matches), `database_queries` (read-only SQLite counts), `sift`,
`matching` (two views), `sfm` (mappers, bundle adjustment), `reconstruction` (models as arrays),
`geometry` (pixel conventions), `vocabtree`, `synthetic`, and beside them `model` (models for
exports), `build` (databases from arrays) and `refine` / `tracks` (refining a model with known poses).
What they return is sara's own: names, ids, numpy arrays, small dataclasses.

Pixel convention: COLMAP's, where the centre of the top-left pixel is (0.5, 0.5). hloc's HDF5
files use (0, 0) for that centre; `colmap_to_hloc_keypoints` converts.
"""

from __future__ import annotations

import PIL.Image  # noqa: F401 - before pycolmap: its bundled zlib otherwise breaks Pillow's PNG writer (heap corruption)

from .consistency import CONTRADICTION_PX, Agreement, model_agreement
from .database import (
    cameras_by_image,
    clear_matches,
    copy_database,
    copy_pairs,
    create_database,
    delete_pairs_except,
    fisheye_cameras,
    has_two_view_geometry,
    image_ids,
    import_images,
    number_images_by_name,
    remove_database,
    rename_images,
    replace_database,
    set_focal_length,
    shared_camera,
    two_view_inlier_counts,
    verified_image_pairs,
    write_keypoints,
    write_matches,
)
from .database_queries import (
    camera_priors,
    database_images,
    database_summary,
    images_with_keypoints,
    match_counts,
    verified_graph,
    verified_inliers,
)
from .edit import delete_images, keep_keypoints, prune_model, share_cameras
from .geometry import (
    CameraInfo,
    colmap_to_hloc_keypoints,
    hloc_to_colmap_keypoints,
    image_to_normalized,
    mean_focal_px,
)
from .matching import VERIFICATION_SEED, estimate_fundamental, match_pairs, verify_pairs
from .mend import SEAM_HOPS, Cut, cut_at_seam
from .native import ColmapError, quiet_signals_in_worker, send_log_to, set_seed, version
from .reconstruction import (
    ModelSummary,
    cameras_and_poses,
    has_model,
    load_poses,
    read_summary,
    registered_images,
)
from .sfm import MappedModels, global_mapping, incremental_mapping, mapper_init_requirements
from .sift import (
    FeatureReader,
    count_with_keypoints,
    extract_sift,
    image_read_problem,
    read_sift_rows,
    sift_of_image,
)
from .synthetic import synthesize_scene
from .vocabtree import build_visual_index, vocab_tree_retrieval

__all__ = [
    "VERIFICATION_SEED",
    "ColmapError",
    "CameraInfo",
    "FeatureReader",
    "MappedModels",
    "Agreement",
    "CONTRADICTION_PX",
    "Cut",
    "SEAM_HOPS",
    "cut_at_seam",
    "model_agreement",
    "ModelSummary",
    "build_visual_index",
    "camera_priors",
    "cameras_and_poses",
    "cameras_by_image",
    "clear_matches",
    "colmap_to_hloc_keypoints",
    "copy_database",
    "create_database",
    "database_images",
    "database_summary",
    "delete_images",
    "copy_pairs",
    "delete_pairs_except",
    "fisheye_cameras",
    "estimate_fundamental",
    "count_with_keypoints",
    "extract_sift",
    "global_mapping",
    "has_model",
    "has_two_view_geometry",
    "hloc_to_colmap_keypoints",
    "image_ids",
    "image_read_problem",
    "image_to_normalized",
    "images_with_keypoints",
    "keep_keypoints",
    "import_images",
    "incremental_mapping",
    "load_poses",
    "mapper_init_requirements",
    "match_counts",
    "match_pairs",
    "mean_focal_px",
    "number_images_by_name",
    "quiet_signals_in_worker",
    "prune_model",
    "read_sift_rows",
    "read_summary",
    "registered_images",
    "remove_database",
    "rename_images",
    "replace_database",
    "send_log_to",
    "set_focal_length",
    "share_cameras",
    "set_seed",
    "shared_camera",
    "sift_of_image",
    "synthesize_scene",
    "two_view_inlier_counts",
    "verified_graph",
    "verified_image_pairs",
    "verified_inliers",
    "verify_pairs",
    "version",
    "vocab_tree_retrieval",
    "write_keypoints",
    "write_matches",
]
