"""`python -m sara.cli`, the same as `sara` and `python -m sara`."""

import sys

from .main import main

if __name__ == "__main__":
    sys.exit(main())
