"""The Python examples of README.md run as written.

Every ```python block of the sections "Use with 3DGS / nerfstudio / hloc / COLMAP" and "Python API"
runs, in order and in one namespace, in a folder holding `images/` and `gt/` of a synthetic scene.
Until README.md has those sections, the drafts below (proposed for README.md) run instead.

hloc is not installed here (it pulls CUDA torch), so the hloc example runs against a stand-in
`hloc` package with the two functions it calls, mirroring hloc's signatures and file names
(`extract_features.main(conf, image_dir, export_dir) -> export_dir / (conf["output"] + ".h5")`,
`match_features.main(conf, pairs, features, export_dir) ->
export_dir / f"{features}_{conf['output']}_{pairs.stem}.h5"`): the extractor writes SuperPoint-like
features of the scene's true observations and the matcher is a mutual nearest neighbour matcher
(see tests/test_hloc.py).
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

README = Path(__file__).resolve().parents[1] / "README.md"
SECTIONS = ("Use with 3DGS / nerfstudio / hloc / COLMAP", "Python API")

DRAFT = '''
## Use with 3DGS / nerfstudio / hloc / COLMAP

`sara run` leaves a COLMAP model (`out/sparse/0`, SIMPLE_RADIAL cameras, the original images).
`sara export` writes it in the layout each tool reads (`sara run IMAGES OUT --export 3dgs` does both
in one go, into `OUT/3dgs`):

```bash
sara export out/ gs/ --format 3dgs              # gs/images (undistorted), gs/sparse/0 (PINHOLE cameras)
sara export out/ ns/ --format nerfstudio        # ns/transforms.json, ns/images, ns/sparse_pc.ply
sara export out/ colmap_project/ --format colmap  # database.db, sparse/0, project.ini
sara report out/                                # out/report.html: why these pairs, what came of them
```

**3D Gaussian Splatting** accepts only undistorted PINHOLE / SIMPLE_PINHOLE models; the export
undistorts the images with COLMAP's undistorter (`--max-image-size 1600` also downsizes them). In a
clone of graphdeco-inria/gaussian-splatting:

```bash
python train.py -s gs/
```

**nerfstudio** reads the export with its default `nerfstudio-data` parser (OpenCV camera model with
COLMAP's distortion, `applied_transform`, the points for splatfacto's initialisation); neither
ffmpeg nor a colmap binary is needed:

```bash
ns-train splatfacto --data ns/
```

**hloc**: SARA selects the pairs from the features hloc already extracted (SuperPoint, DISK,
ALIKED, ... any local features), in place of `pairs_from_exhaustive` or `pairs_from_retrieval`;
hloc then matches them as usual. `sara.hloc.reconstruct` imports hloc's matches into a COLMAP
database and maps with sara's settings (hloc's own `reconstruction.main` works as well):

```python
from pathlib import Path

from hloc import extract_features, match_features
from sara import hloc as sara_hloc

images, outputs = Path("images"), Path("outputs")
feature_conf = extract_features.confs["superpoint_aachen"]
matcher_conf = match_features.confs["superpoint+lightglue"]
features = extract_features.main(feature_conf, images, outputs)
pairs = sara_hloc.select_pairs(features, outputs / "pairs-sara.txt")
matches = match_features.main(matcher_conf, pairs, feature_conf["output"], outputs)
model_dir = sara_hloc.reconstruct(images, features, matches, pairs, outputs / "sfm")
```

SARA's scores and its global descriptors (hloc's layout: one group per image holding
`global_descriptor`) are left in `outputs/pairs-sara-sara/`.

**COLMAP** 4.x opens the export (the database has COLMAP 4's rig and frame tables, which
Debian's colmap 3.8 cannot read; the models in `sparse/` are readable by 3.8 too):

```bash
colmap gui --project_path colmap_project/project.ini
colmap gui --import_path colmap_project/sparse/0 --database_path colmap_project/database.db --image_path path/to/images
```

## Python API

Every stage is a function; the functions that write files return their paths.

```python
from pathlib import Path

from sara.config import make_config
from sara.pipeline import run

report = run(make_config("sift-offline"), Path("images"), Path("out"))  # resumes like `sara run`
model_dir = Path("out/sparse/0")
print(report.stages["pairs"]["num_pairs"], "pairs matched;", report.stages["map"]["num_registered"], "images posed")
```

Only the pairs (SARA's by default; `pairs.method` takes the other sources or a pairs file), with
any configuration value set as on the command line:

```python
conf = make_config("sift-offline", {"pairs.method": "sara", "retrieval.num_neighbors": 10})
run(conf, Path("images"), Path("pairs_only"), stop_after="pairs")
pairs_txt = Path("pairs_only/pairs.txt")  # `name0 name1` per line, for hloc or COLMAP's matches_importer
```

Accuracy against known poses, the exports and the report:

```python
from sara.evaluation import evaluate
from sara.export import export
from sara.report.html import write_report

metrics = evaluate(Path("out/sparse"), Path("gt"), Path("out/metrics.json"))
print(f"AUC@5: {metrics['auc']['5']:.3f}")
gs_dir = export(Path("out"), Path("gs"), "3dgs")
ns_dir = export(Path("out"), Path("ns"), "nerfstudio")
colmap_dir = export(Path("out"), Path("colmap_project"), "colmap")
report_html = write_report(Path("out"))
```
'''


def python_blocks(markdown: str) -> list[str]:
    """The ```python blocks of the README sections in SECTIONS, in order."""
    blocks = []
    for title in SECTIONS:
        match = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", markdown, re.DOTALL | re.MULTILINE)
        if match is None:
            raise AssertionError(f"README section {title!r} missing")
        blocks += re.findall(r"```python\n(.*?)```", match.group(1), re.DOTALL)
    return blocks


def examples_source() -> str:
    text = README.read_text(encoding="utf-8") if README.exists() else ""
    return text if all(f"## {t}\n" in text for t in SECTIONS) else DRAFT


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


def test_readme_python_examples_run(synthetic_scene, tmp_path: Path, monkeypatch):
    images, gt = synthetic_scene
    shutil.copytree(images, tmp_path / "images")
    shutil.copytree(gt, tmp_path / "gt")
    package = fake_hloc(tmp_path / "gt")
    for name, module in (("hloc", package), ("hloc.extract_features", package.extract_features),
                         ("hloc.match_features", package.match_features)):
        monkeypatch.setitem(sys.modules, name, module)
    monkeypatch.chdir(tmp_path)
    blocks = python_blocks(examples_source())
    assert len(blocks) >= 4
    namespace: dict = {"__name__": "readme"}
    for block in blocks:
        exec(compile(block, "README.md", "exec"), namespace)  # noqa: S102 - the README's own examples

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
    assert len(python_blocks(DRAFT)) == 4
    with pytest.raises(AssertionError, match="missing"):
        python_blocks("## Python API\n```python\npass\n```\n")
