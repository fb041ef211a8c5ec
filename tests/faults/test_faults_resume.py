"""Class 1 of the fault suite: resume trusts state it should not. A damaged, changed or unfinished
output is refused with one line (exit 3) and nothing written, or made again the same when sara
itself derived it (features file, scores, model)."""

from __future__ import annotations

import json
import os
import shutil
import sqlite3
from pathlib import Path

import pytest

from harness import SPACED_NAMES, aliased_in, assert_error, assert_kept, assert_ok, registered, snapshot, truncate


def write_record(out: Path, stage: str, **changes) -> None:
    """Change fields of a stage's record, as a run killed in that stage leaves it."""
    path = Path(out) / ".sara" / f"{stage}.json"
    record = json.loads(path.read_text())
    record.update(changes)
    path.write_text(json.dumps(record))


def _drop_one_geometry(out: Path) -> None:
    con = sqlite3.connect(out / "database.db")
    con.execute("DELETE FROM two_view_geometries WHERE pair_id = (SELECT MIN(pair_id) FROM two_view_geometries)")
    con.commit()
    con.close()


DAMAGE = {
    "killed match, then map": (lambda o: write_record(o, "match", done=False), ["map"], 3, "match stage",
                               "did not finish"),
    "match never ran, then map": (lambda o: (o / ".sara" / "match.json").unlink(), ["map"], 3, "never ran"),
    "matches changed, then map": (_drop_one_geometry, ["map"], 3, "no longer holds the matches", "sara match"),
    "pairs.txt shortened": (lambda o: truncate(o / "pairs.txt", 0.5), ["run"], 3, "pairs.txt was changed", "delete it"),
    "pairs.txt emptied": (lambda o: (o / "pairs.txt").write_text(""), ["run"], 3, "pairs.txt was changed"),
    "pairs.txt line added": (lambda o: (o / "pairs.txt").open("a").write("x.png y.png\n"), ["run"], 3, "was changed"),
    "pairs.txt edited, then match": (lambda o: truncate(o / "pairs.txt", 0.3), ["match"], 3, "pairs.txt was changed"),
    "database truncated": (lambda o: truncate(o / "database.db", 0.4), ["run"], 3, "database.db is damaged",
                           "--overwrite"),
    "database emptied": (lambda o: (o / "database.db").write_bytes(b""), ["run"], 3, "database.db is damaged"),
    "database overwritten": (lambda o: (o / "database.db").write_bytes(b"not a database" * 100), ["run"], 3,
                             "database.db is damaged"),
    "database truncated, then map": (lambda o: truncate(o / "database.db", 0.6), ["map"], 3, "is damaged"),
    "database truncated, then match": (lambda o: truncate(o / "database.db", 0.6), ["match"], 3, "is damaged"),
    "model file truncated": (lambda o: truncate(o / "sparse" / "0" / "images.bin", 0.5), ["run"], 3,
                             "sparse was changed", "move it away"),
    "model file deleted": (lambda o: (o / "sparse" / "0" / "points3D.bin").unlink(), ["run"], 3, "sparse was changed"),
    "killed extraction, then match": (lambda o: write_record(o, "extract", done=False), ["match"], 3,
                                      "extract stage", "did not finish"),
}


@pytest.mark.parametrize("case", list(DAMAGE))
def test_damaged_state_is_refused(case, finished_run, images, run_cli):
    """A record is never taken as proof: damaged or unfinished state stops with one line (exit 3)
    and nothing is written."""
    damage, command, code, *fragments = DAMAGE[case]
    damage(finished_run)
    before = snapshot(finished_run)
    args = {"run": ["run", images, finished_run], "map": ["map", finished_run],
            "match": ["match", finished_run]}[command[0]]
    result = run_cli(*args, "-q")
    assert_error(result, code, *fragments)
    assert_kept(before, finished_run)


def test_other_extraction_settings_refused(finished_run, images, run_cli):
    before = snapshot(finished_run)
    result = run_cli("run", images, finished_run, "-q", "-s", "extract.max_num_features=1000")
    assert_error(result, 3, "other extraction settings", "extract.max_num_features", "--overwrite")
    assert_kept(before, finished_run)


def test_other_image_folder_refused(finished_run, images, tmp_path, run_cli):
    """A folder sharing no image with the run's, under any name, is not an update of it
    (tests/test_incremental.py; the same images renamed are one)."""
    from PIL import Image

    other = tmp_path / "other_images"
    other.mkdir()
    for k, name in enumerate(sorted(os.listdir(images))):
        Image.open(images / name).transpose(Image.Transpose.FLIP_LEFT_RIGHT).save(other / f"other-{k}.png")
    before = snapshot(finished_run)
    result = run_cli("run", other, finished_run, "-q")
    assert_error(result, 3, "other images")
    assert_kept(before, finished_run)


@pytest.mark.parametrize("damage", ["truncated", "overwritten"])
def test_damaged_features_are_made_again(damage, finished_run, images, finished_run_template, run_cli):
    """The features file is derived from the database: a damaged one is written again, the same."""
    from sara.io.h5 import features_digest

    h5 = finished_run / "features-sift.h5"
    if damage == "truncated":
        truncate(h5, 0.3)
    else:
        h5.write_bytes(b"\0" * 4096)
    before = snapshot(finished_run)
    result = run_cli("run", images, finished_run, "-q")
    assert_ok(result)
    assert "extracting the features again" in result.err
    assert features_digest(h5) == features_digest(finished_run_template / "features-sift.h5")
    assert_kept(before, finished_run, ("pairs.txt", "scores.csv", "sparse"))


def test_damaged_scores_are_made_again(finished_run, images, finished_run_template, run_cli):
    truncate(finished_run / "scores.csv", 0.5)
    result = run_cli("run", images, finished_run, "-q")
    assert_ok(result)
    assert "scores.csv differs from what the pairs stage wrote" in result.err
    assert (finished_run / "scores.csv").read_bytes() == (finished_run_template / "scores.csv").read_bytes()
    assert registered(finished_run) == registered(finished_run_template)


@pytest.mark.parametrize("loss", ["sparse deleted", "map record cut short"])
def test_lost_model_is_mapped_again(loss, finished_run, images, finished_run_template, run_cli):
    if loss == "sparse deleted":
        shutil.rmtree(finished_run / "sparse")
    else:
        truncate(finished_run / ".sara" / "map.json", 0.5)
    before = snapshot(finished_run)
    result = run_cli("run", images, finished_run, "-q")
    assert_ok(result)
    assert registered(finished_run) == registered(finished_run_template)
    assert_kept(before, finished_run, ("pairs.txt", "scores.csv", "features-sift.h5"))


def test_aliased_names_left_behind_are_given_back(spaced_folder, tmp_path, run_cli):
    """The same state made without a race: aliasing entered and never left, as a kill leaves it;
    `sara run`, `sara match` and `sara map` each find the names again."""
    from sara.match import space_free_names

    folder = tmp_path / "images"  # the four spaced names and the next view: five to extract, not ten
    folder.mkdir()
    plain = sorted(p.name for p in spaced_folder.iterdir() if p.name not in SPACED_NAMES)
    for name in [*SPACED_NAMES, plain[0]]:
        shutil.copyfile(spaced_folder / name, folder / name)
    out = tmp_path / "out"
    assert_ok(run_cli("run", folder, out, "-q"))
    left = []  # held, so that no clean-up runs when the generator is collected
    for command in (["run", folder, out], ["match", out], ["map", out]):
        left.append(space_free_names(out / "database.db", out))
        left[-1].__enter__()  # noqa: PLC2801 - as a kill leaves it: the exit never runs
        assert aliased_in(out / "database.db")
        assert_ok(run_cli(*command, "-q"))
        assert not aliased_in(out / "database.db")
    assert set(SPACED_NAMES) <= set(registered(out))


def test_a_selection_stopped_while_scoring_scores_only_the_pairs_it_had_not(finished_run, images, finished_run_template,
                                                                          run_cli, monkeypatch):
    """The scores of each shard are kept as it comes back (`.sara/score-journal/`), and the global
    descriptors made before the stop with them: the same command scores only the other pairs,
    describes no image again and selects what an uninterrupted run selects; once the stage ends
    the journal keeps the scores and hands the descriptors to the output folder."""
    import sara.scoring.scorer as scorer
    from sara.retrieval.vlad import VladDescriptor

    (finished_run / "pairs.txt").unlink()
    journal = finished_run / ".sara" / "score-journal"
    shutil.rmtree(journal)  # the finished run's scores: this selection starts with none
    command = ("pairs", images, finished_run, "-q", "--executor", "serial", "-s", "execute.shard_size=8", "-s",
               "retrieval.num_neighbors=5")
    real, scored = scorer._score_shard, []

    def stopping(shard):
        if len(scored) == 2:
            raise KeyboardInterrupt
        scored.append(len(shard.index0))
        return real(shard)

    monkeypatch.setattr(scorer, "_score_shard", stopping)
    assert run_cli(*command).code == 130
    assert len(list(journal.glob("*.json"))) == 2 and not (finished_run / "pairs.txt").exists()
    assert [p.name for p in journal.glob("global-*.h5")] == ["global-vlad.h5"]
    kept = sum(scored)
    scored.clear()
    monkeypatch.setattr(scorer, "_score_shard", lambda shard: scored.append(len(shard.index0)) or real(shard))
    described = []
    compute = VladDescriptor.compute
    monkeypatch.setattr(VladDescriptor, "compute", lambda self, *a, **k: described.append(1) or compute(self, *a, **k))
    result = run_cli(*command)
    assert_ok(result)
    assert not described
    candidates = len((finished_run / "scores.csv").read_text().splitlines()) - 1
    assert kept == 16 and sum(scored) == candidates - kept
    uninterrupted = Path(shutil.copytree(finished_run_template, finished_run.with_name("whole")))
    (uninterrupted / "pairs.txt").unlink()
    shutil.rmtree(uninterrupted / ".sara" / "score-journal")
    assert_ok(run_cli("pairs", images, uninterrupted, *command[3:]))
    for name in ("pairs.txt", "scores.csv"):
        assert (finished_run / name).read_bytes() == (uninterrupted / name).read_bytes()
    assert len(list(journal.glob("*.json"))) > 2 and not list(journal.glob("global-*.h5"))
    assert (finished_run / "global-vlad.h5").is_file()


def test_a_selection_made_again_with_other_graph_settings_scores_no_pair_twice(
        finished_run, images, finished_run_template, run_cli, monkeypatch):
    """The scores stay with the features: selecting again with other graph or budget settings
    scores only candidates never scored, and selects what a folder without those scores selects;
    `--overwrite` scores anew (other features clear the journal: test_scoring.py)."""
    import sara.scoring.scorer as scorer

    journal = finished_run / ".sara" / "score-journal"
    assert list(journal.glob("*.json"))  # the finished run's
    before = (finished_run / "pairs.txt").read_bytes()
    real, scored = scorer._score_shard, []
    monkeypatch.setattr(scorer, "_score_shard", lambda shard: scored.append(len(shard.index0)) or real(shard))
    changed = ("-q", "-s", "graph.use_loops=false", "-s", "budget.max_pairs_per_image=2")
    assert_ok(run_cli("pairs", images, finished_run, *changed))
    assert sum(scored) == 0 and (finished_run / "pairs.txt").read_bytes() != before
    fresh = Path(shutil.copytree(finished_run_template, finished_run.with_name("fresh")))
    shutil.rmtree(fresh / ".sara" / "score-journal")
    assert_ok(run_cli("pairs", images, fresh, *changed))
    from_nothing = sum(scored)
    assert from_nothing >= len((fresh / "scores.csv").read_text().splitlines()) - 1 > 0
    for name in ("pairs.txt", "scores.csv"):
        assert (finished_run / name).read_bytes() == (fresh / name).read_bytes()
    scored.clear()
    assert_ok(run_cli("pairs", images, finished_run, "--overwrite", *changed))
    assert sum(scored) == from_nothing
