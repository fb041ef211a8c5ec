"""The evaluator's relative pose errors, computed block by block, are those of all pairs at once."""

import numpy as np
import pytest

from sara.evaluation.metrics import _pair_blocks, relative_pose_errors


@pytest.mark.parametrize("num, block", [(2, 1), (7, 1), (7, 4), (7, 100), (50, 37)])
def test_pair_blocks_cover_the_upper_triangle_in_its_order(num, block):
    first, second = (np.concatenate(parts) for parts in zip(*_pair_blocks(num, block)))
    expected = np.triu_indices(num, 1)
    assert np.array_equal(first, expected[0]) and np.array_equal(second, expected[1])


def _random_poses(rng, names):
    poses = {}
    for name in names:
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        poses[name] = (q * np.sign(np.linalg.det(q)), rng.normal(size=3))
    return poses


def test_relative_pose_errors_do_not_depend_on_the_block_size():
    rng = np.random.default_rng(0)
    names = [f"{k:03d}.png" for k in range(30)]
    est, gt = _random_poses(rng, names), _random_poses(rng, names[::2] + names[1:5])
    whole = relative_pose_errors(est, gt, names, block_pairs=10**9)
    assert whole[0].size == 17 * 16 // 2  # the 17 names in both
    for block in (1, 5, 64):
        parts = relative_pose_errors(est, gt, names, block_pairs=block)
        assert np.array_equal(parts[0], whole[0]) and np.array_equal(parts[1], whole[1])
