"""`sara bench`: every pair source side by side on scenes with known poses (see docs/BENCHMARKS.md)."""

from __future__ import annotations

import argparse
from collections.abc import Callable


def add_bench_parser(sub: argparse._SubParsersAction, add_output: Callable[[argparse.ArgumentParser], None]) -> None:
    p = sub.add_parser("bench", help="compare pair sources on scenes with ground truth")
    p.add_argument("scenes", nargs="+", help="scene folders holding images/ and gt/")
    add_output(p)


def cmd_bench(args: argparse.Namespace) -> None:
    raise ValueError("sara bench is not available yet in this version")
