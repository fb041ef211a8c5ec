"""Bad input to the commands gives one line that says what is wrong and its documented exit code
(2: bad usage or input; see README, "Bad input"). The fault suite is test_faults.py."""

import subprocess
import sys
from pathlib import Path

import pytest


def sara(*args, cwd=None):
    proc = subprocess.run([sys.executable, "-m", "sara", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=300)
    return proc.returncode, proc.stdout, proc.stderr


def assert_one_line_error(rc, err, *fragments, code=2):
    assert rc == code, err
    assert "Traceback" not in err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("sara: error:")]
    assert len(lines) == 1, err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def test_missing_folder(tmp_path: Path):
    rc, _, err = sara("run", tmp_path / "nope", tmp_path / "out", "-q")
    assert_one_line_error(rc, err, "image folder not found")
    assert not (tmp_path / "out").exists()


def test_folder_without_images(tmp_path: Path):
    (tmp_path / "imgs").mkdir()
    (tmp_path / "imgs" / "notes.txt").write_text("hello")
    rc, _, err = sara("run", tmp_path / "imgs", tmp_path / "out", "-q")
    assert_one_line_error(rc, err, "no images found")


def test_images_without_any_feature_say_so_not_to_relax_thresholds(tmp_path: Path):
    import numpy as np
    from PIL import Image

    (tmp_path / "flat").mkdir()
    for k in range(3):
        Image.fromarray(np.full((96, 128, 3), 128, np.uint8)).save(tmp_path / "flat" / f"f{k}.png")
    rc, _, err = sara("run", tmp_path / "flat", tmp_path / "out", "-q")
    assert_one_line_error(rc, err, "3 of 3 images have no features (flat or featureless)", code=5)
    assert "relax" not in err


def test_unreadable_pairs_file(tmp_path: Path, synthetic_scene):
    images, _ = synthetic_scene
    pairs = tmp_path / "pairs.txt"
    pairs.write_bytes(b"\xff\xfe\x00garbage")
    rc, _, err = sara("run", images, tmp_path / "out", "--pairs", pairs, "-q")
    assert_one_line_error(rc, err, "not UTF-8")


def test_pairs_naming_unknown_images(tmp_path: Path, synthetic_scene):
    images, _ = synthetic_scene
    first = sorted(p.name for p in images.iterdir())[0]
    pairs = tmp_path / "pairs.txt"
    pairs.write_text(f"{first} ghost.png\n")
    rc, _, err = sara("run", images, tmp_path / "out", "--pairs", pairs, "-q")
    assert_one_line_error(rc, err, "'ghost.png' is not among the images")


def test_missing_pairs_source(tmp_path: Path, synthetic_scene):
    images, _ = synthetic_scene
    rc, _, err = sara("run", images, tmp_path / "out", "--pairs", tmp_path / "none.txt", "-q")
    assert_one_line_error(rc, err, "no such pairs file")


def test_bad_option(tmp_path: Path, synthetic_scene):
    images, _ = synthetic_scene
    rc, _, err = sara("run", images, tmp_path / "out", "-s", "retrieval.k=3", "-q")
    assert_one_line_error(rc, err, "unknown option 'retrieval.k'")


def test_evaluate_missing_gt(tmp_path: Path):
    (tmp_path / "model").mkdir()
    rc, _, err = sara("evaluate", tmp_path / "model", tmp_path / "gt")
    assert_one_line_error(rc, err)


def test_match_without_extract(tmp_path: Path):
    rc, _, err = sara("match", tmp_path / "out")
    assert_one_line_error(rc, err, "run `sara extract")



@pytest.mark.parametrize("command", ["run", "extract", "pairs", "match", "map", "evaluate", "demo", "bench"])
def test_help(command):
    rc, out, _ = sara(command, "--help")
    assert rc == 0 and "usage" in out


def test_an_error_caused_by_an_interrupt_is_reported_as_the_interrupt(monkeypatch, capsys, tmp_path) -> None:
    """A library may turn the interrupt raised inside it into its own error (poselib: RuntimeError
    when the import of its extension is interrupted); the user still gets the interrupt's line."""
    import signal

    from sara import cli

    def interrupted_import(args, stage=None):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise RuntimeError("Cannot import the C++ backend") from exc

    def terminated_then_wrapped(args, stage=None):
        cli._RECEIVED.append(signal.SIGTERM)  # as the handler records it; the chain is lost below
        raise RuntimeError("Cannot import the C++ backend")

    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:  # once interrupted, main ignores these signals: put this process's handlers back after
        monkeypatch.setattr(cli, "_cmd_run", interrupted_import)
        code = cli.main(["run", str(tmp_path), str(tmp_path / "out"), "-q"])
        err = capsys.readouterr().err
        assert code == 128 + signal.SIGINT and err.count("sara: error:") == 1 and "interrupted by SIGINT" in err

        monkeypatch.setattr(cli, "_cmd_run", terminated_then_wrapped)
        code = cli.main(["run", str(tmp_path), str(tmp_path / "out"), "-q"])
        err = capsys.readouterr().err
        assert code == 143 and "interrupted by SIGTERM" in err and "internal error" not in err
    finally:
        for signum, handler in saved.items():
            signal.signal(signum, handler)
