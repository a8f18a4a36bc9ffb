"""Data files (CSV / NPZ): reading with errors that name the file's line, writing, and the load-time
checks of the samples against the problem (impossible samples refused, modes with few samples warned).

``.csv`` with header ``x_1..x_n,u,x_next_1..x_next_n`` (``u`` holds mode names), or ``.npz`` with
arrays ``x`` (m, n), ``u`` (m,) and ``x_next`` (m, n). Every mode name in ``u`` must be one of the
``[modes.*]`` tables. Errors name the CSV file's 1-based line.

An optional last column (CSV) or array (npz) ``round`` says in which round of ``robust-imdp improve``
a sample was collected (0: the initial data). The pipeline ignores it, except that samples of a
round > 0 were chosen from earlier data (an adaptive design): the problem file refuses them with
``iid_noise = true`` (:func:`read_rounds`).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from robust_imdp.errors import ProblemFileError

__all__ = ["read_data_file", "write_data_file", "read_rounds", "FEW_SAMPLES", "ROUND_COLUMN"]

#: Name of the optional column (CSV) / array (npz) of the improve round of each sample.
ROUND_COLUMN = "round"


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


def _table(spec) -> str:
    """The learning table as the problem file names it (``[learning]``, or ``[gp]`` in an old file)."""
    return f"[{spec.get('learning_table', 'learning')}]"


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
    learning, t = spec["learning"], _table(spec)
    st = resolve(learning["rkhs_bound"], learning.get("lengthscale"), learning["misspecification"], names,
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
        if spec.get("periodic") is not None and sel.size:  # modulo the period, as the pipeline (docs/periodic.md)
            from robust_imdp.models.geometry import wrap_residuals

            res, rb = wrap_residuals(r_all.y, r_all.bound, spec["lower"], spec["upper"], spec["periodic"])
            nb_m = np.nextafter(nb + rb.max(axis=0), np.inf)
        for i in range(res.shape[1]):
            B, tau = float(st.rkhs_bound[m, i]), float(st.misspecification[m, i])
            lengthscale = st.lengthscale[m, i] if not st.uniform else learning.get("lengthscale", 1.0)
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
            f"{t} declares {component} of mode {names[m]!r} known (rkhs_bound = 0 or known = true), but sample {row} "
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
        f"{t}.rkhs_bound = {B_text} is refuted by the data: mode {names[m]!r}, {component} needs an RKHS norm "
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
            f"as {_table(spec)}.rkhs_bound allows, so expect few Q_yes cells; add samples of these modes",
            RobustImdpWarning, stacklevel=3)



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


def _read_data(path, mode_names=None, n_dims: int | None = None, origin: str | None = None, inputs=None):
    """:func:`read_data_file` plus the 1-based line of every sample (None for .npz).

    ``origin``: where the path was given (e.g. ``[data].path in p.toml``), for the message when
    it names a directory. ``inputs``: the problem's input grid (``models.inputs.InputGrid``): the file then
    has input columns ``u_1..u_m`` (CSV) or an ``(m_samples, m)`` array ``u`` (npz) instead of mode names, and
    every input must be a point of the grid (the sample's mode).
    """
    path = Path(path)
    where = f"data file {path}"
    if not path.exists():
        raise ProblemFileError(f"{where}: file not found")
    if path.is_dir():
        raise ProblemFileError(f"{origin or 'the data file'}: {path} is a directory; expected a data file "
                               "(.csv or .npz)")
    rows = None
    if inputs is not None:
        return _read_input_data(path, where, inputs, n_dims)
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


def _read_input_data(path: Path, where: str, grid, n_dims: int | None):
    """A data file of an input grid: ``(x, mode index, x_next, grid's mode names, lines or None)``."""
    m = grid.n_inputs
    rows = None
    if path.suffix == ".npz":
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [k for k in ("x", "u", "x_next") if k not in z.files]
                if missing:
                    raise ProblemFileError(f"{where}: missing arrays {missing}; expected x, u (the inputs, "
                                           f"(m, {m})), x_next (got {z.files})")
                x, u, x_next = (np.asarray(z[k], dtype=float) for k in ("x", "u", "x_next"))
        except (ValueError, OSError) as exc:
            if isinstance(exc, ProblemFileError):
                raise
            raise ProblemFileError(f"{where}: cannot be read as .npz with numeric x, u, x_next ({exc})") from None
        u = u.reshape(-1, 1) if u.ndim == 1 and m == 1 else u
        if u.ndim != 2 or u.shape[1] != m:
            raise ProblemFileError(f"{where}: u must hold the {m} inputs ({', '.join(grid.names)}) of every sample, "
                                   f"shape (m, {m}); got {u.shape}")
    elif path.suffix == ".csv":
        x, u, x_next, rows = _read_csv(path, where, n_dims, n_inputs=m)
    else:
        raise ProblemFileError(f"{where}: expected a .csv or .npz file; got suffix '{path.suffix}'")
    if n_dims is not None and (x.ndim != 2 or x.shape[1] != n_dims):
        raise ProblemFileError(f"{where}: x must have {n_dims} columns like [space]; got shape {x.shape}")
    idx = grid.locate(u)
    bad = np.flatnonzero(idx < 0)
    if bad.size:
        from robust_imdp.models.inputs import input_name

        raise ProblemFileError(
            f"{where}: {_rows_text(rows, bad)}: the input {input_name(u[bad[0]])} is not a point of the [inputs] grid "
            f"({grid._values_text()}); every sample's input must be one of the grid's (its mode)")
    x, u_idx, x_next, modes = _check_data(x, np.asarray(grid.mode_names, dtype=object)[idx].astype(str), x_next,
                                          list(grid.mode_names), where, rows)
    return x, u_idx, x_next, modes, rows


def _header(n: int, n_inputs: int = 0) -> list:
    if n_inputs:
        return [f"x_{i + 1}" for i in range(n)] + [f"u_{j + 1}" for j in range(n_inputs)] + \
            [f"x_next_{i + 1}" for i in range(n)]
    return [f"x_{i + 1}" for i in range(n)] + ["u"] + [f"x_next_{i + 1}" for i in range(n)]


def _read_csv(path: Path, where: str, n_dims: int | None = None, n_inputs: int = 0):
    """Arrays of a CSV data file and the 1-based line of every sample; with ``n_inputs`` the inputs are
    ``n_inputs`` numeric columns ``u_1..u_m`` (an input grid's data) and ``u`` is returned as (k, m) floats."""
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
    n = (len(header) - max(n_inputs, 1)) // 2
    want = n_dims if n_dims is not None else max(n, 1)
    expected = _header(want, n_inputs)
    if header == expected + [ROUND_COLUMN]:  # the improve rounds' column: read by read_rounds only
        expected = header
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
    n = want
    if n_inputs:  # every column numeric: x, the inputs, x_next
        values = _numeric_columns(table, list(range(2 * n + n_inputs)), header, lines, where)
        return values[:, :n], values[:, n:n + n_inputs], values[:, n + n_inputs:], lines
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


def _numeric_columns(table, cols, header, lines, where):
    """The columns ``cols`` of a CSV table as floats; the first bad field is named by its line and column."""
    values = np.empty((table.shape[0], len(cols)))
    for k, c in enumerate(cols):
        try:
            values[:, k] = table[:, c].astype(float)
        except ValueError:
            for i, text in enumerate(table[:, c].tolist()):
                try:
                    float(text)
                except ValueError:
                    what = "is empty" if not text.strip() else f"is not a number: {text!r}"
                    raise ProblemFileError(f"{where}: line {int(lines[i])}, column {header[c]} {what}") from None
            raise  # pragma: no cover - astype and float() accept the same strings
    return values


def read_rounds(path):
    """The ``round`` column (CSV) or array (npz) of a data file as an int array, or None without one.

    Raises ProblemFileError naming the line (CSV) when a round is not an integer >= 0.
    """
    path = Path(path)
    where = f"data file {path}"
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            if ROUND_COLUMN not in z.files:
                return None
            values, lines = np.asarray(z[ROUND_COLUMN]).reshape(-1).tolist(), None
    else:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            header = [h.strip() for h in next(reader, [])]
            if not header or header[-1] != ROUND_COLUMN:
                return None
            values, lines = [], []
            for r in reader:
                if r:
                    values.append(r[-1].strip())
                    lines.append(reader.line_num)
    out = np.empty(len(values), dtype=np.int64)
    for i, v in enumerate(values):
        try:
            out[i] = int(v)
            ok = out[i] >= 0 and float(v) == out[i]
        except (TypeError, ValueError):
            ok = False
        if not ok:
            at = f"line {lines[i]}, column {ROUND_COLUMN}" if lines is not None else f"{ROUND_COLUMN}[{i}]"
            raise ProblemFileError(f"{where}: {at} must be an integer >= 0 (the improve round); got {v!r}")
    return out


#: Why the iid route refuses adaptively chosen inputs (the problem file's check and ``improve``'s).
ADAPTIVE_IID_MESSAGE = (
    "iid_noise = true assumes the inputs were chosen independently of the noise, but samples of "
    "improve rounds > 0 were chosen from earlier data (an adaptive design); set iid_noise = false "
    "(the deterministic bound holds for any inputs)")


def refuse_adaptive_iid(path, iid_noise: bool) -> None:
    """ProblemFileError when ``iid_noise`` is on and the data file has samples of a round > 0."""
    if not iid_noise:
        return
    rounds = read_rounds(path)
    if rounds is not None and np.any(rounds > 0):
        raise ProblemFileError(f"data file {Path(path)}: {int(np.sum(rounds > 0))} samples of rounds > 0: "
                               + ADAPTIVE_IID_MESSAGE)


def write_data_file(path, x, u, x_next, modes=None, rounds=None) -> None:
    """Write a data file (.csv or .npz) readable by :func:`read_data_file`.

    Parameters
    ----------
    x, x_next : (m, n) float arrays
    u : (m,) int (indices into ``modes``) or str array (mode names)
    modes : sequence of str, optional
        Mode names; required when ``u`` holds indices.
    rounds : (m,) int array, optional
        The improve round of each sample: written as the last column / array ``round``.
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
    extra = {} if rounds is None else {ROUND_COLUMN: np.asarray(rounds, dtype=np.int64)}
    if path.suffix == ".npz":
        np.savez(path, x=x, u=u, x_next=x_next, **extra)
        return
    header = [f"x_{i + 1}" for i in range(n)] + ["u"] + [f"x_next_{i + 1}" for i in range(n)]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header + list(extra))
        tails = ([[int(r)] for r in extra[ROUND_COLUMN]] if extra else [[]] * x.shape[0])
        for xi, ui, yi, tail in zip(x, u, x_next, tails):
            w.writerow([repr(float(v)) for v in xi] + [ui] + [repr(float(v)) for v in yi] + tail)

