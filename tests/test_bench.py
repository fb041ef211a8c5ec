"""`sara bench` on a small synthetic scene: shared features, one row per method, JSON/CSV/MD, resume."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

import sara.bench.tables  # noqa: F401
import sara.pipeline
from sara import bench, colmap, extract
from sara.cli import main
from sara.config import apply_overrides, make_config
from sara.io import records
from sara.pipeline import share_features


def _features_shared(scene_features: Path, bench_out: Path, scene: Path) -> None:
    """The bench's extraction of `scene` into `bench_out` done already (the scene's shared features): its
    own extraction skips, as when a bench runs again (the name-orders test extracts for real)."""
    share_features(scene_features, bench_out / scene.name / "features")


@pytest.fixture(scope="module")
def bench_run(tmp_path_factory, synthetic_scene, scene_features):
    images, _ = synthetic_scene
    out = tmp_path_factory.mktemp("bench")
    _features_shared(scene_features, out, images.parent)
    conf = make_config("sift-offline", {"sequential.overlap": "3"})
    result = bench.run_bench([images.parent], out, conf, methods=["exhaustive", "sequential"], progress=False)
    return images.parent, out, conf, result


def test_bench_writes_tables_with_expected_rows_and_columns(bench_run):
    scene, out, _, result = bench_run
    for name in ("results.json", "results.csv", "results.md"):
        assert (out / name).is_file(), name
    with open(out / "results.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert list(rows[0]) == list(bench.tables.ROW_FIELDS)
    assert [(r["scene"], r["method"]) for r in rows] == [(scene.name, "exhaustive"), (scene.name, "sequential")]
    by_method = {r["method"]: r for r in json.loads((out / "results.json").read_text())["rows"]}
    assert by_method["exhaustive"]["pairs"] == 45 and by_method["sequential"]["pairs"] == 24  # 10 images, overlap 3
    assert by_method["exhaustive"]["pairs_vs_exhaustive"] == 1.0
    assert by_method["sequential"]["pairs_vs_exhaustive"] == pytest.approx(24 / 45)
    for method, row in by_method.items():
        assert row["error"] is None
        assert row["num_registered"] == 10 and row["registered_pct"] == 100.0
        assert row["auc@5"] > 0.8 and row["points3d"] > 0 and row["track_length"] > 2
        assert row["matches_per_pair"] > 0 and row["match_s"] > 0
        # no vocabulary tree in these methods: the selection time is the pairs stage's own, as recorded
        stages = json.loads((out / scene.name / method / "run.json").read_text())["stages"]
        assert row["tree_build_s"] == 0.0 and row["select_s"] == stages["pairs"]["time_s"] > 0
    markdown = (out / "results.md").read_text()
    for _, title, _ in bench.TABLE_COLUMNS:
        assert title in markdown
    assert "| exhaustive |" in markdown and "| sequential |" in markdown


def test_bench_shares_one_extraction(bench_run):
    scene, out, _, _ = bench_run
    features_key = records.read_record(out / scene.name / "features", extract.STAGE)["key"]
    for method in ("exhaustive", "sequential"):
        method_dir = out / scene.name / method
        assert records.read_record(method_dir, extract.STAGE)["key"] == features_key
        run_json = json.loads((method_dir / "run.json").read_text())
        assert run_json["config"]["pairs"]["method"] == method
        assert run_json["stages"]["extract"]["num_images"] == 10  # recorded by the shared extraction


def test_bench_rerun_skips_finished_methods(bench_run, monkeypatch):
    scene, out, conf, first = bench_run
    calls = []
    original = sara.pipeline.run

    def counting_run(*args, **kwargs):
        calls.append(kwargs.get("stop_after"))
        return original(*args, **kwargs)

    monkeypatch.setattr(sara.pipeline, "run", counting_run)
    again = bench.run_bench([scene], out, conf, methods=["exhaustive", "sequential"], progress=False, plot=False)
    assert calls == ["extract"]  # only the (skipped) shared extraction; no method ran again
    assert again.rows == first.rows


def test_bench_cli_resumes_and_prints(bench_run, capsys):
    scene, out, _, _ = bench_run
    code = main(["bench", str(scene), "--out", str(out), "--methods", "exhaustive,sequential",
                 "-s", "sequential.overlap=3", "--no-plot", "-q"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "| exhaustive |" in printed and "results.csv" in printed


def test_prepare_method_dir_recopies_stale_features(bench_run, tmp_path: Path):
    scene, out, _, _ = bench_run
    features = out / scene.name / "features"
    target = tmp_path / "method"
    assert share_features(features, target) is True
    assert share_features(features, target) is False  # same features: kept, so a run resumes
    records.mark_done(target, "match", "some-key")
    records.mark_done(target, extract.STAGE, "features-of-another-extraction")
    assert share_features(features, target) is True
    assert records.read_record(target, "match") is None  # no stage may skip on matches of other features
    summary = colmap.database_summary(target / extract.DB_NAME)  # the features, without matches
    assert summary["num_images"] == 10 and summary["num_matched_pairs"] == 0


def test_bench_input_errors(tmp_path: Path):
    with pytest.raises(ValueError, match="unknown method 'nope'"):
        bench.parse_methods("exhaustive,nope")
    assert bench.parse_methods("sara, exhaustive,sara") == ["sara", "exhaustive"]
    (tmp_path / "scene" / "images").mkdir(parents=True)
    with pytest.raises(FileNotFoundError, match="has no gt/"):
        bench.run_bench([tmp_path / "scene"], tmp_path / "out", make_config(), methods=["exhaustive"])
    assert main(["bench", str(tmp_path / "scene"), "--out", str(tmp_path / "out"), "-s", "pairs.method=sara"]) == 2
    (tmp_path / "scene" / "gt").mkdir()
    with pytest.raises(ValueError, match="name_orders must be >= 0"):
        bench.run_bench([tmp_path / "scene"], tmp_path / "out", make_config(), methods=["exhaustive"], name_orders=-1)


def test_markdown_marks_failed_methods():
    rows = [{"scene": "s", "method": "exhaustive", "pairs": 10, "auc@5": 0.5, "error": None},
            {"scene": "s", "method": "sara", "error": "ModuleNotFoundError: no sara"}]
    table = bench.tables.method_table(rows, bench.TABLE_COLUMNS)
    assert "| sara | failed: ModuleNotFoundError: no sara |" in table
    assert "| exhaustive | - |" in table  # missing values print as '-'


def test_ablation_variants_switch_the_graph_stages():
    conf = make_config()
    for variant, overrides in bench.ABLATION_VARIANTS.items():
        graph = apply_overrides(conf, overrides).graph
        flags = (graph.use_loops, graph.use_anchors, graph.use_weak)
        expected = {"full": (True, True, True), "tree_only": (False, False, False),
                    "only_loops": (True, False, False), "no_weak": (True, True, False)}
        if variant in expected:
            assert flags == expected[variant], variant
    assert len(bench.ABLATION_VARIANTS) == 8


def test_a_renamed_scene_holds_the_same_images_and_poses_under_new_names(synthetic_scene, tmp_path: Path):
    import numpy as np
    import pycolmap

    from sara.bench.names import MAPPING_FILE, new_names, renamed_scene

    images, gt = synthetic_scene
    scene = images.parent
    renamed = renamed_scene(scene, tmp_path, 1)
    assert renamed == tmp_path / f"{scene.name}~names1"
    mapping = json.loads((renamed / MAPPING_FILE).read_text())
    originals = sorted(p.name for p in images.iterdir())
    assert sorted(mapping) == originals
    assert sorted(p.name for p in (renamed / "images").iterdir()) == sorted(mapping.values())
    assert sorted(mapping.values()) != [mapping[n] for n in originals]  # the name order is not kept
    for old, new in mapping.items():
        assert (renamed / "images" / new).read_bytes() == (images / old).read_bytes()
    truth, moved = pycolmap.Reconstruction(str(gt)), pycolmap.Reconstruction(str(renamed / "gt"))
    by_name = {im.name: im for im in moved.images.values()}
    for image in truth.images.values():
        other = by_name[mapping[image.name]]
        assert np.allclose(other.cam_from_world().matrix(), image.cam_from_world().matrix())
        assert np.allclose(moved.cameras[other.camera_id].params, truth.cameras[image.camera_id].params)
    # the same order gives the same names and reuses the folder; another order other names
    stamp = (renamed / MAPPING_FILE).stat().st_mtime_ns
    assert renamed_scene(scene, tmp_path, 1) == renamed and (renamed / MAPPING_FILE).stat().st_mtime_ns == stamp
    assert new_names(originals, 2) != mapping and new_names(originals, 1) == mapping
    with pytest.raises(ValueError, match="positive"):
        new_names(originals, 0)


def test_bench_over_name_orders_sums_each_method_up_over_the_namings(five_view_scene, tmp_path: Path):
    images, _ = five_view_scene  # 5 views: two namings, two extractions
    out = tmp_path / "bench"
    result = bench.run_bench([images.parent], out, make_config(), methods=["exhaustive"], progress=False,
                             plot=False, name_orders=1)
    name = images.parent.name
    assert [r["scene"] for r in result.rows] == [name, f"{name}~names1"]
    assert all(r["registered_pct"] == 100.0 and r["auc@5"] is not None for r in result.rows)
    summary = json.loads((out / "names.json").read_text())["summary"]
    assert [(e["scene"], e["method"], e["namings"]) for e in summary] == [(name, "exhaustive", 2)]
    aucs = [r["auc@1"] for r in result.rows]
    assert summary[0]["auc@1_min"] == min(aucs) and summary[0]["auc@1_max"] == max(aucs)
    assert summary[0]["auc@1_mean"] == pytest.approx(sum(aucs) / 2)
    assert "| " + name + " | exhaustive | 2 |" in (out / "names.md").read_text()


def test_names_summary_counts_only_the_namings_that_ran():
    rows = [{"scene": "s", "method": "sara", "auc@1": 0.5, "auc@5": 0.9, "registered_pct": 100.0, "pairs": 10},
            {"scene": "s~names1", "method": "sara", "auc@1": 0.7, "auc@5": 0.8, "registered_pct": 90.0, "pairs": 12},
            {"scene": "s~names2", "method": "sara", "error": "RuntimeError: no model"}]
    (entry,) = bench.names_summary(rows)
    assert entry["namings"] == 2 and entry["auc@1_mean"] == pytest.approx(0.6)
    spread = (entry["auc@5_min"], entry["auc@5_max"], entry["registered_pct_min"], entry["pairs_mean"])
    assert spread == (0.8, 0.9, 90.0, 11)
    assert "0.6000 (0.5000-0.7000)" in bench.render_names([entry])
    assert "auc@1_vs_exhaustive" not in entry  # no exhaustive row to compare with


def test_names_summary_compares_with_exhaustive_under_the_same_naming():
    def row(scene, method, auc1, auc5):
        return {"scene": scene, "method": method, "auc@1": auc1, "auc@5": auc5, "registered_pct": 100.0, "pairs": 1}
    rows = [row("s", "exhaustive", 0.50, 0.90), row("s", "sara", 0.52, 0.89),
            row("s~names1", "exhaustive", 0.40, 0.80), row("s~names1", "sara", 0.39, 0.81),
            row("s~names2", "sara", 0.99, 0.99)]  # no exhaustive under naming 2: not paired
    by_method = {e["method"]: e for e in bench.names_summary(rows)}
    assert "auc@1_vs_exhaustive" not in by_method["exhaustive"]
    diff = by_method["sara"]["auc@1_vs_exhaustive"]
    assert (diff["namings"], diff["at_least"]) == (2, 1)
    assert (diff["mean"], diff["min"], diff["max"]) == pytest.approx((0.005, -0.01, 0.02))
    assert by_method["sara"]["namings"] == 3
    assert "+0.0050 (-0.0100 to +0.0200); at least in 1 of 2" in bench.render_names([by_method["sara"]])


def test_renaming_leaves_hidden_files_out_and_keeps_true_images_that_are_missing(synthetic_scene, tmp_path: Path):
    import shutil

    from sara.bench.names import MAPPING_FILE, renamed_scene
    from sara.colmap.model import read_model

    images, gt = synthetic_scene
    scene = tmp_path / "scene"
    shutil.copytree(images.parent, scene)
    first, *rest = sorted(p.name for p in (scene / "images").iterdir())
    (scene / "images" / first).rename(scene / "images" / f".{first}")  # hidden: runs skip it
    renamed = renamed_scene(scene, tmp_path / "renamed", 3)
    mapping = json.loads((renamed / MAPPING_FILE).read_text())
    assert sorted(mapping) == rest and len(list((renamed / "images").iterdir())) == len(rest)
    names = read_model(renamed / "gt").names
    assert first in names and sorted(set(names) - {first}) == sorted(mapping.values())


def _kind_row(scene, method, auc1, auc5, pairs=10, after=5.0):
    return {"scene": scene, "method": method, "auc@1": auc1, "auc@5": auc5, "pairs": pairs, "num_registered": 9,
            "num_components": 1, "after_extract_s": after, "end_to_end_s": after + 2}


def test_kind_summary_reads_sara_against_each_method_with_exhaustives_band():
    rows = [_kind_row("s", "exhaustive", 0.50, 0.90), _kind_row("s~names1", "exhaustive", 0.48, 0.90),
            _kind_row("s", "sara", 0.51, 0.91), _kind_row("s~names1", "sara", 0.49, 0.89),
            _kind_row("s", "retrieval", 0.40, 0.85), _kind_row("s", "sequential-loop", 0.60, 0.95)]
    entries = {e["method"]: e for e in bench.kind_summary(rows, {"s": "driving"})}
    assert entries["sara"]["band"] == pytest.approx({"auc@1": 0.04, "auc@5": 0.0})
    assert entries["exhaustive"]["sara_verdict"] == "within band"  # @1 +0.01 < 0.04, @5 equal
    assert entries["retrieval"]["sara_verdict"] == "better"
    assert entries["sequential-loop"]["sara_verdict"] == "worse"
    assert entries["sara"]["kind"] == "driving" and entries["sara"]["sara_verdict"] == ""
    text = bench.render_kinds(list(entries.values()))
    assert "## driving" in text and "0.500 (0.490-0.510)" in text


def test_kind_summary_without_namings_has_no_band():
    rows = [_kind_row("s", "exhaustive", 0.5, 0.9), _kind_row("s", "sara", 0.9, 0.99)]
    (sara_row,) = [e for e in bench.kind_summary(rows, {}) if e["method"] == "exhaustive"]
    assert sara_row["sara_verdict"] == "no band" and sara_row["kind"] == "unspecified"


def test_kinds_are_parsed_and_bad_ones_refused():
    assert bench.parse_kinds(["kitti-seq1=driving", " a = b "]) == {"kitti-seq1": "driving", "a": "b"}
    with pytest.raises(ValueError, match="SCENE=KIND"):
        bench.parse_kinds(["kitti-seq1"])


def test_sequential_with_loop_detection_is_a_bench_method(bench_run, scene_features, tmp_path: Path):
    scene, _, conf, _ = bench_run
    _features_shared(scene_features, tmp_path / "b", scene)
    assert bench.parse_methods("sequential-loop,sara") == ["sequential-loop", "sara"]
    result = bench.run_bench([scene], tmp_path / "b", conf, methods=["sequential-loop"], progress=False, plot=False,
                             kinds={scene.name: "orbit"})
    (row,) = result.rows
    assert row["method"] == "sequential-loop" and not row.get("error")
    pairs = json.loads((tmp_path / "b" / scene.name / "sequential-loop" / "run.json").read_text())["stages"]["pairs"]
    assert pairs["num_loop_pairs_added"] > 0
    assert row["end_to_end_s"] >= row["after_extract_s"] > 0
    assert "## orbit" in (tmp_path / "b" / "kinds.md").read_text()
