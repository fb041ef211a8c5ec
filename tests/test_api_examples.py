"""The Python examples of the docs run as written.

Every ```python block of the sections "hloc" (docs/interop.md) and "Python API" (docs/usage.md)
runs, in order and in one namespace, in a folder holding `images/` and `gt/` of a synthetic scene.

hloc is not installed here (it pulls CUDA torch), so the hloc example runs against a stand-in
`hloc` package with the two functions it calls, mirroring hloc's signatures and file names
(`extract_features.main(conf, image_dir, export_dir) -> export_dir / (conf["output"] + ".h5")`,
`match_features.main(conf, pairs, features, export_dir) ->
export_dir / f"{features}_{conf['output']}_{pairs.stem}.h5"`): the extractor writes SuperPoint-like
features of the scene's true observations and the matcher is a mutual nearest neighbour matcher
(see tests/test_hloc.py).

The examples' output folders `out/` and `pairs_only/` start with the scene's SIFT features
(`scene_features`, made once for the session), so their runs resume after extraction, as a run
does on a folder that holds its features: two extractions less, and extraction is tested elsewhere.
"""

from __future__ import annotations

import os
import re
import shutil
import sys
import types
from pathlib import Path

import pytest

from test_hloc import match_mutual_nn, write_superpoint_like

DOCS = [Path(__file__).resolve().parents[1] / "docs" / name for name in ("interop.md", "usage.md")]
SECTIONS = ("hloc", "Python API")



def python_blocks(markdown: str) -> list[str]:
    """The ```python blocks of the sections in SECTIONS, in order."""
    blocks = []
    for title in SECTIONS:
        match = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", markdown, re.DOTALL | re.MULTILINE)
        if match is None:
            raise AssertionError(f"docs section {title!r} missing")
        blocks += re.findall(r"```python\n(.*?)```", match.group(1), re.DOTALL)
    return blocks


def examples_source() -> str:
    return "\n".join(path.read_text(encoding="utf-8") for path in DOCS)


def fake_hloc(gt_dir: Path) -> types.ModuleType:
    """A stand-in `hloc` package: extract_features and match_features with hloc's signatures."""
    extract_features = types.ModuleType("hloc.extract_features")
    extract_features.confs = {"superpoint_aachen": {"output": "feats-superpoint-n4096-r1024"}}

    def extract(conf: dict, image_dir: Path, export_dir: Path) -> Path:
        path = Path(export_dir) / (conf["output"] + ".h5")
        path.parent.mkdir(parents=True, exist_ok=True)
        write_superpoint_like(gt_dir, path)
        return path

    extract_features.main = extract
    match_features = types.ModuleType("hloc.match_features")
    match_features.confs = {"superpoint+lightglue": {"output": "matches-superpoint-lightglue"}}

    def match(conf: dict, pairs: Path, features: str, export_dir: Path) -> Path:
        out = Path(export_dir) / f"{features}_{conf['output']}_{Path(pairs).stem}.h5"
        return match_mutual_nn(Path(export_dir) / f"{features}.h5", Path(pairs), out)

    match_features.main = match
    package = types.ModuleType("hloc")
    package.extract_features, package.match_features = extract_features, match_features
    return package


def test_readme_python_examples_run(synthetic_scene, scene_features, tmp_path: Path, monkeypatch):
    from sara.pipeline import share_features

    images, gt = synthetic_scene
    shutil.copytree(images, tmp_path / "images")
    shutil.copytree(gt, tmp_path / "gt")
    for out in ("out", "pairs_only"):
        share_features(scene_features, tmp_path / out)
    package = fake_hloc(tmp_path / "gt")
    for name, module in (("hloc", package), ("hloc.extract_features", package.extract_features),
                         ("hloc.match_features", package.match_features)):
        monkeypatch.setitem(sys.modules, name, module)
    monkeypatch.chdir(tmp_path)
    blocks = python_blocks(examples_source())
    assert len(blocks) >= 4
    namespace: dict = {"__name__": "readme"}
    for block in blocks:
        exec(compile(block, "docs", "exec"), namespace)  # noqa: S102 - the docs' own examples

    assert (tmp_path / "outputs" / "sfm" / "sparse" / "0" / "images.bin").exists()
    assert namespace["model_dir"] == Path("out/sparse/0") and (tmp_path / "out/sparse/0").is_dir()
    assert (tmp_path / "pairs_only" / "pairs.txt").stat().st_size > 0
    assert not (tmp_path / "pairs_only" / "sparse").exists()
    assert (tmp_path / "gs" / "sparse" / "0" / "cameras.bin").exists()
    assert (tmp_path / "ns" / "transforms.json").exists()
    assert (tmp_path / "colmap_project" / "project.ini").exists()
    assert namespace["report_html"] == Path("out/report.html") and (tmp_path / "out/report.html").exists()
    assert namespace["metrics"]["num_registered"] == len(os.listdir(images))


def test_draft_has_the_sections():
    assert len(python_blocks(examples_source())) == 5
    with pytest.raises(AssertionError, match="missing"):
        python_blocks("## Python API\n```python\npass\n```\n")
