"""How long work will take: the matching estimate from its first chunk, durations in words, and the
time budget of the rounds after the first mapping (issue 31)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from sara import eta
from sara.config import BudgetConfig, RoundsConfig, make_config
from sara.io import read_json
from sara.pairs.sara.budget import PairBudget


def test_the_estimate_scales_the_first_chunk_to_all_pairs():
    est = eta.from_first_chunk(1225, 128, 20.0)
    assert est.rate_pairs_per_s == pytest.approx(6.4)
    assert est.seconds == pytest.approx(1225 / 6.4)
    assert est.line() == "match: 1,225 pairs, about 3 min 11 s at 6.4 pairs/s (first chunk)"
    # four workers each had a chunk in flight: four chunks are done when the first comes back
    assert eta.from_first_chunk(1000, 10, 5.0, concurrency=4).seconds == pytest.approx(1000 / 8.0)
    # an interrupted run's time counts in the whole, its pairs do not
    resumed = eta.from_first_chunk(100, 10, 2.0, earlier_s=30.0)
    assert resumed.seconds == pytest.approx(50.0) and resumed.earlier_s == 30.0
    # a single chunk: the estimate is the time it took
    assert eta.from_first_chunk(9, 9, 1.5).seconds == pytest.approx(1.5)
    with pytest.raises(ValueError):
        eta.from_first_chunk(10, 0, 1.0)


def test_a_cost_per_image_and_call_weighs_the_chunks():
    """COLMAP's matcher builds each image's index once per call: a first chunk of exhaustive pairs
    (a star around the first image) touches more images per pair than the chunks after it."""
    names = [f"i{k:02d}" for k in range(11)]
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]  # 55, exhaustive order
    chunks = [pairs[:8], pairs[8:]]
    assert eta.chunk_work(chunks, 0.0) == [8, 47]
    assert eta.chunk_work(chunks, 1.5) == [8 + 1.5 * 9, 47 + 1.5 * 11]
    work = eta.chunk_work(chunks, 1.5)
    # fountain-P11's first chunk took 23.6 s: 55 / 8 of it would be 162 s, the work says 92 s
    est = eta.from_first_chunk(55, 8, 23.6, work_ratio=sum(work) / work[0])
    assert est.seconds == pytest.approx(23.6 * (55 + 1.5 * 20) / (8 + 1.5 * 9))
    assert est.rate_pairs_per_s == pytest.approx(55 / est.seconds)
    assert est.seconds < eta.from_first_chunk(55, 8, 23.6).seconds


@pytest.mark.parametrize("seconds, words", [
    (0.04, "0.0 s"), (2.46, "2.5 s"), (9.94, "9.9 s"), (10.2, "10 s"), (59.4, "59 s"), (59.6, "1 min"),
    (190.4, "3 min 10 s"), (3599.4, "59 min 59 s"), (3600, "1 h"), (7530, "2 h 6 min"), (86400 * 2, "48 h")])
def test_durations_read_as_people_say_them(seconds, words):
    assert eta.format_duration(seconds) == words


def test_a_duration_is_finite_and_not_negative():
    for bad in (-1.0, math.inf, math.nan):
        with pytest.raises(ValueError):
            eta.format_duration(bad)


def test_the_rounds_time_budget():
    budget = eta.TimeBudget(0.5, first_match_s=60.0, first_map_s=40.0, spent_s=20.0, rate_pairs_per_s=2.0)
    assert budget.total_s == pytest.approx(50.0) and budget.left_s == pytest.approx(30.0)
    assert budget.pairs_that_fit() == 60
    spent = eta.TimeBudget(0.5, 60.0, 40.0, spent_s=55.0, rate_pairs_per_s=2.0)
    assert spent.left_s == 0.0 and spent.pairs_that_fit() == 0
    # the rate unknown: no cut of the pairs, but the time still ends the rounds
    assert eta.TimeBudget(0.5, 60.0, 40.0, spent_s=10.0).pairs_that_fit() is None
    assert eta.TimeBudget(0.5, 60.0, 40.0, spent_s=60.0).pairs_that_fit() == 0
    # 0: no limit at all
    free = eta.TimeBudget(0.0, 60.0, 40.0, spent_s=1e6, rate_pairs_per_s=2.0)
    assert math.isinf(free.total_s) and free.pairs_that_fit() is None
    # less than a pair's time left
    assert eta.TimeBudget(0.5, 1.0, 1.0, spent_s=0.9, rate_pairs_per_s=5.0).pairs_that_fit() == 0


def test_the_time_limit_wins_over_the_pair_caps_of_the_rounds_after_mapping():
    budget, rounds = BudgetConfig(), RoundsConfig()
    free = PairBudget(100, budget, rounds)
    assert free.pose_guided(200, 100) == 100 and free.repair(300, 5) == 100
    held = PairBudget(100, budget, rounds, time_limit=30)
    assert held.pose_guided(200, 100) == 30 and held.repair(300, 5) == 30
    assert PairBudget(100, budget, rounds, time_limit=0).repair(400, 5) == 0  # not even one per left-out view
    assert held.pose_guided(400, 100) == 0  # the pair cap is reached: the time limit gives no more
    # the rounds before mapping and the first selection are not held to it
    assert held.support(200) == free.support(200) and held.first_round() == free.first_round()


def test_run_json_carries_the_estimate_and_the_rounds_share(tmp_path: Path, synthetic_scene, scene_features, caplog):
    """`sara run` with small chunks: the estimate is logged after the first chunk, run.json holds it
    beside the time taken, and both reports show them with the rounds' share of the time."""
    from sara.pipeline import run, share_features
    from sara.report.html import write_report

    images, gt = synthetic_scene
    caplog.set_level("INFO", logger="sara")
    out = tmp_path / "out"
    share_features(scene_features, out)  # the estimates come after extraction
    report = run(make_config("sift-offline", {"match.chunk_size": 3, "rounds.max_time_fraction": 0.5}), images, out,
                 progress=False)
    assert "pairs, about" in caplog.text and "pairs/s (first chunk)" in caplog.text
    saved = read_json(out / "run.json")["stages"]
    match, rounds = saved["match"], saved["rounds"]
    assert match["time_s"] > 0 and match["estimate_s"] > 0
    # the sum of every matching's estimate: made early, never wildly off on this small scene
    assert 0.2 < match["estimate_s"] / match["time_s"] < 5
    assert rounds["first_match_estimate_s"] <= match["estimate_s"]
    assert 0 < rounds["share_after_extraction"] < 1
    assert rounds["total_time_s"] == pytest.approx(rounds.get("before_mapping", {}).get("match_time_s", 0.0)
                                                   + rounds["time_s"])
    assert rounds["time_budget_s"] == pytest.approx(
        0.5 * (rounds["first_match_time_s"] + rounds["first_map_time_s"]))
    assert report.stages["match"]["estimate_s"] == match["estimate_s"]
    text = (out / "report.md").read_text()
    assert "estimated" in text and "of the time after extraction" in text
    html = write_report(out).read_text()
    assert "rounds (in match and map)" in html and "after the first chunk" in html


def test_the_rounds_stop_when_their_time_is_spent_and_do_not_repeat_a_round_without_gain(
        tmp_path: Path, synthetic_scene, scene_features, caplog, monkeypatch):
    from sara.pairs import Round
    from sara.pairs.sara.rounds import SaraRounds
    from sara.pipeline import run, share_features

    images, _ = synthetic_scene
    caplog.set_level("INFO", logger="sara")
    out = tmp_path / "out"
    share_features(scene_features, out)  # the rounds' budget counts the time after extraction
    # a budget no round fits in: the first model is the final one (its tracks extended)
    report = run(make_config("sift-offline", {"rounds.max_time_fraction": 1e-9}), images, out, progress=False)
    rounds = read_json(out / "run.json")["stages"]["rounds"]
    assert rounds["rounds"] == 0 and rounds["stopped"] == "time budget spent"
    assert report.stages["pairs"].get("num_added_after_mapping", 0) == 0
    assert "too little left to match a pair" in caplog.text

    # a round that asks for the same kind of pairs again after one that gained nothing
    asked = []

    def toy_round(self, ctx, pairs, model_dir):
        done = {tuple(sorted(p)) for p in pairs}
        fresh = [(a, b) for i, a in enumerate(ctx.names) for b in ctx.names[i + 1:] if (a, b) not in done]
        asked.append(fresh[0])
        return Round(fresh[:1], "toy")

    monkeypatch.setattr(SaraRounds, "after_mapping", toy_round)
    monkeypatch.setattr(SaraRounds, "refine", lambda self, *args: None)
    run(make_config("sift-offline", {"rounds.max_time_fraction": 0, "rounds.repair_rounds": 3}), images, out,
        progress=False)
    rounds = read_json(out / "run.json")["stages"]["rounds"]
    assert len(asked) == 2 and rounds["rounds"] == 1  # asked twice, run once
    assert rounds["stopped"] == "a round without gain asked for again" and rounds["unproductive_roles"] == ["toy"]
    assert rounds["history"][0]["registered"] == [10, 10] and rounds["history"][0]["gain"] is False
    assert rounds["time_budget_s"] is None  # 0: no limit


def test_the_first_chunk_is_small_so_that_the_estimate_comes_early():
    from sara.match import chunked

    pairs = [(f"a{k}", f"b{k}") for k in range(1081)]
    chunks = chunked(pairs, 128)
    assert [len(c) for c in chunks[:2]] == [55, 128] and sum(map(len, chunks)) == 1081
    assert [p for c in chunks for p in c] == pairs  # every pair once, in order
    assert [len(c) for c in chunked(pairs[:55], 128)] == [8, 47]
    assert [len(c) for c in chunked(pairs[:5], 128)] == [5]
    assert [len(c) for c in chunked(pairs[:20], 4)] == [4] * 5  # never above a chunk
    assert chunked([], 128) == []
