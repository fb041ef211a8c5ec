"""Compare runs of the old and new code: pairs.txt bytes, registration, AUC@1/@5 per scene and method."""
import hashlib
import json
import sys
from pathlib import Path

root = Path(sys.argv[1])
tags = sys.argv[2:]
scenes = ["strecha-fountain-P11", "middlebury-templeSparseRing", "strecha-Herz-Jesus-P25", "strecha-castle-P30",
          "middlebury-templeRing", "bm-moldGoldCape"]
print("| scene | method | " + " | ".join(tags) + " |")
print("|---|---|" + "---|" * len(tags))
for s in scenes:
    for m in ("exhaustive", "sara"):
        cells = []
        for t in tags:
            d = root / t / s / m
            mf = d / "metrics.json"
            if not mf.exists():
                cells.append("-")
                continue
            x = json.loads(mf.read_text())
            h = hashlib.sha256((d / "pairs.txt").read_bytes()).hexdigest()[:8]
            n = len((d / "pairs.txt").read_text().splitlines())
            cells.append(f"{n} pairs {h}, {x['num_registered']}/{x['num_images_gt']} ({x['num_components']}), "
                         f"{x['auc']['1']:.4f} / {x['auc']['5']:.4f}")
        print(f"| {s} | {m} | " + " | ".join(cells) + " |")
