"""The layout's rule: a part of the package imports only from its own layer or below.

The layers are the table in CONTRIBUTING.md ("What may import what"); this test reads it, so
the table and the code cannot drift apart.  A part is a top-level folder or module of
``src/flyvpr`` (``localization``, ``metrics``, ``_io``); every ``import`` and ``from ...
import`` of the package's own modules is one edge, wherever it sits (inside functions too).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "src" / "flyvpr"


def read_layers(text: str) -> dict[str, int]:
    """The table after the ``layers`` marker: part name -> layer."""
    marker = text.index("<!-- layers:")
    layers: dict[str, int] = {}
    for line in text[marker:].splitlines()[1:]:
        if not line.startswith("|"):
            if layers:
                break
            continue
        cells = [c.strip() for c in line.strip("|").split("|")]
        if not cells[0].isdigit():
            continue  # the header and its rule
        for name in re.findall(r"`([^`]+)`", cells[1]):
            assert name not in layers, f"{name} is in two layers"
            layers[name] = int(cells[0])
    return layers


def part_of(module: str) -> str:
    """``flyvpr.localization.maps`` -> ``localization``; ``flyvpr`` -> ``__init__``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def import_edges(package: Path) -> set[tuple[str, str, str]]:
    """(importing part, imported part, file) for every import of the package's own modules."""
    edges = set()
    for path in sorted(package.rglob("*.py")):
        rel = path.relative_to(package.parent).with_suffix("")
        module = ".".join(rel.parts)
        is_package = module.endswith(".__init__")
        if is_package:
            module = module[: -len(".__init__")]
        here = module if is_package else module.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = here.split(".")[: len(here.split(".")) - (node.level - 1)]
                    stem = ".".join(base + ([node.module] if node.module else []))
                    names = [f"{stem}.{a.name}" for a in node.names]
                    targets = [stem] if node.module else names
                else:
                    targets = [node.module or ""]
            for target in targets:
                if target == "flyvpr" or target.startswith("flyvpr."):
                    a, b = part_of(module), part_of(target)
                    if module.count(".") == 0 and path.name == "__main__.py":
                        a = "__main__"
                    if a != b:
                        edges.add((a, b, str(path.relative_to(package.parent))))
    return edges


def violations(edges, layers) -> list[str]:
    """Imports that run back up, parts missing from the table, and cycles between parts."""
    out = []
    for a, b, where in sorted(edges):
        for name in (a, b):
            if name not in layers:
                out.append(f"{name} ({where}) is not in CONTRIBUTING.md's layer table")
        if a in layers and b in layers and layers[b] > layers[a]:
            out.append(f"{where}: {a} (layer {layers[a]}) imports {b} (layer {layers[b]})")
    graph: dict[str, set[str]] = {}
    for a, b, _ in edges:
        graph.setdefault(a, set()).add(b)

    def reaches(start, goal, seen):
        for nxt in graph.get(start, ()):
            if nxt == goal or (nxt not in seen and (seen.add(nxt) or reaches(nxt, goal, seen))):
                return True
        return False

    for a, b, where in sorted(edges):
        if reaches(b, a, set()):
            out.append(f"{where}: {a} -> {b} closes a cycle")
    return out


@pytest.fixture(scope="module")
def layers():
    return read_layers((ROOT / "CONTRIBUTING.md").read_text(encoding="utf-8"))


def test_the_package_follows_the_layer_table(layers):
    edges = import_edges(PACKAGE)
    assert len(edges) > 50  # (the parser found the package's imports)
    assert violations(edges, layers) == []


def test_every_part_of_the_package_is_in_the_table(layers):
    modules = {p.stem for p in PACKAGE.glob("*.py")}
    folders = {p.parent.name for p in PACKAGE.glob("*/__init__.py")}
    assert modules | folders == set(layers)


def test_an_import_running_back_up_is_caught(layers, tmp_path):
    # A copy of three parts where metrics (layer 1) imports methods (layer 4).
    pkg = tmp_path / "flyvpr"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("from .methods import make_method\n")
    (pkg / "methods.py").write_text("from .metrics import pr_auc\n")
    (pkg / "metrics.py").write_text("def pr_auc():\n    from flyvpr.methods import make_method\n")
    found = violations(import_edges(pkg), layers)
    assert any("metrics (layer 1) imports methods (layer 4)" in v for v in found)
    assert any("closes a cycle" in v for v in found)
    # and a part the table does not know
    (pkg / "extra.py").write_text("from . import metrics\n")
    assert any("extra" in v and "not in" in v for v in violations(import_edges(pkg), layers))
