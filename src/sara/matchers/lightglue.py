"""LightGlue (for ALIKED and DISK features) and LighterGlue (for XFeat) through kornia.

The network is built without weights (`features=None`, the per-feature configuration of
`kornia.feature.LightGlue.features`) and loaded from the file `sara.weights.find` names, so
kornia's download path is never taken. The released files use older key names, renamed here
(`self_attn.i` -> `transformers.i.self_attn`, `cross_attn.i` -> `transformers.i.cross_attn`); the
DISK file carries unused `log_assignment.*.r` scalars, and `xfeat-lighterglue.pt` holds an XFeat
copy beside the matcher's `matcher.*` entries, of which only the latter are kept.

LightGlue's adaptive defaults stay on: early stopping (`depth_confidence` 0.95) and point
pruning (`width_confidence` 0.99; LighterGlue: pruning 0.95, no early stopping), which make an
easy pair several times cheaper on a CPU; matches need a score above 0.1.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import weights
from ..config import MatchConfig
from ..io.h5 import Features
from . import resolve_name

if TYPE_CHECKING:
    import torch
    from torch import nn

logger = logging.getLogger(__name__)

#: local-feature backend -> (kornia's LightGlue configuration, weights key)
FEATURES: dict[str, tuple[str, str]] = {
    "aliked-n16": ("aliked", "lightglue-aliked"),
    "aliked-n16rot": ("aliked", "lightglue-aliked"),
    "aliked-n32": ("aliked", "lightglue-aliked"),
    "disk": ("disk", "lightglue-disk"),
    "xfeat": ("xfeat", "lighterglue-xfeat"),
}


def _renamed(state: dict[str, Any], num_layers: int) -> dict[str, Any]:
    """The released state dict in kornia's key layout (see the module docstring)."""
    if any(k.startswith("matcher.") for k in state):  # xfeat-lighterglue.pt: keep the matcher only
        state = {k.removeprefix("matcher."): v for k, v in state.items() if k.startswith("matcher.")}
    out = {}
    for key, value in state.items():
        if key.startswith("log_assignment.") and key.endswith(".r"):
            continue  # unused scalars of the DISK file
        for i in range(num_layers):
            key = key.replace(f"self_attn.{i}.", f"transformers.{i}.self_attn.")
            key = key.replace(f"cross_attn.{i}.", f"transformers.{i}.cross_attn.")
        out[key] = value
    return out


def build(kind: str, path: Path) -> nn.Module:
    """kornia's LightGlue for features `kind` ("aliked", "disk", "xfeat"), weights from `path`."""
    kf = weights.require("kornia.feature")
    conf = {**kf.LightGlue.features[kind], "weights": None}
    model = kf.LightGlue(features=None, **conf)
    state = _renamed(weights.load_state_dict(path), model.conf.n_layers)
    weights.load_into(model, state, path=path, allow_missing=("confidence_thresholds",))
    return model.eval()


class LightGlueMatcher:
    """Matches two images' features with LightGlue; see the module docstring."""

    def __init__(self, name: str, model: nn.Module, device: torch.device, dim: int) -> None:
        self.name = name
        self.device = device
        self.dim = dim
        self._model = model

    def _inputs(self, feats: Features) -> dict[str, torch.Tensor]:
        torch = weights.require("torch")
        desc = np.asarray(feats.descriptors)
        if desc.ndim != 2 or desc.shape[1] != self.dim:
            raise ValueError(f"{self.name} takes (N, {self.dim}) descriptors, got shape {desc.shape}")
        width, height = (float(v) for v in feats.image_size)
        # LightGlue rejects a keypoint outside the image; clipping to [0, size] moves no valid one
        xy = np.clip(np.asarray(feats.keypoints, np.float32), 0.0, [width, height]).astype(np.float32)
        return {
            "keypoints": torch.from_numpy(xy)[None].to(self.device),
            "descriptors": torch.from_numpy(desc.astype(np.float32))[None].to(self.device),
            "image_size": torch.tensor([[width, height]], device=self.device),
        }

    def match(self, feats0: Features, feats1: Features) -> tuple[np.ndarray, np.ndarray]:
        """(K, 2) int32 indices (i0, i1) and (K,) float32 match scores in (0.1, 1]."""
        if len(feats0.keypoints) == 0 or len(feats1.keypoints) == 0:
            return np.zeros((0, 2), np.int32), np.zeros(0, np.float32)
        torch = weights.require("torch")
        with torch.inference_mode():
            out = self._model({"image0": self._inputs(feats0), "image1": self._inputs(feats1)})
        matches = out["matches"][0].cpu().numpy().astype(np.int32).reshape(-1, 2)
        scores = out["scores"][0].float().cpu().numpy().astype(np.float32)
        return matches, scores


def make(conf: MatchConfig, features: str) -> LightGlueMatcher:
    """LightGlue for `features` ("aliked-*", "disk") or LighterGlue ("xfeat"), on `conf.device`.

    Raises:
        ValueError: no such network for these features (e.g. SIFT, or LighterGlue for ALIKED).
        sara.weights.WeightsNotFoundError: no weights file (before torch is imported).
    """
    name = resolve_name(conf, features)
    if features not in FEATURES:
        raise ValueError(f"{name} has weights for the features {', '.join(FEATURES)}, not {features!r}; "
                         "use match.backend=nearest for other features")
    kind, key = FEATURES[features]
    if (kind == "xfeat") != (name == "lighterglue"):
        usual = "lighterglue" if kind == "xfeat" else "lightglue"
        raise ValueError(f"{name} has no weights for {features} features; use match.backend={usual} (or auto)")
    path = weights.find(key, conf.weights)
    device = weights.resolve_device(conf.device)
    model = build(kind, path).to(device)
    logger.info("%s for %s on %s, weights %s", name, features, device, path)
    return LightGlueMatcher(name, model, device, dim=model.conf.input_dim)


def weights_needed(conf: MatchConfig, features: str) -> list[tuple[str, str]]:
    """(weights key, explicit path) that `make` will look up: checked before any work."""
    return [(FEATURES[features][1], conf.weights)] if features in FEATURES else []


make.weights_needed = weights_needed  # type: ignore[attr-defined]
