"""What the documentation promises about itself: a short README that starts with install and test,
the user docs in docs/, relative links that lead somewhere, and no path of a developer's machine in
any file of the repository."""

from __future__ import annotations

import re
import shlex
import subprocess
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
USER_DOCS = ("usage.md", "configuration.md", "method.md", "interop.md", "extending.md", "results.md")
README_MAX_LINES = 150
INSTALL = "python3 -m venv .venv && . .venv/bin/activate && pip install -e '.[test]' && sara demo"
TEST_COMMAND = "python -m pytest -q"
#: a folder of a developer's machine: work or root at the top, or a user's home (the pattern is
#: spelled in pieces so that this file does not match itself)
MACHINE_PATH = re.compile("/" + "(?:work|root)/" + "|/" + "home/[a-z]")
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.DOTALL | re.MULTILINE)


def repository_files() -> list[Path]:
    """Files git tracks or would track (untracked but not ignored), that exist in the working tree."""
    try:
        listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                                cwd=ROOT, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: the repository's files cannot be listed")
    return [ROOT / name for name in listed.decode().split("\0") if name and (ROOT / name).is_file()]


def text_of(path: Path) -> str | None:
    """The file's text, or None for a binary file (NUL bytes or not UTF-8)."""
    data = path.read_bytes()
    if b"\0" in data:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def code_blocks(markdown: str) -> list[str]:
    """The fenced blocks of a Markdown text, in order, without their fences."""
    return [block.split("\n", 1)[1].rsplit("```", 1)[0] for block in FENCE.findall(markdown)]


def markdown_files() -> list[Path]:
    return [README, *sorted((ROOT / "docs").glob("*.md"))]


def test_no_machine_path_in_any_file() -> None:
    found = []
    for path in repository_files():
        text = text_of(path)
        if text is None:
            continue
        for number, line in enumerate(text.splitlines(), 1):
            if MACHINE_PATH.search(line):
                found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()[:100]}")
    assert not found, "absolute paths of a developer's machine:\n" + "\n".join(found)


def test_machine_path_pattern_catches_them() -> None:
    for line in ("see /" + "work/q19/six995", "/" + "root/.cache/x", "/" + "home/alice/data"):
        assert MACHINE_PATH.search(line), line
    for line in ("../shared/data", "lab/notes/ACCURACY.md", "/tmp/faults", "/home/"):
        assert not MACHINE_PATH.search(line), line


def test_readme_is_short_and_starts_with_install_and_tests() -> None:
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) < README_MAX_LINES
    blocks = code_blocks(text)
    assert len(blocks) >= 2
    assert blocks[0].strip() == INSTALL
    assert blocks[1].strip() == TEST_COMMAND


def test_the_test_command_uses_every_core_and_keeps_each_file_on_one_worker() -> None:
    """The README's test command takes its options from pyproject.toml: the suite on every core
    (pytest-xdist, in the test extra) and each file's tests on one worker, which the Ray tests'
    shared cluster needs (a second cluster started beside it stops the first)."""
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    options = shlex.split(pyproject["tool"]["pytest"]["ini_options"]["addopts"])
    assert options[options.index("-n") + 1] == "auto"
    assert options[options.index("--dist") + 1] == "loadfile"
    assert any(spec.startswith("pytest-xdist") for spec in pyproject["project"]["optional-dependencies"]["test"])


def test_docs_holds_the_user_documents() -> None:
    missing = [name for name in USER_DOCS if not (ROOT / "docs" / name).is_file()]
    assert not missing, f"docs/ lacks {missing}"


def test_relative_links_lead_to_files() -> None:
    broken = []
    for path in markdown_files():
        prose = FENCE.sub("", path.read_text(encoding="utf-8"))
        for target in LINK.findall(prose):
            if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
                continue  # a URL or an anchor in the same page
            if not (path.parent / target.split("#", 1)[0]).exists():
                broken.append(f"{path.relative_to(ROOT)}: {target}")
    assert not broken, "links to missing files:\n" + "\n".join(broken)
