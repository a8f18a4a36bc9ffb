"""Cache keys (fingerprints of exactly the inputs of a stage) and cache entries, written atomically with
checksums and read back only when intact.
"""

from __future__ import annotations

import hashlib
import json
import os
import warnings
from dataclasses import fields, is_dataclass
from pathlib import Path

import numpy as np

from robust_imdp.errors import interrupt_in

from robust_imdp.pipeline.problem import CHECK_DELTA, Problem, _map_key, _setting_value


def _fingerprint(h, obj) -> None:
    """Feed a canonical description of ``obj`` into the hash ``h`` (arrays by value)."""
    if isinstance(obj, np.ndarray) or isinstance(obj, np.generic):
        a = np.ascontiguousarray(obj)
        h.update(f"nd{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    elif isinstance(obj, dict):
        h.update(b"{")
        for k in sorted(obj, key=str):
            _fingerprint(h, str(k))
            _fingerprint(h, obj[k])
        h.update(b"}")
    elif isinstance(obj, (list, tuple)):
        h.update(f"[{len(obj)}".encode())
        for v in obj:
            _fingerprint(h, v)
        h.update(b"]")
    elif obj is None or isinstance(obj, (bool, int, float, str)):
        h.update(f"{type(obj).__name__}:{obj!r};".encode())
    elif is_dataclass(obj):
        h.update(type(obj).__qualname__.encode())
        _fingerprint(h, {f.name: getattr(obj, f.name) for f in fields(obj)})
    elif hasattr(obj, "__dict__"):
        h.update(type(obj).__qualname__.encode())
        _fingerprint(h, {k: v for k, v in vars(obj).items() if not k.startswith("_")})
    else:
        h.update(repr(obj).encode())


def bounds_key(problem: Problem) -> str:
    """Hash of everything the learned cell bounds depend on (data, modes, noise, grid, GP)."""
    import robust_imdp

    h = hashlib.sha256()
    d = problem.data
    _fingerprint(h, [
        robust_imdp.__version__, problem.space_lower, problem.space_upper, problem.cell_size,
        {k: [(np.asarray(lo, float), np.asarray(up, float)) for lo, up in v]
         for k, v in problem.regions.items()},
        *_data_key(d),
        list(problem.mode_names), [_map_key(m) for m in problem.maps],
        problem.noise, _setting_value(problem.rkhs_bound), problem.gp_options, float(problem.bound_tol),
        int(problem.bound_max_boxes), problem.error_bound, _setting_value(problem.misspecification),
        bool(problem.iid_noise), float(problem.confidence) if problem.method.confidence_in_bounds else None,
        problem.local_points,
    ] + _periodic_key(problem) + _split_key(problem))
    return h.hexdigest()[:20]


def _data_key(d) -> list:
    """The data's arrays (x, u, x_next), or ``["no data"]`` for known dynamics (``Problem.data`` None)."""
    if d is None:
        return ["no data"]
    return [np.asarray(d.x, float), np.asarray(d.u), np.asarray(d.x_next, float)]


def _periodic_key(problem: Problem) -> list:
    """``[("periodic", flags)]`` when a dimension is periodic, else ``[]`` (keys without one are unchanged)."""
    periodic = getattr(problem, "periodic", None)
    return [] if periodic is None else [("periodic", list(periodic))]


def _split_key(problem: Problem) -> list:
    """``[("split_tol", value)]`` when sub-box certification is on, else ``[]`` (keys without it are unchanged)."""
    tol = getattr(problem, "split_tol", None)
    return [] if tol is None else [("split_tol", float(tol))]


def _transitions_key(problem: Problem) -> list:
    """``[("transitions", value)]`` unless Thm 1's bounds are used (keys of Thm 1 abstractions are unchanged)."""
    kind = getattr(problem, "transitions", "thm1")
    return [] if kind == "thm1" else [("transitions", kind)]


def _form_key(problem: Problem) -> list:
    """``[("form", "factored")]`` when the grid's abstraction is factored (``Problem.form_choice``), else ``[]``
    (keys of joint abstractions are unchanged)."""
    choice = getattr(problem, "form_choice", None)
    return [("form", "factored")] if choice is not None and choice()[0] == "factored" else []


def abstraction_key(problem: Problem) -> str:
    """Hash of everything the abstraction depends on (not the formula, threshold, horizon)."""
    h = hashlib.sha256(bounds_key(problem).encode())
    _fingerprint(h, [None if problem.eta is None else np.asarray(problem.eta, float),
                     problem.eps_rule, problem.combine, problem.guarantee,
                     float(problem.confidence)] + _transitions_key(problem) + _form_key(problem))
    return h.hexdigest()[:20]


# --------------------------------------------------------------------------- cache entries
# Every file of the cache is an entry ``NAME`` with a checksum file ``NAME.sha256`` (sha256 of
# the bytes, their count, and NAME). An entry is written under a temporary name, flushed to disk
# (fsync) and renamed, so a crash leaves either the old entry, no entry, or an entry whose
# checksum does not match; an entry that does not match its checksum, or cannot be read, gets
# one warning line and is computed again.
CHECKSUM_SUFFIX = ".sha256"


def _checksum_file(path: Path) -> Path:
    return path.with_name(path.name + CHECKSUM_SUFFIX)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _fsync(path: Path, directory: bool = False) -> None:
    """Flush ``path`` (a file, or a directory's entries) to disk."""
    try:
        fd = os.open(path, os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0))
    except OSError:  # pragma: no cover - a directory that cannot be opened (non-POSIX)
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover - file systems without fsync of directories
        pass
    finally:
        os.close(fd)


def write_cache_entry(path, write) -> None:
    """Write the cache entry ``path`` with ``write(tmp_path)`` and its checksum file.

    ``tmp_path`` is a hidden file in the same directory with the same suffix (``np.savez``
    appends ``.npz`` to names without it). It is flushed to disk before it is renamed, and
    the checksum file is written the same way after it.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.part{path.suffix}")
    side = _checksum_file(path)
    side_tmp = side.with_name(f".{side.name}.part")
    try:
        write(tmp)
        _fsync(tmp)
        side_tmp.write_text(f"{_sha256(tmp)} {tmp.stat().st_size} {path.name}\n")
        _fsync(side_tmp)
        os.replace(tmp, path)
        os.replace(side_tmp, side)
        _fsync(path.parent, directory=True)
    finally:
        for t in (tmp, side_tmp):
            t.unlink(missing_ok=True)


def cache_entry_problem(path) -> str | None:
    """Why the cache entry ``path`` cannot be trusted (no checksum, size or digest mismatch), or None."""
    path = Path(path)
    side = _checksum_file(path)
    try:
        fields_ = side.read_text(encoding="ascii").split()
    except (OSError, UnicodeDecodeError):
        return f"has no readable checksum file {side.name}"
    if len(fields_) != 3 or fields_[2] != path.name or not fields_[1].isdigit():
        return f"has a checksum file {side.name} for another entry or in another form"
    size = path.stat().st_size
    if size != int(fields_[1]):
        return f"is {size} bytes, its checksum file says {fields_[1]} (truncated or changed)"
    if _sha256(path) != fields_[0]:
        return "does not match its sha256 checksum (changed or damaged)"
    return None


def read_cache_entry(path, read):
    """``read(path)`` when the cache entry exists and matches its checksum, else None.

    A damaged entry (checksum mismatch, or ``read`` fails on it) gets one warning line and is
    deleted, so that the caller computes it again.
    """
    from robust_imdp.errors import RobustImdpWarning

    path = Path(path)
    if not path.exists():
        return None
    why = cache_entry_problem(path)
    if why is None:
        try:
            return read(path)
        except Exception as exc:  # a damaged or foreign file: any reader error means "recompute"
            if interrupt_in(exc) is not None:
                raise
            why = f"cannot be read ({type(exc).__name__}: {exc})"
    warnings.warn(f"cache entry {path} {why}; computing it again", RobustImdpWarning, stacklevel=2)
    for f in (path, _checksum_file(path)):
        f.unlink(missing_ok=True)
    return None


def _write_json_entry(path: Path, doc) -> None:
    from robust_imdp.jsonable import jsonable as _jsonable

    write_cache_entry(path, lambda tmp: tmp.write_text(json.dumps(_jsonable(doc)), encoding="utf-8"))


def _read_json(path: Path):
    return json.loads(path.read_text(encoding="utf-8"))


_EB_FIELDS = ("rkhs_bound", "sub_gaussian", "regulariser", "info_gain", "n_samples")


def _save_bounds(path: Path, cell_bounds, error_models, diagnostics: dict) -> None:
    from robust_imdp.jsonable import jsonable as _jsonable

    arrays = {k: np.asarray(getattr(cell_bounds, k)) for k in ("image_lower", "image_upper")}
    if cell_bounds.std_upper is not None:
        arrays["std_upper"] = np.asarray(cell_bounds.std_upper)
    if error_models is not None:
        for f in _EB_FIELDS:
            arrays[f"eb_{f}"] = np.array([[getattr(e, f) for e in row] for row in error_models])
    arrays["diagnostics"] = np.array(json.dumps(_jsonable(diagnostics)))
    write_cache_entry(path, lambda tmp: _savez(tmp, arrays))


def _savez(path: Path, arrays: dict) -> None:
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


def _load_npz(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _load_bounds(path: Path):
    from robust_imdp.abstraction.rows import CellBounds
    from robust_imdp.bounds.gp import RKHSErrorBound

    with np.load(path, allow_pickle=False) as z:
        cb = CellBounds(z["image_lower"], z["image_upper"], z["std_upper"] if "std_upper" in z else None)
        cols = {f: z[f"eb_{f}"] for f in _EB_FIELDS} if "eb_rkhs_bound" in z else None
        diagnostics = json.loads(str(z["diagnostics"])) if "diagnostics" in z else {}
    if cols is None:
        return cb, None, diagnostics
    n_modes, n = cols["rkhs_bound"].shape
    models = tuple(tuple(RKHSErrorBound(**{f: (int(cols[f][u, i]) if f == "n_samples"
                                               else float(cols[f][u, i])) for f in _EB_FIELDS})
                         for i in range(n)) for u in range(n_modes))
    return cb, models, diagnostics


def check_key(problem: Problem) -> str:
    """Hash of everything the assumption check depends on: the data and the assumption.

    The data, the modes' known parts (the residuals), the noise model (its bound), the
    lengthscale, ``rkhs_bound`` and ``misspecification``; not the grid, regions or formula.
    """
    import robust_imdp

    h = hashlib.sha256(b"assumption-check")
    d = problem.data
    _fingerprint(h, [
        robust_imdp.__version__, *_data_key(d),
        list(problem.mode_names), [_map_key(m) for m in problem.maps],
        problem.noise, problem.gp_options.get("lengthscale", 1.0), _setting_value(problem.rkhs_bound),
        _setting_value(problem.misspecification), CHECK_DELTA,
    ] + _periodic_key(problem))
    return h.hexdigest()[:20]


def _read_checks(path: Path):
    """The NormChecks and noise bound of a saved assumption check (ValueError/KeyError if malformed)."""
    from robust_imdp.bounds.rkhs import NormCheck

    doc = _read_json(path)
    checks = tuple(NormCheck(**c) for c in doc["checks"])
    if not checks:
        raise ValueError("no checks")
    return checks, np.asarray(doc["noise_bound"], float)


def load_abstraction_file(path):
    """The abstraction in ``path``: a ``FactoredAbstraction`` (docs/factored.md) or a joint ``Abstraction``."""
    from robust_imdp.abstraction.factored import FactoredAbstraction, is_factored_file
    from robust_imdp.abstraction.rows import Abstraction

    return FactoredAbstraction.load(path) if is_factored_file(path) else Abstraction.load(path)


def _load_abstraction_entry(cache_file: Path):
    """(abstraction, the JSON document saved beside it) from the cache, or None (absent or damaged); the
    abstraction is joint or factored, as it was saved."""
    doc = read_cache_entry(cache_file.with_suffix(".json"), _read_json)
    if doc is None:
        return None
    abstraction = read_cache_entry(cache_file, load_abstraction_file)
    return None if abstraction is None else (abstraction, doc)


def _save_abstraction_entry(cache_file: Path, abstraction, doc: dict) -> None:
    """The JSON document first, the abstraction last: its presence means the pair is complete."""
    _write_json_entry(cache_file.with_suffix(".json"), doc)
    write_cache_entry(cache_file, abstraction.save)


def refined_key(problem: Problem) -> str:
    """Hash of everything a refined abstraction depends on: the abstraction's, the options and the spec."""
    h = hashlib.sha256(abstraction_key(problem).encode())
    spec = [problem.refine.to_dict(), problem.formula, float(problem.threshold), problem.horizon]
    if getattr(problem, "semantics", "auto") != "auto":  # only then: the keys of "auto" runs are as before
        spec.append(problem.semantics)
    _fingerprint(h, spec)
    return h.hexdigest()[:20]
