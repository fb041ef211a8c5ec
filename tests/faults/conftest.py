"""The fault suite (issue 11): bad input and faults, by class; nothing lost, nothing silently wrong.

Every case runs a `sara` command (in this process through `run_cli`, or as a subprocess where a
signal or a kill is the point) on `finished_run`, a copy of one finished run, then checks the exit
code, that stderr holds exactly one `sara: error:` line (naming the problem and the fix) and no
traceback or native stack dump, and that the previous outputs are byte-identical where they should
be. One file per class of fault:

    test_faults_resume.py     resume trusts state it should not (damaged or unfinished outputs)
    test_faults_no_result.py  a failed or degenerate run never destroys a good one
    test_faults_names.py      file names: odd, unusable, in pairs files, end to end
    test_faults_folder.py     what else is in the image folder: output folders, files not used, HEIC
    test_faults_decoders.py   files that one decoder reads and another does not
    test_faults_disk.py       the file system: paths, write errors, full and read-only disks, umask
    test_faults_signals.py    signals during a run, then resume
    test_faults_options.py    options and commands: ranges, usage, evaluate, too few images
    test_faults_slow.py       the slow ones (`-m slow`): signals during extraction, kills while matching
"""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture
def images(synthetic_scene) -> Path:
    """The synthetic scene's image folder."""
    return synthetic_scene[0]


@pytest.fixture
def spaced_folder(images, tmp_path) -> Path:
    """The scene's images, the first ones renamed to `SPACED_NAMES`."""
    import shutil

    from harness import SPACED_NAMES

    folder = tmp_path / "spaced"
    folder.mkdir()
    for k, path in enumerate(sorted(images.iterdir())):
        shutil.copyfile(path, folder / (SPACED_NAMES[k] if k < len(SPACED_NAMES) else path.name))
    return folder
