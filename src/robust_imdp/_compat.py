"""The module paths of the flat layout (``robust_imdp.solve``, ``robust_imdp.rkhs``, ...) still import.

Before the subpackages, every module sat directly in ``robust_imdp``. A user's ``import
robust_imdp.solve`` or ``from robust_imdp.rkhs import cell_ranges`` now gets the module's new home
(the same module object, so monkeypatching works as before) and one ``DeprecationWarning`` naming
the new path. Names that became subpackages (``bounds``, ``abstraction``, ``synthesis``, ``pipeline``,
``io``, ``casestudies``) need no alias: their public names resolve lazily from the subpackage.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import warnings

#: old module name -> its new home, below ``robust_imdp``
MOVED = {
    "imdp": "models.imdp", "geometry": "models.geometry", "system": "models.system", "noise": "models.noise",
    "known": "models.known", "rkhs": "bounds.rkhs", "gp": "bounds.gp", "assumptions": "bounds.assumptions",
    "ltlf": "spec.ltlf", "dfa": "spec.dfa", "solve": "solvers.api", "lp": "solvers.lp", "product": "solvers.product",
    "controller": "synthesis.controller", "refine": "synthesis.refine", "advice": "synthesis.advice",
    "parallel": "pipeline.parallel", "formats": "io.formats",
}


class _Alias(importlib.abc.Loader):
    def __init__(self, new: str):
        self.new = new

    def create_module(self, spec):
        warnings.warn(f"{spec.name} is now {self.new} (the package is organised in subpackages, see "
                      "docs/ARCHITECTURE.md); the old path still works for now", DeprecationWarning, stacklevel=2)
        return importlib.import_module(self.new)

    def exec_module(self, module) -> None:
        """Nothing to run: the module was imported under its new name."""


class OldPaths(importlib.abc.MetaPathFinder):
    """Finds ``robust_imdp.<old>`` for the names of :data:`MOVED` (last on ``sys.meta_path``)."""

    def find_spec(self, fullname, path=None, target=None):
        head, _, old = fullname.partition(".")
        if head != "robust_imdp" or old not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, _Alias(f"robust_imdp.{MOVED[old]}"))
