"""`rounds.pose_guided_last`: once the repairs used up `rounds.repair_rounds`, one more round, asked
for with `ctx.last_round`, whose pairs SARA takes from the pose-guided round."""

from __future__ import annotations

from pathlib import Path

import pytest

from sara.config import make_config
from sara.io import read_json


def test_the_round_after_the_repairs_is_asked_for_as_the_last(tmp_path: Path, synthetic_scene, scene_features,
                                                              monkeypatch):
    from sara.pairs import Round
    from sara.pairs.sara.rounds import SaraRounds
    from sara.pipeline import run, share_features

    images, _ = synthetic_scene
    out = tmp_path / "out"
    share_features(scene_features, out)
    asked: list[bool] = []

    def toy_round(self, ctx, pairs, model_dir):
        done = {tuple(sorted(p)) for p in pairs}
        fresh = [(a, b) for i, a in enumerate(ctx.names) for b in ctx.names[i + 1:] if (a, b) not in done]
        asked.append(ctx.last_round)
        return Round(fresh[:1], "pose-guided" if ctx.last_round else "repair")

    monkeypatch.setattr(SaraRounds, "after_mapping", toy_round)
    monkeypatch.setattr(SaraRounds, "refine", lambda self, *args: None)
    settings = {"rounds.repair_rounds": 1, "rounds.pose_guided_last": True}
    run(make_config("sift-offline", settings), images, out, progress=False)
    rounds = read_json(out / "run.json")["stages"]["rounds"]
    assert asked == [False, True]
    assert [h["role"] for h in rounds["history"]] == ["repair", "pose-guided"]
    assert rounds["rounds"] == len(asked) and "stopped" not in rounds
    # each round's continued model was checked against its pairs; none contradicts a sound scene
    assert [h["continued_pairs_contradicted"] for h in rounds["history"]] == [0, 0]
    assert not any(h.get("continued_mended") for h in rounds["history"])

    asked.clear()  # the same run again: every round is done, none is asked for
    run(make_config("sift-offline", settings), images, out, progress=False)
    assert asked == []


@pytest.mark.parametrize(("settings", "info", "due"), [
    ({}, {"rounds": 3}, True),
    ({"rounds.pose_guided_last": False}, {"rounds": 3}, False),
    ({}, {"rounds": 2}, False),  # the repairs stopped before their count
    ({}, {"rounds": 4}, False),  # the last round ran
    ({}, {"rounds": 3, "stopped": "time budget spent"}, False),
    ({}, {"rounds": 3, "refined_rounds": 1}, False),  # a round refined the model already
])
def test_the_last_round_is_due_once_after_repairs_that_used_up_their_count(settings, info, due):
    from types import SimpleNamespace

    from sara.pipeline.rounds import _last_round_due

    conf = make_config("sift-offline", {"rounds.repair_rounds": 3, "rounds.pose_guided_last": True, **settings})
    assert _last_round_due(SimpleNamespace(conf=conf), info) is due


def test_sara_gives_only_the_pose_guided_pairs_in_the_last_round(tmp_path: Path, monkeypatch):
    from types import SimpleNamespace

    from sara.config import PipelineConfig
    from sara.pairs.sara import rounds as sara_rounds

    monkeypatch.setattr(sara_rounds, "pose_guided_round", lambda ctx, pairs, model_dir: [("a", "c")])
    monkeypatch.setattr(sara_rounds.colmap, "registered_images", lambda model_dir: pytest.fail("a repair was asked"))
    ctx = SimpleNamespace(names=["a", "b", "c"], out_dir=tmp_path, conf=PipelineConfig(), max_round_pairs=None,
                          last_round=True, db_path=tmp_path / "database.db")
    added = sara_rounds.after_mapping(ctx, [("a", "b"), ("b", "c")], tmp_path / "sparse" / "0")
    assert (added.pairs, added.role) == ([("a", "c")], "pose-guided")
