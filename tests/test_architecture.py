"""The layering of docs/ARCHITECTURE.md holds: subpackages import only lower layers, and every module
imports only modules listed before it.

The table of docs/ARCHITECTURE.md lists the modules bottom-up. Every ``import`` of a
robust_imdp module, at module level or inside a function, must name a module listed earlier;
so there is no import cycle, and the documented layers are the real ones (issue 12, item 12).
"""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).parents[1]
SRC = ROOT / "src" / "robust_imdp"


def table_order(text: str) -> list:
    """Module paths (``models/imdp``) in the order of the table rows ``| `models/imdp.py` | ...``."""
    return re.findall(r"^\| `([a-z_/]+)\.py` \|", text, flags=re.M)


def _is_module(path: str) -> bool:
    return (SRC / f"{path}.py").exists()


def _target(dotted: str, name: str | None = None) -> str:
    """The module an import names: ``robust_imdp.a.b`` (+ ``name`` from ``from ... import name``)."""
    parts = dotted.split(".")[1:]
    path = "/".join(parts)
    if name is not None and (not path or _is_module(f"{path}/{name}")):
        return f"{path}/{name}" if path else name
    return path


def imports_of(source: str) -> dict:
    """``{imported robust_imdp module: line}`` for every import in ``source`` (any nesting)."""
    found = {}
    for node in ast.walk(ast.parse(source)):
        names = []
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module == "robust_imdp" or node.module.startswith("robust_imdp."):
                # from robust_imdp import errors / from robust_imdp.bounds import rkhs / from robust_imdp.x.y import f
                # (__version__ is the package's, like ``import robust_imdp``: not a module)
                names = sorted({_target(node.module, a.name) for a in node.names if not a.name.startswith("__")} - {""})
        elif isinstance(node, ast.Import):
            names = [_target(a.name) for a in node.names if a.name.startswith("robust_imdp.")]
        for name in names:
            found.setdefault(name, node.lineno)
    return found


def violations(order: list, sources: dict) -> list:
    """``"a.py:LINE imports b (listed after a)"`` for every import that goes up or sideways."""
    rank = {m: i for i, m in enumerate(order)}
    out = []
    for mod, src in sorted(sources.items()):
        for dep, line in sorted(imports_of(src).items()):
            if dep not in rank:
                out.append(f"{mod}.py:{line} imports {dep}, which the table does not list")
            elif rank[dep] >= rank[mod]:
                out.append(f"{mod}.py:{line} imports {dep} (listed after {mod})")
    return out


def test_checker_finds_a_cycle_and_a_lazy_upward_import():
    # The two shapes of the old cycles: a module-level import down plus a lazy import back up.
    sources = {
        "low": "import numpy\n\ndef f():\n    from robust_imdp.high import g\n",
        "high": "from robust_imdp import low\n",
    }
    assert violations(["low", "high"], sources) == ["low.py:4 imports high (listed after low)"]
    assert violations(["high", "low"], sources) == ["high.py:1 imports low (listed after high)"]
    assert violations(["low"], {"low": "from robust_imdp.nowhere import x\n"}) == [
        "low.py:1 imports nowhere, which the table does not list"]


def test_every_module_is_in_the_table_once():
    order = table_order((ROOT / "docs" / "ARCHITECTURE.md").read_text())
    modules = sorted(str(p.relative_to(SRC).with_suffix("")) for p in SRC.rglob("*.py") if p.stem != "__init__")
    assert sorted(order) == modules  # each module exactly once, none missing, none stale


def test_imports_only_go_down_the_table():
    order = table_order((ROOT / "docs" / "ARCHITECTURE.md").read_text())
    sources = {str(p.relative_to(SRC).with_suffix("")): p.read_text() for p in SRC.rglob("*.py") if p.stem != "__init__"}
    assert violations(order, sources) == []


def ranking(text: str) -> list:
    """Layers of the section "Subpackages, bottom-up": ``| rank | `name` ... |`` rows; a layer may hold
    several subpackages or top-level modules (comma-separated in backquotes)."""
    section = text.split("## Subpackages, bottom-up", 1)[1].split("\n## ", 1)[0]
    layers = []
    for row in re.findall(r"^\| (\d+) \| ([^|]+) \|", section, flags=re.M):
        layers.append(re.findall(r"`([a-z_]+)/?`", row[1]))
    return layers


def package_violations(layers: list, sources: dict) -> list:
    """``"pkg/mod.py:LINE imports other (layer j >= layer i)"`` for imports into a layer not below the
    importer's own (imports inside one subpackage are ranked by the module table instead)."""
    rank = {name: i for i, names in enumerate(layers) for name in names}
    out = []
    for mod, src in sorted(sources.items()):
        own = mod.split("/")[0]
        for dep, line in sorted(imports_of(src).items()):
            other = dep.split("/")[0]
            if other == own:
                continue
            if own not in rank or other not in rank:
                out.append(f"{mod}.py:{line} imports {dep}: {own if own not in rank else other} is not ranked")
            elif rank[other] >= rank[own]:
                out.append(f"{mod}.py:{line} imports {dep} (layer {rank[other]} >= {own}'s layer {rank[own]})")
    return out


def test_package_checker_finds_an_upward_import():
    layers = [["errors"], ["models"], ["bounds", "spec"]]
    sources = {"models/a": "from robust_imdp.bounds import rkhs\n", "bounds/b": "from robust_imdp.spec.dfa import x\n",
               "spec/c": "from robust_imdp.models.a import y\n"}
    assert package_violations(layers, sources) == [
        "bounds/b.py:1 imports spec/dfa (layer 2 >= bounds's layer 2)",
        "models/a.py:1 imports bounds/rkhs (layer 2 >= models's layer 1)"]


def test_subpackages_import_only_lower_layers():
    text = (ROOT / "docs" / "ARCHITECTURE.md").read_text()
    layers = ranking(text)
    top = {p.stem for p in SRC.glob("*.py") if p.stem != "__init__"} | {p.name for p in SRC.iterdir() if p.is_dir()
                                                                        and (p / "__init__.py").exists()}
    assert sorted(n for names in layers for n in names) == sorted(top)  # every subpackage and top-level module once
    sources = {str(p.relative_to(SRC).with_suffix("")): p.read_text() for p in SRC.rglob("*.py") if p.stem != "__init__"}
    assert package_violations(layers, sources) == []
