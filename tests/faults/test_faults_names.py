"""Class 3 of the fault suite: file names. Each name is decided once, when the folder is scanned:
it works end to end (spaces, '#', non-ASCII) or is skipped with one warning naming it (control
characters, bytes that are not UTF-8, hidden files); a pairs file never misreads a name."""

from __future__ import annotations

import json
import os
import shutil

import pytest
from PIL import Image

from harness import assert_ok, registered, run_redirected

#: name -> works end to end (True) or is skipped with a warning naming it (False)
NAMES = {
    "#hash.png": True,
    "# hash space.png": True,
    " leading.png": True,
    "trailing .png": True,
    "two  spaces.png": True,
    "ü ñ é.png": True,
    "\u3000ideographic space.png": True,
    "quote'\"q.png": True,
    "comma,semi;.png": True,
    "-dash.png": True,
    "new\nline.png": False,
    "tab\t.png": False,
    "carriage\r.png": False,
    "line\u2028separator.png": False,
    os.fsdecode(b"latin1-\xe9.png"): False,
    ".hidden.png": False,
}


@pytest.fixture(scope="module")
def small_png(tmp_path_factory, synthetic_scene) -> bytes:
    first = sorted(synthetic_scene[0].iterdir())[0]
    path = tmp_path_factory.mktemp("png") / "small.png"
    Image.open(first).convert("L").resize((96, 72)).save(path)
    return path.read_bytes()


@pytest.mark.parametrize("name", list(NAMES), ids=lambda n: ascii(n))
def test_each_name_is_decided_once_at_scan(name, small_png, tmp_path, caplog, monkeypatch):
    import logging

    from sara.io.images import display_name, scan_images

    monkeypatch.setattr(logging.getLogger("sara"), "propagate", True)  # the CLI's own tests turn it off

    folder = tmp_path / "imgs"
    folder.mkdir()
    (folder / "plain.png").write_bytes(small_png)
    with open(os.fsencode(folder) + b"/" + os.fsencode(name), "wb") as f:
        f.write(small_png)
    images = scan_images(folder, progress=False)
    if NAMES[name]:
        assert name in images.names and not images.skipped
    else:
        assert name not in images.names and list(images.skipped) == [display_name(name)]
        assert any(display_name(name) in r.getMessage() for r in caplog.records)
        json.dumps(images.skipped, ensure_ascii=False).encode("utf-8")  # run.json can hold it


PAIR_FILES = {
    "hash names are pairs, not comments": (["#a.png", "b.png"], "#a.png b.png\n", [("#a.png", "b.png")]),
    "a comment stays a comment": (["a.png", "b.png"], "# a.png b.png\na.png b.png\n", [("a.png", "b.png")]),
    "leading space": ([" a.png", "a.png", "b.png"], " a.png b.png\n", [(" a.png", "b.png")]),
    "trailing space": (["a .png", "b.png"], "a .png b.png\n", [("a .png", "b.png")]),
    "inner spaces": (["x y.png", "z.png"], "x y.png z.png\n", [("x y.png", "z.png")]),
    "score column": (["x y.png", "z.png"], "x y.png z.png 0.5\n", [("x y.png", "z.png")]),
    "windows line ends": (["a.png", "b.png"], "a.png b.png\r\n", [("a.png", "b.png")]),
    "byte-order mark": (["a.png", "b.png"], "\ufeffa.png b.png\r\n", [("a.png", "b.png")]),
    "byte-order mark, unknown names": (None, "\ufeffa.png b.png\n", [("a.png", "b.png")]),
}


@pytest.mark.parametrize("case", list(PAIR_FILES))
def test_pairs_file_never_misreads_a_name(case, tmp_path):
    from sara.io.pairs import read_pairs, write_pairs

    names, text, expected = PAIR_FILES[case]
    path = tmp_path / "pairs.txt"
    path.write_text(text, newline="")
    assert read_pairs(path, known_names=names) == expected
    write_pairs(path, expected)  # and what sara writes reads back the same
    assert read_pairs(path, known_names=names) == expected


def test_pairs_file_with_a_byte_order_mark_through_the_cli(finished_run, tmp_path, run_cli):
    """`sara match OUT --pairs F` with F saved by a Windows editor (UTF-8 with a byte-order mark,
    CRLF line ends): every pair is matched, the first one too (issue 30: it was refused)."""
    from sara.io.pairs import read_pairs

    pairs = read_pairs(finished_run / "pairs.txt")
    path = tmp_path / "pairs-windows.txt"
    path.write_bytes(b"\xef\xbb\xbf" + "".join(f"{a} {b}\r\n" for a, b in pairs).encode("utf-8"))
    result = run_cli("match", finished_run, "--pairs", path, "-q")
    assert_ok(result)
    assert f"matched {len(pairs)} pairs" in result.out


def test_ambiguous_pair_line_is_an_error(tmp_path):
    from sara.io.pairs import read_pairs

    path = tmp_path / "pairs.txt"
    path.write_text("a b c\n")
    with pytest.raises(ValueError, match="more than one pair"):
        read_pairs(path, known_names=["a", "b c", "a b", "c"])


def test_names_sara_cannot_carry_are_refused_by_the_writer(tmp_path):
    from sara.io.pairs import write_pairs

    with pytest.raises(ValueError, match="control character"):
        write_pairs(tmp_path / "p.txt", [("a\nb.png", "c.png")])


# An end-to-end run on odd names, a file COLMAP cannot read and an image that COLMAP's extraction
# skips (as when it vanishes or changes during extraction): one run, checked per name.


ODD_NAMES = ["#hash.png", " leading.png", "trailing .png", "two  spaces.png", "ü ñ.png"]
ODD_SKIPPED = {"new\nline.png": "control character", os.fsdecode(b"bad-\xff.png"): "not valid UTF-8",
               ".hidden.png": "hidden file", "webp-inside.png": "COLMAP's image reader cannot decode it",
               "vanishes.png": "COLMAP's extraction skipped it"}


@pytest.fixture(scope="module")
def odd_run(tmp_path_factory, synthetic_scene):
    """(output folder, result of the run, result of a second run) on 5 views with odd names."""
    from sara import colmap

    src = sorted(synthetic_scene[0].iterdir())
    folder = tmp_path_factory.mktemp("odd") / "images"
    folder.mkdir()
    for path, name in zip(src[:5], ODD_NAMES):
        shutil.copyfile(path, folder / name)
    for path, name in zip(src[5:], [n for n in ODD_SKIPPED if n not in ("webp-inside.png",)]):
        with open(os.fsencode(folder) + b"/" + os.fsencode(name), "wb") as f:
            f.write(path.read_bytes())
    Image.open(src[0]).save(folder / "webp-inside.png", format="WEBP")
    out = folder.parent / "out"
    original = colmap.extract_sift

    def extract_but_one(db_path, image_dir, names, **kwargs):  # as if the file changed under COLMAP
        return original(db_path, image_dir, [n for n in names if n != "vanishes.png"], **kwargs)

    mp = pytest.MonkeyPatch()
    mp.setattr(colmap, "extract_sift", extract_but_one)
    try:
        first = run_redirected("run", folder, out, "-q")
    finally:
        mp.undo()
    second = run_redirected("run", folder, out, "-q")
    return out, first, second


@pytest.mark.parametrize("name", ODD_NAMES, ids=ascii)
def test_odd_name_works_end_to_end(name, odd_run):
    from sara.io.pairs import read_pairs

    out, first, second = odd_run
    assert_ok(first)
    assert_ok(second)
    assert name in registered(out)
    assert any(name in pair for pair in read_pairs(out / "pairs.txt", known_names=ODD_NAMES))


@pytest.mark.parametrize("name", list(ODD_SKIPPED), ids=ascii)
def test_odd_file_is_skipped_with_a_warning(name, odd_run):
    """Skipped once, before extraction (or when COLMAP skips it), named in a warning and in run.json;
    the next run (all stages done) neither fails nor forgets it."""
    from sara.io.images import display_name

    out, first, second = odd_run
    assert_ok(first)
    assert_ok(second)
    shown = display_name(name)
    skipped = json.loads((out / "run.json").read_text())["skipped_images"]
    assert ODD_SKIPPED[name] in skipped[shown]
    assert f"skipping {shown}:" in first.err and f"skipping {shown}:" in second.err
    assert first.err.count(f"skipping {shown}:") == 1
