"""Result files: ``result.json`` (the documented contract, see :func:`result_to_dict` and the JSON
schema ``docs/result.schema.json``) and ``result.npz`` (the same arrays in binary form). Both are
written under temporary names and renamed only when complete, so an interrupted run never leaves a
result that looks finished. :class:`ResultFile` reads ``result.json`` back as arrays; like the live ``Result`` it has a short
``repr``, :meth:`~ResultFile.summary`, :attr:`~ResultFile.counts` and
:meth:`~ResultFile.controller` (the deployable refined switching controller).

A command's whole set of outputs (result, figures, validation) is replaced as one by
:func:`staged_outputs`: the new files are written into a fresh folder inside the output directory
and swapped in only when all of them are complete; a failure or an interrupt before or during the
swap leaves the previous outputs exactly as they were.
"""

from __future__ import annotations

import gc
import json
import math
import os
import secrets
import shutil
import signal
import tempfile
import threading
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from robust_imdp.errors import DimensionError, InvalidInputError, ProblemFileError
from robust_imdp.io.data_file import _read_text
from robust_imdp.jsonable import jsonable as _jsonable

__all__ = ["result_to_dict", "save_result", "load_result", "ResultFile", "as_result_file", "RESULT_FORMAT",
           "staged_outputs", "OutputStage"]


@contextmanager
def _gc_paused():
    """Hold the cyclic garbage collector while the block runs (and restore its state after).

    Building or parsing a result makes about a million lists and strings, none of them in a cycle; each batch of
    new containers would otherwise start a collection that walks every object of the process (seconds at 64^3
    cells in a run that holds the abstraction). Reference counting still frees everything as usual.
    """
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


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


# --------------------------------------------------------------------------- a command's outputs, swapped in as one
#: Prefixes of the folders :class:`OutputStage` makes inside an output directory (hidden; removed when done).
STAGE_PREFIX, BACKUP_PREFIX = ".robust-imdp-new-", ".robust-imdp-old-"


def _fsync(path: Path, directory: bool = False) -> None:
    """Flush ``path`` (a file, or a directory's entries) to disk; a no-op where the OS refuses (e.g. no
    directory fsync)."""
    try:
        fd = os.open(path, os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextmanager
def _sigint_deferred():
    """Hold a Ctrl-C back while the block runs and deliver it afterwards (the main thread only; elsewhere
    Python delivers no SIGINT anyway). The block is the few renames of a swap, which must not stop half-way."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(frame))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught and callable(previous):  # Python's default handler raises KeyboardInterrupt here
            previous(signal.SIGINT, caught[0])


def _dead_owner(folder: Path, prefix: str) -> bool:
    """Whether the process that made ``folder`` (``PREFIX<pid>-...``) is gone; False when it may live, or when
    the name carries no pid."""
    pid = folder.name[len(prefix):].split("-", 1)[0]
    if not pid.isdigit():
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return True
    except OSError:  # e.g. PermissionError: it exists, under another user
        return False
    return False


def recover_stale(out_dir, owned) -> list:
    """Clean up after a command killed without a chance to clean (SIGKILL, power loss) in ``out_dir``.

    A staging folder of a dead process holds an unfinished new result: removed. A backup folder of a dead
    process means the swap of :meth:`OutputStage.commit` was cut: when ``result.json`` is in ``out_dir`` the new
    result was complete (it is renamed in last), so the backup is removed; otherwise the previous outputs in the
    backup are put back over whatever new files had arrived (of ``owned``), as the swap's own rollback does.
    Folders of a live process are left alone. Returns the folders handled.
    """
    out = Path(out_dir)
    done = []
    for folder in sorted(out.glob(BACKUP_PREFIX + "*")):
        if not folder.is_dir() or not _dead_owner(folder, BACKUP_PREFIX):
            continue
        if not (out / "result.json").exists():
            for name in owned:  # new files of the cut swap
                if (out / name).exists() and not (folder / name).exists():
                    (out / name).unlink()
            for f in folder.iterdir():
                os.replace(f, out / f.name)
        shutil.rmtree(folder, ignore_errors=True)
        done.append(folder)
    for folder in sorted(out.glob(STAGE_PREFIX + "*")):
        if folder.is_dir() and _dead_owner(folder, STAGE_PREFIX):
            shutil.rmtree(folder, ignore_errors=True)
            done.append(folder)
    return done


class OutputStage:
    """A command's new outputs, written into a fresh folder inside ``out_dir`` and swapped in as one.

    Parameters
    ----------
    out_dir : str or Path
        The output directory (created if needed).
    owned : sequence of str
        The file names the command's outputs consist of. :meth:`commit` replaces all of them: a name the
        new outputs do not contain is removed from ``out_dir`` (it belonged to the previous outputs: e.g.
        the previous result's validation). Other files in ``out_dir`` (the cache folder, the user's own
        files) are never touched.

    Attributes
    ----------
    path : Path
        The staging folder (``out_dir/.robust-imdp-new-*``, same file system, so the swap is renames).
    written : list of Path
        After :meth:`commit`: the final paths of the new files.
    committed : bool
        Whether the new files have replaced the previous ones (True even when a Ctrl-C held back during
        the swap is raised from :meth:`commit` after it).
    """

    def __init__(self, out_dir, owned):
        self.out = Path(out_dir)
        self.owned = tuple(owned)
        self.out.mkdir(parents=True, exist_ok=True)
        recover_stale(self.out, owned)
        self.path = Path(tempfile.mkdtemp(dir=self.out, prefix=f"{STAGE_PREFIX}{os.getpid()}-"))
        self.written: list = []
        self.committed = False

    def discard(self) -> None:
        """Remove the staging folder and what was written into it; ``out_dir`` is left as it was."""
        shutil.rmtree(self.path, ignore_errors=True)

    def commit(self) -> list:
        """Swap the staged files in for the previous outputs; return their final paths.

        Order: every file is flushed to disk; the previous outputs are renamed into a backup folder
        (``result.json`` first, so that the old ``result.json`` never sits beside new files), then the
        new ones into ``out_dir`` (``result.json`` last: its presence means the result is complete),
        then the backup is deleted. A failure among the renames puts everything back; Ctrl-C is held
        until the swap is over (:func:`_sigint_deferred`).
        """
        new = sorted(f.name for f in self.path.iterdir())
        for name in new:
            _fsync(self.path / name)
        replaced = [n for n in dict.fromkeys([*self.owned, *new]) if os.path.lexists(self.out / n)]
        backup = Path(tempfile.mkdtemp(dir=self.out, prefix=f"{BACKUP_PREFIX}{os.getpid()}-"))
        moved_old, moved_new = [], []
        with _sigint_deferred():  # a Ctrl-C during the swap arrives after it, the folders cleaned up
            try:
                for name in sorted(replaced, key=lambda n: n != "result.json"):
                    os.replace(self.out / name, backup / name)
                    moved_old.append(name)
                for name in sorted(new, key=lambda n: n == "result.json"):
                    os.replace(self.path / name, self.out / name)
                    moved_new.append(name)
                _fsync(self.out, directory=True)
            except BaseException:
                for name in reversed(moved_new):
                    os.replace(self.out / name, self.path / name)
                for name in reversed(moved_old):
                    os.replace(backup / name, self.out / name)
                shutil.rmtree(backup, ignore_errors=True)
                raise
            self.committed = True
            shutil.rmtree(backup, ignore_errors=True)
            self.discard()
            self.written = [self.out / name for name in new]
        return self.written


@contextmanager
def staged_outputs(out_dir, owned):
    """``with staged_outputs(out, names) as stage:`` write the new outputs into ``stage.path``; when the
    block completes they replace the previous ones (:meth:`OutputStage.commit`), when it raises (an
    error, Ctrl-C) they are discarded and ``out`` is left exactly as it was.

    Yields
    ------
    OutputStage
    """
    stage = OutputStage(out_dir, owned)
    try:
        yield stage
    except BaseException:
        stage.discard()
        raise
    try:
        stage.commit()
    except BaseException:
        stage.discard()
        raise


RESULT_FORMAT = "robust_imdp.result/1"


def _inputs_entry(result) -> dict:
    """``{"inputs": {...}}`` for a problem with an input grid (``models.inputs``), else ``{}`` (files unchanged)."""
    grid = getattr(getattr(result, "problem", None), "inputs", None)
    if grid is None:
        return {}
    return {"inputs": {"names": list(grid.names), "values": [np.asarray(a, float) for a in grid.values],
                       "points": np.asarray(grid.points, float)}}


def _inputs_of(doc: dict, n_modes: int):
    """``(points (n_modes, m) or None, names or None)`` of a document's ``inputs``."""
    entry = doc.get("inputs")
    if entry is None:
        return None, None
    points = np.asarray(entry["points"], dtype=float)
    if points.ndim != 2 or points.shape[0] != n_modes or len(entry["names"]) != points.shape[1]:
        raise ValueError(f"inputs.points must be ({n_modes}, m) with m names; got {points.shape} and {entry['names']}")
    return points, tuple(entry["names"])


def _semantics_of(doc: dict) -> str:
    """The reading of a ``result.json`` document: its ``semantics`` ("safety"), "reach" when absent."""
    value = doc.get("semantics", "reach")
    if value not in ("reach", "safety"):
        raise ValueError(f"semantics must be 'reach' or 'safety'; got {value!r}")
    return value


def _margin_entry(result) -> dict:
    """``{"b_margin": [...]}`` (NaN, a Q_? cell, written as null) when the result has assumption margins, else ``{}``."""
    b = getattr(result, "b_margin", None)
    return {} if b is None else {"b_margin": np.asarray(b, dtype=float)}


def _margin_of(doc: dict, n_cells: int):
    """A document's ``b_margin`` as a (n_cells,) float array (null read as NaN), or None."""
    if doc.get("b_margin") is None:
        return None
    b = np.array([np.nan if v is None else v for v in doc["b_margin"]], dtype=float)
    if b.shape != (n_cells,):
        raise ValueError(f"b_margin must have one entry per cell ({n_cells}); got {b.shape[0]}")
    return b


CLASS_NAMES = ("yes", "no", "maybe")


def result_to_dict(result) -> dict[str, Any]:
    """The ``result.json`` contract as a plain dict.

    Keys
    ----
    format : str
        ``"robust_imdp.result/1"``.
    space : {"lower", "upper", "names"?}
        The compact set X; leaving it is a violation. ``names``: the dimension names
        (``[space].names``), only when the problem gives them. ``periodic``: d booleans, only when a
        dimension is periodic (states wrap there and never leave X through it; docs/periodic.md).
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
    inputs : {"names", "values", "points"}, only for an input grid
        The modes are the points of an input grid (``models.inputs``): ``names`` (m), ``values`` (per input,
        its values), ``points`` (per mode, in ``modes`` order, its input vector; ``modes[k]`` is its name,
        ``u=(v1, v2)``).
    semantics : str, only for the safety reading
        ``"safety"``: the bounds are of "no prefix is a bad prefix and the path stays in X" (within the
        horizon, or for ever); absent: the reach reading, "some prefix is accepted" (README, "Two readings
        of a formula").
    b_margin : list of float or null, only when the run computed assumption margins
        Per cell the largest factor beta of (1, 1.25, 1.5, 2, 3, 4) such that the run's controller keeps
        the cell's class (Q_yes or Q_no) with every ``rkhs_bound`` B replaced by beta B, at beta and every
        smaller factor; null for Q_? cells (docs/margins.md). ``diagnostics.margins`` has the counts.
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
    find the new cell q' and set ``s = delta[s][L(q')]``. With ``semantics`` "safety" an accepting s
    decides nothing: the run is violated at a sink or on leaving X and satisfied at the horizon.
    """
    with _gc_paused():
        return _document(result)


def _document(result, arrays: bool = False) -> dict:
    """:func:`result_to_dict`'s document; with ``arrays`` the per-cell float entries (:data:`_FLOAT_ENTRIES`) are
    kept as float64 arrays with NaN where the document has null (for :func:`save_result`, which writes them
    without making lists of them)."""
    part = result.partition
    dfa = result.dfa
    syn = result.synthesis
    modes = list(result.mode_names)
    labels = _label_lists(_jsonable(list(part.atoms)), np.asarray(part.labels, dtype=np.int64))
    names = np.asarray(_jsonable(modes), dtype=object)

    def named(table):
        table = np.asarray(table, dtype=np.int64)
        return np.where(table >= 0, names[np.clip(table, 0, len(modes) - 1)], None).tolist()

    strategy = np.asarray(syn.strategy, dtype=np.int64)
    by_time = None
    if strategy.ndim == 3:  # k-step: strategy[t, q, s]; "strategy" is the time-0 table
        by_time, strategy = named(strategy), strategy[0]
    strategy_named = named(strategy)
    accepting = np.flatnonzero(np.asarray(dfa.accepting, dtype=bool)).tolist()
    space = {"lower": result.space_lower, "upper": result.space_upper}
    if getattr(result, "dim_names", None) is not None:
        space["names"] = list(result.dim_names)
    if getattr(part, "periodic", None) is not None:  # only then: results without periodic dimensions are unchanged
        space["periodic"] = list(part.periodic)
    doc = {
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
        "strategy": strategy_named,  # plain already (str or None): not walked again below
        "strategy_by_time": by_time,
        "p_low": np.asarray(syn.p_low, dtype=float),
        "p_up": np.asarray(syn.p_up, dtype=float),
        "p_up_star": np.asarray(syn.p_up_star, dtype=float),
        "error": np.asarray(syn.error, dtype=float),
        "classes": np.asarray(result.class_names),
        "no_strategy_can": np.asarray(syn.p_up_star, dtype=float) < result.threshold,
        "formula": result.formula,
        "threshold": result.threshold,
        "horizon": result.horizon,
        **({"semantics": "safety"} if getattr(result, "semantics", "reach") == "safety" else {}),
        **_inputs_entry(result),
        **_margin_entry(result),
        "parameters": result.parameters,
        "diagnostics": {**(getattr(result, "diagnostics", {}) or {}),
                        **({"advice": result.advice} if getattr(result, "advice", None) else {}),
                        **({"margins": result.margins} if getattr(result, "margins", None) else {})},
        "timings": result.timings,
    }
    if not arrays:
        return {k: v if k in _PLAIN else _jsonable(v) for k, v in doc.items()}
    cells = {k: _float_entry(v) for k, v in doc["cells"].items()}
    return {k: cells if k == "cells" else v if k in _PLAIN else _float_entry(v) if k in _FLOAT_ENTRIES else _jsonable(v)
            for k, v in doc.items()}


def _float_entry(value):
    """A 1-D or 2-D float array as a float64 array with NaN for every non-finite entry (``jsonable`` writes them as
    null, read back as NaN); anything else (an int array, a list) as ``jsonable`` gives it."""
    if type(value) is np.ndarray and value.dtype.kind == "f" and value.dtype.itemsize <= 8 and value.ndim in (1, 2):
        return _nan_for_nonfinite(value)
    return _jsonable(value)


#: Entries of :func:`result_to_dict` built as plain JSON values (lists of lists of str or None), one per cell:
#: ``jsonable`` would only walk them element by element to return them unchanged.
_PLAIN = frozenset(("labels", "strategy", "strategy_by_time"))
#: Entries of the document that are per-cell floats (``cells`` holds two more: ``lower`` and ``upper``).
_FLOAT_ENTRIES = frozenset(("p_low", "p_up", "p_up_star", "error", "b_margin"))


def _label_lists(atoms: list, letters: np.ndarray) -> list:
    """``labels[q]``: the atoms whose bit is set in ``letters[q]`` (bit i = ``atoms[i]``), a new list per cell.

    Built once per distinct letter (at most ``2**len(atoms)``, a handful) and copied per cell.
    """
    uniq, inverse = np.unique(letters, return_inverse=True)
    lists = [[a for i, a in enumerate(atoms) if (int(v) >> i) & 1] for v in uniq.tolist()]
    return [lists[i].copy() for i in inverse.ravel().tolist()]


def save_result(result, out_dir) -> Path:
    """Write ``result.npz`` then ``result.json`` into ``out_dir`` (created if needed).

    Each file is written under a temporary name and renamed when complete; ``result.json``
    is written last, so its presence means the result is complete.

    ``result.npz`` holds ``result.json``'s arrays: ``cells_lower``, ``cells_upper`` (n_cells, d),
    ``strategy`` (n_cells, S) or (k, n_cells, S) mode indices into ``modes``, ``dfa_delta``, ``p_low``,
    ``p_up``, ``p_up_star``, ``error``, ``classes``, ``no_strategy_can``, ``modes``; and what the controller
    needs besides (``Controller.from_tables``; files written before they were added lack them, and
    ``load_result`` reads ``result.json`` in any case): ``label_letters`` int64 (n_cells,) letters over
    ``dfa_atoms`` (str (A,)), ``dfa_initial`` int64 (), ``dfa_accepting`` bool (S,), ``space_lower``,
    ``space_upper`` float (d,), and ``periodic`` bool (d,) only when a dimension is periodic; ``b_margin``
    float (n_cells,) (NaN for Q_? cells) only when the run computed assumption margins.

    ``result.json`` is ``result_to_dict``'s document, indented by one space, except that each per-cell list
    (``cells.lower``, ``cells.upper``, ``labels``, ``strategy``, ``strategy_by_time``, ``p_low``, ``p_up``,
    ``p_up_star``, ``error``, ``classes``, ``no_strategy_can``, ``b_margin``) is on one line: ``json.loads`` gives
    the document exactly (floats as ``repr`` writes them, so they read back bit for bit).

    Returns
    -------
    Path
        The path of ``result.json``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with _gc_paused():
        return _save_result(result, out)


def _save_result(result, out: Path) -> Path:
    doc = _document(result, arrays=True)  # the per-cell floats as arrays (NaN for null): written without lists
    part, syn = result.partition, result.synthesis
    atoms = list(doc["dfa"]["atoms"])
    accepting = np.zeros(len(doc["dfa"]["delta"]), dtype=bool)
    accepting[np.asarray(doc["dfa"]["accepting"], dtype=np.int64)] = True
    controller_arrays = {
        "label_letters": _dfa_letters(atoms, _jsonable(list(part.atoms)), np.asarray(part.labels, dtype=np.int64)),
        "dfa_atoms": np.asarray(atoms, dtype=str),
        "dfa_initial": np.int64(doc["dfa"]["initial"]), "dfa_accepting": accepting,
        "space_lower": np.asarray(doc["space"]["lower"], dtype=float),
        "space_upper": np.asarray(doc["space"]["upper"], dtype=float),
        **({"periodic": np.asarray(doc["space"]["periodic"], dtype=bool)} if "periodic" in doc["space"] else {}),
    }
    # the per-cell arrays as result.json has them (non-finite floats are null there: NaN)
    arrays = {
        "cells_lower": np.asarray(doc["cells"]["lower"], dtype=float),
        "cells_upper": np.asarray(doc["cells"]["upper"], dtype=float),
        "strategy": np.asarray(syn.strategy, dtype=np.int64),  # (k, C, S) if k-step
        "dfa_delta": np.asarray(doc["dfa"]["delta"], dtype=np.int64),
        **{key: np.asarray(doc[key], dtype=float) for key in ("p_low", "p_up", "p_up_star", "error")},
        "classes": np.asarray(doc["classes"], dtype=str),
        "no_strategy_can": np.asarray(doc["no_strategy_can"], dtype=bool),
        "modes": np.asarray(doc["modes"], dtype=str),
        **controller_arrays,
        **({} if getattr(result, "b_margin", None) is None else {"b_margin": np.asarray(result.b_margin, float)}),
    }

    def write_npz(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)

    def write_json(tmp: Path) -> None:
        with open(tmp, "w") as fh:
            for piece in _json_pieces(doc):
                fh.write(piece)

    _atomic_write(out / "result.npz", write_npz)
    _atomic_write(out / "result.json", write_json)
    return out / "result.json"


def _nan_for_nonfinite(x) -> np.ndarray:
    """``x`` as a new float array with NaN for every non-finite entry (what reading result.json's null gives)."""
    a = np.array(x, dtype=float)
    a[~np.isfinite(a)] = np.nan
    return a


def _dfa_letters(dfa_atoms: list, part_atoms: list, part_letters: np.ndarray) -> np.ndarray:
    """(n_cells,) int64: bit i set where ``dfa_atoms[i]`` is in the cell's label (the partition's atoms of the bits
    set in ``part_letters``, int64: at most 64 atoms), from the partition's bits by a shift per atom."""
    letters = np.zeros(part_letters.shape[0], dtype=np.int64)
    for i, a in enumerate(dfa_atoms):  # a loop over the atoms (a handful)
        held = np.zeros(part_letters.shape[0], dtype=bool)
        for j, b in enumerate(part_atoms):
            if b == a:
                held |= ((part_letters >> j) & 1).astype(bool)
        letters |= held.astype(np.int64) << i
    return letters


#: The per-cell entries of result.json (paths into :func:`result_to_dict`'s document) written on one line each
#: (:func:`_json_pieces`); the rest keeps ``indent=1``.
_ONE_LINE = (("cells", "lower"), ("cells", "upper"), ("labels",), ("strategy",), ("strategy_by_time",),
             ("p_low",), ("p_up",), ("p_up_star",), ("error",), ("classes",), ("no_strategy_can",), ("b_margin",))


def _json_pieces(doc: dict) -> list:
    """The text of ``json.dumps(doc, indent=1)`` up to the layout (``json.loads`` gives the same document), as
    pieces to write one after the other: the per-cell entries (:data:`_ONE_LINE`) are written on one line each, a
    list by the C encoder, a float array by :func:`_float_text` (the pure-Python encoder that ``indent`` needs takes
    seconds per million numbers), and spliced into the indented rest in place of placeholder strings.

    A placeholder carries a random nonce and must occur exactly once in the indented text (so no string of the
    document, a region or mode name, can be taken for one); otherwise a fresh nonce is drawn, and after a few
    tries the whole document is encoded with ``indent=1``.
    """
    for _ in range(4):
        nonce = secrets.token_hex(16)
        skeleton, bodies = dict(doc), {}
        for n, path in enumerate(_ONE_LINE):
            parent = skeleton
            for key in path[:-1]:
                if not isinstance(parent.get(key), dict):
                    break
                parent[key] = parent = dict(parent[key])  # copies along the path: doc is not changed
            else:
                if isinstance(parent.get(path[-1]), (list, np.ndarray)):
                    token = f"robust_imdp-one-line-{nonce}-{n}"
                    bodies[json.dumps(token)] = parent[path[-1]]
                    parent[path[-1]] = token
        text = json.dumps(skeleton, indent=1)
        if all(text.count(quoted) == 1 for quoted in bodies):
            pieces = []
            for quoted in sorted(bodies, key=text.index):
                head, text = text.split(quoted)
                body = bodies[quoted]
                pieces += [head, _float_text(body) if isinstance(body, np.ndarray) else json.dumps(body)]
            return pieces + [text]
    return [json.dumps(_jsonable(doc), indent=1)]


def _float_text(a: np.ndarray) -> str:
    """``json.dumps(jsonable(a))`` (up to spaces) of a 1-D or 2-D float64 array, NaN written as null.

    Each distinct value (by its bits: -0.0 is not 0.0) is written once by ``repr``, which is what the JSON encoder
    writes for a float; the text of the cells is then put together by joins. The cells of a grid have a few
    distinct coordinates per axis, so most of the work of formatting a float per entry goes away.
    """
    a = np.asarray(a, dtype=np.float64)
    if a.size == 0 or a.ndim not in (1, 2):
        return json.dumps(_jsonable(a))
    a = np.ascontiguousarray(a)  # for the int64 view of its bits
    bits, inverse = np.unique(a.view(np.int64).ravel(), return_inverse=True)
    words = np.array([repr(v) if math.isfinite(v) else "null" for v in bits.view(np.float64).tolist()], dtype=object)
    text = words[inverse.ravel()]
    if a.ndim == 1:
        return "[" + ", ".join(text.tolist()) + "]"
    n, d = a.shape
    parts = np.empty((n, 2 * d), dtype=object)
    parts[:, 0::2] = text.reshape(n, d)
    parts[:, 1::2] = ", "
    parts[:, -1] = "], ["  # between rows
    parts[-1, -1] = ""
    return "[[" + "".join(parts.ravel().tolist()) + "]]"


def load_result(path):
    """Read a ``result.json`` (or the directory holding it) into a :class:`ResultFile`."""
    path = Path(path)
    if path.is_dir():
        path = path / "result.json"
    if not path.exists():
        raise ProblemFileError(f"result file {path}: cannot be read (No such file or directory)")
    try:
        with _gc_paused():
            doc = json.loads(_read_text(path, f"result file {path}", "result.json or the directory holding it"))
    except json.JSONDecodeError as exc:
        raise ProblemFileError(f"result file {path}: not valid JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != RESULT_FORMAT:
        raise ProblemFileError(
            f"result file {path}: expected format '{RESULT_FORMAT}'; "
            f"got {doc.get('format') if isinstance(doc, dict) else type(doc).__name__!r}"
        )
    with _gc_paused():
        return ResultFile.from_dict(doc)


# --------------------------------------------------------------------------- result tables (read back)
@dataclass(frozen=True, eq=False)
class ResultFile:
    """The ``result.json`` contract as arrays (see :func:`robust_imdp.io.result_file.result_to_dict`).

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
    periodic : tuple of bool or None
    diagnostics : dict
        ``result.json``'s ``diagnostics`` (the advice under ``"advice"``); empty for files without it.
    semantics : {"reach", "safety"}
        The reading the bounds are of (``semantics``; "reach" when the document has none).
    b_margin : (n_cells,) float array or None
        The assumption margins (``b_margin``; NaN for Q_? cells), None for files without them.
    inputs : (n_modes, m) float array or None
        The modes' input vectors (``inputs.points``) of an input grid; ``input_names`` their names.
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
    periodic: tuple | None = None
    diagnostics: dict = field(default_factory=dict)
    semantics: str = "reach"
    inputs: np.ndarray | None = None
    input_names: tuple | None = None
    b_margin: np.ndarray | None = None

    @property
    def n_cells(self) -> int:
        return self.cells_lower.shape[0]

    @property
    def mode_names(self) -> tuple:
        """The mode names (``modes``; the name the live ``Result`` uses)."""
        return self.modes

    @property
    def class_names(self) -> np.ndarray:
        """(n_cells,) ``"yes"`` / ``"no"`` / ``"maybe"`` (``classes``; the name the live ``Result`` uses)."""
        return self.classes

    @property
    def margins(self) -> dict:
        """The assumption margins' counts (``diagnostics.margins``; ``b_margin`` has the cells), or an empty dict."""
        return dict(self.diagnostics.get("margins") or {})

    @property
    def advice(self) -> dict:
        """The advice estimated by the run (``diagnostics.advice``), or an empty dict."""
        return dict(self.diagnostics.get("advice") or {})

    @property
    def counts(self):
        """Number of cells per class: ``{"yes": .., "no": .., "maybe": ..}`` (``pipeline.result.ClassCounts``:
        ``counts()`` works too)."""
        from robust_imdp.pipeline.result import ClassCounts

        return ClassCounts.of(self.classes)

    def summary(self) -> str:
        """The run's summary as ``Result.summary`` prints it: class counts (Q_no split by whether any controller
        could do better), mean p_low and error, the bound diagnostics, the advice and the stage times."""
        from robust_imdp.pipeline.result import summary_text

        return summary_text(formula=self.formula, threshold=self.threshold, horizon=self.horizon,
                            classes=self.classes, p_low=self.p_low, error=self.error, p_up_star=self.p_up_star,
                            diagnostics=self.diagnostics, advice=self.advice, timings=self.timings,
                            source="read from result.json", semantics=self.semantics)

    def controller(self, mode_names=None):
        """The refined switching controller of this result (``synthesis.controller.Controller``): the same
        controller as the live ``Result.controller()`` of the run that wrote the file, ready to deploy
        (``ctrl.reset(x0)``, ``ctrl.act(x)``, ``ctrl.save(prefix)``).

        Parameters
        ----------
        mode_names : sequence of str, optional
            Names :meth:`Controller.act` returns (default: the result's ``modes``).
        """
        from robust_imdp.synthesis.controller import Controller

        return Controller.from_tables(self, mode_names)

    def __repr__(self) -> str:  # a few lines: the dataclass default prints every array
        c = self.counts
        d = self.cells_lower.shape[1]
        return (f"ResultFile({self.n_cells} cells in {d}-D: Q_yes {c['yes']}, Q_no {c['no']}, Q_? {c['maybe']}; "
                f"formula {self.formula!r}, threshold {self.threshold:g}"
                + ("" if self.horizon is None else f", horizon {self.horizon}") + "\n"
                f"  mean p_low {float(np.mean(self.p_low)):.4f}, mean error {float(np.mean(self.error)):.4f}; "
                f"modes {list(self.modes)}\n"
                "  arrays: p_low, p_up, p_up_star, error, classes, strategy; summary(), counts, controller())")

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
                # converted once per distinct row (a few mode combinations), looked up for the other cells
                seen = {}

                def convert(row):
                    return [index[m] if m is not None else -1 for m in row]

                return np.array([seen[r] if r in seen else seen.setdefault(r, convert(r)) for r in map(tuple, rows)],
                                dtype=np.int64)

            strategy = table(doc["strategy"])
            by_time = doc.get("strategy_by_time")
            by_time = None if by_time is None else np.stack([table(t) for t in by_time])
            labels = tuple(tuple(lab) for lab in doc["labels"])
            bit = {a: 1 << i for i, a in enumerate(atoms)}
            seen = {}  # once per distinct label
            letters = np.array([seen[lab] if lab in seen else seen.setdefault(lab, sum(bit.get(a, 0) for a in lab))
                                for lab in labels], dtype=np.int64)
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
                periodic=None if not any(doc["space"].get("periodic") or ()) else tuple(doc["space"]["periodic"]),
                diagnostics=dict(doc.get("diagnostics") or {}),
                semantics=_semantics_of(doc),
                **dict(zip(("inputs", "input_names"), _inputs_of(doc, len(modes)))),
                b_margin=_margin_of(doc, cl.shape[0]),
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
        from robust_imdp.synthesis.controller import grid_of_cells

        n = self.cells_lower.shape[1]
        bps, table = grid_of_cells(self.cells_lower, self.cells_upper)
        shape = tuple(len(b) - 1 for b in bps)
        if table is None:  # the cells are the grid's boxes in C order
            table = np.arange(self.n_cells, dtype=np.int64).reshape(shape)
        slo, sup = self.space_lower, self.space_upper

        def locate(x):
            x = np.atleast_2d(np.asarray(x, dtype=float))
            if self.periodic is not None:
                x = self.wrap(x)
            inside = np.all((x >= slo) & (x <= sup), axis=1)
            idx = [np.clip(np.searchsorted(bps[i], x[:, i], side="right") - 1, 0, shape[i] - 1)
                   for i in range(n)]
            cell = table[tuple(idx)]
            return np.where(inside, cell, -1)

        return locate

    def wrap(self, x) -> np.ndarray:
        """``x`` with its periodic coordinates moved into X (``geometry.wrap_points``); a copy."""
        from robust_imdp.models.geometry import wrap_points

        return wrap_points(x, self.space_lower, self.space_upper, self.periodic)


def as_result_file(result) -> "ResultFile":
    """A :class:`ResultFile` from a ResultFile, a pipeline ``Result``, a result dict or a path."""
    if isinstance(result, ResultFile):
        return result
    if isinstance(result, dict):
        return ResultFile.from_dict(result)
    if isinstance(result, (str, bytes)) or hasattr(result, "__fspath__"):
        return load_result(result)
    return ResultFile.from_dict(result_to_dict(result))
