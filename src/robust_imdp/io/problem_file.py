"""Problem files (TOML) -> :class:`robust_imdp.pipeline.problem.Problem`.

Problem file contract (keys in ``[brackets]`` are tables; ``?`` marks optional keys)::

    [space]         lower, upper, cell_size          (lists of n floats), names? (n dimension names)
    [[regions.NAME]] lower, upper                    (one entry per box; any number of regions)
    [spec]          formula, threshold, horizon?     (horizon: int for k-step, absent = unbounded),
                    semantics? ("auto" | "reach" | "safety": the reading of the formula, README "Two
                    readings of a formula"; auto: safety for a safety formula such as G safe, else reach)
    [data]?         path                             (.csv or .npz, relative to the problem file; not for
                                                      known dynamics)
    [modes.NAME]    A (n x n), b (n)                 (known affine part f_u(x) = A x + b), or
                    f (n expressions in x1..xn)       (known nonlinear part, robust_imdp.models.known)
    [inputs]        lower, upper, step (m values each: a box quantised by a step) or values (m lists),
                    names? (m names): an input grid whose points are the modes, named by their values
                    (u=(17), u=(0.5, -1); robust_imdp.models.inputs), instead of [modes.NAME], with
    [dynamics]      f (n expressions in x1..xn, u1..um: the dynamics f(x, u) of every point); data
                    then carry input columns u_1..u_m instead of u (io.data_file)
    [noise]         kind = "truncated_gaussian" (sigma, bound) | "gaussian" (sigma) | "uniform" (bound)
    [learning]?     rkhs_bound, lengthscale?, error_bound? ("optimal" | "ridge" | "chowdhury"),
                    misspecification? (0), iid_noise? (false), local_points? (all points up to 1000
                    per mode, else 100), known? (n true/false: components not learned),
                    split_tol? (> 0: sub-box certificates where a cell's Taylor term exceeds it);
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

Known dynamics: when every component of every mode is known (``[learning].rkhs_bound = 0``, a scalar, or
per component and mode; or no ``[learning]`` table at all), ``[data]`` and ``[learning]`` may be left out:
nothing is learned, no data are read and no assumption is checked (a ``[data]`` table is then read and
ignored, with a warning). Otherwise both are required.

``[learning]`` was called ``[gp]`` (the default route is not a GP, but the table configures it):
``[gp]`` is still read, with a ``DeprecationWarning`` saying to rename it, and its messages keep
naming ``[gp]``; a file with both tables is refused.

:func:`load_problem` also reads the data file (:mod:`robust_imdp.io.data_file`), checks the data
against the assumption (impossible samples are refused) and warns about modes with few samples
and regions that refine the grid.
"""

from __future__ import annotations

import difflib
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from robust_imdp.bounds import methods
from robust_imdp.errors import InvalidInputError, ProblemFileError, RobustImdpWarning
from robust_imdp.io.data_file import (
    _check_samples_possible, _read_data, _read_text, _warn_few_samples, refuse_adaptive_iid,
)
from robust_imdp.pipeline.problem import BOUND_MAX_BOXES, BOUND_TOL, GUARANTEES  # the one definition of these
from robust_imdp.pipeline.problem import DEFAULT_TRANSITIONS, FORMS, TRANSITIONS

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
]

# --------------------------------------------------------------------------- schema
#: The table of the learning options; ``OLD_LEARNING_TABLE`` is its former name (still read, warned).
LEARNING_TABLE = "learning"
OLD_LEARNING_TABLE = "gp"
# table -> (required keys, optional keys)
_SCHEMA: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "space": (("lower", "upper", "cell_size"), ("names", "periodic")),
    "spec": (("formula", "threshold"), ("horizon", "semantics")),
    "data": (("path",), ()),
    "noise": (("kind",), ("sigma", "bound")),
    LEARNING_TABLE: (("rkhs_bound",), ("lengthscale", "error_bound", "misspecification", "iid_noise", "local_points",
                                       "split_tol", "known", "signal_variance",
                                       "optimize", "info_gain", "bound_tol", "bound_max_boxes")),
    "abstraction": ((), ("eta", "eps_rule", "combine", "guarantee", "confidence", "transitions", "form")),
    "refine": (("max_cells",), ("max_rounds", "min_cell_size", "time_budget", "split", "growth", "focus")),
    "inputs": ((), ("names", "lower", "upper", "step", "values")),
    "dynamics": (("f",), ()),
}
_TOP_REQUIRED = ("space", "regions", "spec", "noise")
# [data] and [learning] are required unless every component of every mode is known (_data_and_learning);
# [modes.NAME] tables, or an [inputs] grid with one [dynamics] f (_parse_modes_or_inputs)
_TOP_OPTIONAL = ("modes", "inputs", "dynamics", "data", LEARNING_TABLE, "abstraction", "refine")
_NOISE_KEYS = {
    "truncated_gaussian": ("sigma", "bound"),
    "gaussian": ("sigma",),
    "uniform": ("bound",),
}
EPS_RULES = ("optimized", "paper")
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



def _learning_table(doc: dict, where: str) -> str:
    """The name the learning table goes by in ``doc``: ``learning``, or its former name ``gp`` (warned)."""
    if OLD_LEARNING_TABLE in doc and LEARNING_TABLE in doc:
        raise ProblemFileError(
            f"{where}: tables [{LEARNING_TABLE}] and [{OLD_LEARNING_TABLE}] are both given; [{OLD_LEARNING_TABLE}] "
            f"is the former name of [{LEARNING_TABLE}]: keep one table [{LEARNING_TABLE}]")
    if OLD_LEARNING_TABLE in doc:
        warnings.warn(
            f"{where}: table [{OLD_LEARNING_TABLE}] is now called [{LEARNING_TABLE}] (same keys; the default route "
            f"is not a GP): rename [{OLD_LEARNING_TABLE}] to [{LEARNING_TABLE}]", DeprecationWarning, stacklevel=2)
        return OLD_LEARNING_TABLE
    return LEARNING_TABLE


def _check_tables(doc: dict, learning: str, where: str) -> None:
    """Every table of the schema that is present is a table with only known keys and its required ones."""
    for name, (req, opt) in _SCHEMA.items():
        shown = learning if name == LEARNING_TABLE else name  # messages name the table as the file does
        if name in doc:
            if not isinstance(doc[name], dict):
                raise ProblemFileError(f"{where}: [{shown}] must be a table; got {doc[name]!r}")
            _check_keys(doc[name], shown, req, opt, where)


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
        ``{name: known.KnownDynamics}`` for ``f = [...]``, in file order), ``noise`` (``{"kind", "sigma", "bound"}``),
        ``learning`` (dict of the given ``[learning]`` keys), ``learning_table`` (``"learning"``, or ``"gp"``
        for a file with the former name: what messages call the table),
        ``abstraction`` (dict with ``eta`` ((n,) array or None), ``eps_rule``, ``combine``), ``refine``.

    Raises
    ------
    ProblemFileError
        Naming the table and key that is missing, misspelt (with the closest valid key) or
        has a bad value.
    """
    if not isinstance(doc, dict):
        raise ProblemFileError(f"{where}: expected a TOML document; got {type(doc).__name__}")
    learning = _learning_table(doc, where)
    if learning != LEARNING_TABLE:  # read under the current name, in the file's table order
        doc = {(LEARNING_TABLE if k == learning else k): v for k, v in doc.items()}
    _check_keys(doc, "top level", _TOP_REQUIRED, _TOP_OPTIONAL, where)
    _check_tables(doc, learning, where)
    lower, upper, cell_size, dim_names = _parse_space(doc["space"], where)
    n = lower.shape[0]
    periodic = _parse_periodic(doc["space"], n, where)
    regions = _parse_regions(doc["regions"], lower, upper, where, periodic)
    formula, threshold, horizon = _parse_spec(doc["spec"], where)
    semantics = _parse_semantics(doc["spec"], where)
    modes, inputs = _parse_modes_or_inputs(doc, n, where)
    noise = _parse_noise(doc["noise"], n, where)
    gp, data_path = _data_and_learning(doc, list(modes), n, learning, where)
    ab = _parse_abstraction(doc.get("abstraction", {}), n, where)
    refine = None
    if "refine" in doc:  # adaptive refinement (robust_imdp.synthesis.refine.RefineOptions)
        refine = _parse_refine(doc["refine"], gp, n, f"[{learning}]", where)
    return {
        "lower": lower, "upper": upper, "cell_size": cell_size, "names": dim_names, "regions": regions,
        "formula": formula, "threshold": threshold, "horizon": horizon, "semantics": semantics,
        "data_path": data_path, "modes": modes, "noise": noise, "learning": gp, "learning_table": learning,
        "abstraction": ab, "refine": refine, "periodic": periodic, "inputs": inputs,
    }


def _data_and_learning(doc: dict, mode_names: list, n: int, learning: str, where: str):
    """``([learning] parsed, [data].path or None)``.

    Known dynamics (every component of every mode known: ``[learning].rkhs_bound = 0``, or no ``[learning]``
    table and no ``[data]``) need neither table; otherwise both are required."""
    t = f"[{learning}]"
    if LEARNING_TABLE not in doc:
        if "data" in doc:
            raise ProblemFileError(
                f"{where}: [data] is given but there is no {t} table; add {t} with rkhs_bound (the assumption on "
                "the unknown parts the data are for), or remove [data] if every component is known")
        gp = _parse_learning({"rkhs_bound": 0.0}, mode_names, n, t, where)
    else:
        gp = _parse_learning(doc[LEARNING_TABLE], mode_names, n, t, where)
    if "data" not in doc:
        if not _all_known(gp, mode_names, n):
            raise ProblemFileError(
                f"{where}: missing required table [data] (path = the samples of the unknown components); only a "
                f"problem whose every component of every mode is known ({t}.rkhs_bound = 0, or no {t} table) "
                "needs no data")
        return gp, None
    data_path = doc["data"]["path"]
    if not isinstance(data_path, str) or not data_path:
        raise ProblemFileError(f"{where}: [data].path must be a file name; got {data_path!r}")
    return gp, data_path


def _all_known(gp: dict, mode_names: list, n: int) -> bool:
    """Whether a parsed [learning] table declares every component of every mode known (B = 0)."""
    from robust_imdp.bounds.assumptions import resolve

    st = resolve(gp["rkhs_bound"], gp.get("lengthscale"), gp.get("misspecification", 0.0), mode_names, n)
    return bool(np.all(st.known))


def _parse_space(sp: dict, where: str):
    """``[space]``: (lower, upper, cell_size, names or None)."""
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
    return lower, upper, cell_size, dim_names


def _parse_periodic(sp: dict, n: int, where: str):
    """``[space].periodic``: a tuple of n bools, or None (absent, or no dimension periodic)."""
    flags = sp.get("periodic")
    if flags is None:
        return None
    if not isinstance(flags, list) or len(flags) != n or not all(isinstance(v, bool) for v in flags):
        raise ProblemFileError(
            f"{where}: [space].periodic must be a list of {n} booleans (true = periodic, period upper - lower), "
            f"one per dimension; got {flags!r}" + (f" ({len(flags)} values)" if isinstance(flags, list) else ""))
    return tuple(flags) if any(flags) else None


def _parse_regions(doc_regions, lower, upper, where: str, periodic=None) -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
    """``[[regions.NAME]]``: name -> list of (lower, upper) boxes inside the space.

    On a periodic dimension a box may cross the seam (at most one period wide; ``Partition`` cuts it)."""
    n = lower.shape[0]
    regions: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    if not isinstance(doc_regions, dict) or not doc_regions:
        raise ProblemFileError(
            f"{where}: [regions] must define at least one region as [[regions.NAME]] boxes"
        )
    for rname, boxes in doc_regions.items():
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
            if periodic is not None:
                wide = [k for k in range(n) if periodic[k] and bup[k] - blo[k] > upper[k] - lower[k]]
                if wide:
                    k = wide[0]
                    raise ProblemFileError(
                        f"{where}: region '{rname}': [{tname}] is {bup[k] - blo[k]:g} wide in dimension {k + 1}, which "
                        f"is periodic with period {upper[k] - lower[k]:g}; a region box may be at most one period "
                        "wide (it may cross the seam: e.g. lower = upper_X - a, upper = upper_X + b)")
            out = [k for k in range(n) if (blo[k] < lower[k] or bup[k] > upper[k])
                   and not (periodic is not None and periodic[k])]
            if out:
                seam = ("" if periodic is None else
                        "; only on a periodic dimension ([space].periodic) may a box cross the seam, at most one "
                        "period wide")
                raise ProblemFileError(
                    f"{where}: region '{rname}': [{tname}] = [{blo.tolist()}, {bup.tolist()}] lies outside the "
                    f"space [{lower.tolist()}, {upper.tolist()}] in dimension {out[0] + 1}; expected lower and "
                    f"upper of {n} numbers each with [space].lower <= lower < upper <= [space].upper{seam}"
                )
            parsed.append((blo, bup))
        regions[rname] = parsed
    return regions


def _parse_spec(spec: dict, where: str):
    """``[spec]``: (formula, threshold, horizon or None)."""
    formula = spec["formula"]
    if not isinstance(formula, str) or not formula.strip():
        raise ProblemFileError(f"{where}: [spec].formula must be a non-empty string; got {formula!r}")
    threshold = float(_number(spec["threshold"], "[spec].threshold", where, lo=0.0, hi=1.0))
    horizon = spec.get("horizon")
    if horizon is not None:
        horizon = _number(horizon, "[spec].horizon", where, lo=1, integer=True)
    return formula, threshold, horizon


def _parse_semantics(spec: dict, where: str) -> str:
    """``[spec].semantics``: the reading of the formula ("auto" when absent)."""
    from robust_imdp.spec.dfa import SEMANTICS

    value = spec.get("semantics", "auto")
    if value not in SEMANTICS:
        raise ProblemFileError(
            f"{where}: [spec].semantics must be one of {', '.join(SEMANTICS)} (auto: safety for a safety formula "
            f"such as G safe, reach otherwise); got {value!r}"
            + (f" (did you mean {close[0]!r}?)" if isinstance(value, str)
               and (close := difflib.get_close_matches(value, SEMANTICS, n=1, cutoff=0.6)) else ""))
    return value


def _parse_modes_or_inputs(doc: dict, n: int, where: str):
    """``(modes, inputs)``: ``[modes.NAME]`` tables (inputs None), or an ``[inputs]`` grid and one ``[dynamics]``
    f in ``x1..xn, u1..um`` whose points are the modes (``models.inputs``: ``{name: InputMode}``, the grid)."""
    has_modes, has_inputs, has_dyn = "modes" in doc, "inputs" in doc, "dynamics" in doc
    if has_modes and (has_inputs or has_dyn):
        raise ProblemFileError(f"{where}: give either [modes.NAME] tables or an [inputs] grid with [dynamics] f(x, u), "
                               "not both")
    if has_modes:
        return _parse_modes(doc["modes"], n, where), None
    if not (has_inputs and has_dyn):
        missing = "[modes.NAME] tables (one per mode)" if not (has_inputs or has_dyn) else (
            "[dynamics] (f = n expressions in x1..xn, u1..um)" if has_inputs else "[inputs] (the input grid)")
        raise ProblemFileError(f"{where}: missing {missing}; the modes are [modes.NAME] tables, or the points of an "
                               "[inputs] grid with one [dynamics] f(x, u)")
    grid = _parse_inputs(doc["inputs"], where)
    f = doc["dynamics"]["f"]
    m = grid.n_inputs
    if not isinstance(f, list) or len(f) != n or not all(isinstance(e, str) for e in f):
        got = f"{len(f)} entries: {f!r}" if isinstance(f, list) else repr(f)
        raise ProblemFileError(f"{where}: [dynamics].f must be a list of {n} expressions in x1..x{n}, u1..u{m} "
                               f"(strings, one per component); got {got}")
    from robust_imdp.models.inputs import input_modes

    try:
        maps = input_modes(f, grid, name=f"{where}: [dynamics]")
    except InvalidInputError as exc:
        raise ProblemFileError(str(exc)) from None
    return dict(zip(grid.mode_names, maps)), grid


def _parse_inputs(t: dict, where: str):
    """``[inputs]``: a box and a step per input (``lower``, ``upper``, ``step``) or ``values`` (one list per
    input), optional ``names``: a ``models.inputs.InputGrid``."""
    from robust_imdp.models.inputs import InputGrid

    box = [k for k in ("lower", "upper", "step") if k in t]
    if "values" in t and box:
        raise ProblemFileError(f"{where}: [inputs] takes either values (one list per input) or lower, upper and step, "
                               f"not both; got keys {sorted(t)}")
    if "values" not in t and len(box) != 3:
        missing = [k for k in ("lower", "upper", "step") if k not in t]
        raise ProblemFileError(f"{where}: [inputs] needs lower, upper and step (one value per input) or values (one "
                               f"list per input); missing {missing}")
    names = t.get("names")
    try:
        if "values" in t:
            values = t["values"]
            if not isinstance(values, list) or not values or not all(isinstance(v, list) for v in values):
                raise ProblemFileError(f"{where}: [inputs].values must be a list with one list of numbers per input "
                                       f"(values = [[17, 18, 19, 20]] for one input); got {values!r}")
            return InputGrid.from_values(values, names)
        m = len(t["lower"]) if isinstance(t["lower"], list) else None
        lower = _float_vector(t["lower"], "[inputs].lower", where)
        upper = _float_vector(t["upper"], "[inputs].upper", where, lower.shape[0])
        step = (float(t["step"]) if isinstance(t["step"], (int, float)) and not isinstance(t["step"], bool)
                else _float_vector(t["step"], "[inputs].step", where, m))
        return InputGrid.from_box(lower, upper, step, names)
    except InvalidInputError as exc:
        if isinstance(exc, ProblemFileError):
            raise
        raise ProblemFileError(f"{where}: [inputs]: {exc}") from None


def _parse_modes(doc_modes, n: int, where: str) -> dict:
    """``[modes.NAME]``: name -> (A, b) or ``known.KnownDynamics``, in file order (mode index = table order)."""
    if not isinstance(doc_modes, dict) or not doc_modes:
        raise ProblemFileError(f"{where}: [modes] must define at least one [modes.NAME] table")
    modes: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for mname, table in doc_modes.items():
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
    return modes


def _parse_noise(nz: dict, n: int, where: str) -> dict:
    """``[noise]``: ``{"kind", "sigma", "bound"}`` (the keys the kind does not take are None)."""
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
    return noise


def _parse_learning(gp_in: dict, mode_names: list, n: int, t: str, where: str) -> dict[str, Any]:
    """``[learning]`` (``t``: the table as messages name it, ``"[learning]"`` or ``"[gp]"``): the
    assumption, then the GP-posterior keys, then the error-bound method and its options."""
    gp: dict[str, Any] = {}
    per_component = any(not _is_plain_setting(gp_in.get(k, 1.0), k) for k in ("rkhs_bound", "lengthscale",
                                                                            "misspecification")) or "known" in gp_in
    if not per_component:  # one value each: checked and typed as before
        gp["rkhs_bound"] = float(_number(gp_in["rkhs_bound"], f"{t}.rkhs_bound", where))
        if not (gp["rkhs_bound"] >= 0 and np.isfinite(gp["rkhs_bound"])):
            raise ProblemFileError(f"{where}: {t}.rkhs_bound must be > 0, or 0 for known dynamics (every component "
                                   f"of every mode known), or 0 per component for a known one; got "
                                   f"{gp_in['rkhs_bound']!r}")
        if "lengthscale" in gp_in:
            gp["lengthscale"] = _positive_vector(gp_in["lengthscale"], f"{t}.lengthscale", where, n)
    else:  # per mode and component (robust_imdp.bounds.assumptions), with B = 0 where a component is known
        gp.update(_per_component_gp(gp_in, mode_names, n, where, t))
    gp.update(_parse_gp_posterior(gp_in, t, where))
    method = _file_rule(t, methods.get, gp_in.get("error_bound", methods.DEFAULT), where)
    gp["error_bound"] = method.name
    _file_rule(t, method.check_file_options, gp_in, where)
    if not per_component:
        gp["misspecification"] = float(_number(gp_in.get("misspecification", 0.0), f"{t}.misspecification", where,
                                               lo=0.0))
    gp["local_points"] = None
    if "local_points" in gp_in:
        _file_rule(t, method.check_file_local_points, where)
        gp["local_points"] = _number(gp_in["local_points"], f"{t}.local_points", where, lo=1, integer=True)
    gp["split_tol"] = None
    if "split_tol" in gp_in:
        _file_rule(t, method.check_file_split, where)
        gp["split_tol"] = float(_number(gp_in["split_tol"], f"{t}.split_tol", where, lo=0.0))
        if not gp["split_tol"] > 0:
            raise ProblemFileError(f"{where}: {t}.split_tol must be > 0 (leave it out to never split a cell); got "
                                   f"{gp_in['split_tol']!r}")
    gp["iid_noise"] = gp_in.get("iid_noise", False)
    if not isinstance(gp["iid_noise"], bool):
        raise ProblemFileError(f"{where}: {t}.iid_noise must be true or false; got {gp_in['iid_noise']!r}")
    return gp


def _file_rule(t: str, rule, *args):
    """``rule(*args)``: a problem-file rule of the method registry (``bounds.methods``). Its messages name
    the learning table by its former name ``[gp]``; they name it as the file does (``t``)."""
    try:
        return rule(*args)
    except ProblemFileError as exc:
        if t == "[gp]":
            raise
        raise ProblemFileError(str(exc).replace("[gp].", f"{t}.")) from None


def _parse_gp_posterior(gp_in: dict, t: str, where: str) -> dict[str, Any]:
    """The keys of a GP posterior (``signal_variance``, ``bound_max_boxes``, ``optimize``, ``info_gain``,
    ``bound_tol``), checked and typed; whether the method takes them is checked after."""
    gp: dict[str, Any] = {}
    if "signal_variance" in gp_in:
        if gp_in["signal_variance"] == "tune":
            gp["signal_variance"] = "tune"
        else:
            gp["signal_variance"] = float(
                _number(gp_in["signal_variance"], f"{t}.signal_variance", where, lo=1e-300)
            )
    if "bound_max_boxes" in gp_in:
        gp["bound_max_boxes"] = _number(gp_in["bound_max_boxes"], f"{t}.bound_max_boxes", where,
                                        lo=1, integer=True)
    if "optimize" in gp_in:
        if not isinstance(gp_in["optimize"], bool):
            raise ProblemFileError(f"{where}: {t}.optimize must be true or false; got {gp_in['optimize']!r}")
        gp["optimize"] = gp_in["optimize"]
    if "info_gain" in gp_in:
        if gp_in["info_gain"] not in ("data", "trivial"):
            raise ProblemFileError(
                f"{where}: {t}.info_gain must be one of data, trivial; got {gp_in['info_gain']!r}"
            )
        gp["info_gain"] = gp_in["info_gain"]
    if "bound_tol" in gp_in:
        gp["bound_tol"] = float(_number(gp_in["bound_tol"], f"{t}.bound_tol", where, lo=1e-12))
    return gp


def _parse_abstraction(ab_in: dict, n: int, where: str) -> dict[str, Any]:
    """``[abstraction]``: eta, eps_rule, combine, guarantee, confidence (defaults where absent); transitions
    and form (only where given: the Problem's defaults apply otherwise)."""
    ab: dict[str, Any] = {"eta": None, "eps_rule": "optimized", "combine": "product",
                          "guarantee": "confidence", "confidence": 0.99}
    if "eta" in ab_in:
        ab["eta"] = _positive_vector(ab_in["eta"], "[abstraction].eta", where, n)
    if "confidence" in ab_in:
        c = _number(ab_in["confidence"], "[abstraction].confidence", where)
        if not 0.0 < float(c) < 1.0:
            raise ProblemFileError(f"{where}: [abstraction].confidence must lie in (0, 1); got {c!r}")
        ab["confidence"] = float(c)
    for key, valid in (("eps_rule", EPS_RULES), ("combine", COMBINE_RULES), ("guarantee", GUARANTEES),
                       ("transitions", TRANSITIONS), ("form", FORMS)):
        if key in ab_in:
            if ab_in[key] not in valid:
                raise ProblemFileError(
                    f"{where}: [abstraction].{key} must be one of {', '.join(valid)}; "
                    f"got {ab_in[key]!r}"
                )
            ab[key] = ab_in[key]
    return ab


def _parse_refine(r_in: dict, gp: dict, n: int, t: str, where: str) -> dict[str, Any]:
    """``[refine]``: the given keys of ``refine.RefineOptions``, checked; refused for bounds whose event
    does not cover new cells (``gp``: the parsed learning table)."""
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
    _file_rule(t, methods.get(gp.get("error_bound", methods.DEFAULT)).check_file_refine, gp.get("iid_noise"), where)
    return refine


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


def _per_component_gp(gp_in: dict, mode_names: list, n: int, where: str, t: str = "[learning]") -> dict:
    """[learning].rkhs_bound / lengthscale / misspecification / known per mode and component, checked by
    ``assumptions.resolve``; the returned values are what the Problem takes (known folded into rkhs_bound)."""
    from robust_imdp.bounds.assumptions import resolve

    known = gp_in.get("known")
    try:
        st = resolve(gp_in["rkhs_bound"], gp_in.get("lengthscale"), gp_in.get("misspecification", 0.0), mode_names, n,
                     prefix=f"{t}.", known=known)
    except InvalidInputError as exc:
        raise ProblemFileError(f"{where}: {exc}") from None
    out = {"rkhs_bound": gp_in["rkhs_bound"], "misspecification": gp_in.get("misspecification", 0.0)}
    if known is not None:  # the B table with 0 for the known components
        out["rkhs_bound"] = {m: st.rkhs_bound[u].tolist() for u, m in enumerate(mode_names)}
    if "lengthscale" in gp_in:
        out["lengthscale"] = gp_in["lengthscale"]
    return out



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
    spec["data_file"] = None if spec["data_path"] is None else str((path.parent / spec["data_path"]).resolve())
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
        A sample is impossible under ``[learning].rkhs_bound``, ``misspecification`` and the noise bound.
    """
    from robust_imdp.pipeline.problem import Problem
    from robust_imdp.models.system import AffineMap, Dataset

    spec = parse_problem_file(path)
    names = list(spec["modes"])
    n = spec["lower"].shape[0]
    noise = make_noise(spec["noise"])
    known = _all_known(spec["learning"], names, n)
    inputs = spec.get("inputs")
    data = None
    if known:  # known dynamics: nothing is learned, so the data are neither read nor checked
        if spec["data_file"] is not None:
            warnings.warn(f"{path}: every component of every mode is known ([{spec['learning_table']}].rkhs_bound = "
                          f"0), so the data file {spec['data_file']} is not used; remove [data] to say so",
                          RobustImdpWarning, stacklevel=2)
    else:
        x, u, x_next, _, rows = _read_data(spec["data_file"], names, n, origin=f"[data].path in {path}", inputs=inputs)
        refuse_adaptive_iid(spec["data_file"], spec["learning"].get("iid_noise", False))
        missing = [names[i] for i in range(len(names)) if not np.any(u == i)]
        if missing:
            raise ProblemFileError(
                f"data file {spec['data_file']}: modes {missing} have no samples; every [modes.*] "
                "table needs data (or rkhs_bound = 0 for a mode whose every component is known)"
            )
        data = Dataset(x, u, x_next, modes=tuple(names))
    _check_known_domains(spec, str(path))
    if not known:
        _check_samples_possible(spec, noise, x, u, x_next, rows)
        _warn_few_samples(spec, u, rows)
    _warn_refined_grid(spec, str(path))
    gp = dict(spec["learning"])
    rkhs_bound = gp.pop("rkhs_bound")
    error_bound = gp.pop("error_bound")
    misspecification = gp.pop("misspecification")
    iid_noise = gp.pop("iid_noise")
    local_points = gp.pop("local_points")
    split_tol = gp.pop("split_tol", None)
    bound_tol = gp.pop("bound_tol", BOUND_TOL)
    bound_max_boxes = gp.pop("bound_max_boxes", BOUND_MAX_BOXES)
    ab = spec["abstraction"]
    return Problem(
        space_lower=spec["lower"], space_upper=spec["upper"], cell_size=spec["cell_size"],
        regions=spec["regions"], formula=spec["formula"], threshold=spec["threshold"],
        horizon=spec["horizon"], data=data,
        mode_names=tuple(names), maps=tuple(m if not isinstance(m, tuple) else AffineMap(*m)
                                            for m in spec["modes"].values()),
        noise=noise, rkhs_bound=rkhs_bound, gp_options=gp,
        bound_tol=bound_tol, bound_max_boxes=bound_max_boxes, eta=ab["eta"], eps_rule=ab["eps_rule"], combine=ab["combine"],
        guarantee=ab["guarantee"], confidence=ab["confidence"], transitions=ab.get("transitions", DEFAULT_TRANSITIONS),
        form=ab.get("form", "auto"), error_bound=error_bound,
        misspecification=misspecification, iid_noise=iid_noise, local_points=local_points,
        refine=spec["refine"], dim_names=spec["names"], periodic=spec.get("periodic"), split_tol=split_tol,
        semantics=spec.get("semantics", "auto"), inputs=inputs,
    )


def _check_known_domains(spec, where: str = "the problem file") -> None:
    """Refuse a nonlinear known part undefined on part of X, at load time: its interval enclosure over
    every cell of the grid (``KnownDynamics.image_bounds``, the natural extension the bound stage starts
    from) raises ``ExpressionDomainError`` naming the file, the mode's table, the component and the box."""
    nonlinear = [m for m in spec["modes"].values() if not isinstance(m, tuple)]
    if not nonlinear:
        return
    from robust_imdp.pipeline.bound_stage import known_images

    part = _file_partition(spec, where, range(spec["lower"].shape[0]))
    known_images(nonlinear, part.cells_lower, part.cells_upper, form="natural")  # an input grid's modes at once




def _file_partition(spec, where: str, dims):
    """The grid of a parsed problem file on the dimensions ``dims`` (all of them, or one), its regions cut at
    the seam of the periodic ones (``geometry.wrap_region_boxes``). A region the partition refuses is named with
    the file and the form a region box must have (a ``ProblemFileError``), not as an internal box."""
    from robust_imdp.models.geometry import Box, Partition, Region

    dims = list(dims)
    periodic = spec.get("periodic")
    flags = None if periodic is None else tuple(bool(periodic[j]) for j in dims)
    regions = [Region(name, [Box(np.asarray(lo)[dims], np.asarray(up)[dims]) for lo, up in boxes])
               for name, boxes in spec["regions"].items()]
    try:
        return Partition(Box(spec["lower"][dims], spec["upper"][dims]), spec["cell_size"][dims], regions,
                         periodic=flags if flags is not None and any(flags) else None)
    except InvalidInputError as exc:
        raise ProblemFileError(
            f"{where}: the regions do not fit [space] ({exc}); each [[regions.NAME]] box needs lower < upper inside "
            "[space].lower .. [space].upper, except on a periodic dimension, where it may cross the seam by at most "
            "one period") from None


def _warn_refined_grid(spec, where: str) -> None:
    """Warn when region boundaries off the uniform grid add breakpoints (``geometry.Partition``'s rule)."""
    import warnings

    from robust_imdp.errors import RobustImdpWarning
    from robust_imdp.models.geometry import dimension_text

    lower, upper, h = spec["lower"], spec["upper"], spec["cell_size"]
    uniform, refined, notes = [], [], []
    for j in range(lower.shape[0]):
        # the breakpoints of dimension j depend only on dimension j: a 1-D partition has them (with the
        # seam-crossing boxes of a periodic dimension cut as the full partition cuts them)
        part = _file_partition(spec, where, [j])
        bp = part.breakpoints[0]
        k = int(round((upper[j] - lower[j]) / h[j]))
        uniform.append(k)
        refined.append(bp.size - 1)
        if bp.size - 1 > k:
            ticks = lower[j] + np.arange(k + 1) * ((upper[j] - lower[j]) / k)
            new = [v for v in bp.tolist() if np.min(np.abs(ticks - v)) > 1e-9 * h[j]]
            owners = {v: sorted({r.name for r in part.regions for b in r.boxes
                                 if v in (float(b.lower[0]), float(b.upper[0]))}) for v in new}
            notes.append(f"{dimension_text(j, spec.get('names'))}: {k} -> {bp.size - 1} intervals, at "
                         + ", ".join(f"{v:g} ({', '.join(owners[v])})" for v in new[:4])
                         + (f" and {len(new) - 4} more" if len(new) > 4 else ""))
    if notes:
        warnings.warn(
            f"{where}: region boundaries off the grid refine it from {int(np.prod(uniform)):,} to "
            f"{int(np.prod(refined)):,} cells ({'; '.join(notes)}); to keep the uniform grid, put region "
            "boundaries at [space].lower + k * cell_size",
            RobustImdpWarning, stacklevel=3)

