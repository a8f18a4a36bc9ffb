"""The flat layout's module paths still import (robust_imdp._compat), as the same module objects,
with a DeprecationWarning naming the new path; names that became subpackages keep their public names."""

import importlib
import sys

import pytest

import robust_imdp
from robust_imdp._compat import MOVED


@pytest.mark.parametrize("old", sorted(MOVED))
def test_old_module_path_is_the_new_module_with_a_warning(old):
    sys.modules.pop(f"robust_imdp.{old}", None)
    with pytest.warns(DeprecationWarning, match=rf"robust_imdp\.{old} is now robust_imdp\.{MOVED[old]}"):
        module = importlib.import_module(f"robust_imdp.{old}")
    assert module is importlib.import_module(f"robust_imdp.{MOVED[old]}")
    assert getattr(robust_imdp, old) is module  # `from robust_imdp import solve` as before


@pytest.mark.parametrize("old, name", [("pipeline", "Problem"), ("pipeline", "synthesize_from_data"),
                                       ("bounds", "bound_image"), ("io", "load_problem"), ("io", "save_result"),
                                       ("abstraction", "abstract"), ("synthesis", "synthesize"),
                                       ("casestudies", "true_system")])
def test_old_modules_that_are_subpackages_keep_their_public_names(old, name):
    assert callable(getattr(importlib.import_module(f"robust_imdp.{old}"), name))


def test_an_unknown_module_is_still_not_found():
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("robust_imdp.no_such_module")


def test_old_paths_do_not_shadow_new_modules():
    # the finder comes after the path finder (real modules win) and knows only the old names
    kinds = [f.__name__ if isinstance(f, type) else type(f).__name__ for f in sys.meta_path]
    assert kinds.count("OldPaths") == 1 and kinds.index("OldPaths") > kinds.index("PathFinder")
    assert set(MOVED).isdisjoint(p.stem for p in __import__("pathlib").Path(robust_imdp.__file__).parent.glob("*.py"))
