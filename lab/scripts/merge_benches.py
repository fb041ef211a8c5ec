"""One summary by kind from several `sara bench` folders, as one bench over all of them would give.

    python lab/scripts/merge_benches.py B0 B1 B2 --kind bm-moldGoldCape=object > kinds.md

Each folder's `results.json` rows are put together and summed up by `sara.bench.kinds` (a scene
named `X~namesK`, as the bench names a renaming, counts as a naming of `X`). For namings run as
benches of their own, beside each other: `sara bench RENAMED_SCENE --out B1 ...` on the folders a
bench with `--name-orders` made under `B0/renamed/`, so that the namings share no machine time
one after the other.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from sara.bench.kinds import kind_summary, parse_kinds, render_kinds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("benches", nargs="+", type=Path)
    ap.add_argument("--kind", action="append", default=[], metavar="SCENE=KIND")
    args = ap.parse_args()
    rows = [row for bench in args.benches for row in json.loads((bench / "results.json").read_text())["rows"]]
    print(render_kinds(kind_summary(rows, parse_kinds(args.kind))))


if __name__ == "__main__":
    main()
