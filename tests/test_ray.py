"""The Ray executor on a real two-node Ray cluster on this machine (a head plus a second node joined
to it, both stopped at the end, and no other Ray node): the same pairs as a serial run, and a worker that dies
mid-run is replaced (its task runs again) and the run completes."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

pytest.importorskip("ray")
# pytest-xdist keeps this file's tests on one worker (`--dist loadfile` in pyproject.toml): they share
# one cluster (the module's fixture) instead of each worker starting its own.

from sara.cli import main  # noqa: E402


@pytest.fixture(scope="module")
def ray_cluster():
    """A head node and a worker node on localhost, one CPU each; yields the head's address. Ray's
    session folder is a short one under the system's temporary folder: its sockets' paths must stay
    under 108 bytes, which pytest's per-worker folders exceed."""
    from sara.execute_ray import local_cluster

    stack = contextlib.ExitStack()
    temp_dir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="ray")))
    try:
        address = stack.enter_context(local_cluster(2, 1, temp_dir))
    except (subprocess.CalledProcessError, subprocess.TimeoutExpired) as exc:
        stack.close()
        pytest.fail(f"could not start a local Ray cluster: {exc}; {(exc.stderr or b'')[-600:]!r}")
    with stack:
        yield address


def test_ray_cluster_gives_the_serial_pairs(ray_cluster, synthetic_scene, scene_features, tmp_path: Path,
                                           monkeypatch) -> None:
    from sara.pipeline import share_features

    images, _ = synthetic_scene
    serial, clustered = tmp_path / "serial", tmp_path / "ray"
    for out in (serial, clustered):  # COLMAP's SIFT runs in the driver: the runs start at pair selection
        share_features(scene_features, out)
    # 45 candidates in 6 shards: the scorer really runs on Ray. The pairs added for weakly matched
    # views depend on COLMAP's verified inlier counts, which vary by a few between identical runs
    # (multi-threaded RANSAC): off, so that pairs.txt compares the selection itself
    shards = ["-s", "execute.shard_size=8", "-s", "rounds.support_min_view_inliers=0"]
    assert main(["run", str(images), str(serial), "-q", "--workers", "1", *shards]) == 0
    monkeypatch.setenv("RAY_ADDRESS", ray_cluster)
    assert main(["run", str(images), str(clustered), "-q", "--executor", "ray", "--ray-address", "auto",
                 *shards]) == 0
    assert (clustered / "pairs.txt").read_bytes() == (serial / "pairs.txt").read_bytes()
    assert (clustered / "scores.csv").read_bytes() == (serial / "scores.csv").read_bytes()
    assert (clustered / "sparse" / "0").is_dir()


def test_a_local_cluster_stops_its_own_nodes_only(ray_cluster) -> None:
    """Leaving `local_cluster` ends the nodes it started; the cluster of the fixture (another user's
    on a shared machine) still runs a task. `ray stop --force`, used before, stopped both."""
    from sara.execute_ray import local_cluster

    with tempfile.TemporaryDirectory(prefix="ray") as temp_dir, local_cluster(1, 1, Path(temp_dir)) as other:
        assert other != ray_cluster
    probe = (f"import ray; ray.init(address={ray_cluster!r}, logging_level='ERROR'); "
             "print(ray.get(ray.remote(lambda: 'ran').remote()))")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120,
                            env={**os.environ, "RAY_USAGE_STATS_ENABLED": "0"})
    assert result.stdout.strip().endswith("ran"), result.stderr[-800:]


def _dies_once(item: tuple[str, int]) -> int:
    """Kills its own worker process the first time it sees item 2 (a marker file remembers)."""
    marker, value = item
    if value == 2 and not Path(marker).exists():
        Path(marker).touch()
        os._exit(1)
    return value * value


def test_a_dead_worker_is_replaced_and_the_work_completes(ray_cluster, tmp_path: Path) -> None:
    import ray.cloudpickle

    from sara.execute import make_executor

    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # workers cannot import this test file
    executor = make_executor("ray", 0, ray_cluster)
    try:
        marker = str(tmp_path / "died")
        assert list(executor.map(_dies_once, [(marker, v) for v in range(6)])) == [0, 1, 4, 9, 16, 25]
        assert Path(marker).exists()  # a worker really died on the way
    finally:
        executor.close()
    shutil.rmtree(tmp_path, ignore_errors=True)


@pytest.mark.slow  # each Ray worker imports torch and builds the network: 93 s on 2 busy cores
def test_learned_extraction_runs_on_the_ray_cluster(ray_cluster, synthetic_scene, tmp_path: Path,
                                                   monkeypatch) -> None:
    """XFeat's extraction spread over the two nodes (10 images in chunks of 8: two tasks) gives the
    features of a serial extraction in this process."""
    pytest.importorskip("torch")
    pytest.importorskip("kornia")
    import numpy as np

    from sara import extract, weights
    from sara.io.h5 import list_names, read_features

    try:
        weights.find("xfeat")
    except weights.WeightsNotFoundError as exc:
        pytest.skip(f"XFeat's weights are not installed: {exc}")
    images, _ = synthetic_scene
    serial, clustered = tmp_path / "serial", tmp_path / "ray"
    preset = ["--preset", "xfeat-lighterglue", "-s", "extract.max_image_size=320"]  # quick on a CPU
    assert main(["extract", str(images), str(serial), "-q", "--executor", "serial", *preset]) == 0
    monkeypatch.setenv("RAY_ADDRESS", ray_cluster)
    assert main(["extract", str(images), str(clustered), "-q", "--executor", "ray", "--ray-address", "auto",
                 *preset]) == 0
    assert extract.EXTRACT_CHUNK < 10  # more than one task
    one, two = serial / "features-xfeat.h5", clustered / "features-xfeat.h5"
    assert list_names(one) == list_names(two) and len(list_names(one)) == 10
    for name in list_names(one):
        a, b = read_features(one, name), read_features(two, name)
        assert len(a.keypoints) > 100
        assert np.allclose(a.keypoints, b.keypoints) and np.allclose(a.descriptors, b.descriptors, atol=1e-5)
