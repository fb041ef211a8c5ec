"""A photo-collection stand-in: two similar facades (strecha-castle-P30 and strecha-Herz-Jesus-P25, same
camera, similar stone) mixed in one folder, each image resized and re-lit at random (lab/notes/AMBIGUITY.md).

Every image of both scenes is written to OUT/images as `photoNNN.jpg` (shuffled, so names say nothing
about the scene), resized to a long side drawn from 1536 (the original), 1152, 960 and 768 pixels, and
re-lit by a gain drawn from [0.55, 1.45] and a gamma drawn from [0.7, 1.4]
(v' = 255 (gain v / 255)^gamma, clipped), JPEG quality 90. OUT/sources.csv tells each name's scene,
original name, long side, gain and gamma. Seeded: the same DATA and seed give the same stand-in.

    python lab/scripts/collection_standin.py DATA OUT [--seed 0]

Then `sara pairs OUT/images RUN` (or `sara run`) and
`python lab/scripts/collection_standin.py --analyse OUT RUN DATA [--recheck-deg 20]` prints the accepted
candidate pairs that join the two scenes (wrong by construction), how many the cycle check rejected and
how many were selected, and the true rotation errors of the pairs within a scene that it rejected.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

SCENES = ("strecha-castle-P30", "strecha-Herz-Jesus-P25")
LONG_SIDES = (1536, 1152, 960, 768)


def make(data: Path, out: Path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    sources = [(scene, p) for scene in SCENES for p in sorted((data / scene / "images").glob("*.jpg"))]
    order = rng.permutation(len(sources))
    (out / "images").mkdir(parents=True, exist_ok=True)
    rows = []
    for k, index in enumerate(order):
        scene, path = sources[index]
        side = int(rng.choice(LONG_SIDES))
        gain, gamma = float(rng.uniform(0.55, 1.45)), float(rng.uniform(0.7, 1.4))
        image = Image.open(path).convert("RGB")
        scale = side / max(image.size)
        image = image.resize((round(image.width * scale), round(image.height * scale)), Image.LANCZOS)
        values = np.asarray(image, dtype=np.float64) / 255.0
        values = 255.0 * np.clip(gain * values, 0.0, 1.0) ** gamma
        name = f"photo{k:03d}.jpg"
        Image.fromarray(values.round().astype(np.uint8)).save(out / "images" / name, quality=90)
        rows.append({"name": name, "scene": scene, "original": path.name, "long_side": side,
                     "gain": round(gain, 3), "gamma": round(gamma, 3)})
    with open(out / "sources.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print(f"{len(rows)} images in {out / 'images'}")


def true_rotations(data: Path) -> dict[tuple[str, str], Rotation]:
    import pycolmap

    out = {}
    for scene in SCENES:
        gt = pycolmap.Reconstruction()
        gt.read_text(str(data / scene / "gt"))
        for im in gt.images.values():
            out[scene, im.name] = Rotation.from_matrix(im.cam_from_world().rotation.matrix())
    return out


def recheck(scores, max_error_deg: float) -> None:
    """Mark the inconsistent pairs of `scores` again with this tree's check (the run may predate it)."""
    from sara.config import GraphConfig
    from sara.selection import mark_inconsistent

    names = sorted(set(scores.name0) | set(scores.name1))
    index = {n: i for i, n in enumerate(names)}
    edges = np.array([(index[a], index[b]) for a, b in zip(scores.name0, scores.name1)], dtype=np.int64)
    conf = GraphConfig(reject_inconsistent=True, max_cycle_error_deg=max_error_deg)
    mark_inconsistent(len(names), edges, scores, conf)


def analyse(standin: Path, run: Path, data: Path, max_error_deg: float | None) -> None:
    from sara.io.scores import read_scores_csv
    from sara.selection import SELECTED_ROLES

    source = {r["name"]: (r["scene"], r["original"]) for r in csv.DictReader(open(standin / "sources.csv"))}
    scores, roles = read_scores_csv(run / "scores.csv")
    roles = roles or [""] * len(scores)
    if max_error_deg is not None:
        recheck(scores, max_error_deg)
    truth = true_rotations(data)
    cross = {"candidates": 0, "accepted": 0, "inconsistent": 0, "selected": 0}
    inside_rejected, inside_errors = [], []
    for k, (a, b) in enumerate(zip(scores.name0, scores.name1)):
        selected = roles[k] in SELECTED_ROLES or roles[k] == "rescue"
        if source[a][0] != source[b][0]:
            cross["candidates"] += 1
            cross["accepted"] += bool(scores.accepted[k]) or scores.reason[k] == "inconsistent"
            cross["inconsistent"] += scores.reason[k] == "inconsistent"
            cross["selected"] += selected
            continue
        if not np.all(np.isfinite(scores.rotvec[k])):
            continue
        true = truth[source[b]] * truth[source[a]].inv()
        error = float(np.degrees((Rotation.from_rotvec(scores.rotvec[k]).inv() * true).magnitude()))
        if scores.reason[k] == "inconsistent":
            inside_rejected.append(round(error, 1))
        elif scores.accepted[k]:
            inside_errors.append(error)
    print(f"pairs across the two scenes: {cross}")
    if inside_errors:
        print(f"within a scene: accepted pairs' true rotation error median {np.median(inside_errors):.1f}, "
              f"90th pct {np.percentile(inside_errors, 90):.1f} deg, {sum(e > 30 for e in inside_errors)} above 30")
    print(f"within a scene, rejected as inconsistent: {len(inside_rejected)}, true errors {sorted(inside_rejected)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", type=Path, nargs="+", help="DATA OUT, or with --analyse: OUT RUN DATA")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--analyse", action="store_true")
    parser.add_argument("--recheck-deg", type=float, help="with --analyse: run this tree's cycle check again first")
    args = parser.parse_args()
    if args.analyse:
        analyse(*args.paths, args.recheck_deg)
    else:
        make(*args.paths, args.seed)


if __name__ == "__main__":
    main()
