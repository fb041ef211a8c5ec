"""A backend is one file: a toy local-feature backend (OpenCV's SIFT, another library than COLMAP's)
and a toy matcher (mutual nearest neighbours), both defined and registered here, run `sara run`
end to end through the registries."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sara import features, matchers
from sara.cli import main
from sara.colmap import registered_images
from sara.descriptors import mutual_nearest_neighbours
from sara.features import Keypoints
from sara.io.h5 import Features


class ToyOpenCvSift:
    """OpenCV's SIFT: float descriptors, keypoints from another library than COLMAP."""

    name = "toy-cv-sift"

    def __init__(self, conf) -> None:
        import cv2

        self.sift = cv2.SIFT_create(nfeatures=conf.max_num_features)

    def extract(self, image: np.ndarray) -> Keypoints:
        import cv2

        kps, desc = self.sift.detectAndCompute(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), None)
        if desc is None:
            return Keypoints(np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros((0, 128), np.float32))
        xy = np.array([k.pt for k in kps], np.float32)  # OpenCV's pixel centres are integers, as hloc's
        return Keypoints(xy, np.array([k.size for k in kps], np.float32), desc.astype(np.float32))


class ToyMutualNN:
    name = "toy-nn"

    def __init__(self, conf, features: str) -> None:
        pass

    def match(self, feats0: Features, feats1: Features) -> tuple[np.ndarray, np.ndarray]:
        return mutual_nearest_neighbours(feats0.descriptors, feats1.descriptors)


#: the toy run's settings. The toy matcher's mutual neighbours hold many outliers: COLMAP's verification
#: runs RANSAC to its limit on each pair, its time grows with the matches. 400 keypoints and each image
#: with the next three (24 pairs): 2 s; 8192 keypoints (790 found) and the 45 exhaustive pairs: 20 s
TOY_RUN = ["-q", "--workers", "1", "-s", "extract.backend=toy-cv-sift", "-s", "extract.max_num_features=400",
           "-s", "sequential.overlap=3"]


@pytest.fixture(scope="module")
def toy_backends():
    features.BACKENDS.register("toy-cv-sift", ToyOpenCvSift)
    matchers.BACKENDS.register("toy-nn", ToyMutualNN)
    yield
    features.BACKENDS.unregister("toy-cv-sift")
    matchers.BACKENDS.unregister("toy-nn")


@pytest.fixture(scope="module")
def toy_run(toy_backends, synthetic_scene, tmp_path_factory) -> tuple[int, Path]:
    """`sara run` with the toy backends, once for the module: (exit code, output folder). Read it only."""
    images, _ = synthetic_scene
    out = tmp_path_factory.mktemp("toy") / "out"
    code = main(["run", str(images), str(out), *TOY_RUN, "-s", "match.backend=toy-nn", "--pairs", "sequential"])
    return code, out


def test_toy_backends_run_end_to_end(toy_run, synthetic_scene) -> None:
    images, _ = synthetic_scene
    code, out = toy_run
    assert code == 0
    assert (out / "features-toy-cv-sift.h5").is_file()
    num_images = len(list(images.iterdir()))
    assert len(registered_images(out / "sparse" / "0")) >= 0.8 * num_images


def test_unknown_backend_lists_the_valid_ones(synthetic_scene, tmp_path: Path, capsys) -> None:
    images, _ = synthetic_scene
    assert main(["run", str(images), str(tmp_path / "o"), "-q", "-s", "extract.backend=nope"]) == 2
    err = capsys.readouterr().err
    assert err.count("sara: error:") == 1 and "'nope'" in err and "sift, aliked-n16" in err


class RecordingExecutor:
    """Runs jobs here, as two workers would get them, and records each job's pairs."""

    workers = 2

    def __init__(self) -> None:
        self.jobs: list[int] = []

    def map(self, fn, items):
        for item in items:
            self.jobs.append(len(item.pairs))
            yield fn(item)


def test_match_stage_keeps_every_worker_busy_and_run_settings_keep_matches(toy_run, tmp_path: Path) -> None:
    import shutil

    from sara import match
    from sara.config import MatchConfig
    from sara.io import records

    code, finished = toy_run
    assert code == 0
    out = Path(shutil.copytree(finished, tmp_path / "out"))
    pairs_path, db, feats = out / "pairs.txt", out / "database.db", out / "features-toy-cv-sift.h5"
    num_pairs = len(pairs_path.read_text().split("\n")) - 1
    # fewer pairs than one chunk: split so that both workers get several chunks each
    executor = RecordingExecutor()
    match.run(MatchConfig(backend="toy-nn", chunk_size=128), pairs_path, db, out, features_path=feats,
              features_backend="toy-cv-sift", executor=executor, progress=False, overwrite=True)
    assert sum(executor.jobs) == num_pairs
    assert max(executor.jobs) == math.ceil(num_pairs / (2 * match.CHUNKS_PER_WORKER))
    assert len(executor.jobs) >= 2 * match.CHUNKS_PER_WORKER - 1
    # chunk size, threads and device change how matching runs, not its result: nothing is redone
    again = RecordingExecutor()
    match.run(MatchConfig(backend="toy-nn", chunk_size=3, num_threads=1, device="cpu"), pairs_path, db, out,
              features_path=feats, features_backend="toy-cv-sift", executor=again, progress=False)
    assert again.jobs == []
    assert records.is_done(out, match.STAGE, records.read_record(out, match.STAGE)["key"])


class AnyJobExecutor:
    """Runs jobs here, as two workers would get them, and records them."""

    workers = 2

    def __init__(self) -> None:
        self.jobs: list = []

    def map(self, fn, items):
        for item in items:
            self.jobs.append(item)
            yield fn(item)


class ToyGpuNN(ToyMutualNN):
    """The toy matcher, saying it runs on a GPU (it does not: nothing here needs one)."""

    name = "toy-gpu-nn"
    device = "cuda"


class ToyGpuSift(ToyOpenCvSift):
    name = "toy-gpu-sift"
    device = "cuda:0"


def test_networks_on_a_gpu_run_in_the_driver_not_in_every_worker(toy_backends, synthetic_scene,
                                                                  tmp_path: Path) -> None:
    from sara import colmap, extract, match
    from sara.config import ExtractConfig, MatchConfig
    from sara.io.images import scan_images

    features.BACKENDS.register("toy-gpu-sift", ToyGpuSift)
    matchers.BACKENDS.register("toy-gpu-nn", ToyGpuNN)
    try:
        images, _ = synthetic_scene
        out = tmp_path / "out"
        executor = AnyJobExecutor()
        # 400 keypoints, as TOY_RUN: the toy matches' verification is quick
        extract.run(ExtractConfig(backend="toy-gpu-sift", max_num_features=400), scan_images(images, progress=False),
                    out, executor=executor, progress=False)
        assert executor.jobs == []  # no extraction job went to a worker
        feats = out / "features-toy-gpu-sift.h5"
        assert feats.is_file()
        names = sorted(p.name for p in images.iterdir())
        pairs_path = out / "pairs.txt"
        pairs_path.write_text("".join(f"{a} {b}\n" for a, b in zip(names, names[1:])))
        match.run(MatchConfig(backend="toy-gpu-nn"), pairs_path, out / "database.db", out, features_path=feats,
                  features_backend="toy-gpu-sift", executor=executor, progress=False)
        assert executor.jobs == []  # nor any matching job
        assert len(colmap.verified_image_pairs(out / "database.db")) == len(names) - 1
    finally:
        features.BACKENDS.unregister("toy-gpu-sift")
        matchers.BACKENDS.unregister("toy-gpu-nn")
