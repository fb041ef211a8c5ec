"""Issue 31: the first matching of finished runs, chunk by chunk, and what the estimate made from its
first chunk would be with a given cost per image and call (`sara.eta.chunk_work`).

    python lab/scripts/eta_chunks.py RUN_DIR... [--image-cost 1.5]   # from the repository root

Reads each run's stderr.log (written by eta_measure.py: tqdm's progress line after every chunk, to
the second) and its pairs: pairs.txt for exhaustive matching, the first selection of scores.csv for
SARA, in the order the match stage reads them (sorted). Prints per run the chunks (pairs, images,
seconds), a least-squares fit of seconds = a * pairs + b * images over the chunks, and the estimate
from the first chunk against the time the matching took.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np

from sara import eta, selection
from sara.io.pairs import canonical_pairs, read_pairs
from sara.io.scores import read_scores_csv
from sara.match import chunked

BAR = re.compile(r"match pairs \(\w+\):\s+\d+%\|[^|]*\|\s*(\d+)/(\d+) \[(?:(\d+):)?(\d+):(\d+)<")


def first_matching_progress(stderr: str) -> list[tuple[int, float]]:
    """(pairs done, seconds) at each progress line of the first matching's bar."""
    points, total = [], None
    for line in stderr.replace("\r", "\n").splitlines():
        found = BAR.search(line)
        if not found:
            continue
        done, of = int(found.group(1)), int(found.group(2))
        if total is None:
            total = of
        elif of != total:
            break  # a later matching (a round)
        seconds = int(found.group(3) or 0) * 3600 + int(found.group(4)) * 60 + int(found.group(5))
        if not points or done > points[-1][0]:
            points.append((done, float(seconds)))
    return points


def first_pairs(run: Path) -> list[tuple[str, str]]:
    scores = run / "scores.csv"
    if not scores.exists():
        return read_pairs(run / "pairs.txt")
    table, roles = read_scores_csv(scores)
    keep = [(a, b) for a, b, r in zip(table.name0, table.name1, roles)
            if r in selection.SELECTED_ROLES or r == "rescue"]
    return canonical_pairs(keep)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--image-cost", type=float, default=1.5)
    parser.add_argument("--chunk-size", type=int, default=128)
    args = parser.parse_args()
    for run in args.runs:
        pairs = first_pairs(run)
        chunks = chunked(pairs, args.chunk_size)
        progress = first_matching_progress((run / "stderr.log").read_text())
        ends = dict(progress)
        bounds = np.cumsum([len(c) for c in chunks])
        if not progress or progress[-1][0] != len(pairs) or not all(int(b) in ends for b in bounds):
            print(f"{run.name}: {len(pairs)} pairs in {len(chunks)} chunks, the bar says {progress}: skipped")
            continue
        times = np.diff([0.0] + [ends[int(b)] for b in bounds])
        if times[0] < 2:
            print(f"{run.name}: a first chunk of {times[0]:.0f} s is too short for the bar's one-second steps")
            continue
        images = [len({n for p in c for n in p}) for c in chunks]
        print(f"\n{run.name}: {len(pairs)} pairs; chunks (pairs, images, s): "
              + ", ".join(f"({len(c)}, {i}, {t:.0f})" for c, i, t in zip(chunks, images, times)))
        if len(chunks) >= 2:
            design = np.array([[len(c), i] for c, i in zip(chunks, images)], dtype=float)
            (a, b), *_ = np.linalg.lstsq(design, times, rcond=None)
            print(f"  fit: {a:.2f} s a pair, {b:.2f} s an image and call (image cost {b / a:.2f} pairs)")
        total = times.sum()
        for cost in (0.0, args.image_cost):
            work = eta.chunk_work(chunks, cost)
            est = eta.from_first_chunk(len(pairs), len(chunks[0]), times[0], work_ratio=sum(work) / work[0])
            print(f"  image cost {cost}: estimate {est.seconds:.0f} s against {total:.0f} s "
                  f"({100 * (est.seconds - total) / total:+.0f}%)")


if __name__ == "__main__":
    main()
