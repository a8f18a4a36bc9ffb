"""Lazy public names of a subpackage (PEP 562): ``robust_imdp.models.IMDP`` imports ``models.imdp`` on
first use, so importing a subpackage stays cheap and heavy back-ends load only when used."""

from __future__ import annotations

import importlib


def exports(package: str, modules: list[str]):
    """``(__getattr__, __dir__)`` for ``package``: its ``modules`` and every name in their ``__all__``."""

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
        names = set(modules)
        for mod in modules:
            names.update(getattr(importlib.import_module(f"{package}.{mod}"), "__all__", ()))
        return sorted(names)

    return __getattr__, __dir__
