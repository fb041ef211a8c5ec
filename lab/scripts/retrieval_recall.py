"""Recall of truly overlapping pairs among the retrieval kNN candidates, per descriptor variant.

For every scene whose features are ready (`<cache>/<scene>/.sara/extract.json` says done), the
ground-truth overlaps come from `sara.gt_pairs` (mutual-NN SIFT matches consistent with the gt
epipolar geometry; cached under `<cache>/gt_pairs/`). Each variant proposes the symmetric union of
every image's top-k neighbours, for k in K_VALUES, and we report:

- cand%: candidates as a percentage of all N(N-1)/2 pairs;
- recall: share of gt-overlapping pairs (>= min_matches gt-consistent matches) among the candidates;
- strong: the same for the strongest half of the overlapping pairs (by gt-consistent match count);
- tree: the same for the edges of the maximum spanning tree of the gt overlap graph (weights =
  match counts): the pairs a spanning structure needs most;
- comps: connected components of the candidate graph (1 = connected);
- time: seconds to compute the descriptors (kNN is negligible), one run on this machine.

The script only reads `<cache>/<scene>/`; it writes the gt cache and, with --out, JSON/CSV/Markdown.

    python lab/scripts/retrieval_recall.py [CACHE_ROOT] [DATA_ROOT] [--out DIR] [--variants a,b]
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import logging
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np

import sara.retrieval.vlad  # noqa: F401 - makes retrieval.vlad an attribute
from sara import colmap, gt_pairs, retrieval
from sara.config import RetrievalConfig
from sara.io.h5 import list_names, read_features
from sara.selection import connected_components, maximum_spanning_forest

K_VALUES = (5, 10, 15, 20, 30)
REPO = Path(__file__).resolve().parents[2]
logger = logging.getLogger("retrieval_recall")


@dataclasses.dataclass(frozen=True)
class Variant:
    name: str
    kind: str  # "descriptor", "vocabtree" or "oracle" (ranked by the gt match counts: the ceiling)
    backend: retrieval.GlobalDescriptor | None = None
    conf: RetrievalConfig = RetrievalConfig()
    vocab_words: int = 0
    vocab_max_features: int = -1


def make_variants() -> list[Variant]:
    base = RetrievalConfig()
    vlad, white = retrieval.vlad.VladDescriptor(), retrieval.vlad.VladDescriptor(whiten=True)
    out = [Variant(f"vlad K={k} f=1000", "descriptor", vlad, dataclasses.replace(base, codebook_size=k))
           for k in (16, 32, 64, 128, 256)]
    out += [Variant(f"vlad K=64 f={f}", "descriptor", vlad, dataclasses.replace(base, features_per_image=f))
            for f in (500, 2000, 4000)]
    out += [Variant(f"vlad K={k} f=2000", "descriptor", vlad,
                    dataclasses.replace(base, codebook_size=k, features_per_image=2000)) for k in (128, 256)]
    out += [Variant("vlad K=64 f=all", "descriptor", vlad, dataclasses.replace(base, features_per_image=0))]
    out += [Variant("vlad K=64 f=1000 +pca-white", "descriptor", white, base)]
    out += [Variant("bow tf-idf 1024 f=1000", "descriptor", retrieval.vlad.BowDescriptor(), base)]
    out += [Variant("oracle: top-k by gt matches", "oracle")]
    out += [Variant("colmap vocabtree 4096 f=all", "vocabtree", vocab_words=4096, vocab_max_features=-1)]
    out += [Variant("colmap vocabtree 4096 f=1000", "vocabtree", vocab_words=4096, vocab_max_features=1000)]
    return out


# ---------------------------------------------------------------------------------------------
# pycolmap's vocabulary tree (measurement only): built from the collection, queried per image
# ---------------------------------------------------------------------------------------------


def vocabtree_rankings(db_src: Path, features_path: Path, names: list[str], variant: Variant,
                       max_k: int, seed: int = 0) -> list[list[int]]:
    """Per image, indices of its retrieved images, best first, from COLMAP's VocabTreePairGenerator.

    The tree is built (20 k-means iterations, 1 round) on a random sample of at most
    `retrieval.CODEBOOK_SAMPLE_SIZE` raw uint8 SIFT descriptors cast to float (as COLMAP does);
    the database is copied to a temporary folder first, never opened in place.
    """
    import pycolmap

    rng = np.random.default_rng(seed)
    per_image = -(-retrieval.CODEBOOK_SAMPLE_SIZE // len(names))
    parts = []
    for name in names:  # raw uint8 SIFT, cast to float as COLMAP's own vocab_tree_builder does
        desc = read_features(features_path, name).descriptors
        pick = rng.choice(len(desc), min(per_image, len(desc)), replace=False)
        parts.append(desc[np.sort(pick)].astype(np.float32))
    raw = np.concatenate(parts)
    pycolmap.set_random_seed(seed)
    index = pycolmap.VisualIndex.create(128, 64)
    build = pycolmap.VisualIndex.BuildOptions()
    build.num_visual_words, build.num_iterations, build.num_rounds = variant.vocab_words, 20, 1
    index.build(build, pycolmap.FeatureDescriptorsFloat(type=pycolmap.FeatureExtractorType.SIFT, data=raw))
    with tempfile.TemporaryDirectory() as tmp:
        tree_path, db_path = Path(tmp) / "tree.bin", Path(tmp) / "database.db"
        index.write(str(tree_path))
        shutil.copyfile(db_src, db_path)
        opts = pycolmap.VocabTreePairingOptions()
        opts.vocab_tree_path = str(tree_path)
        opts.num_images = max_k + 1  # the query image finds itself
        opts.max_num_features = variant.vocab_max_features
        db = pycolmap.Database.open(str(db_path))
        try:
            id_to_name = {im.image_id: im.name for im in db.read_all_images()}
            gen = pycolmap.VocabTreePairGenerator(opts, db)
            ranked: dict[str, list[str]] = {}
            while not gen.has_finished():
                for a, b in gen.next():
                    if a != b:
                        ranked.setdefault(id_to_name[a], []).append(id_to_name[b])
        finally:
            db.close()
    index_of = {n: i for i, n in enumerate(names)}
    return [[index_of[m] for m in ranked.get(n, [])][:max_k] for n in names]


def oracle_rankings(counts: dict, names: list[str], max_k: int) -> list[list[int]]:
    """Per image, the other images by decreasing gt-consistent match count (ties: lower index)."""
    index_of = {n: i for i, n in enumerate(names)}
    matrix = np.full((len(names), len(names)), -1.0)
    for (a, b), n in counts.items():
        matrix[index_of[a], index_of[b]] = matrix[index_of[b], index_of[a]] = n
    np.fill_diagonal(matrix, -np.inf)
    return np.argsort(-matrix, axis=1, kind="stable")[:, :max_k].tolist()


def pairs_from_rankings(rankings: list[list[int]], k: int) -> np.ndarray:
    pairs = {tuple(sorted((i, j))) for i, row in enumerate(rankings) for j in row[:k] if i != j}
    return np.array(sorted(pairs), dtype=np.int64).reshape(-1, 2)


# ---------------------------------------------------------------------------------------------
# Measurement
# ---------------------------------------------------------------------------------------------


def ready_scenes(cache_root: Path, data_root: Path) -> list[str]:
    out = []
    for rec in sorted(cache_root.glob("*/.sara/extract.json")):
        scene = rec.parent.parent.name
        try:
            done = json.loads(rec.read_text()).get("done") is True
        except ValueError:
            done = False
        if done and (rec.parent.parent / "features.h5").exists() and (data_root / scene / "gt").is_dir():
            out.append(scene)
    return out


def gt_sets(counts: dict, names: list[str], min_matches: int) -> dict[str, set[tuple[int, int]]]:
    index_of = {n: i for i, n in enumerate(names)}

    def to_idx(pairs: set) -> set[tuple[int, int]]:
        return {tuple(sorted((index_of[a], index_of[b]))) for a, b in pairs}

    overlap = to_idx(gt_pairs.overlapping_pairs(counts, min_matches))
    strong = to_idx(gt_pairs.strong_pairs(counts, min_matches))
    edges = np.array(sorted(overlap), dtype=np.int64).reshape(-1, 2)
    weight = np.array([counts.get((names[i], names[j]), counts.get((names[j], names[i]), 0)) for i, j in edges],
                      dtype=np.float64)
    tree = {tuple(e) for e in edges[maximum_spanning_forest(len(names), edges, weight)].tolist()}
    return {"overlap": overlap, "strong": strong, "tree": tree}


def score(cands: np.ndarray, sets: dict[str, set], num_images: int) -> dict[str, float]:
    cand = {tuple(p) for p in cands.tolist()}
    total = num_images * (num_images - 1) // 2
    out = {"num_candidates": len(cand), "cand_pct": 100.0 * len(cand) / max(total, 1),
           "components": int(connected_components(num_images, cands).max()) + 1 if num_images else 0}
    for key, gt in sets.items():
        out[key] = len(cand & gt) / len(gt) if gt else float("nan")
    out["precision"] = len(cand & sets["overlap"]) / len(cand) if cand else float("nan")
    return out


def measure_scene(scene: str, cache_root: Path, data_root: Path, variants: list[Variant], args) -> list[dict]:
    features_path = cache_root / scene / "features.h5"
    names = list_names(features_path)
    t0 = time.perf_counter()
    counts = gt_pairs.gt_overlap_counts(data_root / scene / "gt", features_path, names,
                                        cache_dir=args.gt_cache, progress=not args.quiet)
    logger.info("%s: %d images, gt overlaps in %.1f s", scene, len(names), time.perf_counter() - t0)
    sets = gt_sets(counts, names, args.min_matches)
    rows = []
    for variant in variants:
        t0 = time.perf_counter()
        if variant.kind == "oracle":
            rankings = oracle_rankings(counts, names, max(K_VALUES))
            candidates: Callable[[int], np.ndarray] = partial(pairs_from_rankings, rankings)
        elif variant.kind == "vocabtree":
            rankings = vocabtree_rankings(cache_root / scene / "database.db", features_path, names, variant,
                                          max(K_VALUES), seed=args.seed)
            candidates = partial(pairs_from_rankings, rankings)
        else:
            desc = variant.backend.compute(features_path, names, variant.conf, progress=False, seed=args.seed)
            candidates = partial(retrieval.knn_pairs, desc)
        seconds = time.perf_counter() - t0
        for k in K_VALUES:
            rows.append({"scene": scene, "num_images": len(names), "variant": variant.name, "k": k,
                         "time_s": seconds, "num_overlapping": len(sets["overlap"]),
                         **score(candidates(k), sets, len(names))})
        logger.info("%s %-30s %.1f s  recall@k=10 %.3f", scene, variant.name, seconds,
                    next(r["overlap"] for r in rows[-len(K_VALUES):] if r["k"] == 10))
    return rows


# ---------------------------------------------------------------------------------------------
# Tables
# ---------------------------------------------------------------------------------------------


def scene_table(rows: list[dict], scene: str) -> str:
    sub = [r for r in rows if r["scene"] == scene]
    first = sub[0]
    head = (f"### {scene}: {first['num_images']} images, {first['num_overlapping']} overlapping pairs "
            f"of {first['num_images'] * (first['num_images'] - 1) // 2}\n\n"
            "recall / strong / tree (cand%) at each k; comps = components at k=5\n\n")
    lines = ["| variant | time s | " + " | ".join(f"k={k}" for k in K_VALUES) + " | comps |",
             "|---|---:|" + "---|" * len(K_VALUES) + "---:|"]
    for variant in dict.fromkeys(r["variant"] for r in sub):
        vr = {r["k"]: r for r in sub if r["variant"] == variant}
        cells = [f"{vr[k]['overlap']:.2f}/{vr[k]['strong']:.2f}/{vr[k]['tree']:.2f} ({vr[k]['cand_pct']:.0f}%)"
                 for k in K_VALUES]
        lines.append(f"| {variant} | {vr[K_VALUES[0]]['time_s']:.1f} | " + " | ".join(cells)
                     + f" | {vr[K_VALUES[0]]['components']} |")
    return head + "\n".join(lines) + "\n"


def summary_table(rows: list[dict]) -> str:
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    head = (f"### Mean over {len(scenes)} scenes ({', '.join(scenes)})\n\n"
            "recall / strong / tree (mean cand%) at each k; time = total seconds over the scenes\n\n")
    lines = ["| variant | time s | " + " | ".join(f"k={k}" for k in K_VALUES) + " |",
             "|---|---:|" + "---|" * len(K_VALUES)]
    for variant in dict.fromkeys(r["variant"] for r in rows):
        cells = []
        for k in K_VALUES:
            sel = [r for r in rows if r["variant"] == variant and r["k"] == k]
            mean = {key: float(np.nanmean([r[key] for r in sel])) for key in ("overlap", "strong", "tree", "cand_pct")}
            cells.append(f"{mean['overlap']:.3f}/{mean['strong']:.3f}/{mean['tree']:.3f} ({mean['cand_pct']:.0f}%)")
        seconds = sum(r["time_s"] for r in rows if r["variant"] == variant and r["k"] == K_VALUES[0])
        lines.append(f"| {variant} | {seconds:.1f} | " + " | ".join(cells) + " |")
    return head + "\n".join(lines) + "\n"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("cache_root", nargs="?", type=Path, default=REPO.parent / "cache")
    parser.add_argument("data_root", nargs="?", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--gt-cache", type=Path, default=None, help="default: CACHE_ROOT/gt_pairs")
    parser.add_argument("--out", type=Path, default=None, help="folder for results.json/.csv/.md")
    parser.add_argument("--scenes", default="", help="comma-separated subset of the ready scenes")
    parser.add_argument("--variants", default="", help="comma-separated substrings of variant names")
    parser.add_argument("--min-matches", type=int, default=gt_pairs.DEFAULT_MIN_MATCHES)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    args.gt_cache = args.gt_cache or args.cache_root / "gt_pairs"
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, format="%(message)s")
    colmap.send_log_to(None)  # COLMAP's own log: errors only
    scenes = ready_scenes(args.cache_root, args.data_root)
    if args.scenes:
        scenes = [s for s in scenes if s in args.scenes.split(",")]
    if not scenes:
        print(f"no scene with finished features under {args.cache_root}", file=sys.stderr)
        return 1
    variants = make_variants()
    if args.variants:
        variants = [v for v in variants if any(s in v.name for s in args.variants.split(","))]
    rows = [row for scene in scenes for row in measure_scene(scene, args.cache_root, args.data_root, variants, args)]
    text = summary_table(rows) + "\n" + "\n".join(scene_table(rows, s) for s in scenes)
    print(text)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "retrieval_recall.json").write_text(json.dumps(rows, indent=1) + "\n")
        (args.out / "retrieval_recall.md").write_text(text)
        with open(args.out / "retrieval_recall.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
