"""`sara extract` against plain pycolmap SIFT extraction on the same images, back to back.

Plain: a new COLMAP database, `pycolmap.import_images` with one shared camera (what sara does for
images of one size), `pycolmap.extract_features` with the options sara passes (max_image_size,
max_num_features, CPU) and nothing else. sara: the real entry point, `sara extract IMAGES OUT -q`
in a fresh output folder, so everything it does is counted (digests, the image check, the
features file, the focal check). Each round runs both, alternating which goes first; the ratio is
taken per round and the median reported, for the wall time and for the CPU time (user + system,
of this process for plain pycolmap, of the `sara` process and its children for sara): on a machine
shared with other work the CPU time is the steadier of the two.

The in-process plain call is timed after `import pycolmap`, where `sara extract` (a command)
pays for starting Python and its imports. With `--script`, each round also runs plain pycolmap as
a script in a new Python process (`python THIS --plain-only ...`: the interpreter, `import pycolmap`
and the same calls, nothing of sara imported), what a user who writes that script waits for, and
reports `script_ratio` and `script_cpu_ratio` beside the others.

    python lab/scripts/extract_vs_pycolmap.py IMAGES WORK [--rounds 2] [--threads -1] [--script]
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pycolmap


def _cpu(who: int) -> float:
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def _sara_settings() -> list[str]:
    from sara.config import make_config

    conf = make_config("sift-offline").extract
    return [conf.camera_model, str(conf.max_image_size), str(conf.max_num_features)]


def _extract_plain(images: Path, db: Path, threads: int, camera_model: str, max_image_size: int,
                   max_num_features: int) -> None:
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    opts = pycolmap.FeatureExtractionOptions()
    opts.max_image_size = max_image_size
    opts.num_threads = threads
    opts.sift.max_num_features = max_num_features
    pycolmap.extract_features(str(db), str(images), camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=opts, device=pycolmap.Device.cpu)


def plain(images: Path, work: Path, threads: int) -> tuple[float, float]:
    camera_model, max_image_size, max_num_features = _sara_settings()
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    tic, cpu = time.perf_counter(), _cpu(resource.RUSAGE_SELF)
    _extract_plain(images, work / "database.db", threads, camera_model, int(max_image_size), int(max_num_features))
    return time.perf_counter() - tic, _cpu(resource.RUSAGE_SELF) - cpu


def script(images: Path, work: Path, threads: int) -> tuple[float, float]:
    settings = _sara_settings()
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    tic, cpu = time.perf_counter(), _cpu(resource.RUSAGE_CHILDREN)
    cmd = [sys.executable, __file__, "--plain-only", str(images), str(work / "database.db"), str(threads), *settings]
    subprocess.run(cmd, check=True, capture_output=True)
    return time.perf_counter() - tic, _cpu(resource.RUSAGE_CHILDREN) - cpu


def sara(images: Path, work: Path, threads: int) -> tuple[float, float]:
    shutil.rmtree(work, ignore_errors=True)
    tic, cpu = time.perf_counter(), _cpu(resource.RUSAGE_CHILDREN)
    cmd = [sys.executable, "-m", "sara", "extract", str(images), str(work), "-q",
           "-s", f"extract.num_threads={threads}"]
    subprocess.run(cmd, check=True, capture_output=True)
    return time.perf_counter() - tic, _cpu(resource.RUSAGE_CHILDREN) - cpu


def main() -> None:
    if sys.argv[1:2] == ["--plain-only"]:  # the script a user would write; nothing of sara imported
        images, db, threads, camera_model, max_image_size, max_num_features = sys.argv[2:8]
        _extract_plain(Path(images), Path(db), int(threads), camera_model, int(max_image_size), int(max_num_features))
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("images", type=Path)
    ap.add_argument("work", type=Path)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--threads", type=int, default=-1)
    ap.add_argument("--script", action="store_true", help="also time plain pycolmap as a script of its own")
    args = ap.parse_args()
    rows = []
    for r in range(args.rounds):
        order = [("plain", plain), ("sara", sara)] if r % 2 == 0 else [("sara", sara), ("plain", plain)]
        if args.script:
            order.insert(r % 3, ("script", script))
        found = {name: fn(args.images, args.work / name, args.threads) for name, fn in order}
        row = {"round": r, "plain_s": found["plain"][0], "sara_s": found["sara"][0],
               "plain_cpu_s": found["plain"][1], "sara_cpu_s": found["sara"][1]}
        row["ratio"] = row["sara_s"] / row["plain_s"]
        row["cpu_ratio"] = row["sara_cpu_s"] / row["plain_cpu_s"]
        if args.script:
            row.update(script_s=found["script"][0], script_cpu_s=found["script"][1])
            row["script_ratio"] = row["sara_s"] / row["script_s"]
            row["script_cpu_ratio"] = row["sara_cpu_s"] / row["script_cpu_s"]
        rows.append(row)
        print(json.dumps({k: round(v, 3) for k, v in row.items()}), flush=True)

    def median(key: str) -> float:
        values = sorted(row[key] for row in rows)
        return round(values[len(values) // 2], 3)

    print(json.dumps({"images": str(args.images.parent.name or args.images.name), "rounds": len(rows),
                      "median_ratio": median("ratio"), "median_cpu_ratio": median("cpu_ratio"),
                      "ratios": sorted(round(row["ratio"], 3) for row in rows),
                      "cpu_ratios": sorted(round(row["cpu_ratio"], 3) for row in rows),
                      **({"median_script_ratio": median("script_ratio"),
                          "median_script_cpu_ratio": median("script_cpu_ratio"),
                          "script_ratios": sorted(round(row["script_ratio"], 3) for row in rows)}
                         if args.script else {})}))


if __name__ == "__main__":
    main()
