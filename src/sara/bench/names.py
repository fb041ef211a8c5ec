"""A bench scene under other file names: the same images and true poses, the names drawn at random.

COLMAP numbers images in name order, and its matching and mapping break ties by those numbers: which
image of a pair is the first, which pair starts the model, which view is registered next. SARA's
spanning tree breaks ties between equal weights the same way. So every method's accuracy depends a
little on the file names. On the shared scenes, random names move exhaustive matching's AUC@1 by up
to 0.04, far more than many differences between methods. `sara bench
--name-orders K` runs each scene again under K random namings, so that a comparison can be read over
several of them instead of one.

A renamed scene is ``ROOT/<scene>~names<k>/`` with ``images/`` (links to the original files, copies
where links cannot be made), ``gt/`` (the true model with the new names, COLMAP text), ``masks/``
where the scene has masks (each linked under its image's new name), and ``names.json`` mapping each
original name to its new one. It is built in a temporary folder and
moved into place, and reused when it exists with the same names.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from ..colmap.model import read_model, write_model
from ..io import link_or_copy, read_json, write_json_atomic
from ..io.images import list_image_files
from ..masks import mask_file

#: separates a scene's name from its naming in the renamed scene's folder name
SEPARATOR = "~names"
MAPPING_FILE = "names.json"


def new_names(names: list[str], order: int) -> dict[str, str]:
    """Each of `names` (flat file names) -> ``n<index><suffix>``, the indices a random permutation
    drawn from `order` (>= 1); the same `order` always gives the same names."""
    if order < 1:
        raise ValueError(f"a name order is a positive integer, got {order}")
    permutation = np.random.default_rng([order, len(names)]).permutation(len(names))
    width = len(str(max(len(names) - 1, 0)))
    return {name: f"n{int(k):0{width}d}{Path(name).suffix.lower()}" for name, k in zip(names, permutation)}


def renamed_scene(scene: Path, root: Path, order: int) -> Path:
    """``root/<scene name>~names<order>``: `scene` (``images/`` and ``gt/``) under the names of
    `new_names`; built once, reused after. Hidden files are left out, as runs skip them; images of the
    true model that images/ lacks keep their names. Raises ValueError for a scene whose images are in
    sub-folders."""
    scene = Path(scene).resolve()
    images = scene / "images"
    names = [n for n in list_image_files(images) if not n.startswith(".")]  # hidden files are skipped by runs
    if any("/" in n for n in names):
        raise ValueError(f"{scene}: renaming needs the images directly in images/, not in sub-folders")
    mapping = new_names(names, order)
    dest = Path(root) / f"{scene.name}{SEPARATOR}{order}"
    if ((dest / MAPPING_FILE).is_file() and read_json(dest / MAPPING_FILE) == mapping
            and (dest / "masks").is_dir() == (scene / "masks").is_dir()):
        return dest
    # images the true model has and images/ lacks keep their names (a run counts them as not registered)
    clashes = sorted((set(read_model(scene / "gt").names) - set(mapping)) & set(mapping.values()))
    if clashes:
        raise ValueError(f"{scene}: the true model names {clashes[0]}, which is not in images/ and is one of "
                         "the new names; rename it")
    Path(root).mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", dir=root))
    try:
        (work / "images").mkdir()
        for name, new in mapping.items():
            link_or_copy(images / name, work / "images" / new, symbolic=True)
        write_model(scene / "gt", work / "gt", rename=mapping, text=True)
        if (scene / "masks").is_dir():  # each image's mask under its new name, as COLMAP names masks
            (work / "masks").mkdir()
            for name, new in mapping.items():
                if (found := mask_file(scene / "masks", name)) is not None:
                    link_or_copy(found, work / "masks" / f"{new}.png", symbolic=True)
        write_json_atomic(work / MAPPING_FILE, mapping)
        if dest.exists():
            shutil.rmtree(dest)
        work.rename(dest)
    finally:
        if work.exists():
            shutil.rmtree(work, ignore_errors=True)
    return dest


def base_scene(name: str) -> str:
    """The original scene's name of a (possibly) renamed scene's name."""
    return name.split(SEPARATOR)[0]
