"""Hash-based descriptors: no table, the same RootSIFT-like vector for a key every time, observed
with a drift that grows with the viewing angle and the distance."""

from __future__ import annotations

import math

import numpy as np

from .config import DESCRIPTOR_DIM, STYLE_KEY_BIT, WorldConfig

_SM_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_SM_M1 = np.uint64(0xBF58476D1CE4E5B9)
_SM_M2 = np.uint64(0x94D049BB133111EB)


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser, element-wise on a uint64 array (wraps modulo 2^64)."""
    x = x + _SM_GAMMA
    x = (x ^ (x >> np.uint64(30))) * _SM_M1
    x = (x ^ (x >> np.uint64(27))) * _SM_M2
    return x ^ (x >> np.uint64(31))


def _hash_uniform(keys: np.ndarray, seed: int, dim: int = DESCRIPTOR_DIM) -> np.ndarray:
    """(K,) uint64 keys -> (K, dim) float32 uniforms in (0, 1), four 16-bit draws per 64-bit hash."""
    keys = np.asarray(keys, dtype=np.uint64)
    mixed = _splitmix64(keys ^ _splitmix64(np.full(1, seed, dtype=np.uint64)))
    words = -(-dim // 4)
    bits = _splitmix64(mixed[:, None] + np.arange(1, words + 1, dtype=np.uint64)[None, :])
    parts = bits.view(np.uint16).reshape(len(keys), words * 4)[:, :dim]
    return (parts.astype(np.float32) + 0.5) / 65536.0


def base_descriptors(keys: np.ndarray, seed: int) -> np.ndarray:
    """(K,) keys -> (K, 128) float32 unit RootSIFT-like vectors (non-negative entries)."""
    hist = (-np.log(_hash_uniform(keys, seed))) ** 1.5
    hist /= hist.sum(axis=1, keepdims=True)
    return np.sqrt(hist)


# A fixed permutation per drift direction: the drift of a point is its own vector, shuffled and
# centred, so it costs no more hashing and is the same in every image.
_PERM_VIEW = np.random.default_rng(101).permutation(DESCRIPTOR_DIM)
_PERM_SCALE = np.random.default_rng(202).permutation(DESCRIPTOR_DIM)


def point_descriptors(keys: np.ndarray, point_ids: np.ndarray, conf: WorldConfig) -> np.ndarray:
    """(K,) descriptor keys and point ids (-1: none) -> (K, 128) float32 unit descriptors of the points.

    A repeated point (its key a style word) is its word's vector plus ``repeat_jitter`` times a
    centred vector of its own: look-alike, as windows of one facade are, but not identical.
    """
    base = base_descriptors(keys, conf.seed)
    repeated = np.flatnonzero((np.asarray(keys, np.uint64) & STYLE_KEY_BIT) != 0)
    if conf.repeat_jitter > 0 and len(repeated):
        own = base_descriptors(np.asarray(point_ids)[repeated].astype(np.uint64), conf.seed + 1)
        own -= own.mean(axis=1, keepdims=True)
        mixed = np.maximum(base[repeated] + conf.repeat_jitter * own, 0.0)
        base[repeated] = mixed / np.maximum(np.linalg.norm(mixed, axis=1, keepdims=True), 1e-9)
    return base


def observe_descriptors(keys: np.ndarray, view_angle_rad: np.ndarray, log_distance: np.ndarray,
                        rng: np.random.Generator, conf: WorldConfig, point_ids: np.ndarray | None = None) -> np.ndarray:
    """(K,) keys and viewing conditions -> (K, 128) uint8 noisy observations (RootSIFT x 512, clipped)."""
    base = point_descriptors(keys, np.full(len(keys), -1) if point_ids is None else point_ids, conf)
    if len(base) == 0:
        return np.zeros((0, DESCRIPTOR_DIM), np.uint8)
    centred = base - base.mean(axis=1, keepdims=True)
    drift_v = centred[:, _PERM_VIEW]
    drift_v /= np.maximum(np.linalg.norm(drift_v, axis=1, keepdims=True), 1e-9)
    drift_s = centred[:, _PERM_SCALE]
    drift_s /= np.maximum(np.linalg.norm(drift_s, axis=1, keepdims=True), 1e-9)
    sigma = conf.descriptor_noise * np.exp(0.2 * rng.standard_normal(len(base), dtype=np.float32))
    noise = rng.standard_normal(base.shape, dtype=np.float32) * (sigma / math.sqrt(DESCRIPTOR_DIM))[:, None]
    obs = base + noise
    obs += (conf.view_drift * view_angle_rad.astype(np.float32))[:, None] * drift_v
    obs += (conf.scale_drift * log_distance.astype(np.float32))[:, None] * drift_s
    np.maximum(obs, 0.0, out=obs)
    obs /= np.maximum(np.linalg.norm(obs, axis=1, keepdims=True), 1e-9)
    return np.minimum(np.rint(obs * 512.0), 255.0).astype(np.uint8)
