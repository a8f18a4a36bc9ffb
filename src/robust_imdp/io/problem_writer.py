"""A :class:`~robust_imdp.pipeline.problem.Problem` written as a problem file (TOML) and its data file: the
inverse of :func:`robust_imdp.io.problem_file.load_problem`, so that a problem built in Python
(``Problem.from_arrays``) can be given to ``robust-imdp run``, ``suggest`` and ``improve``.

``load_problem(save_problem(p, "p.toml"))`` is the same problem: the same grid, regions, specification,
samples (written with ``repr``, exact), known parts, noise, assumption per mode and component and options,
hence the same result. Numbers are written with ``repr`` (the shortest text that reads back to the same
float). What a problem file cannot say is refused with a message naming it: a known part built from casadi
symbols whose text does not read back to the same expression, a noise model of another type than the
file's three, or an option of ``gp_options`` the file has no key for.
"""

from __future__ import annotations

import json
import os
import re
import sys
import tempfile
from pathlib import Path

import numpy as np

from robust_imdp.errors import InvalidInputError
from robust_imdp.io.data_file import write_data_file
from robust_imdp.io.problem_file import parse_problem_dict
from robust_imdp.io.result_file import _atomic_write

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib

__all__ = ["problem_to_toml", "save_problem"]

#: ``gp_options`` keys a problem file's ``[learning]`` table has (the rest of the table is Problem attributes).
_GP_OPTION_KEYS = ("lengthscale", "signal_variance", "optimize", "info_gain")
_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def _key(name: str) -> str:
    """A TOML key: bare where TOML allows it, else a quoted string."""
    return name if _BARE_KEY.match(name) else json.dumps(name)


def _value(v) -> str:
    """A TOML value for the types a problem file holds (numbers by ``repr``, exact; lists; inline tables)."""
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, str):
        return json.dumps(v)  # JSON's escapes are TOML basic-string escapes
    if isinstance(v, np.ndarray):
        return _value(v.tolist())
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(str(k))} = {_value(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise InvalidInputError(f"a problem file cannot hold {type(v).__name__} {v!r}")


def _setting(value):
    """A per-mode / per-component setting as the file writes it: a number, a list or a table per mode."""
    if isinstance(value, dict):
        return {str(k): _setting(v) for k, v in value.items()}
    arr = np.asarray(value, dtype=float)
    return float(arr) if arr.ndim == 0 else arr.tolist()


def _known_part(name: str, m, n: int) -> dict:
    """``[modes.NAME]``: ``A`` and ``b``, or ``f`` (expressions that read back to the same known part)."""
    if hasattr(m, "A") and hasattr(m, "b"):
        return {"A": np.asarray(m.A, dtype=float), "b": np.asarray(m.b, dtype=float)}
    from robust_imdp.models.known import KnownDynamics

    exprs = list(getattr(m, "expressions", ()))
    try:
        same = len(exprs) == n and KnownDynamics(exprs).fingerprint() == m.fingerprint()
    except InvalidInputError:
        same = False
    if not same:
        raise InvalidInputError(
            f"the known part of mode {name!r} cannot be written as [modes.{name}].f: its expressions {exprs!r} do not "
            "read back to the same function (built from casadi symbols?); give the mode as a list of expressions in "
            f"x1..x{n} (Problem.from_arrays(modes={{{name!r}: ['...', ...]}}))")
    return {"f": exprs}


def _noise(noise, n: int) -> dict:
    """``[noise]`` of a noise model (``models.noise``)."""
    from robust_imdp.models import noise as nz

    # the exact types: a subclass may be another law, which the file's kind would not say
    if type(noise) is nz.TruncatedGaussianNoise:
        return {"kind": "truncated_gaussian", "sigma": np.asarray(noise.sigma, float), "bound": np.asarray(noise.bound, float)}
    if type(noise) is nz.GaussianNoise:
        return {"kind": "gaussian", "sigma": np.asarray(noise.sigma, float)}
    if type(noise) is nz.UniformNoise:
        return {"kind": "uniform", "bound": np.asarray(noise.bound, float)}
    raise InvalidInputError(f"a problem file's [noise] is a TruncatedGaussianNoise, GaussianNoise or UniformNoise; "
                            f"the problem's noise is a {type(noise).__name__}")


def _tables(problem, data_path: str) -> list:
    """The problem file as (header, {key: value}) pairs in file order (``[[regions.NAME]]`` once per box)."""
    from robust_imdp.pipeline.problem import DEFAULT_TRANSITIONS

    n = int(np.size(problem.space_lower))
    space = {"lower": np.asarray(problem.space_lower, float), "upper": np.asarray(problem.space_upper, float),
             "cell_size": np.broadcast_to(np.asarray(problem.cell_size, float), (n,))}
    if problem.dim_names is not None:
        space["names"] = list(problem.dim_names)
    if problem.periodic is not None:
        space["periodic"] = [bool(v) for v in problem.periodic]
    out = [("[space]", space)]
    for name, boxes in problem.regions.items():
        for lo, up in boxes:
            out.append((f"[[regions.{_key(name)}]]", {"lower": np.asarray(lo, float), "upper": np.asarray(up, float)}))
    spec = {"formula": problem.formula, "threshold": float(problem.threshold)}
    if problem.horizon is not None:
        spec["horizon"] = int(problem.horizon)
    if problem.semantics != "auto":
        spec["semantics"] = problem.semantics
    out.append(("[spec]", spec))
    if problem.data is not None:  # known dynamics need no [data] (problem_file, "Known dynamics")
        out.append(("[data]", {"path": data_path}))
    for name, m in zip(problem.mode_names, problem.maps):
        out.append((f"[modes.{_key(name)}]", _known_part(name, m, n)))
    out.append(("[noise]", _noise(problem.noise, n)))
    out.append(("[learning]", _learning(problem)))  # also for known dynamics: it may carry a misspecification
    ab = {"eps_rule": problem.eps_rule, "combine": problem.combine, "guarantee": problem.guarantee,
          "confidence": float(problem.confidence)}
    if problem.eta is not None:
        ab = {"eta": np.broadcast_to(np.asarray(problem.eta, float), (n,)), **ab}
    if problem.transitions != DEFAULT_TRANSITIONS:
        ab["transitions"] = problem.transitions
    if problem.form != "auto":
        ab["form"] = problem.form
    out.append(("[abstraction]", ab))
    if problem.refine is not None:
        out.append(("[refine]", {k: v for k, v in problem.refine.to_dict().items() if v is not None}))
    return out


def _learning(problem) -> dict:
    """``[learning]``: the assumption and the bound options that differ from the file's defaults."""
    from robust_imdp.pipeline.problem import BOUND_MAX_BOXES, BOUND_TOL

    learning = {"rkhs_bound": _setting(problem.rkhs_bound)}
    unknown = sorted(set(problem.gp_options) - set(_GP_OPTION_KEYS))
    if unknown:
        raise InvalidInputError(f"gp_options {unknown} have no key in a problem file's [learning] table (it has "
                                f"{list(_GP_OPTION_KEYS)})")
    for key in _GP_OPTION_KEYS:
        if key in problem.gp_options:
            v = problem.gp_options[key]
            learning[key] = _setting(v) if key == "lengthscale" else v
    tau = problem.misspecification
    if isinstance(tau, dict) or np.ndim(tau) or float(tau) != 0.0:  # 0, the file's default, is left out
        learning["misspecification"] = _setting(tau)
    learning["error_bound"] = problem.error_bound
    if problem.iid_noise:
        learning["iid_noise"] = True
    if problem.local_points is not None:
        learning["local_points"] = int(problem.local_points)
    if problem.split_tol is not None:
        learning["split_tol"] = float(problem.split_tol)
    if float(problem.bound_tol) != BOUND_TOL:
        learning["bound_tol"] = float(problem.bound_tol)
    if int(problem.bound_max_boxes) != BOUND_MAX_BOXES:
        learning["bound_max_boxes"] = int(problem.bound_max_boxes)
    return learning


def problem_to_toml(problem, data_path: str = "data.csv") -> str:
    """The problem file of ``problem`` (its data in ``data_path``, relative to the file), as text.

    Parameters
    ----------
    problem : pipeline.problem.Problem
    data_path : str
        ``[data].path``.

    Returns
    -------
    str
        TOML that :func:`robust_imdp.io.problem_file.parse_problem_dict` accepts (checked here).

    Raises
    ------
    InvalidInputError
        Something of ``problem`` a problem file cannot say (named in the message).
    """
    lines = ["# written by robust_imdp.io.problem_writer.save_problem"]
    for header, table in _tables(problem, data_path):
        lines += ["", header] + [f"{_key(k)} = {_value(v)}" for k, v in table.items()]
    text = "\n".join(lines) + "\n"
    try:
        parse_problem_dict(tomllib.loads(text), where="the written problem file")
    except (InvalidInputError, tomllib.TOMLDecodeError) as exc:
        raise InvalidInputError(f"this Problem cannot be written as a problem file: {exc}") from None
    return text


def save_problem(problem, path, *, data_path: str | None = None) -> Path:
    """Write ``problem`` as a problem file and its samples as a data file.

    Parameters
    ----------
    problem : pipeline.problem.Problem
    path : str or Path
        The problem file (``.toml``).
    data_path : str, optional
        The data file, relative to the problem file's folder (``.csv`` or ``.npz``); default
        ``<stem>_data.csv`` beside it.

    Returns
    -------
    Path
        ``path``; ``robust_imdp.load_problem(path)`` reads the same problem back.

    Raises
    ------
    InvalidInputError
        Something of ``problem`` a problem file cannot say (nothing is written then).
    """
    path = Path(path)
    data_path = data_path or f"{path.stem}_data.csv"
    text = problem_to_toml(problem, data_path)  # refuses before anything is written
    if problem.data is None:  # known dynamics: the file alone
        path.parent.mkdir(parents=True, exist_ok=True)
        _atomic_write(path, lambda tmp: tmp.write_text(text))
        return path
    data_file = path.parent / data_path
    data_file.parent.mkdir(parents=True, exist_ok=True)
    d = problem.data
    # written under a temporary name that keeps the suffix (write_data_file picks the format by it), then renamed
    fd, tmp = tempfile.mkstemp(dir=data_file.parent, prefix=f".{data_file.name}.", suffix=data_file.suffix)
    os.close(fd)
    try:
        write_data_file(tmp, d.x, d.u, d.x_next, modes=problem.mode_names)
        os.replace(tmp, data_file)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _atomic_write(path, lambda tmp: tmp.write_text(text))
    return path
