"""Bad input to the commands gives one line that says what is wrong and its documented exit code
(2: bad usage or input; see README, "Bad input"), through the real entry point `sara.cli.main`.
Faults on a finished run (damaged state, full disks, signals) are the fault suite, tests/faults/."""

import os
import signal
import time
from pathlib import Path

import pytest

import sara.pipeline
from harness import assert_error
from sara.cli import EXIT_INTERRUPTED, EXIT_TERMINATED


def test_missing_folder(tmp_path: Path, run_cli):
    assert_error(run_cli("run", tmp_path / "nope", tmp_path / "out", "-q"), 2, "image folder not found")
    assert not (tmp_path / "out").exists()


def test_folder_without_images(tmp_path: Path, run_cli):
    (tmp_path / "imgs").mkdir()
    (tmp_path / "imgs" / "notes.txt").write_text("hello")
    assert_error(run_cli("run", tmp_path / "imgs", tmp_path / "out", "-q"), 2, "no images found")


def test_images_without_any_feature_say_so_not_to_relax_thresholds(tmp_path: Path, run_cli):
    import numpy as np
    from PIL import Image

    (tmp_path / "flat").mkdir()
    for k in range(3):
        Image.fromarray(np.full((96, 128, 3), 128, np.uint8)).save(tmp_path / "flat" / f"f{k}.png")
    result = run_cli("run", tmp_path / "flat", tmp_path / "out", "-q")
    assert_error(result, 5, "3 of 3 images have no features (flat or featureless)")
    assert "relax" not in result.err


def test_unreadable_pairs_file(tmp_path: Path, synthetic_scene, run_cli):
    images, _ = synthetic_scene
    pairs = tmp_path / "pairs.txt"
    pairs.write_bytes(b"\xff\xfe\x00garbage")
    assert_error(run_cli("run", images, tmp_path / "out", "--pairs", pairs, "-q"), 2, "not UTF-8")
    assert not (tmp_path / "out").exists()  # before any work: no features extracted first


def test_pairs_naming_unknown_images(tmp_path: Path, synthetic_scene, run_cli):
    images, _ = synthetic_scene
    first = sorted(p.name for p in images.iterdir())[0]
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{first} ghost.png\n")
    result = run_cli("run", images, tmp_path / "out", "--pairs", pairs, "-q")
    assert_error(result, 2, "'ghost.png' is not among the images")
    assert not (tmp_path / "out").exists()


def test_missing_pairs_source(tmp_path: Path, synthetic_scene, run_cli):
    images, _ = synthetic_scene
    result = run_cli("run", images, tmp_path / "out", "--pairs", tmp_path / "none.txt", "-q")
    assert_error(result, 2, "no such pairs file")


def test_evaluate_missing_gt(tmp_path: Path, run_cli):
    (tmp_path / "model").mkdir()
    assert_error(run_cli("evaluate", tmp_path / "model", tmp_path / "gt"), 2)


def test_match_without_extract(tmp_path: Path, run_cli):
    assert_error(run_cli("match", tmp_path / "out"), 2, "run `sara extract")


@pytest.mark.parametrize("command", ["run", "extract", "pairs", "match", "map", "evaluate", "demo", "bench"])
def test_help(command, run_cli):
    result = run_cli(command, "--help")
    assert result.code == 0 and "usage" in result.out


@pytest.fixture
def own_signal_handlers():
    """Once interrupted, `main` ignores further termination signals until it returns: this
    process's own handlers are put back after the test."""
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    yield
    for signum, handler in saved.items():
        signal.signal(signum, handler)


def test_an_error_caused_by_an_interrupt_is_reported_as_the_interrupt(monkeypatch, run_cli, tmp_path,
                                                                      own_signal_handlers) -> None:
    """A library may turn the interrupt raised inside it into its own error (poselib: RuntimeError
    when the import of its extension is interrupted); the user still gets the interrupt's line."""

    def interrupted_import(*args, **kwargs):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise RuntimeError("Cannot import the C++ backend") from exc

    monkeypatch.setattr(sara.pipeline, "run", interrupted_import)
    result = run_cli("run", tmp_path, tmp_path / "out", "-q")
    assert_error(result, EXIT_INTERRUPTED, "interrupted by SIGINT")


def test_a_termination_a_library_swallowed_is_still_reported(monkeypatch, run_cli, tmp_path,
                                                            own_signal_handlers) -> None:
    """A real SIGTERM whose exception a library caught and replaced by its own error, the chain
    lost: the command still reports the termination (exit 143), not an internal error."""

    def terminated_then_wrapped(*args, **kwargs):
        if not callable(signal.getsignal(signal.SIGTERM)):  # SIGTERM would end the test session
            pytest.fail("`sara.cli.main` installed no SIGTERM handler")
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:  # until the handler raises
                time.sleep(0.01)
        except KeyboardInterrupt:  # sara's Terminated; the library swallows it
            pass
        else:
            pytest.fail("SIGTERM did not reach the handler that `sara.cli.main` installs")
        raise RuntimeError("Cannot import the C++ backend")

    monkeypatch.setattr(sara.pipeline, "run", terminated_then_wrapped)
    result = run_cli("run", tmp_path, tmp_path / "out", "-q")
    assert_error(result, EXIT_TERMINATED, "interrupted by SIGTERM")
    assert "internal error" not in result.err

