"""Experiment: the final track extension (and its adjustment) on a saved model, as sara's last step does it.

`sara.colmap.refine.extend_and_adjust` with the extension of the default settings for SIFT
(`rounds.extend_tracks_*`, the scale test on), on MODEL with the keypoints and descriptors of
FEATURES, written to OUT; then score OUT with `sara evaluate OUT GT`. `--max-values` sets
`TrackExtension.max_values` (descriptor values held as float32; up to twice as many as float16):
a small value forces the float16 path on a model that would take the float32 one.

    python lab/scripts/extend_model.py MODEL FEATURES OUT [--max-values N]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import time
from pathlib import Path

from sara.colmap.refine import extend_and_adjust
from sara.config import make_config
from sara.pairs.sara.pose_guided import _extension


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("features", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--max-values", type=int, default=None)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    ext = _extension(make_config().rounds, "sift")
    if args.max_values is not None:
        ext = dataclasses.replace(ext, max_values=args.max_values)
    tic = time.perf_counter()
    counts = extend_and_adjust(args.model, args.out, args.features, ext)
    print(f"{counts} in {time.perf_counter() - tic:.1f} s")


if __name__ == "__main__":
    main()
