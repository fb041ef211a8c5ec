"""The incremental mapper's global bundle adjustments by the size of the scene: COLMAP's schedule
below `LARGE_SCENE_IMAGES` images, sparser and fewer adjustments from there, unless set by hand."""

from __future__ import annotations

from .colmap.stepwise import DIRECT_SOLVER_MAX_IMAGES
from .config import MapConfig

#: scenes of at least this many images are adjusted as a whole less often (`map.ba_global_growth` 0)
LARGE_SCENE_IMAGES = 500
#: the growth between two global adjustments from LARGE_SCENE_IMAGES on; COLMAP's is 1.1
LARGE_SCENE_BA_GROWTH = 1.4
#: the most refinement rounds of a global adjustment from LARGE_SCENE_IMAGES on; COLMAP's is 5
LARGE_SCENE_BA_REFINEMENTS = 1
#: from this many images sara drives the mapper step by step (`map.ba_direct_max_images` 0); COLMAP's
#: global adjustments switch to Ceres' iterative solver above it
STEPWISE_IMAGES = 1000


def ba_global_growth(conf: MapConfig, num_images: int) -> float | None:
    """The growth of the model between two global bundle adjustments; None keeps COLMAP's 1.1.

    COLMAP adjusts the whole model each time its views or points grew by 10%: about
    ln(N / N0) / ln(1.1) adjustments of a growing model, costing about 11 adjustments of the final
    one. On the 1,000-image synthetic world every 40% instead cut the mapping by 18-38% (five mappings
    of three graphs) for the same views and AUC (lab/notes/SCALE.md). Below 500 images COLMAP's
    schedule stays: the shared scenes were measured with it."""
    if conf.ba_global_growth > 0:
        return conf.ba_global_growth
    return LARGE_SCENE_BA_GROWTH if num_images >= LARGE_SCENE_IMAGES else None


def ba_global_refinements(conf: MapConfig, num_images: int) -> int | None:
    """The most refinement rounds of each global bundle adjustment; None keeps COLMAP's 5.

    Each global adjustment of COLMAP's incremental mapper adjusts, re-triangulates and filters up to
    5 times, until under 0.05% of the observations change. Past about 1,000 registered views one
    adjustment of the 3,000-image synthetic world took minutes (lab/notes/SCALE.md); on the
    1,000-image world one round gave the same views and AUC to 0.0001 (two graphs); its 7-9% less
    time there is within the machine's run-to-run spread, so no gain is claimed.
    Below 500 images COLMAP's 5 stay: the shared scenes were measured with them."""
    if conf.ba_global_refinements > 0:
        return conf.ba_global_refinements
    return LARGE_SCENE_BA_REFINEMENTS if num_images >= LARGE_SCENE_IMAGES else None


def ba_direct_max_images(conf: MapConfig, num_images: int) -> int | None:
    """The largest model whose global adjustments use Ceres' direct sparse solver, for sara's
    step-by-step mapping (`colmap.stepwise`); None: COLMAP's own loop (direct up to 1,000 images).

    On a converged 992-view model of the 1,000-image synthetic world, one global adjustment took
    6.8 s with the direct solver and 103.5 s with the iterative one COLMAP uses above 1,000 images,
    to the same reprojection error (lab/notes/SCALE.md)."""
    if conf.ba_direct_max_images > 0:
        return conf.ba_direct_max_images
    return DIRECT_SOLVER_MAX_IMAGES if num_images >= STEPWISE_IMAGES else None
