"""The house's rules, checked on the source: arrows point down (no module imports a higher layer),
no import cycle between rooms, pycolmap only in `sara.colmap`, heavy optional packages only inside
the backends that need them (and never at import time of the package)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "sara"

#: room -> floor; a room may import rooms on its own floor or below, never above
FLOORS = {
    "__init__": 0, "registry": 0, "tables": 0, "descriptors": 0, "rotations": 0, "config": 0, "execute": 0,
    "eta": 0,
    "io": 1,
    "colmap": 2, "weights": 2,
    "features": 3, "matchers": 3, "scoring": 3, "retrieval": 3, "selection": 3, "evaluation": 3,
    "execute_ray": 3, "model_files": 3,
    "cameras": 4, "overlay": 4, "masks": 4,
    "extract": 4, "incremental": 4, "match": 4, "mapping": 4, "map_retries": 4, "map_schedule": 4, "pairs": 4,
    "gt_pairs": 4, "synthetic": 4, "video": 4,
    "pipeline": 5, "export": 5,
    "report": 6, "hloc": 6,
    "bench": 7, "demo": 7,
    "cli": 8, "__main__": 9,
}
HEAVY = {"torch", "kornia", "ray", "faiss", "matplotlib"}


def _room(module_path: Path) -> str:
    return module_path.relative_to(SRC).parts[0].removesuffix(".py")


def _imports(path: Path) -> list[tuple[str, int, bool]]:
    """(imported sara room or external top-level name, line, at module level?) of one file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = path.relative_to(SRC.parent).with_suffix("").parts
    if package[-1] == "__init__":
        package = package[:-1]
    else:
        package = package[:-1]
    top_level = {id(node) for node in tree.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                out.append((parts[1] if parts[0] == "sara" and len(parts) > 1 else parts[0], node.lineno,
                            id(node) in top_level))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = list(package[: len(package) - node.level + 1])
                parts = base + (node.module.split(".") if node.module else [])
                if len(parts) == 1:  # `from . import x` at the top of the package: x is a room
                    out += [(alias.name, node.lineno, id(node) in top_level) for alias in node.names]
                    continue
                out.append((parts[1], node.lineno, id(node) in top_level))
            else:
                parts = node.module.split(".")
                out.append((parts[1] if parts[0] == "sara" and len(parts) > 1 else parts[0], node.lineno,
                            id(node) in top_level))
    return out


def _files() -> list[Path]:
    return sorted(SRC.rglob("*.py"))


def test_every_room_has_a_floor() -> None:
    rooms = {_room(p) for p in _files()}
    assert rooms <= set(FLOORS), f"rooms without a floor in this test: {rooms - set(FLOORS)}"


def test_arrows_point_down() -> None:
    upward = []
    for path in _files():
        room = _room(path)
        for target, line, _ in _imports(path):
            if target in FLOORS and FLOORS[target] > FLOORS[room]:
                upward.append(f"{path.relative_to(SRC)}:{line} imports {target} (floor {FLOORS[target]} > "
                              f"{FLOORS[room]})")
    assert not upward, "\n".join(upward)


def test_no_cycle_between_rooms() -> None:
    edges: dict[str, set[str]] = {}
    for path in _files():
        room = _room(path)
        for target, _, _ in _imports(path):
            if target in FLOORS and target != room and target != "__init__":
                edges.setdefault(room, set()).add(target)
    state: dict[str, int] = {}

    def visit(node: str, trail: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(edges.get(node, ())):
            if state.get(nxt) == 1:
                pytest.fail("import cycle: " + " -> ".join(trail[trail.index(nxt):] + [nxt]))
            if nxt not in state:
                visit(nxt, trail + [nxt])
        state[node] = 2

    for room in sorted(edges):
        if room not in state:
            visit(room, [room])


def test_pycolmap_only_in_the_adapter() -> None:
    outside = [f"{p.relative_to(SRC)}:{line}" for p in _files() if _room(p) != "colmap"
               for name, line, _ in _imports(p) if name == "pycolmap"]
    assert not outside, f"pycolmap imported outside sara.colmap: {outside}"


def test_heavy_packages_are_imported_inside_functions() -> None:
    at_module_level = [f"{p.relative_to(SRC)}:{line} {name}" for p in _files()
                       for name, line, top in _imports(p) if name in HEAVY and top]
    assert not at_module_level, f"optional heavy packages imported at module level: {at_module_level}"


def test_importing_the_cli_loads_no_heavy_package() -> None:
    code = ("import sys, sara.cli, sara.pipeline, sara.bench; "
            "print(sorted(m for m in ('torch', 'kornia', 'ray', 'matplotlib') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_the_pipeline_imports_no_scipy() -> None:
    """`sara extract` imports the pipeline and is measured against plain pycolmap (issue 31): scipy
    (about 0.7 s) is imported where a stage uses it, not on import."""
    code = "import sys, sara.cli.main, sara.cli.commands, sara.pipeline; print('scipy' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


#: floors inside a package: a module imports its siblings on lower floors only
SUB_FLOORS = {
    "pipeline": {"advice": 0, "rounds": 0, "pairs_stage": 1, "record": 2, "run": 3, "single": 4, "__init__": 5},
    # the pair sources stand side by side: none imports another, all import the package's protocols
    "pairs": {"__init__": 0, "exhaustive": 1, "sequential": 1, "vocabtree": 1, "retrieval_only": 1, "sara": 1},
}
MAX_MODULE_LINES = 450
MAX_FUNCTION_LINES = 80  # the aim is about 60: a function read at once


def _sibling_imports(path: Path) -> list[tuple[str, int]]:
    """(sibling module, line) that a module of a package imports with `from .x` or `from . import x`."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.level == (2 if path.parent.name == "sara" and
                                                                path.parent.parent.name == "pairs" else 1):
            names = [node.module.split(".")[0]] if node.module else [alias.name for alias in node.names]
            out += [(name, node.lineno) for name in names]
    return out


def test_modules_inside_a_package_keep_their_floors() -> None:
    wrong = []
    for package, floors in SUB_FLOORS.items():
        for path in sorted((SRC / package).rglob("*.py")):
            rel = path.relative_to(SRC / package).parts
            module = rel[0].removesuffix(".py")
            assert module in floors, f"{package}/{rel[0]} has no floor in SUB_FLOORS"
            if len(rel) > 1 and rel[0] == "sara":  # inside pairs/sara: its imports of pairs' own modules
                imports = [(name, line) for name, line in _sibling_imports(path) if name in floors]
            elif len(rel) > 1:
                continue
            else:
                imports = [(name, line) for name, line in _sibling_imports(path) if name in floors]
            for name, line in imports:
                if name != module and floors[name] >= floors[module]:
                    wrong.append(f"{package}/{'/'.join(rel)}:{line} imports {name}")
    assert not wrong, "\n".join(wrong)


def test_the_pipeline_knows_no_pair_source_by_name() -> None:
    """SARA's logic lives in sara.pairs.sara; the pipeline drives any source through its protocols,
    and no other room imports SARA's package (the registry names it in a string)."""
    pipeline = sorted((SRC / "pipeline").rglob("*.py"))
    named = [f"{path.relative_to(SRC)}:{node.lineno} {node.value!r}" for path in pipeline
             for node in ast.walk(ast.parse(path.read_text(encoding="utf-8")))
             if isinstance(node, ast.Constant) and node.value in ("sara", "repair", "vocab_tree.bin", "global-*.h5")]
    assert not named, f"the pipeline names a pair source or its files: {named}"
    importers = [f"{path.relative_to(SRC)}:{node.lineno}" for path in _files() if "pairs/sara" not in path.as_posix()
                 for node in ast.walk(ast.parse(path.read_text(encoding="utf-8")))
                 if isinstance(node, ast.ImportFrom) and "pairs.sara" in f"{'.' * node.level}{node.module or ''}"]
    assert not importers, f"modules outside sara.pairs.sara import it: {importers}"


def test_no_module_or_function_too_long_to_read() -> None:
    long_modules = [f"{p.relative_to(SRC)} ({n})" for p in _files()
                    if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES]
    assert not long_modules, f"modules over {MAX_MODULE_LINES} lines: {long_modules}"
    long_functions = []
    for path in _files():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    long_functions.append(f"{path.relative_to(SRC)}:{node.lineno} {node.name} ({length})")
    assert not long_functions, f"functions over {MAX_FUNCTION_LINES} lines: {long_functions}"


def test_the_colmap_adapter_hands_out_sara_types_only() -> None:
    """No public function of sara.colmap takes or returns a pycolmap object: an API change of
    pycolmap is mended inside the adapter, never in the rooms that call it."""
    import inspect

    import sara.colmap as adapter

    leaking = []
    for name in adapter.__all__:
        target = getattr(adapter, name)
        if not callable(target) or inspect.isclass(target):
            continue
        signature = inspect.signature(target)
        annotations = [str(signature.return_annotation)] + [str(p.annotation) for p in signature.parameters.values()]
        if any("pycolmap" in text for text in annotations):
            leaking.append(name)
    assert not leaking, f"sara.colmap functions with pycolmap types in their signature: {leaking}"
