"""Pairs files: one `name0 name1` per line, as read by hloc and COLMAP's `matches_importer`.

Names may contain spaces: COLMAP splits each line at the first space, so we cannot write such
names to a file that COLMAP reads. `write_pairs` therefore refuses them with a clear message, and
the pipeline hands COLMAP a file keyed by safe aliases when needed (see `match.py`).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from . import write_text_atomic

Pair = tuple[str, str]


def canonical_pairs(pairs: Iterable[Pair]) -> list[Pair]:
    """Deduplicated, self pairs removed, each pair ordered (a < b), sorted."""
    out = {(a, b) if a < b else (b, a) for a, b in pairs if a != b}
    return sorted(out)


def write_pairs(path: Path, pairs: Iterable[Pair]) -> Path:
    lines = []
    for a, b in canonical_pairs(pairs):
        lines.append(f"{a} {b}")
    write_text_atomic(Path(path), "\n".join(lines) + ("\n" if lines else ""))
    return Path(path)


def read_pairs(path: Path, known_names: Iterable[str] | None = None) -> list[Pair]:
    """Read a pairs file. Names with spaces are supported when `known_names` is given.

    Raises FileNotFoundError / ValueError with the offending line when the file is unusable.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"pairs file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"pairs file {path} is not UTF-8 text (expected 'name0 name1' per line)") from None
    known = set(known_names) if known_names is not None else None
    pairs = []
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        pair = _split_line(line, known)
        if pair is None:
            raise ValueError(f"{path}:{lineno}: cannot read {line!r} as a pair 'name0 name1'")
        if known is not None:
            unknown = [n for n in pair if n not in known]
            if unknown:
                raise ValueError(
                    f"{path}:{lineno}: image {unknown[0]!r} is not among the images of this run "
                    "(names are relative to the image folder)"
                )
        pairs.append(pair)
    return canonical_pairs(pairs)


def _split_line(line: str, known: set[str] | None) -> Pair | None:
    parts = line.split()
    if len(parts) >= 2 and len(parts) <= 3 and known is None:
        return parts[0], parts[1]  # an optional third column (a score) is ignored
    if known is None:
        return None
    if len(parts) == 2 or (len(parts) == 3 and parts[0] in known and parts[1] in known):
        return parts[0], parts[1]
    for i in range(1, len(line)):  # names with spaces: find the split where both halves are known
        if line[i] == " " and line[:i].strip() in known and line[i + 1:].strip() in known:
            return line[:i].strip(), line[i + 1:].strip()
    return (parts[0], parts[1]) if len(parts) == 2 else None
