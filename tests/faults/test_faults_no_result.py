"""Class 2 of the fault suite: a failed or degenerate run never destroys a good one. A run or a
match that ends without a result (exit 5) or stops on a bad option (exit 2) leaves the previous
matches, model, run.json and report.md as they were, and no half-made copy beside them."""

from __future__ import annotations

from pathlib import Path

import pytest

from harness import PREVIOUS_OUTPUTS, assert_error, assert_kept, best_matched_pair, snapshot


def _pairs_file(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "my_pairs.txt"
    path.write_text(text)
    return path


NO_RESULT = {
    "empty pairs file": (lambda t, out: ["--pairs", _pairs_file(t, "")], "lists no pairs"),
    "pairs file of comments": (lambda t, out: ["--pairs", _pairs_file(t, "# nothing\n\n#  a b\n")], "lists no pairs"),
    "scores reject every pair": (lambda t, out: ["-s", "score.min_overlap=1"], "selected no pairs",
                                 "relax the score.* thresholds"),
    "verification rejects every pair": (lambda t, out: ["-s", "match.min_num_inliers=100000"], "none of the",
                                        "match.min_num_inliers"),
}


@pytest.mark.parametrize("case", list(NO_RESULT))
def test_run_without_result_keeps_previous_outputs(case, finished_run, images, tmp_path, run_cli):
    """Exit 5, one line saying why, and the previous matches, model, run.json and report.md kept."""
    make_args, *fragments = NO_RESULT[case]
    args = make_args(tmp_path, finished_run)
    before = snapshot(finished_run)
    result = run_cli("run", images, finished_run, "-q", *args)
    assert_error(result, 5, *fragments)
    assert_kept(before, finished_run, PREVIOUS_OUTPUTS)
    assert not (finished_run / ".sara" / "database.next.db").exists()
    assert not (finished_run / ".sara" / "pairs.next").exists()


def test_a_mapping_without_a_model_keeps_previous_outputs(finished_run, images, tmp_path, run_cli, monkeypatch):
    """The mapper builds nothing from the pair of the scene with the most inlier matches (over the 100
    COLMAP's mapper needs to start): exit 5, the reason from the verified pairs, the previous outputs
    kept. Two views make a model now (with the points seen in two views), so COLMAP's refusal is
    stood in for: every mapping returns no model."""
    from sara import colmap

    monkeypatch.setattr(colmap, "incremental_mapping", lambda *args, **kwargs: colmap.MappedModels({}))
    pairs = _pairs_file(tmp_path, "{} {}\n".format(*best_matched_pair(finished_run)[:2]))
    before = snapshot(finished_run)
    result = run_cli("run", images, finished_run, "-q", "--pairs", pairs)
    assert_error(result, 5, "no model could be built", "degrees of triangulation angle", "two views only")
    assert_kept(before, finished_run, PREVIOUS_OUTPUTS)
    assert not (finished_run / ".sara" / "database.next.db").exists()


@pytest.mark.parametrize("case", ["empty pairs file", "no verified pair"])
def test_match_without_result_keeps_previous_matches(case, finished_run, tmp_path, run_cli):
    args = ["--pairs", _pairs_file(tmp_path, "")] if case == "empty pairs file" else \
        ["-s", "match.min_num_inliers=100000"]
    before = snapshot(finished_run)
    result = run_cli("match", finished_run, "-q", *args)
    assert_error(result, 5)
    assert_kept(before, finished_run)


BAD_OPTIONS_OF_A_RUN = {
    "seed": (["--seed", "-1"], "--seed", "seed must be an integer from 0 to"),
    "extract backend": (["-s", "extract.backend=nope"], "extract.backend must be one of"),
    "matcher": (["-s", "match.backend=nope"], "match.backend must be auto or one of"),
    "descriptor": (["-s", "retrieval.descriptor=nope"], "retrieval.descriptor must be one of"),
    "pair source": (["--pairs", "nope"], "not a pair source"),
    "unknown option": (["-s", "retrieval.k=3"], "unknown option 'retrieval.k'"),
}


@pytest.mark.parametrize("case", list(BAD_OPTIONS_OF_A_RUN))
def test_bad_option_leaves_run_json(case, finished_run, images, run_cli):
    """A run stopped by a bad option writes nothing: run.json still describes sparse/0 and report.md."""
    args, *fragments = BAD_OPTIONS_OF_A_RUN[case]
    before = snapshot(finished_run)
    result = run_cli("run", images, finished_run, "-q", *args)
    assert_error(result, 2, *fragments)
    assert_kept(before, finished_run)


