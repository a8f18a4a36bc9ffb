"""Write docs/api.md, the API reference, from the docstrings of every public module.

    .venv/bin/python docs/make_api.py           # rewrite docs/api.md
    .venv/bin/python docs/make_api.py --check   # exit 1 when docs/api.md is out of date

Public modules are every module of ``src/robust_imdp`` and its subpackages whose name does not start
with ``_``. Per module: its first docstring paragraph, then its public names (``__all__``; a module
without one lists the functions and classes it defines, marked so) with their signature and first
docstring paragraph. Names a module re-exports from another are listed with their home, not again.
``tests/test_api_docs.py`` regenerates the text in memory and compares, so the file never goes stale.
"""

from __future__ import annotations

import enum
import importlib
import inspect
import pkgutil
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
API_MD = ROOT / "docs" / "api.md"
PACKAGE = "robust_imdp"
#: What regenerates the file (the one command the stale-file message names).
COMMAND = ".venv/bin/python docs/make_api.py"
#: Longest value shown for a module constant, in characters (longer reprs are cut with "...").
MAX_VALUE_CHARS = 80

_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")  # reprs of defaults that are functions/objects


def public_modules() -> list[str]:
    """Names of the package, its subpackages and their modules, none private: the package and its
    top-level modules first, then each subpackage followed by its modules, alphabetically."""
    pkg = importlib.import_module(PACKAGE)
    names = [info.name for info in pkgutil.walk_packages(pkg.__path__, prefix=f"{PACKAGE}.")
             if not any(part.startswith("_") for part in info.name.split("."))]
    subpackages = {info.name for info in pkgutil.iter_modules(pkg.__path__, prefix=f"{PACKAGE}.") if info.ispkg}
    top = sorted(n for n in names if n.count(".") == 1 and n not in subpackages)
    return [PACKAGE, *top, *sorted(n for n in names if n not in top)]


def first_paragraph(obj) -> str:
    """The first paragraph of ``obj``'s own docstring, on one line ("" when it has none)."""
    doc = obj.__doc__ if isinstance(obj, type) or inspect.ismodule(obj) else inspect.getdoc(obj)
    doc = inspect.cleandoc(doc) if doc else ""
    return " ".join(doc.split("\n\n")[0].split())


def public_names(module) -> tuple[list[str], bool]:
    """``(names, from __all__)``: ``__all__``, or else the functions and classes the module defines."""
    if hasattr(module, "__all__"):
        return list(module.__all__), True
    own = [name for name, obj in vars(module).items()
           if not name.startswith("_") and (inspect.isfunction(obj) or inspect.isclass(obj))
           and getattr(obj, "__module__", None) == module.__name__]
    return own, False


def signature(obj) -> str:
    """``(a, b=1)`` of a function or class, addresses of default values removed ("" when none)."""
    if isinstance(obj, type) and issubclass(obj, enum.Enum):
        return ""
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):
        return ""
    params = [p.replace(annotation=_Source(p.annotation)) if isinstance(p.annotation, str) else p
              for p in sig.parameters.values()]
    params = [p.replace(default=_stable(p.default)) if p.default is not inspect.Parameter.empty else p
              for p in params]
    ret = sig.return_annotation
    sig = sig.replace(parameters=params, return_annotation=_Source(ret) if isinstance(ret, str) else ret)
    return _ADDRESS.sub("", str(sig))


#: Significant digits of a float shown in the reference. The last digits of a float's repr differ
#: between machines for values computed by numpy or libm (``np.logspace`` gave 316.22776601683796 on
#: one machine and 316.2277660168379 on another), and the reference must not depend on them.
FLOAT_DIGITS = 12


def _stable(value):
    """``value`` shown without machine-dependent digits: floats (also inside tuples and lists) with
    ``FLOAT_DIGITS`` significant digits; anything else as it is."""
    if isinstance(value, float):
        text = f"{value:.{FLOAT_DIGITS}g}"
        return _Source(text + ".0" if text.lstrip("-").isdigit() else text)
    if isinstance(value, (tuple, list)) and any(isinstance(v, float) for v in value):
        items = ", ".join(repr(_stable(v)) for v in value)
        if isinstance(value, tuple):
            return _Source(f"({items},)" if len(value) == 1 else f"({items})")
        return _Source(f"[{items}]")
    return value


class _Source(str):
    """An annotation kept as its source text (``from __future__ import annotations``), shown unquoted."""

    def __repr__(self) -> str:
        return str(self)


def home(obj) -> str | None:
    """The module that defines ``obj`` (functions and classes), else None."""
    if inspect.isfunction(obj) or inspect.isclass(obj):
        return getattr(obj, "__module__", None)
    return None


def reexported_from(module, name: str) -> str | None:
    """The module ``module.name`` comes from when it is a function or class defined elsewhere, else None."""
    where = home(getattr(module, name))
    return where if where is not None and where != module.__name__ else None


def describe(module, name: str) -> str:
    """One markdown bullet for ``module.name``."""
    obj = getattr(module, name)
    where = reexported_from(module, name)
    if inspect.ismodule(obj):
        return f"- `{name}`: the module `{obj.__name__}`"
    if where is not None:
        return f"- `{name}`: re-exported from `{where}`"
    if inspect.isclass(obj):
        sig = signature(obj).removesuffix(" -> None")
        line = f"- class **`{name}{sig}`**"
        if issubclass(obj, enum.Enum):
            line += " (enum: " + ", ".join(f"`{m.name}`" for m in obj) + ")"
        methods = [k for k, v in vars(obj).items() if not k.startswith("_")
                   and (callable(v) or isinstance(v, (property, classmethod, staticmethod)))]
        text = first_paragraph(obj)
        line += f": {text}" if text else ""
        return line + (f" Members: {', '.join(f'`{m}`' for m in methods)}." if methods else "")
    if callable(obj):
        text = first_paragraph(obj)
        return f"- **`{name}{signature(obj)}`**" + (f": {text}" if text else "")
    value = " ".join(_ADDRESS.sub("", repr(_stable(obj))).split())
    if len(value) > MAX_VALUE_CHARS:
        value = value[: MAX_VALUE_CHARS - 3] + "..."
    return f"- `{name} = {value}`"


def module_section(name: str) -> list[str]:
    """The heading, first paragraph and name bullets of one module."""
    module = importlib.import_module(name)
    level = "##" if name == PACKAGE or hasattr(module, "__path__") else "###"
    lines = [f"{level} `{name}`", "", first_paragraph(module) or "(no docstring)", ""]
    if hasattr(module, "__path__") and name != PACKAGE:
        return lines  # a subpackage: its names are those of its modules, below
    names, declared = public_names(module)
    if not declared:
        lines += ["(no `__all__`: the functions and classes it defines)", ""]
    lines += [describe(module, n) for n in names if reexported_from(module, n) is None]
    homes: dict[str, list[str]] = {}
    for n in names:
        where = reexported_from(module, n)
        if where is not None:
            homes.setdefault(where, []).append(n)
    lines += [f"- from `{where}`: " + ", ".join(f"`{n}`" for n in group) for where, group in homes.items()]
    return lines + [""]


def render() -> str:
    """The whole text of docs/api.md."""
    out = ["# robust_imdp API reference", "",
           f"Generated from the docstrings by `{COMMAND}`; do not edit by hand. Per subpackage and module:",
           "the module's first docstring paragraph, then its public names (`__all__`) with their signature",
           "and first docstring paragraph. The layering of the modules is in `docs/ARCHITECTURE.md`.", ""]
    for name in public_modules():
        out += module_section(name)
    return "\n".join(out).rstrip("\n") + "\n"


def main(argv: list[str]) -> int:
    text = render()
    if "--check" in argv:
        if API_MD.read_text() != text:
            print(f"docs/api.md is out of date; regenerate it with: {COMMAND}", file=sys.stderr)
            return 1
        return 0
    API_MD.write_text(text)
    print(f"wrote {API_MD.relative_to(ROOT)} ({len(text.splitlines())} lines)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
