"""Pairs files: one `name0 name1` per line, as read by hloc and COLMAP's `matches_importer`.

Image names may hold spaces, start with `#`, or have leading and trailing spaces: with the names
of the run at hand (`known_names`), `read_pairs` finds the one split of each line into two known
names, so such a line is never misread (a line that starts with `#` is a comment only when it is
not a pair of known names). COLMAP's importer splits at the first space and skips lines that
start with `#`, so the match stage hands it aliases for such names (see `sara.match`).

Names that no line-based file can carry (control characters such as newlines or tabs, bytes that
are not UTF-8) are set aside when the images are scanned (`sara.io.images`); `write_pairs`
refuses them.
"""

from __future__ import annotations

import unicodedata
from collections.abc import Iterable
from pathlib import Path

from . import write_text_atomic

Pair = tuple[str, str]

#: Unicode categories that line-based files cannot carry: control characters and line separators
_UNCARRIABLE = ("Cc", "Cs", "Zl", "Zp")


def name_problem(name: str) -> str | None:
    """Why an image name cannot go through sara's files (None when it can)."""
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        return "its name is not valid UTF-8, which the pairs file, HDF5 and the database need; rename the file"
    bad = next((c for c in name if unicodedata.category(c) in _UNCARRIABLE), None)
    if bad is not None:
        return (f"its name holds the control character {bad!r}, which a pairs file (one pair per line) "
                "cannot carry; rename the file")
    return None


def canonical_pairs(pairs: Iterable[Pair]) -> list[Pair]:
    """Deduplicated, self pairs removed, each pair ordered (a < b), sorted."""
    out = {(a, b) if a < b else (b, a) for a, b in pairs if a != b}
    return sorted(out)


def write_pairs(path: Path, pairs: Iterable[Pair]) -> Path:
    lines = []
    for a, b in canonical_pairs(pairs):
        for name in (a, b):
            problem = name_problem(name)
            if problem is not None:
                raise ValueError(f"cannot write image {name!r} to {path}: {problem}")
        lines.append(f"{a} {b}")
    write_text_atomic(Path(path), "\n".join(lines) + ("\n" if lines else ""))
    return Path(path)


def read_pairs(path: Path, known_names: Iterable[str] | None = None) -> list[Pair]:
    """Read a pairs file. Names with spaces or a leading `#` are read right when `known_names` is given.

    Raises FileNotFoundError / IsADirectoryError / ValueError with the offending line when the
    file is unusable.
    """
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder, not a pairs file ('name0 name1' per line)")
    if not path.exists():
        raise FileNotFoundError(f"pairs file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark (Windows editors) is not part of a name
    except UnicodeDecodeError:
        raise ValueError(f"pairs file {path} is not UTF-8 text (expected 'name0 name1' per line)") from None
    known = set(known_names) if known_names is not None else None
    pairs = []
    for lineno, raw in enumerate(text.split("\n"), 1):
        line = raw[:-1] if raw.endswith("\r") else raw
        if not line.strip():
            continue
        pair = _split_line(line, known, f"{path}:{lineno}")
        if pair is None:
            if line.lstrip().startswith("#"):
                continue  # a comment
            raise ValueError(f"{path}:{lineno}: cannot read {line!r} as a pair 'name0 name1'"
                             + _unknown_hint(line, known))
        pairs.append(pair)
    return canonical_pairs(pairs)


def _split_line(line: str, known: set[str] | None, where: str) -> Pair | None:
    if known is None:
        parts = line.split()
        if line.lstrip().startswith("#") or not 2 <= len(parts) <= 3:
            return None
        return parts[0], parts[1]  # an optional third column (a score) is ignored
    parts = line.split(" ")
    if len(parts) == 2 and parts[0] in known and parts[1] in known:
        return parts[0], parts[1]  # the usual case, fast
    found: set[Pair] = set()
    for variant in _variants(line):
        for i, char in enumerate(variant):
            if char in " \t" and variant[:i] in known and variant[i + 1:] in known:
                found.add((variant[:i], variant[i + 1:]))
        if found:
            break
    if len(found) > 1:
        raise ValueError(f"{where}: {line!r} can be read as more than one pair of image names "
                         f"({' or '.join(repr(f'{a} | {b}') for a, b in sorted(found))})")
    return found.pop() if found else None


def _variants(line: str) -> list[str]:
    """The line as written, without surrounding blanks, and without a third (score) column."""
    out = [line, line.strip(" \t")]
    for variant in list(out):
        head, _, last = variant.rstrip(" \t").rpartition(" ")
        if head and _is_number(last):
            out.append(head)
    return list(dict.fromkeys(out))


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _unknown_hint(line: str, known: set[str] | None) -> str:
    if known is None:
        return ""
    parts = line.strip().split()
    unknown = next((p for p in parts if p not in known), None)
    if len(parts) == 2 and unknown is not None:
        return f": image {unknown!r} is not among the images of this run (names are relative to the image folder)"
    return ": the two names must be images of this run (names are relative to the image folder)"
