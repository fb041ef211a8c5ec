from pathlib import Path

import pytest

from sara.io.pairs import canonical_pairs, read_pairs, write_pairs
from sara.pairs.exhaustive import exhaustive_pairs
from sara.pairs.sequential import sequential_pairs


def names(n):
    return [f"img{i:03d}.jpg" for i in range(n)]


def test_exhaustive_count():
    assert len(exhaustive_pairs(names(12))) == 66
    assert exhaustive_pairs(["b", "a"]) == [("a", "b")]


def test_sequential_exact():
    pairs = sequential_pairs(names(10), 3)
    # each image i pairs with i+1..i+3 when they exist: 3*7 + 2 + 1
    assert len(pairs) == 24
    assert ("img000.jpg", "img003.jpg") in pairs and ("img000.jpg", "img004.jpg") not in pairs


def test_sequential_quadratic_exact():
    pairs = sequential_pairs(names(20), 3, quadratic=True)
    # pycolmap 4.2's quadratic overlap uses only the offsets 2^k, k < overlap: 1, 2, 4
    assert len(pairs) == 19 + 18 + 16
    assert ("img000.jpg", "img004.jpg") in pairs and ("img000.jpg", "img003.jpg") not in pairs


def test_canonical_and_roundtrip(tmp_path: Path):
    pairs = [("b", "a"), ("a", "b"), ("a", "a"), ("c", "a")]
    assert canonical_pairs(pairs) == [("a", "b"), ("a", "c")]
    path = write_pairs(tmp_path / "pairs.txt", pairs)
    assert read_pairs(path) == [("a", "b"), ("a", "c")]


def test_read_pairs_errors(tmp_path: Path):
    with pytest.raises(FileNotFoundError, match="pairs file not found"):
        read_pairs(tmp_path / "missing.txt")
    bad = tmp_path / "bad.txt"
    bad.write_text("only_one_name\n")
    with pytest.raises(ValueError, match="bad.txt:1"):
        read_pairs(bad)
    unknown = tmp_path / "unknown.txt"
    unknown.write_text("a b\n")
    with pytest.raises(ValueError, match="'b' is not among the images"):
        read_pairs(unknown, known_names=["a"])
    binary = tmp_path / "bin.txt"
    binary.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ValueError, match="not UTF-8"):
        read_pairs(binary)


def test_names_with_spaces_when_known(tmp_path: Path):
    path = tmp_path / "pairs.txt"
    path.write_text("my img 1.jpg other.jpg\n")
    assert read_pairs(path, known_names=["my img 1.jpg", "other.jpg"]) == [("my img 1.jpg", "other.jpg")]
