"""Problem files (TOML), data files (CSV / NPZ) and result files (JSON + NPZ).

Problem file contract (keys in ``[brackets]`` are tables; ``?`` marks optional keys)::

    [space]         lower, upper, cell_size          (lists of n floats), names? (n dimension names)
    [[regions.NAME]] lower, upper                    (one entry per box; any number of regions)
    [spec]          formula, threshold, horizon?     (horizon: int for k-step, absent = unbounded)
    [data]          path                             (.csv or .npz, relative to the problem file)
    [modes.NAME]    A (n x n), b (n)                 (known affine part f_u(x) = A x + b), or
                    f (n expressions in x1..xn)       (known nonlinear part, robust_imdp.models.known)
    [noise]         kind = "truncated_gaussian" (sigma, bound) | "gaussian" (sigma) | "uniform" (bound)
    [gp]            rkhs_bound, lengthscale?, error_bound? ("optimal" | "ridge" | "chowdhury"),
                    misspecification? (0), iid_noise? (false), local_points? (all points up to 1000
                    per mode, else 100), known? (n true/false: components not learned);
                    rkhs_bound, lengthscale, misspecification and known each take one value, a list
                    per component or a table per mode (robust_imdp.bounds.assumptions; rkhs_bound = 0
                    declares a component known);
                    only with error_bound = "chowdhury": signal_variance? (number, default 1.0, or
                    "tune": minutes, it bounds every candidate), optimize?, info_gain? ("data" |
                    "trivial"), bound_tol? (1e-3), bound_max_boxes? (2000)
    [abstraction]?  eta?, eps_rule?, combine?, guarantee? ("confidence" | "paper"), confidence?
    [refine]?       max_cells, max_rounds? (8), min_cell_size? (float or n floats), time_budget? (s),
                    split? ("longest" | "all"), growth? (0.35), focus? ("open" | "undecided"):
                    adaptive refinement of the undecided cells (on when the table is present;
                    see robust_imdp.synthesis.refine)

Data files: ``.csv`` with header ``x_1..x_n,u,x_next_1..x_next_n`` (``u`` holds mode names), or
``.npz`` with arrays ``x`` (m, n), ``u`` (m,) and ``x_next`` (m, n). Every mode name in ``u``
must be one of the ``[modes.*]`` tables. Errors name the CSV file's 1-based line.
:func:`load_problem` also checks the data against the assumption (impossible samples are
refused) and warns about modes with few samples and regions that refine the grid.

Result files: ``result.json`` (the documented contract, see :func:`result_to_dict` and the JSON
schema ``docs/result.schema.json``) and ``result.npz`` (the same arrays in binary form). Both
are written under temporary names and renamed only when complete, so an interrupted run never
leaves a result that looks finished. :class:`ResultFile` reads ``result.json`` back as arrays.
"""

from __future__ import annotations

import csv
import difflib
import json
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from robust_imdp.errors import DimensionError, InvalidInputError, ProblemFileError
from robust_imdp.jsonable import jsonable as _jsonable
from robust_imdp.pipeline.problem import ERROR_BOUNDS, GUARANTEES  # the one definition of these modes

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

__all__ = [
    "ProblemFileError",
    "parse_problem_file",
    "parse_problem_dict",
    "load_problem",
    "make_noise",
    "read_data_file",
    "write_data_file",
    "result_to_dict",
    "save_result",
    "load_result",
    "ResultFile",
    "as_result_file",
]

# --------------------------------------------------------------------------- schema
# table -> (required keys, optional keys)
_SCHEMA: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "space": (("lower", "upper", "cell_size"), ("names",)),
    "spec": (("formula", "threshold"), ("horizon",)),
    "data": (("path",), ()),
    "noise": (("kind",), ("sigma", "bound")),
    "gp": (("rkhs_bound",), ("lengthscale", "error_bound", "misspecification", "iid_noise", "local_points", "known",
                             "signal_variance",
                             "optimize", "info_gain", "bound_tol", "bound_max_boxes")),
    "abstraction": ((), ("eta", "eps_rule", "combine", "guarantee", "confidence")),
    "refine": (("max_cells",), ("max_rounds", "min_cell_size", "time_budget", "split", "growth", "focus")),
}
_TOP_REQUIRED = ("space", "regions", "spec", "data", "modes", "noise", "gp")
_TOP_OPTIONAL = ("abstraction", "refine")
_NOISE_KEYS = {
    "truncated_gaussian": ("sigma", "bound"),
    "gaussian": ("sigma",),
    "uniform": ("bound",),
}
EPS_RULES = ("optimized", "paper")
#: [gp] keys that configure a GP posterior (error_bound = "chowdhury" only).
_GP_ONLY_KEYS = ("signal_variance", "optimize", "info_gain", "bound_tol", "bound_max_boxes")
COMBINE_RULES = ("product", "union")


def _suggest(key: str, valid) -> str:
    close = difflib.get_close_matches(key, list(valid), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else f" (valid keys: {', '.join(valid)})"


def _check_keys(table: dict, name: str, required, optional, where: str) -> None:
    """Raise ProblemFileError naming the first missing or unknown key of ``[name]``."""
    valid = tuple(required) + tuple(optional)
    for key in table:
        if key not in valid:
            raise ProblemFileError(
                f"{where}: table [{name}] has unknown key '{key}'{_suggest(key, valid)}"
            )
    for key in required:
        if key not in table:
            raise ProblemFileError(f"{where}: table [{name}] is missing required key '{key}'")


def _float_vector(value, name: str, where: str, n: int | None = None) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ProblemFileError(
            f"{where}: {name} must be a list of numbers; got {value!r}"
        ) from None
    if arr.ndim != 1 or (n is not None and arr.shape[0] != n):
        want = f"{n} numbers" if n is not None else "a list of numbers"
        raise ProblemFileError(f"{where}: {name} must be {want}; got {value!r}")
    if not np.all(np.isfinite(arr)):
        raise ProblemFileError(f"{where}: {name} must be finite; got {value!r}")
    return arr


def _positive_vector(value, name, where, n) -> np.ndarray:
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        value = [float(value)] * n
    arr = _float_vector(value, name, where, n)
    if np.any(arr <= 0):
        raise ProblemFileError(f"{where}: {name} must be > 0 in every dimension; got {value!r}")
    return arr


def _number(value, name, where, *, lo=None, hi=None, integer=False):
    ok_type = int if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, ok_type):
        kind = "an integer" if integer else "a number"
        raise ProblemFileError(f"{where}: {name} must be {kind}; got {value!r}")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise ProblemFileError(f"{where}: {name} must lie in [{lo}, {hi}]; got {value!r}")
    return value


def parse_problem_dict(doc: dict, *, where: str = "problem file") -> dict[str, Any]:
    """Validate a parsed TOML document and return plain, typed values.

    Parameters
    ----------
    doc : dict
        The document as returned by ``tomllib``.
    where : str
        Name used in error messages (usually the file path).

    Returns
    -------
    dict
        Keys ``lower``, ``upper``, ``cell_size`` ((n,) float arrays), ``names`` (tuple of n str or
        None), ``regions``
        (``{name: [(lower, upper), ...]}``), ``formula``, ``threshold``, ``horizon`` (int or
        None), ``data_path`` (str, as written), ``modes`` (``{name: (A (n, n), b (n,))}`` or
        ``{name: known.KnownDynamics}`` for ``f = [...]``, in file order), ``noise`` (``{"kind", "sigma", "bound"}``), ``gp`` (dict of the given keys),
        ``abstraction`` (dict with ``eta`` ((n,) array or None), ``eps_rule``, ``combine``).

    Raises
    ------
    ProblemFileError
        Naming the table and key that is missing, misspelt (with the closest valid key) or
        has a bad value.
    """
    if not isinstance(doc, dict):
        raise ProblemFileError(f"{where}: expected a TOML document; got {type(doc).__name__}")
    _check_keys(doc, "top level", _TOP_REQUIRED, _TOP_OPTIONAL, where)
    for name, (req, opt) in _SCHEMA.items():
        if name in doc:
            if not isinstance(doc[name], dict):
                raise ProblemFileError(f"{where}: [{name}] must be a table; got {doc[name]!r}")
            _check_keys(doc[name], name, req, opt, where)

    sp = doc["space"]
    lower = _float_vector(sp["lower"], "[space].lower", where)
    n = lower.shape[0]
    upper = _float_vector(sp["upper"], "[space].upper", where, n)
    if np.any(upper <= lower):
        raise ProblemFileError(
            f"{where}: [space] needs lower < upper in every dimension; got lower={lower.tolist()}, "
            f"upper={upper.tolist()}"
        )
    cell_size = _positive_vector(sp["cell_size"], "[space].cell_size", where, n)
    dim_names = sp.get("names")
    if dim_names is not None:
        if (not isinstance(dim_names, list) or len(dim_names) != n
                or not all(isinstance(v, str) and v.strip() for v in dim_names) or len(set(dim_names)) != n):
            raise ProblemFileError(
                f"{where}: [space].names must be a list of {n} distinct non-empty names, one per dimension; got "
                f"{dim_names!r}" + (f" ({len(dim_names)} names)" if isinstance(dim_names, list) else ""))
        dim_names = tuple(dim_names)

    regions: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    if not isinstance(doc["regions"], dict) or not doc["regions"]:
        raise ProblemFileError(
            f"{where}: [regions] must define at least one region as [[regions.NAME]] boxes"
        )
    for rname, boxes in doc["regions"].items():
        if isinstance(boxes, dict):
            boxes = [boxes]
        if not isinstance(boxes, list) or not boxes:
            raise ProblemFileError(
                f"{where}: region '{rname}' must be a list of boxes ([[regions.{rname}]]); "
                f"got {boxes!r}"
            )
        parsed = []
        for j, box in enumerate(boxes):
            tname = f"regions.{rname}[{j}]"
            if not isinstance(box, dict):
                raise ProblemFileError(f"{where}: [{tname}] must be a table; got {box!r}")
            _check_keys(box, tname, ("lower", "upper"), (), where)
            blo = _float_vector(box["lower"], f"[{tname}].lower", where, n)
            bup = _float_vector(box["upper"], f"[{tname}].upper", where, n)
            if np.any(bup <= blo):
                raise ProblemFileError(
                    f"{where}: [{tname}] needs lower < upper; got lower={blo.tolist()}, "
                    f"upper={bup.tolist()}"
                )
            if np.any(blo < lower) or np.any(bup > upper):
                raise ProblemFileError(
                    f"{where}: [{tname}] = [{blo.tolist()}, {bup.tolist()}] lies outside the "
                    f"space [{lower.tolist()}, {upper.tolist()}]"
                )
            parsed.append((blo, bup))
        regions[rname] = parsed

    spec = doc["spec"]
    formula = spec["formula"]
    if not isinstance(formula, str) or not formula.strip():
        raise ProblemFileError(f"{where}: [spec].formula must be a non-empty string; got {formula!r}")
    threshold = float(_number(spec["threshold"], "[spec].threshold", where, lo=0.0, hi=1.0))
    horizon = spec.get("horizon")
    if horizon is not None:
        horizon = _number(horizon, "[spec].horizon", where, lo=1, integer=True)

    data_path = doc["data"]["path"]
    if not isinstance(data_path, str) or not data_path:
        raise ProblemFileError(f"{where}: [data].path must be a file name; got {data_path!r}")

    if not isinstance(doc["modes"], dict) or not doc["modes"]:
        raise ProblemFileError(f"{where}: [modes] must define at least one [modes.NAME] table")
    modes: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for mname, table in doc["modes"].items():
        tname = f"modes.{mname}"
        if not isinstance(table, dict):
            raise ProblemFileError(f"{where}: [{tname}] must be a table; got {table!r}")
        _check_keys(table, tname, (), ("A", "b", "f"), where)
        if "f" in table:
            if "A" in table or "b" in table:
                raise ProblemFileError(
                    f"{where}: [{tname}] must give either f (a nonlinear known part) or A and b (an affine one), not "
                    f"both; got keys {sorted(table)}")
            modes[str(mname)] = _known_dynamics(table["f"], tname, where, n)
            continue
        for key in ("A", "b"):
            if key not in table:
                raise ProblemFileError(f"{where}: table [{tname}] is missing required key '{key}' (or give f = "
                                       f"[...], {n} expressions in x1..x{n}, instead of A and b)")
        try:
            A = np.asarray(table["A"], dtype=float)
        except (TypeError, ValueError):
            A = None
        if A is None or A.shape != (n, n) or not np.all(np.isfinite(A)):
            raise ProblemFileError(
                f"{where}: [{tname}].A must be a finite {n}x{n} matrix (list of {n} rows); "
                f"got {table['A']!r}"
            )
        modes[str(mname)] = (A, _float_vector(table["b"], f"[{tname}].b", where, n))

    nz = doc["noise"]
    kind = nz["kind"]
    if kind not in _NOISE_KEYS:
        raise ProblemFileError(
            f"{where}: [noise].kind must be one of {', '.join(_NOISE_KEYS)}; got {kind!r}"
            + (_suggest(str(kind), _NOISE_KEYS) if isinstance(kind, str) else "")
        )
    needed = _NOISE_KEYS[kind]
    _check_keys(nz, "noise", ("kind",) + needed, (), where)
    noise = {"kind": kind, "sigma": None, "bound": None}
    for key in needed:
        noise[key] = _positive_vector(nz[key], f"[noise].{key}", where, n)

    gp_in = doc["gp"]
    gp: dict[str, Any] = {}
    per_component = any(not _is_plain_setting(gp_in.get(k, 1.0), k) for k in ("rkhs_bound", "lengthscale",
                                                                            "misspecification")) or "known" in gp_in
    if not per_component:  # one value each: checked and typed as before
        gp["rkhs_bound"] = float(_number(gp_in["rkhs_bound"], "[gp].rkhs_bound", where))
        if gp["rkhs_bound"] <= 0:
            raise ProblemFileError(f"{where}: [gp].rkhs_bound must be > 0 (or 0 per component for a known one); got "
                                   f"{gp_in['rkhs_bound']!r}")
        if "lengthscale" in gp_in:
            gp["lengthscale"] = _positive_vector(gp_in["lengthscale"], "[gp].lengthscale", where, n)
    else:  # per mode and component (robust_imdp.bounds.assumptions), with B = 0 where a component is known
        gp.update(_per_component_gp(gp_in, list(modes), n, where))
    if "signal_variance" in gp_in:
        if gp_in["signal_variance"] == "tune":
            gp["signal_variance"] = "tune"
        else:
            gp["signal_variance"] = float(
                _number(gp_in["signal_variance"], "[gp].signal_variance", where, lo=1e-300)
            )
    if "bound_max_boxes" in gp_in:
        gp["bound_max_boxes"] = _number(gp_in["bound_max_boxes"], "[gp].bound_max_boxes", where,
                                        lo=1, integer=True)
    if "optimize" in gp_in:
        if not isinstance(gp_in["optimize"], bool):
            raise ProblemFileError(f"{where}: [gp].optimize must be true or false; got {gp_in['optimize']!r}")
        gp["optimize"] = gp_in["optimize"]
    if "info_gain" in gp_in:
        if gp_in["info_gain"] not in ("data", "trivial"):
            raise ProblemFileError(
                f"{where}: [gp].info_gain must be one of data, trivial; got {gp_in['info_gain']!r}"
            )
        gp["info_gain"] = gp_in["info_gain"]
    if "bound_tol" in gp_in:
        gp["bound_tol"] = float(_number(gp_in["bound_tol"], "[gp].bound_tol", where, lo=1e-12))
    gp["error_bound"] = gp_in.get("error_bound", "optimal")
    if gp["error_bound"] not in ERROR_BOUNDS:
        raise ProblemFileError(
            f"{where}: [gp].error_bound must be one of {', '.join(ERROR_BOUNDS)}; got {gp['error_bound']!r}"
            + (_suggest(str(gp["error_bound"]), ERROR_BOUNDS) if isinstance(gp["error_bound"], str) else ""))
    if gp["error_bound"] != "chowdhury":
        gp_only = [k for k in _GP_ONLY_KEYS if k in gp_in]
        if gp_only:
            raise ProblemFileError(
                f"{where}: [gp].{gp_only[0]} applies only to error_bound = \"chowdhury\" (a GP posterior); "
                f"error_bound = \"{gp['error_bound']}\" uses the unit-amplitude kernel with the given lengthscale "
                "only: remove the key or set error_bound = \"chowdhury\"")
    if not per_component:
        gp["misspecification"] = float(_number(gp_in.get("misspecification", 0.0), "[gp].misspecification", where,
                                               lo=0.0))
    gp["local_points"] = None
    if "local_points" in gp_in:
        if gp["error_bound"] == "chowdhury":
            raise ProblemFileError(f"{where}: [gp].local_points applies to error_bound = \"optimal\" or \"ridge\" only")
        gp["local_points"] = _number(gp_in["local_points"], "[gp].local_points", where, lo=1, integer=True)
    gp["iid_noise"] = gp_in.get("iid_noise", False)
    if not isinstance(gp["iid_noise"], bool):
        raise ProblemFileError(f"{where}: [gp].iid_noise must be true or false; got {gp_in['iid_noise']!r}")

    ab_in = doc.get("abstraction", {})
    ab: dict[str, Any] = {"eta": None, "eps_rule": "optimized", "combine": "product",
                          "guarantee": "confidence", "confidence": 0.99}
    if "eta" in ab_in:
        ab["eta"] = _positive_vector(ab_in["eta"], "[abstraction].eta", where, n)
    if "confidence" in ab_in:
        c = _number(ab_in["confidence"], "[abstraction].confidence", where)
        if not 0.0 < float(c) < 1.0:
            raise ProblemFileError(f"{where}: [abstraction].confidence must lie in (0, 1); got {c!r}")
        ab["confidence"] = float(c)
    for key, valid in (("eps_rule", EPS_RULES), ("combine", COMBINE_RULES), ("guarantee", GUARANTEES)):
        if key in ab_in:
            if ab_in[key] not in valid:
                raise ProblemFileError(
                    f"{where}: [abstraction].{key} must be one of {', '.join(valid)}; "
                    f"got {ab_in[key]!r}"
                )
            ab[key] = ab_in[key]

    refine = None
    if "refine" in doc:  # issue 13: adaptive refinement (robust_imdp.synthesis.refine.RefineOptions)
        r_in = doc["refine"]
        refine = {"max_cells": _number(r_in["max_cells"], "[refine].max_cells", where, lo=1, integer=True)}
        if "max_rounds" in r_in:
            refine["max_rounds"] = _number(r_in["max_rounds"], "[refine].max_rounds", where, lo=0, integer=True)
        if "min_cell_size" in r_in:
            refine["min_cell_size"] = _positive_vector(r_in["min_cell_size"], "[refine].min_cell_size", where, n)
        if "time_budget" in r_in:
            refine["time_budget"] = float(_number(r_in["time_budget"], "[refine].time_budget", where))
            if not refine["time_budget"] > 0:
                raise ProblemFileError(f"{where}: [refine].time_budget must be > 0 seconds; got {r_in['time_budget']!r}")
        if "growth" in r_in:
            refine["growth"] = float(_number(r_in["growth"], "[refine].growth", where))
            if not 0 < refine["growth"] <= 1:
                raise ProblemFileError(f"{where}: [refine].growth must lie in (0, 1]; got {r_in['growth']!r}")
        if "split" in r_in:
            if r_in["split"] not in ("longest", "all"):
                raise ProblemFileError(f"{where}: [refine].split must be one of longest, all; got {r_in['split']!r}")
            refine["split"] = r_in["split"]
        if "focus" in r_in:
            if r_in["focus"] not in ("open", "undecided"):
                raise ProblemFileError(f"{where}: [refine].focus must be one of open, undecided; got {r_in['focus']!r}")
            refine["focus"] = r_in["focus"]
        if gp.get("error_bound", "optimal") == "chowdhury" or gp.get("iid_noise"):
            raise ProblemFileError(f"{where}: [refine] needs [gp].error_bound = \"optimal\" or \"ridge\" without "
                                   "iid_noise (the bounds of new cells must hold on the same event as the grid's)")

    return {
        "lower": lower, "upper": upper, "cell_size": cell_size, "names": dim_names, "regions": regions,
        "formula": formula, "threshold": threshold, "horizon": horizon,
        "data_path": data_path, "modes": modes, "noise": noise, "gp": gp, "abstraction": ab,
        "refine": refine,
    }


def _known_dynamics(value, tname: str, where: str, n: int):
    """``[modes.NAME].f``: n expressions in x1..xn as a ``known.KnownDynamics`` (errors name the file,
    the table and the component)."""
    from robust_imdp.models.known import KnownDynamics

    if not isinstance(value, list) or len(value) != n or not all(isinstance(e, str) for e in value):
        got = f"{len(value)} entries: {value!r}" if isinstance(value, list) else repr(value)
        raise ProblemFileError(f"{where}: [{tname}].f must be a list of {n} expressions in x1..x{n} (strings, one per "
                               f"component); got {got}")
    try:
        return KnownDynamics(value, name=f"{where}: [{tname}]")
    except InvalidInputError as exc:
        raise ProblemFileError(str(exc)) from None


def _is_plain_setting(value, key: str) -> bool:
    """One value for every mode and component (a number; for lengthscale also a list of numbers)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return True
    return key == "lengthscale" and isinstance(value, list) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)


def _per_component_gp(gp_in: dict, mode_names: list, n: int, where: str) -> dict:
    """[gp].rkhs_bound / lengthscale / misspecification / known per mode and component, checked by
    ``assumptions.resolve``; the returned values are what the Problem takes (known folded into rkhs_bound)."""
    from robust_imdp.bounds.assumptions import resolve

    known = gp_in.get("known")
    try:
        st = resolve(gp_in["rkhs_bound"], gp_in.get("lengthscale"), gp_in.get("misspecification", 0.0), mode_names, n,
                     prefix="[gp].", known=known)
    except InvalidInputError as exc:
        raise ProblemFileError(f"{where}: {exc}") from None
    out = {"rkhs_bound": gp_in["rkhs_bound"], "misspecification": gp_in.get("misspecification", 0.0)}
    if known is not None:  # the B table with 0 for the known components
        out["rkhs_bound"] = {m: st.rkhs_bound[u].tolist() for u, m in enumerate(mode_names)}
    if "lengthscale" in gp_in:
        out["lengthscale"] = gp_in["lengthscale"]
    return out


def _read_text(path: Path, where: str, expected: str) -> str:
    """The UTF-8 text of ``path``; a directory, an unreadable file or non-UTF-8 bytes raise a
    :class:`ProblemFileError` naming ``where`` (and the line and column of the first bad byte)."""
    if path.is_dir():
        raise ProblemFileError(f"{where} is a directory; expected {expected}")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ProblemFileError(f"{where}: cannot be read ({exc.strerror or exc})") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        column = exc.start - (data.rfind(b"\n", 0, exc.start) + 1) + 1
        raise ProblemFileError(
            f"{where}: line {line}, column {column}: not UTF-8 text (byte 0x{data[exc.start]:02x}); save the file "
            "as UTF-8") from None


def parse_problem_file(path) -> dict[str, Any]:
    """Read a TOML problem file and validate it with :func:`parse_problem_dict`.

    The returned dict has an extra key ``data_file``: the data path resolved relative to the
    problem file's directory.
    """
    path = Path(path)
    text = _read_text(path, f"problem file {path}", "a TOML problem file")
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ProblemFileError(f"{path}: not valid TOML: {exc}") from None
    spec = parse_problem_dict(doc, where=str(path))
    spec["data_file"] = str((path.parent / spec["data_path"]).resolve())
    return spec


def make_noise(noise: dict):
    """The noise model object for a parsed ``[noise]`` table."""
    from robust_imdp.models import noise as nz

    if noise["kind"] == "truncated_gaussian":
        return nz.TruncatedGaussianNoise(noise["sigma"], noise["bound"])
    if noise["kind"] == "gaussian":
        return nz.GaussianNoise(noise["sigma"])
    return nz.UniformNoise(noise["bound"])


def load_problem(path):
    """Read a problem file and its data file into a :class:`robust_imdp.pipeline.run.Problem`.

    Checks at load time, before any long work:

    * every mode has samples (else ``ProblemFileError``);
    * no sample is impossible under the assumption: ``|g| <= B + tau`` everywhere (the SE
      kernel has unit amplitude), so a residual ``|x_next - f_u(x)|`` above ``B + tau`` + the
      noise bound cannot come from the stated system. The same single-point test as the
      pipeline's assumption check (``rkhs.min_rkhs_norm``), with the same noise bound, so both
      refuse the same samples; here the message names the data file's line
      (``AssumptionError``);
    * a mode with fewer than ``FEW_SAMPLES`` samples gets a warning (the bounds stay valid, but
      away from the data they are as wide as the assumption allows);
    * regions whose boundaries are not on the grid refine it: a warning gives the new cell count.

    Raises
    ------
    ProblemFileError
        For any missing / misspelt key, bad value or bad data file (see
        :func:`parse_problem_file` and :func:`read_data_file`).
    AssumptionError
        A sample is impossible under ``[gp].rkhs_bound``, ``misspecification`` and the noise bound.
    """
    from robust_imdp.pipeline.problem import Problem
    from robust_imdp.models.system import AffineMap, Dataset

    spec = parse_problem_file(path)
    names = list(spec["modes"])
    n = spec["lower"].shape[0]
    x, u, x_next, _, rows = _read_data(spec["data_file"], names, n, origin=f"[data].path in {path}")
    missing = [names[i] for i in range(len(names)) if not np.any(u == i)]
    if missing:
        raise ProblemFileError(
            f"data file {spec['data_file']}: modes {missing} have no samples; every [modes.*] "
            "table needs data"
        )
    noise = make_noise(spec["noise"])
    _check_known_domains(spec)
    _check_samples_possible(spec, noise, x, u, x_next, rows)
    _warn_few_samples(spec, u, rows)
    _warn_refined_grid(spec, str(path))
    gp = dict(spec["gp"])
    rkhs_bound = gp.pop("rkhs_bound")
    error_bound = gp.pop("error_bound")
    misspecification = gp.pop("misspecification")
    iid_noise = gp.pop("iid_noise")
    local_points = gp.pop("local_points")
    bound_tol = gp.pop("bound_tol", 1e-3)
    bound_max_boxes = gp.pop("bound_max_boxes", 2000)
    ab = spec["abstraction"]
    return Problem(
        space_lower=spec["lower"], space_upper=spec["upper"], cell_size=spec["cell_size"],
        regions=spec["regions"], formula=spec["formula"], threshold=spec["threshold"],
        horizon=spec["horizon"], data=Dataset(x, u, x_next, modes=tuple(names)),
        mode_names=tuple(names), maps=tuple(m if not isinstance(m, tuple) else AffineMap(*m)
                                            for m in spec["modes"].values()),
        noise=noise, rkhs_bound=rkhs_bound, gp_options=gp,
        bound_tol=bound_tol, bound_max_boxes=bound_max_boxes, eta=ab["eta"], eps_rule=ab["eps_rule"], combine=ab["combine"],
        guarantee=ab["guarantee"], confidence=ab["confidence"], error_bound=error_bound,
        misspecification=misspecification, iid_noise=iid_noise, local_points=local_points,
        refine=spec["refine"], dim_names=spec["names"],
    )


def _check_known_domains(spec) -> None:
    """Refuse a nonlinear known part undefined on part of X, at load time: its interval enclosure over
    every cell of the grid (``KnownDynamics.image_bounds``, the natural extension the bound stage starts
    from) raises ``ExpressionDomainError`` naming the file, the mode's table, the component and the box."""
    nonlinear = [m for m in spec["modes"].values() if not isinstance(m, tuple)]
    if not nonlinear:
        return
    from robust_imdp.models.geometry import Box, Partition, Region

    regions = [Region(name, [Box(lo, up) for lo, up in boxes]) for name, boxes in spec["regions"].items()]
    part = Partition(Box(spec["lower"], spec["upper"]), spec["cell_size"], regions)
    for m in nonlinear:
        m.image_bounds(part.cells_lower, part.cells_upper, form="natural")


#: A mode with fewer samples than this gets a warning at load time.
FEW_SAMPLES = 10


def _rows_text(rows, idx, limit: int = 5) -> str:
    """Where samples ``idx`` are in the data file: 1-based CSV lines, or npz array indices."""
    idx = np.asarray(idx, dtype=np.int64)
    shown = ", ".join(str(int(v)) for v in (rows[idx[:limit]] if rows is not None else idx[:limit]))
    more = f" and {idx.size - limit} more" if idx.size > limit else ""
    if rows is not None:
        return f"line{'s' if idx.size > 1 else ''} {shown}{more}"
    return f"row{'s' if idx.size > 1 else ''} {shown}{more} (0-based, of the arrays x, u, x_next)"


def _check_samples_possible(spec, noise, x, u, x_next, rows) -> None:
    """Refuse samples that no system allowed by the assumption can produce (see :func:`load_problem`).

    The message reads like the pipeline's assumption check (``rkhs.check_assumption``), which
    refuses the same samples, and adds where they are in the data file.
    """
    from robust_imdp.errors import AssumptionError
    from robust_imdp.pipeline.problem import CHECK_DELTA
    from robust_imdp.bounds.rkhs import min_rkhs_norm, noise_bound_at_confidence

    from robust_imdp.bounds.assumptions import resolve

    names = list(spec["modes"])
    st = resolve(spec["gp"]["rkhs_bound"], spec["gp"].get("lengthscale"), spec["gp"]["misspecification"], names,
                 x.shape[1])
    # the pipeline's assumption check uses this bound (unbounded noise: all samples at 1 - 1e-6)
    nb, fail = noise_bound_at_confidence(noise, x.shape[0], CHECK_DELTA)
    nb = np.broadcast_to(np.asarray(nb, float), (x.shape[1],))
    bad = []  # (single-sample minimum norm, mode, component, data row, residual, limit, other rows)
    for m, part in enumerate(spec["modes"].values()):
        sel = np.flatnonzero(u == m)
        nb_m = nb
        if isinstance(part, tuple):
            from robust_imdp.models.system import AffineMap

            r_all = AffineMap(*part).residuals(x[sel], x_next[sel])
            res = r_all.y
            nb_m = np.nextafter(nb + (r_all.bound.max(axis=0) if sel.size else 0.0), np.inf)
        else:  # a nonlinear known part: its residuals' rounding bound joins the noise allowance (as in the pipeline)
            r_all = part.residuals(x[sel], x_next[sel])
            res = r_all.y
            nb_m = np.nextafter(nb + r_all.bound.max(axis=0), np.inf)
        for i in range(res.shape[1]):
            B, tau = float(st.rkhs_bound[m, i]), float(st.misspecification[m, i])
            lengthscale = st.lengthscale[m, i] if not st.uniform else spec["gp"].get("lengthscale", 1.0)
            r = min_rkhs_norm(x[sel], res[:, i], lengthscale, float(nb_m[i]), tau, solver=False)
            if r["single_minimum"] > B:
                limit = B + tau + float(nb_m[i])
                others = [k for k in sel[np.abs(res[:, i]) > limit].tolist() if k != sel[r["sample"]]]
                bad.append((r["single_minimum"], m, i, int(sel[r["sample"]]), float(res[r["sample"], i]), limit,
                            others, B, lengthscale))
    if not bad:
        return
    minimum, m, i, row, residual, limit, others, B, lengthscale = max(bad, key=lambda c: c[0] - c[7])
    where = f"data file {spec['data_file']}, {_rows_text(rows, [row])}"
    component = f"component {i + 1}" + (f" ({spec['names'][i]})" if spec.get("names") else "")
    if B == 0:
        raise AssumptionError(
            f"[gp] declares {component} of mode {names[m]!r} known (rkhs_bound = 0 or known = true), but sample {row} "
            f"({where}) has residual {residual:.6g} there, beyond the noise bound + misspecification = {limit:.6g}"
            + (f"; {len(others)} more samples of this mode and component are beyond it too "
               f"({_rows_text(rows, np.array(others))})" if others else "")
            + ": the known part does not explain the data; give the component an rkhs_bound > 0, a misspecification "
            "allowance, or check the known part and the data")
    if not st.uniform:
        B_text = f"{B:g} for mode {names[m]!r}, {component}"
    else:
        B_text = f"{B:g}"
    raise AssumptionError(
        f"[gp].rkhs_bound = {B_text} is refuted by the data: mode {names[m]!r}, {component} needs an RKHS norm "
        f"of at least {minimum:.4g} (lengthscale {np.asarray(lengthscale).tolist()}); sample {row} ({where}): its "
        f"residual {residual:.6g} in {component} is impossible under the assumption, since |g| <= B + noise "
        f"bound + misspecification = {limit:.6g} everywhere"
        + (f" (the noise bound holds for all {x.shape[0]} samples with probability 1 - {CHECK_DELTA:g})" if fail else "")
        + (f"; {len(others)} more samples of this mode and component are impossible too "
           f"({_rows_text(rows, np.array(others))})" if others else "")
        + f". Choose rkhs_bound >= {minimum:.4g} (with a margin; the check of all samples together may ask for "
        "more), a different lengthscale, a misspecification allowance, or check the data"
        + (f" ({len(bad)} of {len(names) * x.shape[1]} components are refuted)" if len(bad) > 1 else ""))


def _warn_few_samples(spec, u, rows) -> None:
    import warnings

    from robust_imdp.errors import RobustImdpWarning

    counts = np.bincount(u, minlength=len(spec["modes"]))
    few = [(name, int(c)) for name, c in zip(spec["modes"], counts) if c < FEW_SAMPLES]
    if few:
        warnings.warn(
            f"data file {spec['data_file']}: " + ", ".join(f"mode {name!r} has {c} sample{'s' if c != 1 else ''}"
                                                          for name, c in few)
            + f" (fewer than {FEW_SAMPLES}): the bounds stay valid, but away from the samples they are as wide "
            "as [gp].rkhs_bound allows, so expect few Q_yes cells; add samples of these modes",
            RobustImdpWarning, stacklevel=3)


def _warn_refined_grid(spec, where: str) -> None:
    """Warn when region boundaries off the uniform grid add breakpoints (``geometry.Partition``'s rule)."""
    import warnings

    from robust_imdp.errors import RobustImdpWarning
    from robust_imdp.models.geometry import Box, Partition, Region, dimension_text

    lower, upper, h = spec["lower"], spec["upper"], spec["cell_size"]
    uniform, refined, notes = [], [], []
    for j in range(lower.shape[0]):
        # the breakpoints of dimension j depend only on dimension j: a 1-D partition has them
        regions = [Region(name, [Box([lo[j]], [up[j]]) for lo, up in boxes])
                   for name, boxes in spec["regions"].items()]
        bp = Partition(Box([lower[j]], [upper[j]]), [h[j]], regions).breakpoints[0]
        k = int(round((upper[j] - lower[j]) / h[j]))
        uniform.append(k)
        refined.append(bp.size - 1)
        if bp.size - 1 > k:
            ticks = lower[j] + np.arange(k + 1) * ((upper[j] - lower[j]) / k)
            new = [v for v in bp.tolist() if np.min(np.abs(ticks - v)) > 1e-9 * h[j]]
            owners = {v: sorted({name for name, boxes in spec["regions"].items() for lo, up in boxes
                                 if v in (lo[j], up[j])}) for v in new}
            notes.append(f"{dimension_text(j, spec.get('names'))}: {k} -> {bp.size - 1} intervals, at "
                         + ", ".join(f"{v:g} ({', '.join(owners[v])})" for v in new[:4])
                         + (f" and {len(new) - 4} more" if len(new) > 4 else ""))
    if notes:
        warnings.warn(
            f"{where}: region boundaries off the grid refine it from {int(np.prod(uniform)):,} to "
            f"{int(np.prod(refined)):,} cells ({'; '.join(notes)}); to keep the uniform grid, put region "
            "boundaries at [space].lower + k * cell_size",
            RobustImdpWarning, stacklevel=3)


# --------------------------------------------------------------------------- data files
def _check_data(x, u, x_next, mode_names, where, rows=None):
    """Validate arrays read from a data file; return (x, u_index, x_next, modes).

    ``rows``: the 1-based file line of every sample (CSV), or None (npz: 0-based array rows).
    """
    if x.ndim != 2 or x_next.shape != x.shape:
        raise ProblemFileError(
            f"{where}: x_next must have shape (m, n) like x {x.shape}; got {x_next.shape}"
        )
    if u.shape != (x.shape[0],):
        raise ProblemFileError(f"{where}: u must have shape ({x.shape[0]},); got {u.shape}")
    bad = ~(np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(x_next), axis=1))
    if np.any(bad):
        raise ProblemFileError(
            f"{where}: x and x_next must be finite; {int(bad.sum())} sample"
            f"{' is' if bad.sum() == 1 else 's are'} not "
            f"({_rows_text(rows, np.flatnonzero(bad))})"
        )
    names = [str(v) for v in u.tolist()]
    if mode_names is None:
        mode_names = list(dict.fromkeys(names))
    index = {m: i for i, m in enumerate(mode_names)}
    unknown = sorted(set(names) - set(index))
    if unknown:
        at = np.flatnonzero(~np.isin(np.asarray(names, dtype=object), list(index)))
        raise ProblemFileError(
            f"{where}: column u names modes {unknown} that are not in [modes.*] "
            f"(known modes: {list(mode_names)}; {_rows_text(rows, at)})"
        )
    return x, np.array([index[s] for s in names], dtype=np.int64), x_next, tuple(mode_names)


def read_data_file(path, mode_names=None, n_dims: int | None = None):
    """Read a data file.

    Parameters
    ----------
    path : str or Path
        ``.csv`` (header ``x_1..x_n,u,x_next_1..x_next_n``) or ``.npz`` (``x``, ``u``, ``x_next``).
    mode_names : sequence of str, optional
        The valid mode names (``[modes.*]`` order). Default: the names in order of appearance.
    n_dims : int, optional
        Expected state dimension n.

    Returns
    -------
    x : (m, n) float array
    u : (m,) int array of indices into ``modes``
    x_next : (m, n) float array
    modes : tuple of str

    Raises
    ------
    ProblemFileError
        Naming the file and, for a CSV file, the 1-based line (NaN, empty or non-numeric
        fields, unknown modes, wrong number of fields, a header with the wrong separator).
    """
    return _read_data(path, mode_names, n_dims)[:4]


def _read_data(path, mode_names=None, n_dims: int | None = None, origin: str | None = None):
    """:func:`read_data_file` plus the 1-based line of every sample (None for .npz).

    ``origin``: where the path was given (e.g. ``[data].path in p.toml``), for the message when
    it names a directory.
    """
    path = Path(path)
    where = f"data file {path}"
    if not path.exists():
        raise ProblemFileError(f"{where}: file not found")
    if path.is_dir():
        raise ProblemFileError(f"{origin or 'the data file'}: {path} is a directory; expected a data file "
                               "(.csv or .npz)")
    rows = None
    if path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [k for k in ("x", "u", "x_next") if k not in z.files]
                if missing:
                    raise ProblemFileError(
                        f"{where}: missing arrays {missing}; expected x, u, x_next (got {z.files})"
                    )
                x = np.asarray(z["x"], dtype=float)
                u = np.asarray(z["u"])
                x_next = np.asarray(z["x_next"], dtype=float)
        except (ValueError, OSError) as exc:
            if isinstance(exc, ProblemFileError):
                raise
            raise ProblemFileError(f"{where}: cannot be read as .npz ({exc})") from None
        if x.ndim == 1:
            x, x_next = x[:, None], x_next.reshape(-1, 1) if x_next.ndim == 1 else x_next
    elif path.suffix == ".csv":
        x, u, x_next, rows = _read_csv(path, where, n_dims)
    else:
        raise ProblemFileError(f"{where}: expected a .csv or .npz file; got suffix '{path.suffix}'")
    if n_dims is not None and (x.ndim != 2 or x.shape[1] != n_dims):
        raise ProblemFileError(
            f"{where}: x must have {n_dims} columns like [space]; got shape {x.shape}"
        )
    return (*_check_data(x, u, x_next, mode_names, where, rows), rows)


def _header(n: int) -> list:
    return [f"x_{i + 1}" for i in range(n)] + ["u"] + [f"x_next_{i + 1}" for i in range(n)]


def _read_csv(path: Path, where: str, n_dims: int | None = None):
    """Arrays of a CSV data file and the 1-based line of every sample."""
    from io import StringIO

    text = _read_text(path, where, "a data file (.csv or .npz)")
    with StringIO(text, newline="") as fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise ProblemFileError(f"{where}: file is empty") from None
        rows, lines = [], []
        for r in reader:
            if r:  # blank lines are skipped, but every sample keeps its line number
                rows.append(r)
                lines.append(reader.line_num)
    n = (len(header) - 1) // 2
    want = n_dims if n_dims is not None else max(n, 1)
    expected = _header(want)
    if header != expected:
        raw = ",".join(header)
        seps = [c for c in (";", "\t", "|") if c in raw and len(header) == 1]
        hint = (f" (fields separated by {seps[0]!r}: use commas)" if seps else "")
        raise ProblemFileError(
            f"{where}: line 1: header must be {','.join(expected)} "
            f"({want} state dimension{'s' if want > 1 else ''}"
            + (" like [space]" if n_dims is not None else "") + f"); got {raw!r}{hint}"
        )
    if not rows:
        raise ProblemFileError(f"{where}: no data rows after the header")
    lines = np.asarray(lines, dtype=np.int64)
    for r, line in zip(rows, lines.tolist()):
        if len(r) != len(header):
            raise ProblemFileError(
                f"{where}: line {line} has {len(r)} fields; expected {len(header)} ({','.join(header)})"
            )
    table = np.array(rows, dtype=object)
    cols = list(range(n)) + list(range(n + 1, 2 * n + 1))
    values = np.empty((len(rows), 2 * n))
    for k, c in enumerate(cols):
        try:
            values[:, k] = table[:, c].astype(float)
        except ValueError:  # find the first bad field (only on this error path)
            for i, text in enumerate(table[:, c].tolist()):
                try:
                    float(text)
                except ValueError:
                    what = "is empty" if not text.strip() else f"is not a number: {text!r}"
                    raise ProblemFileError(
                        f"{where}: line {int(lines[i])}, column {header[c]} {what}"
                    ) from None
            raise  # pragma: no cover - astype and float() accept the same strings
    u = np.array([v.strip() for v in table[:, n]], dtype=str)
    empty = np.flatnonzero(u == "")
    if empty.size:
        raise ProblemFileError(f"{where}: line {int(lines[empty[0]])}, column u is empty (a mode name is needed)")
    return values[:, :n], u, values[:, n:], lines


def write_data_file(path, x, u, x_next, modes=None) -> None:
    """Write a data file (.csv or .npz) readable by :func:`read_data_file`.

    Parameters
    ----------
    x, x_next : (m, n) float arrays
    u : (m,) int (indices into ``modes``) or str array (mode names)
    modes : sequence of str, optional
        Mode names; required when ``u`` holds indices.
    """
    path = Path(path)
    x = np.asarray(x, dtype=float)
    x_next = np.asarray(x_next, dtype=float)
    u = np.asarray(u)
    if u.dtype.kind in "iu":
        if modes is None:
            raise ProblemFileError("write_data_file: modes names are needed when u holds indices")
        u = np.asarray(modes, dtype=str)[u]
    u = u.astype(str)
    n = x.shape[1]
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".npz":
        np.savez(path, x=x, u=u, x_next=x_next)
        return
    header = [f"x_{i + 1}" for i in range(n)] + ["u"] + [f"x_next_{i + 1}" for i in range(n)]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for xi, ui, yi in zip(x, u, x_next):
            w.writerow([repr(float(v)) for v in xi] + [ui] + [repr(float(v)) for v in yi])


# --------------------------------------------------------------------------- result files
def _umask() -> int:
    """The process's umask (read by setting it and setting it back; there is no getter)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _atomic_write(path: Path, write) -> None:
    """Write via ``write(tmp_path)`` to a temporary file in the same directory, then rename."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    os.close(fd)
    try:
        # mkstemp creates the file with mode 0600; give it the mode open() gives every other
        # output (PNG figures, validation.json): 0666 less the umask.
        os.chmod(tmp, 0o666 & ~_umask())
        write(Path(tmp))
        # on disk before the rename: a crash cannot leave an empty file under the final name
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


RESULT_FORMAT = "robust_imdp.result/1"
CLASS_NAMES = ("yes", "no", "maybe")


def result_to_dict(result) -> dict[str, Any]:
    """The ``result.json`` contract as a plain dict.

    Keys
    ----
    format : str
        ``"robust_imdp.result/1"``.
    space : {"lower", "upper", "names"?}
        The compact set X; leaving it is a violation. ``names``: the dimension names
        (``[space].names``), only when the problem gives them.
    cells : {"lower", "upper"}
        Per cell (index order), lists of n floats.
    labels : list of list of str
        Per cell, the regions (atoms) containing it.
    modes : list of str
        Mode names; ``strategy`` entries are these names.
    dfa : {"atoms", "initial", "accepting", "delta"}
        ``delta[state][letter]`` where bit i of ``letter`` is ``atoms[i]``; ``accepting`` is the
        list of accepting states.
    strategy : list (cells) of list (DFA states) of str
        ``strategy[q][s]``: the mode to apply in cell q when the DFA is in state s.
    strategy_by_time : list (steps) of such tables, or null
        For k-step results only: ``strategy_by_time[t][q][s]`` is the mode at step t
        (``strategy`` is then step 0).
    p_low, p_up, p_up_star, error : list of float
        Per cell, bounds for the cell's initial product state (q, delta(initial, L(q))).
    classes : list of str
        Per cell ``"yes"`` (p_low >= threshold), ``"no"`` (p_up < threshold) or ``"maybe"``.
    no_strategy_can : list of bool
        Per cell ``p_up_star < threshold``: no controller at all can meet the threshold (a
        refinement of ``"no"``; the other "no" cells are "no" under this controller only).
    formula, threshold, horizon, parameters, timings
        What was solved, with which settings, and stage times in seconds.
    diagnostics : dict
        Why cells are undecided: ``confidence`` (probability over the data with which every
        bound holds; 1 for bounded noise with the deterministic bound) and ``statement``,
        ``eps`` (per mode and component: median and max error radius -- the excess of the
        learned image box over the range of the data-fitted function, per side -- and the median
        over the cell half-width), ``successors_per_row`` (mean listed successors per IMDP row),
        ``assumption`` (rkhs_bound, lengthscale, misspecification and the data-implied
        minimum RKHS norm per mode and component) and, when estimated, ``advice`` (the
        result's ``advice``: estimated Q_yes share per lever and the winner).

    How to run the controller without the library: start in cell q0 with DFA state
    ``s = delta[initial][L(q0)]``; while s is neither accepting nor a sink, apply
    ``strategy[q][s]``, step the system, stop with a violation if the state leaves X, else
    find the new cell q' and set ``s = delta[s][L(q')]``.
    """
    part = result.partition
    dfa = result.dfa
    syn = result.synthesis
    modes = list(result.mode_names)
    part_atoms = list(part.atoms)
    labels_int = np.asarray(part.labels, dtype=np.int64)
    labels = [[a for i, a in enumerate(part_atoms) if (int(v) >> i) & 1] for v in labels_int]
    names = np.asarray(modes, dtype=object)

    def named(table):
        table = np.asarray(table, dtype=np.int64)
        return np.where(table >= 0, names[np.clip(table, 0, len(modes) - 1)], None).tolist()

    strategy = np.asarray(syn.strategy, dtype=np.int64)
    by_time = None
    if strategy.ndim == 3:  # k-step: strategy[t, q, s]; "strategy" is the time-0 table
        by_time, strategy = named(strategy), strategy[0]
    strategy_named = np.asarray(named(strategy), dtype=object)
    accepting = np.flatnonzero(np.asarray(dfa.accepting, dtype=bool)).tolist()
    space = {"lower": result.space_lower, "upper": result.space_upper}
    if getattr(result, "dim_names", None) is not None:
        space["names"] = list(result.dim_names)
    return _jsonable({
        "format": RESULT_FORMAT,
        "space": space,
        "cells": {"lower": part.cells_lower, "upper": part.cells_upper},
        "labels": labels,
        "modes": modes,
        "dfa": {
            "atoms": list(dfa.atoms),
            "initial": int(dfa.initial),
            "accepting": accepting,
            "delta": np.asarray(dfa.delta, dtype=np.int64),
        },
        "strategy": strategy_named.tolist(),
        "strategy_by_time": by_time,
        "p_low": np.asarray(syn.p_low, dtype=float),
        "p_up": np.asarray(syn.p_up, dtype=float),
        "p_up_star": np.asarray(syn.p_up_star, dtype=float),
        "error": np.asarray(syn.error, dtype=float),
        "classes": list(result.class_names),
        "no_strategy_can": np.asarray(syn.p_up_star, dtype=float) < result.threshold,
        "formula": result.formula,
        "threshold": result.threshold,
        "horizon": result.horizon,
        "parameters": result.parameters,
        "diagnostics": {**(getattr(result, "diagnostics", {}) or {}),
                        **({"advice": result.advice} if getattr(result, "advice", None) else {})},
        "timings": result.timings,
    })


def save_result(result, out_dir) -> Path:
    """Write ``result.npz`` then ``result.json`` into ``out_dir`` (created if needed).

    Each file is written under a temporary name and renamed when complete; ``result.json``
    is written last, so its presence means the result is complete.

    Returns
    -------
    Path
        The path of ``result.json``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    doc = result_to_dict(result)
    arrays = {
        "cells_lower": np.asarray(doc["cells"]["lower"], dtype=float),
        "cells_upper": np.asarray(doc["cells"]["upper"], dtype=float),
        "strategy": np.asarray(result.synthesis.strategy, dtype=np.int64),  # (k, C, S) if k-step
        "dfa_delta": np.asarray(doc["dfa"]["delta"], dtype=np.int64),
        "p_low": np.asarray(doc["p_low"], dtype=float),
        "p_up": np.asarray(doc["p_up"], dtype=float),
        "p_up_star": np.asarray(doc["p_up_star"], dtype=float),
        "error": np.asarray(doc["error"], dtype=float),
        "classes": np.asarray(doc["classes"], dtype=str),
        "no_strategy_can": np.asarray(doc["no_strategy_can"], dtype=bool),
        "modes": np.asarray(doc["modes"], dtype=str),
    }

    def write_npz(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)

    def write_json(tmp: Path) -> None:
        tmp.write_text(json.dumps(doc, indent=1))

    _atomic_write(out / "result.npz", write_npz)
    _atomic_write(out / "result.json", write_json)
    return out / "result.json"


def load_result(path):
    """Read a ``result.json`` (or the directory holding it) into a :class:`ResultFile`."""
    path = Path(path)
    if path.is_dir():
        path = path / "result.json"
    if not path.exists():
        raise ProblemFileError(f"result file {path}: cannot be read (No such file or directory)")
    try:
        doc = json.loads(_read_text(path, f"result file {path}", "result.json or the directory holding it"))
    except json.JSONDecodeError as exc:
        raise ProblemFileError(f"result file {path}: not valid JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != RESULT_FORMAT:
        raise ProblemFileError(
            f"result file {path}: expected format '{RESULT_FORMAT}'; "
            f"got {doc.get('format') if isinstance(doc, dict) else type(doc).__name__!r}"
        )
    return ResultFile.from_dict(doc)


# --------------------------------------------------------------------------- result tables (read back)
@dataclass(frozen=True, eq=False)
class ResultFile:
    """The ``result.json`` contract as arrays (see :func:`robust_imdp.io.files.result_to_dict`).

    Attributes
    ----------
    space_lower, space_upper : (n,) float arrays
    cells_lower, cells_upper : (n_cells, n) float arrays
    label_letters : (n_cells,) int array, bit i = ``dfa_atoms[i]`` holds in the cell
    labels : tuple of tuple of str
    modes : tuple of str
    dfa_atoms : tuple of str
    dfa_initial : int
    dfa_accepting : (S,) bool array
    dfa_delta : (S, 2**len(dfa_atoms)) int array
    strategy : (n_cells, S) int array of mode indices (-1 where undefined)
    strategy_by_time : (k, n_cells, S) int array or None (k-step results: mode at step t)
    p_low, p_up, p_up_star, error : (n_cells,) float arrays
    classes : (n_cells,) str array ("yes" / "no" / "maybe")
    formula : str
    threshold : float
    horizon : int or None
    parameters, timings : dict
    dim_names : tuple of str or None
        The dimension names (``space.names``), None when the problem gave none.
    """

    space_lower: np.ndarray
    space_upper: np.ndarray
    cells_lower: np.ndarray
    cells_upper: np.ndarray
    label_letters: np.ndarray
    labels: tuple
    modes: tuple
    dfa_atoms: tuple
    dfa_initial: int
    dfa_accepting: np.ndarray
    dfa_delta: np.ndarray
    strategy: np.ndarray
    p_low: np.ndarray
    p_up: np.ndarray
    p_up_star: np.ndarray
    error: np.ndarray
    classes: np.ndarray
    formula: str
    threshold: float
    horizon: int | None
    parameters: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    strategy_by_time: np.ndarray | None = None
    dim_names: tuple | None = None

    @property
    def n_cells(self) -> int:
        return self.cells_lower.shape[0]

    @property
    def no_strategy_can(self) -> np.ndarray:
        """(n_cells,) bool: ``p_up_star < threshold`` (result.json's ``no_strategy_can``): no
        controller at all can meet the threshold."""
        return self.p_up_star < self.threshold

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> "ResultFile":
        """Build from a parsed ``result.json`` document (validating shapes)."""
        try:
            cl = np.asarray(doc["cells"]["lower"], dtype=float)
            cu = np.asarray(doc["cells"]["upper"], dtype=float)
            modes = tuple(doc["modes"])
            dfa = doc["dfa"]
            atoms = tuple(dfa["atoms"])
            delta = np.asarray(dfa["delta"], dtype=np.int64)
            n_states = delta.shape[0]
            accepting = np.zeros(n_states, dtype=bool)
            accepting[np.asarray(dfa["accepting"], dtype=np.int64)] = True
            index = {m: i for i, m in enumerate(modes)}
            def table(rows):
                return np.array([[index[m] if m is not None else -1 for m in row] for row in rows],
                                dtype=np.int64)

            strategy = table(doc["strategy"])
            by_time = doc.get("strategy_by_time")
            by_time = None if by_time is None else np.stack([table(t) for t in by_time])
            labels = tuple(tuple(lab) for lab in doc["labels"])
            bit = {a: 1 << i for i, a in enumerate(atoms)}
            letters = np.array([sum(bit.get(a, 0) for a in lab) for lab in labels], dtype=np.int64)
            out = cls(
                space_lower=np.asarray(doc["space"]["lower"], dtype=float),
                space_upper=np.asarray(doc["space"]["upper"], dtype=float),
                cells_lower=cl, cells_upper=cu, label_letters=letters, labels=labels,
                modes=modes, dfa_atoms=atoms, dfa_initial=int(dfa["initial"]),
                dfa_accepting=accepting, dfa_delta=delta, strategy=strategy,
                p_low=np.asarray(doc["p_low"], dtype=float),
                p_up=np.asarray(doc["p_up"], dtype=float),
                p_up_star=np.asarray(doc["p_up_star"], dtype=float),
                error=np.asarray(doc["error"], dtype=float),
                classes=np.asarray(doc["classes"], dtype=str),
                formula=str(doc["formula"]), threshold=float(doc["threshold"]),
                horizon=doc.get("horizon"),
                parameters=dict(doc.get("parameters") or {}),
                timings=dict(doc.get("timings") or {}),
                strategy_by_time=by_time,
                dim_names=None if doc["space"].get("names") is None else tuple(doc["space"]["names"]),
            )
        except (KeyError, TypeError, IndexError, ValueError) as exc:
            raise InvalidInputError(
                f"result document does not follow the result.json contract ({type(exc).__name__}: {exc})"
            ) from None
        c = out.n_cells
        if (cu.shape != cl.shape or len(labels) != c or strategy.shape != (c, n_states)
                or delta.shape[1] != 2 ** len(atoms) or out.p_low.shape != (c,)):
            raise DimensionError(
                f"result document: inconsistent shapes (cells {cl.shape}/{cu.shape}, labels "
                f"{len(labels)}, strategy {strategy.shape}, delta {delta.shape}, p_low {out.p_low.shape})"
            )
        return out

    # ----------------------------------------------------------------- controller tables
    def dfa_sink(self) -> np.ndarray:
        """(S,) bool: DFA states from which no accepting state is reachable."""
        reach = self.dfa_accepting.copy()
        while True:  # backward reachability; at most S rounds
            new = reach | np.any(reach[self.dfa_delta], axis=1)
            if np.array_equal(new, reach):
                return ~reach
            reach = new

    def locator(self):
        """A vectorised ``locate(x (k, n)) -> (k,) cell index or -1 (outside X)``.

        Cells are boxes aligned to the breakpoints (all cell faces); every elementary box of
        the breakpoint grid belongs to exactly one cell, so a per-dimension ``searchsorted``
        followed by a table lookup finds the cell.
        """
        n = self.cells_lower.shape[1]
        bps = [np.unique(np.concatenate([self.cells_lower[:, i], self.cells_upper[:, i]]))
               for i in range(n)]
        shape = tuple(len(b) - 1 for b in bps)
        table = np.full(shape, -1, dtype=np.int64)
        lo_idx = [np.searchsorted(bps[i], self.cells_lower[:, i]) for i in range(n)]
        hi_idx = [np.searchsorted(bps[i], self.cells_upper[:, i]) for i in range(n)]
        for q in range(self.n_cells):  # set-up only, once per result
            table[tuple(slice(lo_idx[i][q], hi_idx[i][q]) for i in range(n))] = q
        slo, sup = self.space_lower, self.space_upper

        def locate(x):
            x = np.atleast_2d(np.asarray(x, dtype=float))
            inside = np.all((x >= slo) & (x <= sup), axis=1)
            idx = [np.clip(np.searchsorted(bps[i], x[:, i], side="right") - 1, 0, shape[i] - 1)
                   for i in range(n)]
            cell = table[tuple(idx)]
            return np.where(inside, cell, -1)

        return locate


def as_result_file(result) -> "ResultFile":
    """A :class:`ResultFile` from a ResultFile, a pipeline ``Result``, a result dict or a path."""
    if isinstance(result, ResultFile):
        return result
    if isinstance(result, dict):
        return ResultFile.from_dict(result)
    if isinstance(result, (str, bytes)) or hasattr(result, "__fspath__"):
        return load_result(result)
    return ResultFile.from_dict(result_to_dict(result))
