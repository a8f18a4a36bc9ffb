"""Model exchange: Storm's DRN format, PRISM explicit files, and a bridge to stormpy.

So that users can check our IMDPs with other tools:

* :func:`write_drn` / :func:`read_drn` / :func:`load_drn` -- Storm's explicit "direct
  encoding" (DRN) with ``@type: MDP`` and interval values ``[a, b]``; the files load with
  ``stormpy.build_model_from_drn[stormpy.Interval](path)``.
* :func:`write_prism_explicit` / :func:`read_prism_explicit` -- PRISM explicit files
  ``.tra`` (``s a t [lo,up]``), ``.lab``, ``.sta`` and, with a target, ``.props``
  (``Pmaxmin=?`` / ``Pmaxmax=?``, PRISM's robust / optimistic IMDP queries, written as
  IntervalMDP.jl writes them; PRISM itself was not available to test these files).  Like
  Storm, PRISM wants positive lower bounds (constant support) for unbounded queries; entries
  are written as they are, never clamped.
* :func:`to_stormpy` / :func:`storm_reachability` -- a stormpy interval MDP built in memory
  and Storm's reachability values (stormpy is optional and imported lazily).

**Floors.** DRN and PRISM have no floor concept (an upper bound shared by every state a
row does not list).  Rows with a positive floor are *densified* on export: every unlisted
state becomes an explicit entry ``[0, floor]``.  That costs n entries per such row, so every
writer takes ``max_entries`` and refuses (``InvalidInputError``) models whose densified size
would exceed it.  Reading such a file back gives the equivalent model with ``floor = 0`` and
the entries listed (compare with ``IMDP.to_dense()``); models without floor rows round-trip
to identical arrays (numbers are written with ``repr``, which round-trips float64 exactly).

Malformed files raise :class:`~robust_imdp.errors.InvalidModelError` naming the file and
line; semantic errors (intervals, sums) are then reported by ``IMDP.from_csr`` naming the row.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np

from robust_imdp.errors import InvalidInputError, InvalidModelError
from robust_imdp.models.imdp import IMDP

#: Default limit on the number of stored entries after densifying floor rows.
MAX_ENTRIES = 10_000_000

_LABEL_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass(frozen=True)
class ModelFile:
    """An IMDP read from a file with its state labels.

    Attributes
    ----------
    imdp : IMDP
    labels : dict[str, (n_states,) bool array]
        Every label of the file (``init`` included).
    """

    imdp: IMDP
    labels: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------- shared helpers
def densified_rows(imdp: IMDP, *, max_entries: int = MAX_ENTRIES):
    """CSR rows with floors expanded: every unlisted state of a floor row gets ``[0, floor]``.

    Rows without a positive floor keep exactly their listed entries (in stored order).

    Parameters
    ----------
    imdp : IMDP
    max_entries : int
        Refuse (``InvalidInputError``) when the result would hold more entries.

    Returns
    -------
    row_ptr : (R + 1,) int64
    col : (nnz',) int64
    lower, upper : (nnz',) float64
    """
    R, n = imdp.n_choices, imdp.n_states
    frows = np.flatnonzero((imdp.floor > 0) & (imdp.n_unlisted > 0))
    total = imdp.nnz + int(imdp.n_unlisted[frows].sum())
    if total > max_entries:
        raise InvalidInputError(
            f"imdp has {frows.size} rows with a positive floor; DRN/PRISM have no floor, so they are written "
            f"densely: {total} entries > max_entries = {max_entries}. Raise max_entries or use a model without floors"
        )
    if frows.size == 0:
        return imdp.row_ptr.copy(), imdp.col.copy(), imdp.lower.copy(), imdp.upper.copy()
    entry_row = np.repeat(np.arange(R), np.diff(imdp.row_ptr))
    where = np.full(R, -1)
    where[frows] = np.arange(frows.size)
    listed = np.zeros((frows.size, n), dtype=bool)  # memory frows x n <= max_entries bits
    in_f = where[entry_row] >= 0
    listed[where[entry_row[in_f]], imdp.col[in_f]] = True
    fr, fc = np.nonzero(~listed)
    rows = np.concatenate([entry_row, frows[fr]])
    cols = np.concatenate([imdp.col, fc])
    lo = np.concatenate([imdp.lower, np.zeros(fr.size)])
    up = np.concatenate([imdp.upper, imdp.floor[frows[fr]]])
    # keep the stored order of listed entries, unlisted ones after them (stable by row)
    order = np.argsort(rows, kind="stable")
    row_ptr = np.zeros(R + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=R), out=row_ptr[1:])
    return row_ptr, cols[order], lo[order], up[order]


def _label_masks(imdp: IMDP, target, labels, initial) -> dict:
    """Validated ``{name: (n,) bool mask}``: ``init``, then ``target``, then user labels."""
    n = imdp.n_states
    out = {}
    init = np.zeros(n, dtype=bool)
    ini = np.atleast_1d(np.asarray(initial))
    if ini.size == 0 or not np.issubdtype(ini.dtype, np.integer) or np.any((ini < 0) | (ini >= n)):
        raise InvalidInputError(f"initial must be a state index (or indices) in [0, {n}); got {initial!r}")
    init[ini] = True
    out["init"] = init
    items = [] if target is None else [("target", target)]
    items += list((labels or {}).items())
    for name, sel in items:
        if not isinstance(name, str) or not _LABEL_RE.match(name):
            raise InvalidInputError(f"label names must be identifiers ([A-Za-z_][A-Za-z0-9_]*); got {name!r}")
        if name in out:
            raise InvalidInputError(f"label {name!r} is given twice (init and target are written automatically)")
        arr = np.asarray(sel)
        if arr.dtype == bool:
            if arr.shape != (n,):
                raise InvalidInputError(f"label {name!r} as a mask must have shape ({n},); got {arr.shape}")
            mask = arr.copy()
        else:
            if arr.ndim != 1 or (arr.size and not np.issubdtype(arr.dtype, np.integer)) or np.any((arr < 0) | (arr >= n)):
                raise InvalidInputError(f"label {name!r} must be a bool mask of length {n} or state indices in [0, {n}); got {arr!r}")
            mask = np.zeros(n, dtype=bool)
            mask[arr] = True
        out[name] = mask
    return out


def _fmt(x: np.ndarray) -> list:
    """Shortest round-trip decimal strings of float64 values (``repr``)."""
    return [repr(v) for v in x.tolist()]


def _interleave(n, state_ptr, row_ptr, state_lines, row_lines, entry_lines) -> list:
    """Place state headers, row headers and entries in file order (vectorised positions)."""
    R = row_ptr.shape[0] - 1
    row_state = np.repeat(np.arange(n), np.diff(state_ptr))
    entry_row = np.repeat(np.arange(R), np.diff(row_ptr))
    # line of state s = (s states before) + (rows before) + (entries before)
    s_pos = np.arange(n) + state_ptr[:-1] + row_ptr[state_ptr[:-1]]
    r_pos = row_state + 1 + np.arange(R) + row_ptr[:-1]
    e_pos = row_state[entry_row] + 1 + entry_row + 1 + np.arange(entry_row.size)
    lines = np.empty(n + R + entry_row.size, dtype=object)
    lines[s_pos] = state_lines
    lines[r_pos] = row_lines
    lines[e_pos] = entry_lines
    return lines.tolist()


# ----------------------------------------------------------------------------- DRN
def write_drn(imdp: IMDP, path, *, target=None, labels=None, initial=0, max_entries: int = MAX_ENTRIES) -> None:
    """Write ``imdp`` in Storm's DRN format (``@type: MDP``, interval values).

    Parameters
    ----------
    imdp : IMDP
    path : str or path-like
    target : (n,) bool mask or index array, optional
        Written as the label ``target``.
    labels : dict[str, mask or index array], optional
        Further labels (identifiers).
    initial : int or int array
        Initial state(s), labelled ``init`` (Storm requires one).
    max_entries : int
        Limit after densifying floor rows (module docstring).
    """
    masks = _label_masks(imdp, target, labels, initial)
    row_ptr, col, lo, up = densified_rows(imdp, max_entries=max_entries)
    n = imdp.n_states
    names = list(masks)
    M = np.stack([masks[k] for k in names], axis=1) if names else np.zeros((n, 0), bool)
    state_lines = [f"state {s}" + "".join(f" {names[j]}" for j in np.flatnonzero(M[s])) for s in range(n)]
    row_lines = [f"\taction {a}" for a in imdp.actions.tolist()]
    entry_lines = [f"\t\t{c} : [{a}, {b}]" for c, a, b in zip(col.tolist(), _fmt(lo), _fmt(up))]
    body = _interleave(n, imdp.state_ptr, row_ptr, state_lines, row_lines, entry_lines)
    head = ["// robust_imdp export (floors densified)", "@type: MDP", "@value_type: double-interval",
            "@parameters", "", "@reward_models", "", "@nr_states", str(n), "@nr_choices", str(imdp.n_choices), "@model"]
    with open(path, "w") as fh:
        fh.write("\n".join(head + body) + "\n")


def _bad(path, lineno, msg):
    return InvalidModelError(f"{os.fspath(path)}, line {lineno}: {msg}")


def _parse_value(tok: str, path, lineno):
    """``[a, b]`` -> (a, b); a plain number p -> (p, p)."""
    t = tok.strip()
    try:
        if t.startswith("["):
            if not t.endswith("]") or t.count(",") != 1:
                raise ValueError
            a, b = t[1:-1].split(",")
            return float(a), float(b)
        p = float(t)
        return p, p
    except ValueError:
        raise _bad(path, lineno, f"expected a probability interval '[lower, upper]' or a number; got {t!r}") from None


def load_drn(path) -> ModelFile:
    """Read a DRN file (``@type: MDP`` or ``DTMC``, interval or plain values) with its labels.

    State rewards, reward models, parameters and non-integer action names are not supported
    and raise ``InvalidModelError`` naming the line.
    """
    with open(path) as fh:
        lines = fh.read().splitlines()
    header, i = {}, 0
    while i < len(lines):
        raw = lines[i]
        s = raw.strip()
        i += 1
        if not s or s.startswith("//"):
            continue
        if not s.startswith("@"):
            raise _bad(path, i, f"expected a header line starting with '@' before '@model'; got {s!r}")
        key, _, rest = s.partition(":")
        key = key.strip()
        if key == "@model":
            break
        if key in ("@type", "@value_type"):
            header[key] = rest.strip()
        elif key in ("@parameters", "@reward_models", "@nr_states", "@nr_choices", "@placeholders"):
            val = lines[i].strip() if i < len(lines) else ""
            header[key] = (val, i + 1)
            i += 1
        else:
            raise _bad(path, i, f"unknown header {key!r}")
    else:
        raise _bad(path, len(lines), "no '@model' section")
    mtype = header.get("@type", "")
    if mtype not in ("MDP", "DTMC"):
        raise _bad(path, 1, f"@type must be MDP or DTMC; got {mtype!r}")
    for key in ("@parameters", "@reward_models"):
        if key in header and header[key][0]:
            raise _bad(path, header[key][1], f"{key} are not supported; got {header[key][0]!r}")
    try:
        n_decl = int(header["@nr_states"][0])
    except (KeyError, ValueError):
        raise _bad(path, header.get("@nr_states", ("", 1))[1], "@nr_states must be followed by an integer") from None
    mdp = mtype == "MDP"

    state_start, row_start, col, lo, up, actions = [], [], [], [], [], []
    labels: dict[str, list] = {}
    for k in range(i, len(lines)):
        lineno = k + 1
        s = lines[k].strip()
        if not s or s.startswith("//"):
            continue
        toks = s.split()
        if toks[0] == "state":
            if len(toks) < 2 or not toks[1].isdigit():
                raise _bad(path, lineno, f"expected 'state <index> [labels]'; got {s!r}")
            sid = int(toks[1])
            if sid != len(state_start):
                raise _bad(path, lineno, f"states must appear in order 0, 1, ...; expected state {len(state_start)}, got {sid}")
            if state_start and state_start[-1] == len(row_start):
                raise _bad(path, lineno, f"state {sid - 1} has no choice")
            state_start.append(len(row_start))
            for lab in toks[2:]:
                if lab.startswith("[") or lab.startswith("{"):
                    raise _bad(path, lineno, f"state rewards / observations are not supported; got {lab!r}")
                labels.setdefault(lab, []).append(sid)
            if not mdp:  # a DTMC state has exactly one implicit choice
                row_start.append(len(col))
                actions.append(0)
        elif toks[0] == "action":
            if not state_start:
                raise _bad(path, lineno, "'action' before the first 'state'")
            if not mdp:
                raise _bad(path, lineno, "'action' lines are not allowed in a DTMC")
            if len(toks) != 2 or not re.fullmatch(r"-?\d+", toks[1]):
                raise _bad(path, lineno, f"expected 'action <integer>' (named actions and rewards are not supported); got {s!r}")
            row_start.append(len(col))
            actions.append(int(toks[1]))
        else:
            tgt, sep, val = s.partition(":")
            if not sep or not tgt.strip().isdigit():
                raise _bad(path, lineno, f"expected '<successor> : [lower, upper]', 'action' or 'state'; got {s!r}")
            if not state_start or state_start[-1] == len(row_start):
                raise _bad(path, lineno, "transition before its 'state'/'action' line")
            a, b = _parse_value(val, path, lineno)
            col.append(int(tgt))
            lo.append(a)
            up.append(b)
    if not state_start:
        raise _bad(path, len(lines), "no state in '@model'")
    if state_start[-1] == len(row_start):
        raise _bad(path, len(lines), f"state {len(state_start) - 1} has no choice")
    state_ptr = state_start + [len(row_start)]
    rp = np.array(row_start + [len(col)], dtype=np.int64)
    n = len(state_start)
    if n != n_decl:
        raise _bad(path, header["@nr_states"][1], f"@nr_states says {n_decl} but the model has {n} states")
    if "@nr_choices" in header:
        try:
            r_decl = int(header["@nr_choices"][0])
        except ValueError:
            raise _bad(path, header["@nr_choices"][1], "@nr_choices must be followed by an integer") from None
        if r_decl != len(actions):
            raise _bad(path, header["@nr_choices"][1], f"@nr_choices says {r_decl} but the model has {len(actions)} choices")
    imdp = IMDP.from_csr(np.array(state_ptr), rp, np.array(col, dtype=np.int64), np.array(lo), np.array(up),
                         actions=np.array(actions, dtype=np.int64))
    masks = {}
    for lab, sts in labels.items():
        m = np.zeros(n, dtype=bool)
        m[sts] = True
        masks[lab] = m
    return ModelFile(imdp=imdp, labels=masks)


def read_drn(path) -> IMDP:
    """Read a DRN file into an :class:`IMDP` (labels: see :func:`load_drn`)."""
    return load_drn(path).imdp


# ----------------------------------------------------------------------------- PRISM explicit
def write_prism_explicit(imdp: IMDP, prefix, *, target=None, labels=None, initial=0,
                         max_entries: int = MAX_ENTRIES) -> list:
    """Write PRISM explicit files ``prefix.tra``, ``.lab``, ``.sta`` (and ``.props`` with a target).

    ``.tra``: header ``n_states n_choices n_transitions``, then ``s a t [lo,up]`` (a = choice
    index within the state), plus the action label ``a<label>`` as a fifth column when the
    labels differ from the choice indices.  ``.props`` holds ``Pmaxmin=? [ F "target" ]``
    (robust) and ``Pmaxmax=? [ F "target" ]`` (optimistic).  Floors are densified.

    Returns
    -------
    list of str : the paths written.
    """
    masks = _label_masks(imdp, target, labels, initial)
    row_ptr, col, lo, up = densified_rows(imdp, max_entries=max_entries)
    n, R = imdp.n_states, imdp.n_choices
    prefix = os.fspath(prefix)
    choice = np.arange(R) - np.repeat(imdp.state_ptr[:-1], np.diff(imdp.state_ptr))
    named = not np.array_equal(choice, imdp.actions)
    entry_row = np.repeat(np.arange(R), np.diff(row_ptr))
    src = imdp.row_state[entry_row].tolist()
    ch = choice[entry_row].tolist()
    act = imdp.actions[entry_row].tolist()
    tra = [f"{n} {R} {col.size}"]
    if named:
        tra += [f"{s} {c} {t} [{a},{b}] a{x}" for s, c, t, a, b, x in zip(src, ch, col.tolist(), _fmt(lo), _fmt(up), act)]
    else:
        tra += [f"{s} {c} {t} [{a},{b}]" for s, c, t, a, b in zip(src, ch, col.tolist(), _fmt(lo), _fmt(up))]
    names = list(masks)
    lab = [" ".join(f'{j}="{nm}"' for j, nm in enumerate(names))]
    M = np.stack([masks[k] for k in names], axis=1)
    for s in np.flatnonzero(M.any(axis=1)).tolist():
        lab.append(f"{s}: " + " ".join(str(j) for j in np.flatnonzero(M[s])))
    sta = ["(s)"] + [f"{s}:({s})" for s in range(n)]
    out = {".tra": tra, ".lab": lab, ".sta": sta}
    if target is not None:
        out[".props"] = ['Pmaxmin=? [ F "target" ]', 'Pmaxmax=? [ F "target" ]']
    paths = []
    for ext, body in out.items():
        with open(prefix + ext, "w") as fh:
            fh.write("\n".join(body) + "\n")
        paths.append(prefix + ext)
    return paths


def _n_found(rs: np.ndarray) -> int:
    return int(rs[-1]) + 1 if rs.size else 0


def load_prism_explicit(prefix) -> ModelFile:
    """Read ``prefix.tra`` (intervals ``[lo,up]`` or plain numbers) and ``prefix.lab`` if present."""
    prefix = os.fspath(prefix)
    tra = prefix + ".tra"
    with open(tra) as fh:
        lines = fh.read().splitlines()
    if not lines:
        raise _bad(tra, 1, "empty file; expected 'n_states n_choices n_transitions'")
    head = lines[0].split()
    if len(head) != 3 or not all(h.isdigit() for h in head):
        raise _bad(tra, 1, f"expected 'n_states n_choices n_transitions'; got {lines[0]!r}")
    n, R, T = (int(h) for h in head)
    src, ch, col, lo, up, act = [], [], [], [], [], []
    for k in range(1, len(lines)):
        s = lines[k].strip()
        if not s:
            continue
        toks = s.split()
        if len(toks) not in (4, 5) or not all(re.fullmatch(r"\d+", t) for t in toks[:3]):
            raise _bad(tra, k + 1, f"expected 'source choice target [lower,upper] [action]'; got {s!r}")
        a, b = _parse_value(toks[3], tra, k + 1)
        src.append(int(toks[0]))
        ch.append(int(toks[1]))
        col.append(int(toks[2]))
        lo.append(a)
        up.append(b)
        if len(toks) == 5:
            if not re.fullmatch(r"a-?\d+", toks[4]):
                raise _bad(tra, k + 1, f"action labels must be 'a<integer>' (as written by write_prism_explicit); got {toks[4]!r}")
            act.append(int(toks[4][1:]))
        else:
            act.append(None)
    if len(col) != T:
        raise _bad(tra, 1, f"header says {T} transitions but the file has {len(col)}")
    src_a, ch_a = np.array(src, dtype=np.int64), np.array(ch, dtype=np.int64)
    key_change = np.flatnonzero((src_a[1:] != src_a[:-1]) | (ch_a[1:] != ch_a[:-1])) + 1
    starts = np.concatenate([[0], key_change]) if src_a.size else np.zeros(0, dtype=np.int64)
    rs, rc = src_a[starts], ch_a[starts]
    # rows must come grouped by source in order 0, 1, ... (no gaps), choices 0, 1, ... per source
    step = np.diff(rs, prepend=0)
    bad = np.flatnonzero((step < 0) | (step > 1) | ((np.arange(rs.size) == 0) & (rs != 0)))
    if bad.size:
        j = int(starts[int(bad[0])])
        raise _bad(tra, j + 2, f"transitions must be sorted by source state 0, 1, ... without gaps; got source {src[j]} "
                                f"after {src[j - 1] if j else 'the header'}")
    expect_c = np.arange(rs.size) - np.searchsorted(rs, rs, side="left")
    bad = np.flatnonzero(rc != expect_c)
    if bad.size:
        j = int(starts[int(bad[0])])
        raise _bad(tra, j + 2, f"choices of source {src[j]} must be numbered 0, 1, ... in order; expected {int(expect_c[bad[0]])}, got {ch[j]}")
    if starts.size != R or _n_found(rs) != n:
        raise _bad(tra, 1, f"header says {n} states and {R} choices; the file has {_n_found(rs)} states and {starts.size} choices")
    row_ptr = np.append(starts, len(col)).astype(np.int64)
    state_ptr = np.searchsorted(rs, np.arange(n + 1), side="left").astype(np.int64)
    actions = None
    if any(a is not None for a in act):
        actions = np.array([act[j] if act[j] is not None else int(rc[i]) for i, j in enumerate(starts.tolist())], dtype=np.int64)
    imdp = IMDP.from_csr(state_ptr, row_ptr, np.array(col, dtype=np.int64), np.array(lo), np.array(up), actions=actions)
    masks = {}
    lab = prefix + ".lab"
    if os.path.exists(lab):
        with open(lab) as fh:
            llines = fh.read().splitlines()
        decl = dict()
        for m in re.finditer(r'(\d+)="([^"]*)"', llines[0] if llines else ""):
            decl[int(m.group(1))] = m.group(2)
        if llines and not decl and llines[0].strip():
            raise _bad(lab, 1, f"expected label declarations like 0=\"init\" 1=\"target\"; got {llines[0]!r}")
        for name in decl.values():
            masks[name] = np.zeros(n, dtype=bool)
        for k in range(1, len(llines)):
            s = llines[k].strip()
            if not s:
                continue
            st, sep, rest = s.partition(":")
            if not sep or not st.strip().isdigit() or not all(t.isdigit() for t in rest.split()):
                raise _bad(lab, k + 1, f"expected '<state>: <label index> ...'; got {s!r}")
            sid = int(st)
            if sid >= n:
                raise _bad(lab, k + 1, f"state {sid} is not in [0, {n})")
            for t in rest.split():
                if int(t) not in decl:
                    raise _bad(lab, k + 1, f"label index {t} is not declared on line 1")
                masks[decl[int(t)]][sid] = True
    return ModelFile(imdp=imdp, labels=masks)


def read_prism_explicit(prefix) -> IMDP:
    """Read PRISM explicit files into an :class:`IMDP` (labels: :func:`load_prism_explicit`)."""
    return load_prism_explicit(prefix).imdp


# ----------------------------------------------------------------------------- stormpy bridge
def to_stormpy(imdp: IMDP, target=None, *, avoid=None, labels=None, initial=0, max_entries: int = MAX_ENTRIES,
               chunk: int = 1_000_000):
    """Build a stormpy interval MDP (``SparseMdp[stormpy.Interval]``) in memory.

    Floors are densified (module docstring); entries ``[0, 0]`` are dropped (they are
    probability 0, which is what an absent entry means to Storm).  Labels ``init``,
    ``target`` (and ``avoid``) and ``labels`` are attached.  The matrix is filled in chunks of
    ``chunk`` entries so that at most that many stormpy ``Interval`` objects live at once.

    Returns
    -------
    stormpy model
    """
    import stormpy
    from stormpy import datastructures as ds
    from stormpy.developer import storage as st

    extra = dict(labels or {})
    if avoid is not None:
        extra["avoid"] = avoid
    masks = _label_masks(imdp, target, extra, initial)
    row_ptr, col, lo, up = densified_rows(imdp, max_entries=max_entries)
    keep = up > 0
    entry_row = np.repeat(np.arange(imdp.n_choices), np.diff(row_ptr))[keep]
    col, lo, up = col[keep], lo[keep], up[keep]
    n, R = imdp.n_states, imdp.n_choices
    Interval = stormpy.Interval
    b = ds.SparseMatrixBuilder[Interval](rows=R, columns=n, entries=int(col.size), force_dimensions=True,
                                         has_custom_row_grouping=True, row_groups=n)
    state_ptr = imdp.state_ptr
    # chunk on state boundaries: the row-group starts passed with a chunk are those of its states
    bounds = np.searchsorted(np.searchsorted(entry_row, state_ptr[:-1], side="left"), np.arange(0, col.size, chunk))
    s_cuts = np.unique(np.concatenate([bounds, [n]]))
    e_start = np.searchsorted(entry_row, state_ptr, side="left")
    s0 = 0
    for s1 in s_cuts[1:].tolist():
        a, z = int(e_start[s0]), int(e_start[s1])
        vals = [Interval(x, y) for x, y in zip(lo[a:z].tolist(), up[a:z].tolist())]
        b.add_next_values(entry_row[a:z].tolist(), col[a:z].tolist(), vals, state_ptr[s0:s1].tolist())
        s0 = s1
    matrix = b.build()
    labeling = st.StateLabeling(n)
    for name, m in masks.items():
        labeling.add_label(name)
        labeling.set_states(name, ds.BitVector(n, np.flatnonzero(m).tolist()))
    comps = st.SparseModelComponents[Interval](transition_matrix=matrix, state_labeling=labeling)
    return st.SparseMdp[Interval](comps)


def storm_reachability(imdp_or_model, target=None, *, avoid=None, adversary="pessimistic", objective="maximize",
                       horizon=None, precision: float = 1e-8) -> np.ndarray:
    """Storm's reachability values ``P{max,min}=? [F "target"]`` on an interval MDP.

    Parameters
    ----------
    imdp_or_model : IMDP or a model from :func:`to_stormpy`
        A prebuilt model must carry the labels ``target`` (and ``avoid`` when ``avoid`` is
        not None); ``target``/``avoid`` are then only used as flags.
    target, avoid : (n,) bool mask or index array
    adversary : "pessimistic" | "optimistic"
        Nature against / with the objective (:func:`robust_imdp.solvers.lp.nature_maximises`);
        passed to Storm as ``UncertaintyResolutionMode.MINIMIZE`` / ``MAXIMIZE`` (nature's
        direction), which for ``Pmax`` is Storm's ROBUST / COOPERATIVE.
    objective : "maximize" | "minimize"
    horizon : int or None
        ``F<=horizon`` when given.  Unbounded queries need every stored lower bound to be
        positive (Storm's graph-preservation requirement); models with zero lower bounds
        (or densified floors) raise ``InvalidInputError`` -- use a horizon.
    precision : float
        Absolute termination threshold of Storm's (robust) value iteration.  Storm stops on
        a residual, so its values are not guaranteed to this precision.

    Returns
    -------
    (n,) float array
    """
    import stormpy
    from stormpy import environments as E

    from robust_imdp.solvers.lp import _normalise, nature_maximises

    nat_max = nature_maximises(adversary, objective)
    obj = _normalise(objective, "objective", ("maximize", "minimize"))
    if isinstance(imdp_or_model, IMDP):
        if target is None:
            raise InvalidInputError("target must be a boolean mask or index array of states; got None")
        if horizon is None:
            _, _, lo, up = densified_rows(imdp_or_model)
            bad = np.flatnonzero((lo <= 0) & (up > 0))
            if bad.size:
                raise InvalidInputError(
                    "Storm refuses unbounded reachability on interval models with zero lower bounds "
                    f"(graph preservation); the exported model has {bad.size} entries with lower = 0 (densified floors "
                    "included). Give horizon=K or use positive lower bounds"
                )
        model = to_stormpy(imdp_or_model, target, avoid=avoid)
    else:
        model = imdp_or_model
    if horizon is not None and (int(horizon) != horizon or horizon < 0):
        raise InvalidInputError(f"horizon must be a non-negative integer or None; got {horizon!r}")
    path = ('!"avoid" U' if avoid is not None else "F") + (f"<={int(horizon)}" if horizon is not None else "")
    formula = f'P{"max" if obj == "maximize" else "min"}=? [{path} "target"]'
    env = E.Environment()
    mm = env.solver().min_max()
    mm.method = E.MinMaxMethod.VALUE_ITERATION  # the only method Storm runs on interval models
    frac = Fraction(float(precision)).limit_denominator(10**18)
    mm.precision = stormpy.Rational(f"{frac.numerator}/{frac.denominator}")
    mm.relative_termination_criterion = False
    mode = stormpy.UncertaintyResolutionMode.MAXIMIZE if nat_max else stormpy.UncertaintyResolutionMode.MINIMIZE
    prop = stormpy.parse_properties(formula)[0]
    res = stormpy.model_checking(model, prop, uncertainty_resolution_mode=mode, environment=env)
    return np.asarray(res.get_value_vector(), dtype=float)


__all__ = [
    "MAX_ENTRIES",
    "ModelFile",
    "densified_rows",
    "write_drn",
    "read_drn",
    "load_drn",
    "write_prism_explicit",
    "read_prism_explicit",
    "load_prism_explicit",
    "to_stormpy",
    "storm_reachability",
]
