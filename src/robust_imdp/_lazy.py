"""Lazy public names of a package (PEP 562): ``robust_imdp.models.IMDP`` imports ``models.imdp`` on
first use, so importing a package stays cheap and heavy back-ends load only when used.

>>> import robust_imdp.models as models
>>> models.IMDP.__module__
'robust_imdp.models.imdp'
>>> 'IMDP' in dir(models) and 'imdp' in dir(models)
True
"""

from __future__ import annotations

import importlib
import sys

__all__ = ["exports", "lazy_names"]


def _own_names(package: str) -> set[str]:
    """The names the package module itself defines (``__name__``, ``__path__``, eager imports, ...)."""
    return set(vars(sys.modules[package])) if package in sys.modules else set()


def exports(package: str, modules: list[str]):
    """``(__getattr__, __dir__)`` for ``package``: its ``modules`` and every name in their ``__all__``.

    A name two modules export resolves to the first module's (in the order of ``modules``).
    ``dir(package)`` imports the modules to read their ``__all__``.
    """

    def __getattr__(name: str):
        if name in modules:
            return importlib.import_module(f"{package}.{name}")
        if not name.startswith("_"):
            for mod in modules:
                m = importlib.import_module(f"{package}.{mod}")
                if name in getattr(m, "__all__", ()):
                    return getattr(m, name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__():
        names = _own_names(package) | set(modules)
        for mod in modules:
            names.update(getattr(importlib.import_module(f"{package}.{mod}"), "__all__", ()))
        return sorted(names)

    return __getattr__, __dir__


def lazy_names(package: str, where: dict[str, str]):
    """``(__getattr__, __dir__)`` for ``package``: each name of ``where`` is imported from its module
    (``{name: "robust_imdp.x.y"}``) on first use; ``dir(package)`` lists them without importing.

    A name whose module is the package's submodule of that name (``{"validate":
    "robust_imdp.validate"}``) is that module: importing a submodule binds its name in the package,
    so anything else would change what the name means once the submodule is imported.
    """

    def __getattr__(name: str):
        if name in where:
            module = importlib.import_module(where[name])
            return module if where[name] == f"{package}.{name}" else getattr(module, name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__():
        return sorted(_own_names(package) | set(where))

    return __getattr__, __dir__
