"""A pair source is one new file plus one registry line: a toy source (every image with the next
one) and its rounds (the images two apart, once the first model exists), registered here and run
end to end through the command line, touching no other module."""

from __future__ import annotations

from pathlib import Path

from sara.cli import main
from sara.io import read_json, records
from sara.io.pairs import read_pairs
from sara.mapping import model_digest
from sara.pairs import SOURCES, NoRounds, PairContext, PairResult, PairSource, Round
from sara.pipeline import share_features


def next_image(ctx: PairContext) -> PairResult:
    names = sorted(ctx.names)
    return PairResult(list(zip(names, names[1:])), info={"rule": "next"})


class TwoApart(NoRounds):
    """After the first mapping, once: each image with the one two places ahead."""

    def after_mapping(self, ctx: PairContext, pairs: list, model_dir: Path) -> Round | None:
        names = sorted(ctx.names)
        wanted = [p for p in zip(names, names[2:]) if p not in set(pairs)]
        return Round(wanted, "two-apart")


def test_a_toy_pair_source_with_rounds_runs_end_to_end(synthetic_scene, scene_features, tmp_path: Path,
                                                       monkeypatch) -> None:
    images, _ = synthetic_scene
    monkeypatch.setitem(SOURCES._entries, "next", PairSource(select=next_image, rounds=TwoApart()))
    out = tmp_path / "out"
    share_features(scene_features, out)  # the run starts at pair selection, where the toy source comes in
    assert main(["run", str(images), str(out), "--pairs", "next", "--quiet", "-s", "rounds.extend_tracks=false"]) == 0
    names = sorted(p.name for p in images.iterdir())
    pairs = read_pairs(out / "pairs.txt")
    assert set(pairs) == set(zip(names, names[1:])) | set(zip(names, names[2:]))
    run = read_json(out / "run.json")["stages"]
    assert run["pairs"]["num_selected"] == len(names) - 1
    assert run["pairs"]["num_added_after_mapping"] == len(names) - 2
    assert run["rounds"]["rounds"] == 1  # the second round found nothing more to add
    ledger = records.done_info(out, "rounds")
    assert sorted(tuple(p) for p in ledger["added"]["two-apart"]) == list(zip(names, names[2:]))
    assert run["map"]["num_registered"] == len(names)
    # the pairs record is the selection's own: the rounds never rewrote it
    assert records.done_info(out, "pairs")["num_pairs"] == len(names) - 1
    # a second run resumes: nothing is selected, matched or mapped again
    model = model_digest(out / "sparse")
    assert main(["run", str(images), str(out), "--pairs", "next", "--quiet", "-s", "rounds.extend_tracks=false"]) == 0
    assert read_pairs(out / "pairs.txt") == pairs
    assert model_digest(out / "sparse") == model and records.done_info(out, "rounds") == ledger


def test_a_source_without_rounds_is_a_plain_function(synthetic_scene, scene_features, tmp_path: Path,
                                                     monkeypatch) -> None:
    images, _ = synthetic_scene
    monkeypatch.setitem(SOURCES._entries, "next", next_image)
    out = tmp_path / "out"
    share_features(scene_features, out)  # the run starts at pair selection, where the toy source comes in
    assert main(["run", str(images), str(out), "--pairs", "next", "--quiet"]) == 0
    assert len(read_pairs(out / "pairs.txt")) == len(list(images.iterdir())) - 1
    assert "rounds" not in read_json(out / "run.json")["stages"]
