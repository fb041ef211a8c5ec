from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "2")



@pytest.fixture(scope="session")
def synthetic_scene(tmp_path_factory):
    """A small rendered scene with known poses: (images folder, gt folder), 800x600 (the renderer's
    default; 1024x768 took SIFT 1.6x the time)."""
    from sara.synthetic import make_scene

    return make_scene(tmp_path_factory.mktemp("synthetic"), num_images=10, width=800, height=600)


@pytest.fixture(scope="session")
def five_view_scene(tmp_path_factory):
    """The synthetic scene with 5 views (10 pairs, each verified): (images folder, gt folder), for a
    test that extracts several times and needs a scene, not this one."""
    from sara.synthetic import make_scene

    return make_scene(tmp_path_factory.mktemp("small"), num_images=5, width=800, height=600)


@pytest.fixture(scope="session")
def finished_run_template(tmp_path_factory, synthetic_scene, scene_features) -> Path:
    """One finished `sara run --gt` of the synthetic scene for the whole session, made through the
    command line as a user makes it (report.html included), in a folder that starts with the
    scene's features (`scene_features`, as a bench method's does: one extraction for the session).
    Read it, never write into it: a test that changes a run takes `finished_run`, its own copy."""
    from harness import run_redirected
    from sara.pipeline import share_features

    images, gt = synthetic_scene
    out = tmp_path_factory.mktemp("finished") / "out"
    share_features(scene_features, out)
    result = run_redirected("run", images, out, "-q", "--gt", gt)
    assert result.code == 0, result.err
    return out


@pytest.fixture(scope="session")
def scene_features(tmp_path_factory, synthetic_scene) -> Path:
    """The synthetic scene's features alone (`sara extract`, the default preset), made once for the
    session. A test about a later stage starts its run from them, as bench methods share one
    extraction: `share_features(scene_features, out)` (sara.pipeline), then the run skips
    extraction. Read it, never write into it."""
    from harness import run_redirected

    images, _ = synthetic_scene
    out = tmp_path_factory.mktemp("features") / "out"
    result = run_redirected("extract", images, out, "-q")
    assert result.code == 0, result.err
    return out


@pytest.fixture
def finished_run(finished_run_template, tmp_path) -> Path:
    """This test's own copy of the finished run (`tmp_path / "out"`), free to change or damage."""
    return Path(shutil.copytree(finished_run_template, tmp_path / "out", symlinks=True))


@pytest.fixture
def run_cli(capfd):
    """`run_cli(*args) -> CliResult(code, out, err)`: `sara ARGS` in this process through
    `sara.cli.main`, its output captured at the file descriptors (native libraries' lines too)."""
    from harness import run_in_process

    return lambda *args: run_in_process(capfd, *args)
