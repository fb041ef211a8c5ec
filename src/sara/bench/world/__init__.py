"""A synthetic city with true poses at the feature level, for measuring pair selection at scale.

No photographs: a grid of streets lined with building facades, 3D points on the facades, and a
camera walking the streets. Each image's keypoints are the projections of the points it truly
sees, with pixel noise, plus outliers; each point has a descriptor of its own, observed with noise.
The result is a normal sara output folder (``features-sift.h5`` and ``database.db``), so the pair
selection stage runs on it unchanged, plus the truth (``truth.h5``) to judge the pairs it selects.
`lab/scripts/scale_bench.py` runs the pair selection on worlds of growing size.

Modules, in the order a world is made: ``config`` (WorldConfig, file names), ``city`` (blocks,
facades, points), ``walk`` (the camera's path and poses), ``descriptors`` and ``observe`` (one
image's features), ``files`` (the world on disk, and the selection's context on it), ``truth``.

The world
    Blocks of ``block_size_m`` squared, separated by streets ``street_width_m`` wide, form a grid
    of ``G x G`` blocks walked along their ``(G + 1)^2`` street crossings, with one more ring of
    blocks around so every street has facades on both sides. ``G`` is chosen from the number of
    images so that each street is walked ``visits_per_street`` times on average. Facades carry
    3D points (``point_density`` per m^2, heights 0 to the block's height), each with a physical
    size (log-normal). A share ``repeat_fraction`` of a facade's points repeat one of a few
    descriptors of the facade's style (windows), each deviating from it by ``repeat_jitter``,
    and styles repeat across the city: repeated structure within an image and look-alike
    streets across the city, as in real streets (``repeat_jitter = 0``: identical copies, a
    harder world on which the scorer's top-b-by-similarity matches break down).

The walk
    From a corner, the camera goes from crossing to crossing, always to the least-walked street
    (no U-turns; ties at random), so it closes loops and revisits streets, in either direction.
    It takes an image every ``step_m`` metres, keeping to the right of the street centre
    (``lateral_offset_m``), its heading smoothed round corners; the viewing direction turns
    from the heading by the cycle ``yaw_pattern_deg`` (left, ahead, right, ahead by default),
    with jitter in yaw, pitch, roll, height and lateral position.

What an image sees
    The points within ``max_depth_m``, in front of the camera and inside the image, on a facade
    that faces it at most ``max_view_angle_deg`` from the facade's normal, not hidden behind a
    block (2D ray test: blocks are taller than any facade point is high), and large enough on
    the image (``f * size / distance >= min_scale_px``). Their projections get Gaussian noise of
    ``pixel_noise_px``. Outliers (``outlier_fraction`` of the keypoints) have random positions
    and descriptors. The ``max_keypoints`` with the largest scale are kept; the keypoint score is
    that scale in pixels (as sara's SIFT stores it), so "top M by score" keeps the nearest and
    largest points, consistently across neighbouring views.

Descriptors
    RootSIFT-like: for point ``p``, a 128-d histogram ``g_k = (-log u_k)^1.5`` (``u`` uniform
    from a hash of ``p``, so no table is kept), L1-normalised and square-rooted (a unit vector
    with non-negative entries). An observation adds a drift along a per-point direction,
    proportional to the viewing angle on the facade (``view_drift`` per radian) and to the log
    of the distance (``scale_drift``), and isotropic noise of norm ~``descriptor_noise``; then
    clips, normalises and stores as uint8 scaled by 512 (as COLMAP stores RootSIFT). With the
    defaults, the correct neighbour is the nearest for most points seen from nearby views and for
    fewer across wide changes of viewpoint.

Truth
    ``truth.h5`` holds the names, the true ``cam_from_world`` poses and centres, the 3D points,
    and each image's observed point ids (sorted). Two images truly overlap when they observe at
    least ``min_common`` common 3D points (:class:`Truth`), computed for given pairs only.

Everything is deterministic for a seed; each image draws from its own generator, and memory is
the points (about 20 bytes each) plus one image's features at a time.
"""

from .city import City, build_city
from .config import DB_NAME, TRUTH_NAME, WORLD_JSON, WorldConfig, features_name, grid_blocks, image_name
from .descriptors import base_descriptors, observe_descriptors, point_descriptors
from .files import features_path, image_set, make_world, remove_world, selection_context, world_info
from .observe import ImageObservation, observe_image
from .truth import Truth
from .walk import camera_poses, walk_crossings

__all__ = [
    "DB_NAME", "TRUTH_NAME", "WORLD_JSON", "City", "ImageObservation", "Truth", "WorldConfig", "base_descriptors",
    "build_city", "camera_poses", "features_name", "features_path", "grid_blocks", "image_name", "image_set",
    "make_world", "observe_descriptors", "observe_image", "point_descriptors", "remove_world", "selection_context",
    "walk_crossings", "world_info",
]
