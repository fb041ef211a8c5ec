"""Scale harness: synthetic worlds with true poses at the feature level, no photographs needed.

`world.make_world` writes a normal sara output folder (features-sift.h5, database.db) plus the truth
(truth.h5: poses, observed 3D points); `world.Truth` says which pairs truly overlap.
`scripts/scale_bench.py` runs the pair selection on worlds of growing size. See docs/SCALE.md.
"""

from .world import Truth, WorldConfig, features_path, image_set, make_world, world_info

__all__ = ["Truth", "WorldConfig", "features_path", "image_set", "make_world", "world_info"]
