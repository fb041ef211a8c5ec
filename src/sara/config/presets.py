"""Named presets: overrides of the defaults, chosen with `--preset NAME`, like hloc's `confs`."""

from __future__ import annotations

from typing import Any

#: What the learned presets share. A LightGlue pair costs 3-10x a SIFT pair on a CPU, so their pair
#: budget is 2.5 N for all rounds (SIFT: 4 N) and the pose-guided round adds half a pair per view
#: (SIFT: one); on bm-moldGoldCape this kept the learned presets' accuracy at a fraction of the time.
_LEARNED: dict[str, Any] = {"extract.max_num_features": 2048, "extract.max_image_size": 1024,
                            "budget.max_pairs_per_image": 2.5, "rounds.pose_guided_pairs_per_image": 0.5}

PRESETS: dict[str, dict[str, Any]] = {
    "sift-offline": {},
    # Faster preview on large collections: fewer SIFT features, smaller images.
    "sift-fast": {"extract.max_num_features": 4096, "extract.max_image_size": 1600},
    # The paper's setting: learned features and LightGlue (`pip install 'sara[learned]'` and the weights;
    # `sara weights` says where each file is looked for). 1024 px and 2048 keypoints, which kept the
    # accuracy of larger settings on the benchmark scenes at a fraction of the cost; the licence of each
    # weight file is listed by `sara weights`.
    "aliked-lightglue": {"extract.backend": "aliked-n16", **_LEARNED, "match.backend": "lightglue"},
    "disk-lightglue": {"extract.backend": "disk", **_LEARNED, "match.backend": "lightglue"},
    "xfeat-lighterglue": {"extract.backend": "xfeat", **_LEARNED, "match.backend": "lighterglue"},
}
