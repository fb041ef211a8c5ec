"""sara: Scene-Aware Reconstruction Accelerator.

Chooses which image pairs to match for Structure-from-Motion, then runs
COLMAP's matching and mapping on only those pairs.
"""

import logging
import os

# COLMAP's log (glog, read when pycolmap loads): every line written to sara's log file at once, not
# buffered for up to 30 s, so the log a failure names holds its last lines, and a log file made for
# one run is complete when the run returns
os.environ.setdefault("GLOG_logbuflevel", "-1")

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
