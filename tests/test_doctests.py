"""The ``>>>`` examples of every module's docstrings, and of docs/*.md and README.md, run and pass.

Each module is imported and run through ``doctest`` (``NORMALIZE_WHITESPACE | ELLIPSIS``); an
example that needs a data file or a long run is marked ``# doctest: +SKIP`` with the reason next to it.
"""

import doctest
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "robust_imdp"
FLAGS = doctest.NORMALIZE_WHITESPACE | doctest.ELLIPSIS


def module_names() -> list[str]:
    """Every module of the package (private ones too), as dotted names."""
    names = []
    for path in sorted(SRC.rglob("*.py")):
        parts = path.relative_to(SRC).with_suffix("").parts
        names.append(".".join(("robust_imdp",) + (parts[:-1] if parts[-1] == "__init__" else parts)))
    return names


def markdown_files() -> list[Path]:
    """The docs (and README) that hold ``>>>`` examples."""
    files = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]
    return [p for p in files if ">>>" in p.read_text()]


def run(test_or_tests, name: str) -> None:
    """Run doctests and fail with the runner's report (the example, expected and got)."""
    report = []
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    for test in test_or_tests:
        runner.run(test, out=report.append)
    failed, attempted = runner.summarize(verbose=False)
    assert failed == 0, f"{failed} of {attempted} doctest examples of {name} failed:\n" + "".join(report)


@pytest.mark.parametrize("name", module_names())
def test_module_examples(name):
    module = importlib.import_module(name)
    run(doctest.DocTestFinder().find(module), name)


def test_markdown_examples():
    parser = doctest.DocTestParser()
    for path in markdown_files():
        name = str(path.relative_to(ROOT))
        run([parser.get_doctest(path.read_text(), {}, name, str(path), 0)], name)


def test_the_examples_run_at_all():
    # the finder sees the examples of the package's docstring, of classes and of methods
    import robust_imdp.models.imdp

    tests = [t for t in doctest.DocTestFinder().find(robust_imdp.models.imdp) if t.examples]
    assert [t.name for t in tests] == ["robust_imdp.models.imdp.IMDP"]
    assert len(tests[0].examples) >= 3
