"""The public API: what ``robust_imdp`` and its subpackages expose resolves, stays light to import,
and docs/api.md (generated from the docstrings by docs/make_api.py) is up to date."""

import importlib
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

import robust_imdp

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "robust_imdp"
SUBPACKAGES = sorted(p.parent.name for p in SRC.glob("*/__init__.py"))


def make_api():
    """docs/make_api.py as a module (it is a script, not part of the package)."""
    spec = importlib.util.spec_from_file_location("make_api", ROOT / "docs" / "make_api.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_api_reference_is_up_to_date():
    api = make_api()
    assert api.API_MD.read_text() == api.render(), (
        f"docs/api.md is out of date (a docstring, signature or __all__ changed); regenerate it with: {api.COMMAND}")


def test_api_reference_does_not_show_machine_dependent_float_digits():
    # np.logspace's 316.22776601683796 renders 316.2277660168379 on other machines (numpy, libm):
    # a value one ulp away must render the same, inside a tuple default and as a module constant
    import math
    api = make_api()
    v = 316.22776601683796

    def f(a=v, b=(0.1, v), c=1.0):
        pass

    def g(a=math.nextafter(v, 0.0), b=(0.1, math.nextafter(v, math.inf)), c=1.0):
        pass

    assert api.signature(f) == api.signature(g) == "(a=316.227766017, b=(0.1, 316.227766017), c=1.0)"
    assert repr(api._stable([v])) == repr(api._stable([math.nextafter(v, 0.0)])) == "[316.227766017]"


def test_api_reference_lists_every_public_module():
    api = make_api()
    expected = set()
    for path in SRC.rglob("*.py"):
        parts = path.relative_to(SRC).with_suffix("").parts
        parts = parts[:-1] if parts[-1] == "__init__" else parts
        if not any(part.startswith("_") for part in parts):
            expected.add(".".join(("robust_imdp",) + parts))
    modules = api.public_modules()
    assert sorted(modules) == sorted(expected) and modules[:2] == ["robust_imdp", "robust_imdp.cli"]
    from robust_imdp import validate
    assert api.describe(validate, "wilson_interval") == (
        "- **`wilson_interval(successes, trials, confidence: float = 0.999)`**: "
        "Two-sided Wilson score interval for a binomial proportion.")
    home = validate.ResultFile.__module__  # io's result files
    assert api.describe(validate, "ResultFile") == f"- `ResultFile`: re-exported from `{home}`"


def test_top_level_names_resolve_and_include_both_bound_routes():
    for name in robust_imdp.__all__:
        assert getattr(robust_imdp, name) is not None, name
    assert len(set(robust_imdp.__all__)) == len(robust_imdp.__all__)
    assert set(robust_imdp.__all__) <= set(dir(robust_imdp))
    for name in ("learn", "bound_image",  # GP route
                 "KernelModel", "image_ranges", "cell_ranges", "check_assumption",  # default RKHS route
                 "resynthesize", "validate", "simulate", "ValidationReport"):
        assert name in robust_imdp.__all__, name
    from robust_imdp.bounds.rkhs import image_ranges
    from robust_imdp.pipeline.run import resynthesize
    assert robust_imdp.image_ranges is image_ranges and robust_imdp.resynthesize is resynthesize


def test_validate_is_the_module_and_calls_its_function(monkeypatch):
    import robust_imdp.validate as module
    from robust_imdp import validate

    assert validate is module is robust_imdp.validate and validate.MAX_STEPS == 200
    monkeypatch.setattr(module, "validate", lambda *args, **kwargs: ("called", args, kwargs))
    assert robust_imdp.validate("result", "system", n_per_cell=3) == ("called", ("result", "system"), {"n_per_cell": 3})


def test_import_robust_imdp_stays_light():
    # heavy optional back-ends, and the modules whose names load lazily, are not imported by the package
    heavy = ("cvxpy", "clarabel", "stormpy", "matplotlib", "dask", "distributed", "casadi", "scipy.stats",
             "robust_imdp.validate", "robust_imdp.bounds.rkhs", "robust_imdp.plotting", "robust_imdp.cli")
    code = f"import sys, robust_imdp; dir(robust_imdp); print([m for m in {heavy!r} if m in sys.modules])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("name", SUBPACKAGES)
def test_every_name_a_subpackage_exposes_resolves(name):
    pkg = importlib.import_module(f"robust_imdp.{name}")
    folder = SRC / name
    modules = sorted(p.stem for p in folder.glob("*.py") if p.stem != "__init__")
    exposed = [m for m in modules if m in dir(pkg)]
    assert exposed == [m for m in modules if not m.startswith("_")], (
        f"robust_imdp/{name}/__init__.py must list every public module of {name}/ (and no stale one)")
    names = set(dir(pkg))
    assert {"__name__", "__path__", "__doc__"} <= names  # dir() keeps the package's own names
    for attr in sorted(names):
        value = getattr(pkg, attr)  # a stale name in a module's __all__ raises AttributeError here
        assert value is not None or attr.startswith("_"), f"robust_imdp.{name}.{attr}"
    for mod in exposed:
        module = importlib.import_module(f"robust_imdp.{name}.{mod}")
        for attr in getattr(module, "__all__", ()):
            if attr in exposed:
                continue  # a module's name is the module (synthesis.refine), not the function it exports
            # a name two modules export must be one object, whichever module the package finds first
            assert getattr(pkg, attr) is getattr(module, attr), f"robust_imdp.{name}.{attr} differs from {mod}'s"
    with pytest.raises(AttributeError, match="has no attribute 'no_such_name'"):
        pkg.no_such_name
