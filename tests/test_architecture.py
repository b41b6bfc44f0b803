"""The layout rules of docs/architecture.md, checked on the source tree.

No function over 100 lines and no file over 600 lines in the packages; no two files that
import each other (also through imports inside functions); imports run one way down the
layers; the lens distortion polynomial has one NumPy and one torch home; library code never
touches pyplot or matplotlib's backend.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"freipose": "freipose", "cli": "freipose.cli", "calibration": "freipose.calibration"}

# package -> the freipose packages it may import (besides itself and the bottom layer)
# "freipose": the root (__version__)
BOTTOM = {"freipose", "errors", "_compat", "_frozen", "progress"}
ALLOWED = {
    "geometry": set(),
    "io": {"geometry", "skeleton"},
    "skeleton": {"io"},
    "workers": {"io"},
    "testing": {"geometry"},
    "calibration": {"geometry", "io", "workers", "skeleton"},
    "labels": {"geometry", "io", "skeleton", "workers"},
    "analysis": {"geometry", "io", "skeleton", "workers"},
    # nn and detect start training from the base models shipped in freipose.models
    "nn": {"geometry", "io", "skeleton", "workers", "models"},
    "detect": {"geometry", "io", "skeleton", "workers", "nn", "models"},
    "predict": {"geometry", "io", "skeleton", "workers", "nn", "detect"},
    "synth": {"geometry", "io", "skeleton", "workers", "calibration"},
    "labelui": {"geometry", "io", "skeleton", "labels"},
    # cluster runs the work of predict (and train) as units on an executor
    "cluster": {"geometry", "io", "skeleton", "workers", "nn", "detect", "predict", "analysis"},
    "models": set(),
}


def _modules() -> dict[str, Path]:
    out = {}
    for folder, pkg in PACKAGES.items():
        for p in sorted((ROOT / folder).rglob("*.py")):
            parts = list(p.relative_to(ROOT / folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join([pkg, *parts])] = p
    return out


MODULES = _modules()
TREES = {m: ast.parse(p.read_text(encoding="utf-8")) for m, p in MODULES.items()}


def _imports(mod: str) -> set[str]:
    """Every freipose module that ``mod`` imports, at the top or inside functions."""
    is_pkg = MODULES[mod].name == "__init__.py"
    found = set()
    for node in ast.walk(TREES[mod]):
        if isinstance(node, ast.ImportFrom) and node.module is not None:
            name = node.module
            if node.level:
                base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                name = ".".join(base[: len(base) - node.level + 1] + [node.module])
            found |= {name} | {f"{name}.{a.name}" for a in node.names}
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
    return {m for m in found if m in MODULES and m != mod}


def _package(mod: str) -> str:
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else "freipose"


def test_no_long_functions_or_files() -> None:
    long_files = [
        f"{p.relative_to(ROOT)}: {n} lines"
        for p in MODULES.values()
        if (n := len(p.read_text(encoding="utf-8").splitlines())) > 600
    ]
    long_functions = [
        f"{MODULES[m].relative_to(ROOT)}:{node.lineno} {node.name}: "
        f"{node.end_lineno - node.lineno + 1} lines"
        for m, tree in TREES.items()
        for node in ast.walk(tree)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and node.end_lineno is not None
        and node.end_lineno - node.lineno + 1 > 100
    ]
    assert not long_files, long_files
    assert not long_functions, long_functions


def test_no_import_cycles() -> None:
    graph = {m: _imports(m) for m in MODULES}
    state: dict[str, int] = {}
    cycles = []

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                cycles.append(path[path.index(n) :] + [n] if n in path else [m, n])
            elif n not in state:
                visit(n, [*path, n])
        state[m] = 2

    for m in MODULES:
        if m not in state:
            visit(m, [m])
    assert not cycles, cycles


@pytest.mark.parametrize("pkg", sorted(ALLOWED))
def test_imports_run_down_the_layers(pkg: str) -> None:
    allowed = ALLOWED[pkg] | BOTTOM | {pkg}
    bad = sorted(
        f"{m} imports {n}"
        for m in MODULES
        if _package(m) == pkg
        for n in _imports(m)
        if _package(n) not in allowed
    )
    assert not bad, bad


def test_distortion_polynomial_has_one_numpy_and_one_torch_home() -> None:
    poly = re.compile(r"1 \+ r2 \* \(k1 \+ r2 \* \(k2 \+ r2 \* k3\)\)")
    homes = sorted(
        str(p.relative_to(ROOT)) for p in MODULES.values() if poly.search(p.read_text("utf-8"))
    )
    assert homes == ["freipose/geometry/distortion.py", "freipose/geometry/torch_ops.py"]


def test_library_never_uses_pyplot_or_switches_the_backend() -> None:
    bad = sorted(
        str(p.relative_to(ROOT))
        for p in MODULES.values()
        if re.search(r"matplotlib\.use\(|import matplotlib\.pyplot|from matplotlib import pyplot",
                     p.read_text(encoding="utf-8"))
    )  # fmt: skip
    assert not bad, bad
