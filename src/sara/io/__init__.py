"""Small file helpers: atomic writes, JSON, fingerprints, digests, the output-folder lock, the
errors that say what state an output folder is in, and the clean-up of files left by killed runs."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

# ---------------------------------------------------------------------------------------------
# Errors that say what a user must do (the CLI maps each family to one exit code)
# ---------------------------------------------------------------------------------------------


class OutputStateError(RuntimeError):
    """An output folder cannot be used as it is (damaged, unfinished, in use); the message says
    which file and what to do. Exit code 3 on the command line."""


class DamagedOutputError(OutputStateError):
    """A file in the output folder is damaged or changed since the stage that wrote it."""


class IncompleteStageError(OutputStateError):
    """A stage needs the output of an earlier stage that did not finish."""


class OutputLockedError(OutputStateError):
    pass


class NoResultError(RuntimeError):
    """A run produced nothing usable (no pairs, no verified pair, no model); the previous outputs
    were kept. Exit code 5 on the command line."""


def disk_full_error(path: Path, needed_bytes: int | None = None) -> OSError:
    """An OSError(ENOSPC) whose message says how much space is free and what to do."""
    free = free_bytes(path)
    need = f"; about {needed_bytes / 1e6:.0f} MB are needed" if needed_bytes else ""
    return OSError(errno.ENOSPC, f"no space left on the device of {path} ({free / 1e6:.1f} MB free{need}): "
                                 "free some space and run the same command again to resume", str(path))


def free_bytes(path: Path) -> int:
    """Free bytes on the file system of `path` (or of its nearest existing parent)."""
    path = Path(path).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    try:
        return shutil.disk_usage(path).free
    except OSError:
        return 0


#: below this many free bytes a native library's failure to write is taken for a full disk
LOW_SPACE_BYTES = 8 * 2**20


def ensure_free_space(path: Path, needed_bytes: int) -> None:
    """Raise OSError(ENOSPC) before a write of about `needed_bytes` that the disk cannot hold.

    Native writers (HDF5, SQLite inside COLMAP) crash or give unclear errors on a full disk; this
    check turns the common case into one clear message before any byte is written.
    """
    if free_bytes(path) < int(needed_bytes) + LOW_SPACE_BYTES:
        raise disk_full_error(path, int(needed_bytes) + LOW_SPACE_BYTES)


# ---------------------------------------------------------------------------------------------
# Atomic writes that follow the umask
# ---------------------------------------------------------------------------------------------


def _umask() -> int:
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)  # no /proc: read it by setting it (and put it back at once)
    os.umask(mask)
    return mask


#: the prefix of every temporary file that `atomic_path` creates (cleaned after killed runs)
TMP_SUFFIX = ".tmp"


@contextlib.contextmanager
def atomic_path(path: Path) -> Iterator[Path]:
    """Yield a temporary path beside `path`; rename it onto `path` only on success.

    The file gets the mode a plain `open()` would give it (0666 less the umask), not mkstemp's 0600.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=TMP_SUFFIX, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        os.chmod(tmp_path, 0o666 & ~_umask())
        yield tmp_path
        if tmp_path.exists():
            os.chmod(tmp_path, 0o666 & ~_umask())  # a writer may have replaced the file
        os.replace(tmp_path, path)
    finally:
        tmp_path.unlink(missing_ok=True)


def link_or_copy(src: Path, dst: Path, *, symbolic: bool = False) -> None:
    """Put the read-only file `src` at `dst` without copying where possible: a symbolic link (with
    `symbolic`; it follows `src` wherever `dst` is read from), else a hard link, else (another file
    system, or links not allowed) an atomic copy. Replaces what is at `dst`."""
    src, dst = Path(src), Path(dst)
    dst.unlink(missing_ok=True)
    if symbolic:
        try:
            os.symlink(src.resolve(), dst)
            return
        except OSError:
            pass
    try:
        os.link(src, dst)
    except OSError:
        with atomic_path(dst) as tmp:
            shutil.copyfile(src, tmp)


def write_text_atomic(path: Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def write_json_atomic(path: Path, data: Any) -> None:
    write_text_atomic(path, json.dumps(data, indent=2, sort_keys=False, default=_json_default) + "\n")


def read_json(path: Path) -> Any:
    return json.loads(Path(path).read_text(encoding="utf-8"))


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def without_added_later(values: dict[str, Any], later: dict[str, Any]) -> dict[str, Any]:
    """`values` less the settings of `later` at their value there: settings added after outputs
    were made are left out of a key at their default, so those outputs are not made again."""
    return {k: v for k, v in values.items() if not (k in later and v == later[k])}


def fingerprint(data: Any) -> str:
    """A short stable hash of JSON-serialisable data (configs, image lists)."""
    blob = json.dumps(data, sort_keys=True, default=_json_default).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


#: files up to this size are hashed whole; larger ones by their size, head, middle and tail
FULL_HASH_BYTES = 64 * 2**20
_SAMPLE_BYTES = 2**20


def file_digest(path: Path) -> dict[str, Any] | None:
    """{"size": bytes, "sha256": ...} of a file (None when it does not exist).

    Small files are hashed whole; large ones by their size and three 1 MiB samples, which any
    truncation, extension or rewrite by another run changes.
    """
    path = Path(path)
    if not path.is_file():
        return None
    size = path.stat().st_size
    h = hashlib.sha256()
    with open(path, "rb") as f:
        if size <= FULL_HASH_BYTES:
            for block in iter(lambda: f.read(2**20), b""):
                h.update(block)
        else:
            for offset in (0, size // 2, size - _SAMPLE_BYTES):
                f.seek(offset)
                h.update(f.read(_SAMPLE_BYTES))
    return {"size": size, "sha256": h.hexdigest()[:24]}


# ---------------------------------------------------------------------------------------------
# Output folders: checks, temporary files of killed runs, the lock
# ---------------------------------------------------------------------------------------------


def prepare_output_dir(out_dir: Path) -> Path:
    """Create the output folder; clear errors when the path is a file or cannot be written."""
    out_dir = Path(out_dir)
    for parent in (out_dir, *out_dir.parents):
        if parent.exists() and not parent.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, f"output folder {out_dir}: {parent} is a file, not a folder; "
                                                    "choose another output folder", str(parent))
        if parent.exists():
            break
    out_dir.mkdir(parents=True, exist_ok=True)
    probe = out_dir / f".sara-write-test.{os.getpid()}{TMP_SUFFIX}"
    try:
        probe.write_bytes(b"")
    finally:
        with contextlib.suppress(OSError):
            probe.unlink()
    return out_dir


#: files and folders that a killed run can leave; safe to remove while holding the lock
_TMP_FILE = re.compile(r"^\..+\.tmp(\.[A-Za-z0-9]+)?$")
_SARA_TEMPORARIES = ("match_chunk*", "*chunk*.txt", "score-views-*", "sparse.partial", "sparse.before-round",
                     "pairs.next", "*.tmp")


def clean_temporaries(out_dir: Path) -> list[Path]:
    """Remove what killed runs left in an output folder: `.<name>.XXXX.tmp` files of atomic writes
    (in the folder, `.sara/`, `sparse/` and `images_upright/`), and `.sara/` scratch files and
    folders (pair chunks, score view stores, a half-built model). Resume state is kept: a
    `features-*.h5.partial` (learned extraction) and `.sara/database.next.db` are continued by the
    next run of the same settings. Returns the paths removed. Call it only while holding the lock.
    """
    out_dir = Path(out_dir)
    removed: list[Path] = []
    folders = [out_dir, out_dir / ".sara", out_dir / "sparse", out_dir / "images_upright"]
    if (out_dir / "sparse").is_dir():
        folders += [p for p in (out_dir / "sparse").iterdir() if p.is_dir()]
    for folder in folders:
        if not folder.is_dir():
            continue
        for entry in folder.iterdir():
            if _TMP_FILE.match(entry.name) and entry.is_file():
                removed.append(entry)
    sara_dir = out_dir / ".sara"
    if sara_dir.is_dir():
        for pattern in _SARA_TEMPORARIES:
            removed += [p for p in sara_dir.glob(pattern) if p not in removed]
    for path in removed:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
    return removed


class OutputLock:
    """An exclusive lock on an output folder, so two runs never write the same files.

    Uses `fcntl.flock` on `<out>/.sara.lock`: the OS releases it when the process dies,
    so a killed run never leaves a stale lock behind. With `clean=True`, the temporary files of
    killed runs are removed when the lock is taken and when it is released.
    """

    def __init__(self, out_dir: Path, *, clean: bool = False):
        self.path = Path(out_dir) / ".sara.lock"
        self.clean = clean
        self._fd: int | None = None

    def __enter__(self) -> OutputLock:
        import fcntl

        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise OutputLockedError(
                f"{self.path.parent} is in use by another sara process; "
                "wait for it to finish or choose another output folder"
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd
        if self.clean:
            clean_temporaries(self.path.parent)
        return self

    def __exit__(self, *exc: object) -> None:
        import fcntl

        if self._fd is not None:
            try:
                if self.clean:
                    with contextlib.suppress(OSError):
                        clean_temporaries(self.path.parent)
            finally:
                fcntl.flock(self._fd, fcntl.LOCK_UN)
                os.close(self._fd)
                self._fd = None
