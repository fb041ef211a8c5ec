"""sara: Scene-Aware Reconstruction Accelerator.

Chooses which image pairs to match for Structure-from-Motion, then runs
COLMAP's matching and mapping on only those pairs.
"""

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
