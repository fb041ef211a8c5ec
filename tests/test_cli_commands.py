"""The commands work through the real entry point (`sara.cli.main`, `python -m sara`, the `sara`
script of pyproject.toml) on a finished run, none can be dropped from the parser without a test
failing, and an exception that is not a user error is an internal error: exit 1, one line that says
it is a bug."""

from __future__ import annotations

import errno
import sqlite3
import subprocess
import sys
from importlib import metadata

import pytest

from harness import assert_ok, registered
from sara import cli
from sara.cli.parser import build_parser, commands_without_handler, subcommands

#: every command of `sara`; a command dropped from the parser (or added without a test) fails here
COMMANDS = {"run", "extract", "pairs", "match", "map", "evaluate", "export", "report", "demo", "weights", "bench"}


# ---------------------------------------------------------------------------------------------
# Dispatch: each command carries its handler
# ---------------------------------------------------------------------------------------------


def test_the_parser_has_every_command_and_each_has_a_handler():
    parser = build_parser()
    assert set(subcommands(parser)) == COMMANDS
    assert commands_without_handler(parser) == []
    for name, sub in subcommands(parser).items():
        assert callable(sub.get_default("handler")), name


def test_a_command_without_a_handler_stops_every_command(monkeypatch):
    """The check that would have caught `export` and `report` falling out of the dispatch table."""
    from sara.cli import parser as cli_parser

    def report_without_handler(sub):
        sub.add_parser("report")

    monkeypatch.setitem(cli_parser._COMMANDS, "report", report_without_handler)
    with pytest.raises(RuntimeError, match="commands without a handler: report"):
        cli_parser.build_parser()
    with pytest.raises(RuntimeError, match="commands without a handler: report"):
        cli_parser.build_parser(["report", "OUT"])


def test_a_command_builds_only_its_own_parser():
    """`sara extract` does not import what other commands' choices need (bench's methods, the
    export formats): a tenth of a second on every command; the full parser still lists them all."""
    code = ("import sys; from sara.cli.parser import build_parser, subcommands; "
            "args = build_parser(['extract', 'IMAGES', 'OUT']).parse_args(['extract', 'IMAGES', 'OUT']); "
            "print(args.command, 'sara.bench' in sys.modules, 'sara.export' in sys.modules); "
            "print(len(subcommands(build_parser(['--help']))), len(subcommands(build_parser(['nonsense']))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["extract", "False", "False", str(len(COMMANDS)), str(len(COMMANDS))]


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_help_of_every_command(command, run_cli):
    result = run_cli(command, "--help")
    assert result.code == 0 and f"usage: sara {command}" in result.out


def test_choices_come_from_the_registries():
    from sara.config import PRESETS
    from sara.execute import EXECUTORS
    from sara.export import FORMATS

    commands = subcommands(build_parser())
    choices = {action.dest: action.choices for action in commands["run"]._actions if action.choices}
    assert list(choices["export"]) == FORMATS.names()
    assert list(choices["preset"]) == list(PRESETS)
    assert list(choices["executor"]) == EXECUTORS.names()
    export_choices = {a.dest: a.choices for a in commands["export"]._actions if a.choices}
    assert list(export_choices["format"]) == FORMATS.names()


# ---------------------------------------------------------------------------------------------
# The commands of the README on a finished run
# ---------------------------------------------------------------------------------------------

EXPORTED = {
    "3dgs": ["images", "sparse/0/cameras.bin", "sparse/0/images.bin", "sparse/0/points3D.bin"],
    "nerfstudio": ["images", "transforms.json", "sparse_pc.ply"],
    "colmap": ["database.db", "project.ini", "sparse/0/images.bin"],
}


@pytest.mark.parametrize("fmt", sorted(EXPORTED))
def test_export_from_the_command_line(fmt, finished_run, tmp_path, run_cli):
    dest = tmp_path / "dest"
    result = run_cli("export", finished_run, dest, "--format", fmt, "-q")
    assert_ok(result)
    assert f"{fmt} export of {finished_run / 'sparse' / '0'} -> {dest}" in result.out
    for name in EXPORTED[fmt]:
        assert (dest / name).exists(), name
    if "images" in EXPORTED[fmt]:
        assert len(list((dest / "images").iterdir())) == len(registered(finished_run))


def test_report_from_the_command_line(finished_run, run_cli):
    (finished_run / "report.html").unlink()
    result = run_cli("report", finished_run)
    assert_ok(result)
    assert result.out.strip() == f"report: {finished_run / 'report.html'}"
    assert "<html" in (finished_run / "report.html").read_text(encoding="utf-8")


def test_run_with_export_resumes_and_exports(finished_run, synthetic_scene, run_cli):
    images, _ = synthetic_scene
    result = run_cli("run", images, finished_run, "-q", "--export", "nerfstudio")
    assert_ok(result)
    assert (finished_run / "nerfstudio" / "transforms.json").exists()
    assert f"nerfstudio export -> {finished_run / 'nerfstudio'}" in result.out


def test_python_dash_m_sara_and_the_script_entry_point(finished_run_template):
    """`python -m sara` runs the CLI (a real process), and pyproject's `sara = "sara.cli:main"` loads it."""
    proc = subprocess.run([sys.executable, "-m", "sara", "evaluate", str(finished_run_template),
                           str(finished_run_template / "sparse" / "0")], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "num_registered" in proc.stdout
    scripts = [ep for ep in metadata.entry_points(group="console_scripts") if ep.name == "sara"]
    if scripts:  # the package is installed (editable or not): its script is the same function
        assert scripts[0].value == "sara.cli:main" and scripts[0].load() is cli.main


# ---------------------------------------------------------------------------------------------
# Errors: a bug is exit 1 and says so; only the user's errors are 2-5
# ---------------------------------------------------------------------------------------------


def _raise(exc: BaseException):
    def fail(*args, **kwargs):
        raise exc

    return fail


BUGS = {
    "KeyError": KeyError("image_id"),
    "ZeroDivisionError": ZeroDivisionError("division by zero"),
    "IndexError": IndexError("index 7 is out of bounds for axis 0 with size 7"),
    "TypeError": TypeError("unsupported operand type(s) for +: 'int' and 'NoneType'"),
    "AttributeError": AttributeError("'NoneType' object has no attribute 'names'"),
}


@pytest.mark.parametrize("name", sorted(BUGS))
def test_an_unexpected_exception_is_an_internal_error(name, finished_run, tmp_path, monkeypatch, run_cli):
    """A stage that raises what no user can cause: exit 1 and exactly one stderr line saying it is a bug."""
    import sara.export.gaussian_splatting

    monkeypatch.setattr(sara.export.gaussian_splatting, "write", _raise(BUGS[name]))
    result = run_cli("export", finished_run, tmp_path / "dest", "--format", "3dgs", "-q")
    assert result.code == 1, result.err
    lines = result.err.strip().splitlines()
    assert len(lines) == 1, result.err
    assert lines[0].startswith(f"sara: error: internal error: {name}: "), lines[0]
    assert str(BUGS[name]).strip("'") in lines[0]
    assert "a bug" in lines[0] and "please report" in lines[0]


def test_an_unexpected_exception_in_the_report_shows_its_traceback_with_verbose(finished_run, monkeypatch,
                                                                                  run_cli):
    import sara.report.html

    monkeypatch.setattr(sara.report.html, "write_report", _raise(ZeroDivisionError("division by zero")))
    quiet = run_cli("report", finished_run)
    assert quiet.code == 1 and quiet.err.strip().splitlines() == [
        "sara: error: internal error: ZeroDivisionError: division by zero (a bug: please report it with the "
        "command that caused it; -v shows the traceback)"]
    verbose = run_cli("report", finished_run, "-v")
    assert verbose.code == 1 and "Traceback" in verbose.err and "ZeroDivisionError" in verbose.err
    assert len(verbose.error_lines) == 1


def _mapping_cases() -> dict[str, tuple[BaseException, int]]:
    from sara.colmap import ColmapError
    from sara.config import ConfigError
    from sara.io import DamagedOutputError, NoResultError, OutputStateError
    from sara.weights import MissingExtraError

    return {
        # the user's errors
        "bad value": (ValueError("no images found in x"), 2),
        "option out of range": (ConfigError("seed", "seed must be an integer from 0"), 2),
        "missing extra": (MissingExtraError("pip install 'sara[learned]'"), 2),
        "missing file": (FileNotFoundError(errno.ENOENT, "No such file or directory", "x"), 2),
        "output folder state": (OutputStateError("made from other images"), 3),
        "damaged output": (DamagedOutputError("pairs.txt was changed"), 3),
        "damaged database": (sqlite3.DatabaseError("database disk image is malformed"), 3),
        "unreadable HDF5": (OSError("Unable to open file (truncated file)"), 3),
        "full database": (sqlite3.OperationalError("database or disk is full"), 4),
        "disk full": (OSError(errno.ENOSPC, "No space left on device", "x"), 4),
        "permission": (PermissionError(errno.EACCES, "Permission denied", "x"), 4),
        "out of memory": (MemoryError(), 4),
        "no result": (NoResultError("no model could be built"), 5),
        # COLMAP's own failure: its message (it names the log), exit 1
        "COLMAP": (ColmapError("COLMAP's mapper failed: see logs/colmap.log"), 1),
        # bugs
        "KeyError": (KeyError("x"), 1),
        "LookupError": (LookupError("x"), 1),
        "IndexError": (IndexError("x"), 1),
        "TypeError": (TypeError("x"), 1),
        "AttributeError": (AttributeError("x"), 1),
        "AssertionError": (AssertionError(), 1),
        "RuntimeError": (RuntimeError("x"), 1),
        "ImportError": (ImportError("cannot import name 'x'"), 1),
        "NotImplementedError": (NotImplementedError(), 1),
        "RecursionError": (RecursionError(), 1),
    }


def test_the_error_mapping():
    from sara.cli.errors import describe_error

    wrong = {}
    for case, (exc, code) in _mapping_cases().items():
        got, message = describe_error(exc)
        if got != code or not message or "\n" in message:
            wrong[case] = (got, message)
        bug = code == 1 and case != "COLMAP"
        if bug != message.startswith("internal error:"):
            wrong[case] = (got, message)
    assert not wrong, wrong


def test_map_with_overwrite_maps_again(finished_run, run_cli):
    """`sara map OUT --overwrite` maps again; without it a model that is up to date is kept (the
    option was accepted and ignored: the model was kept either way)."""
    kept = run_cli("map", finished_run, "-v")
    assert_ok(kept)
    assert "model up to date, skipping" in kept.err
    again = run_cli("map", finished_run, "--overwrite", "-v")
    assert_ok(again)
    assert "model up to date, skipping" not in again.err
    assert len(registered(finished_run)) == 10


def test_match_with_overwrite_matches_again(finished_run, run_cli):
    """`sara match OUT --overwrite` matches every pair again (the option was accepted and ignored)."""
    from sara.io import records

    kept = run_cli("match", finished_run, "-q")
    assert_ok(kept)
    before = records.done_info(finished_run, "match")
    again = run_cli("match", finished_run, "--overwrite", "-q")
    assert_ok(again)
    after = records.done_info(finished_run, "match")
    assert after["num_pairs"] == before["num_pairs"] and after["time_s"] != before["time_s"]


def test_colmaps_log_reaches_its_file_at_once(tmp_path):
    """COLMAP's log lines are written as they come, not buffered for up to 30 s by glog: the log
    that a failure names holds its last lines, and a second run's log file in the same process is
    not left empty (a fresh process: glog reads the setting when pycolmap loads)."""
    import os
    import subprocess
    import sys

    code = (
        "import sys, pathlib\n"
        "from sara import colmap\n"
        "import pycolmap\n"
        "first, second = pathlib.Path(sys.argv[1]), pathlib.Path(sys.argv[2])\n"
        "colmap.send_log_to(first); pycolmap.logging.info('first message')\n"
        "colmap.send_log_to(second); pycolmap.logging.info('second message')\n"
        "print(sum(f.read_text().count('second message') for f in second.iterdir()))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "GLOG_logbuflevel"}  # as a user's shell has it
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "a"), str(tmp_path / "b")],
                         capture_output=True, text=True, check=True, env=env).stdout
    assert out.strip() == "1"


def test_map_with_the_global_mapper_from_the_command_line(finished_run, run_cli):
    """`sara map OUT --mapper global` (the `--mapper global` of usage.md): the model is checked against
    its own pairs and the map record says which mapper built the model it kept."""
    from sara.io import records

    result = run_cli("map", finished_run, "--mapper", "global", "--overwrite", "-q")
    assert_ok(result)
    info = records.done_info(finished_run, "map")
    assert info["mapper"] in ("global", "incremental") and info["first_model_pairs_checked"] > 0
    assert len(registered(finished_run)) == 10


def test_map_on_a_run_folder_rewrites_its_run_record_and_sets_its_old_accuracy_aside(finished_run, run_cli,
                                                                                      synthetic_scene):
    """After `sara map OUT --mapper global`, run.json and report.md describe the mapping now in OUT (the
    mapper asked for, its record) and the accuracy of the model it replaced is no longer shown as this
    one's: metrics.json is moved aside, run.json holds none. A map found up to date changes nothing."""
    import json

    from sara.pipeline.single import EARLIER_METRICS

    run_before = json.loads((finished_run / "run.json").read_text())
    assert run_before["config"]["map"]["mapper"] == "incremental" and run_before["metrics"]
    kept = run_cli("map", finished_run, "-q")
    assert_ok(kept)
    assert json.loads((finished_run / "run.json").read_text()) == run_before  # up to date: nothing rewritten
    result = run_cli("map", finished_run, "--mapper", "global", "--overwrite", "-q")
    assert_ok(result)
    run = json.loads((finished_run / "run.json").read_text())
    assert run["config"]["map"]["mapper"] == "global"
    assert run["config"]["pairs"] == run_before["config"]["pairs"]  # the other stages' settings as they ran
    assert run["stages"]["map"]["mapper"] in ("global", "incremental")
    assert run["stages"]["map"]["time_s"] != run_before["stages"]["map"]["time_s"]
    assert run["metrics"] is None and not (finished_run / "metrics.json").exists()
    assert (finished_run / EARLIER_METRICS).exists()
    sizes = run["stages"]["map"]["component_sizes"]
    assert f"{sizes} images registered" in (finished_run / "report.md").read_text()
    # the new model's accuracy, as usage.md says to measure it: `sara evaluate OUT GT --json OUT/metrics.json`
    assert_ok(run_cli("evaluate", finished_run, synthetic_scene[1], "--json", finished_run / "metrics.json"))
    assert json.loads((finished_run / "metrics.json").read_text())["num_registered"] == len(registered(finished_run))
