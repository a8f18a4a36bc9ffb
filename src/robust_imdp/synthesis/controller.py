"""The refined switching controller for the continuous system (paper, eq. mapping-strategy).

The strategy computed on the product is a table ``(cell, DFA state) -> mode`` (``(time, cell, DFA
state) -> mode`` for a k-step horizon). On the real system the controller locates the cell of the
current state, tracks the DFA state from the labels of the visited cells (standard product
semantics: the first label is read at :meth:`Controller.reset`) and looks the mode up::

    ctrl = result.controller(partition, mode_names=("a", "b"))
    ctrl.reset(x0)
    while (u := ctrl.act(x)) is not None:    # None once the spec is decided
        x = system.step(x, u)
    ctrl.status                                # "satisfied" or "violated"

Names or indices. :meth:`Controller.act` returns the mode's *name* when the controller knows the
names (``mode_names``: the pipeline's ``Result.controller()`` and saved controllers with names
do), else its index; :meth:`Controller.act_index` always returns the integer index into
``mode_names``, for deployment code that indexes arrays of modes.

One state or many. :meth:`Controller.locate` returns an ``int`` for one state ``(d,)`` and an array
for a batch ``(k, d)``. ``k`` runs at once: ``runs = ctrl.start_batch(x0)`` (``x0``: ``(k, d)``), then
``runs.act(x)`` gives the ``k`` modes (``None`` where a run is over), each run following the rules of
``act`` (:class:`ControllerRuns`). A saved result gives its controller without the partition:
``load_result(dir).controller()`` or ``Controller.from_result(load_result(dir))``.

Deployment. This module needs only numpy (and the exception classes of
:mod:`robust_imdp.errors`). :meth:`Controller.save` writes two files, and a re-implementation
in any language needs nothing else:

``<prefix>.json``
    ``format`` ("robust_imdp.controller"), ``version`` (1), ``atoms`` (DFA atom order; bit ``i``
    of a letter is ``atoms[i]``), ``dfa`` {``initial``, ``accepting`` (list of states),
    ``delta`` (S lists of 2**len(atoms) successor states)}, ``modes`` (list of names or null),
    ``n_modes``, ``threshold``, ``horizon`` (null = unbounded), ``dim``, ``shape`` (intervals per
    dimension), ``metadata`` (free JSON, e.g. the formula); ``periodic`` (list of d booleans, only
    when some dimension is periodic: there a coordinate ``x_j`` is first replaced by
    ``lower_j + ((x_j - lower_j) mod (upper_j - lower_j))``, so it never leaves X).
``<prefix>.npz`` (``numpy.savez``, no pickled objects)
    ``strategy`` int64 (n_cells, S) or (k, n_cells, S); ``cell_letters`` int64 (n_cells,) letters
    over ``atoms``; ``space_lower``, ``space_upper`` float64 (d,): the set X;
    ``breakpoints_<j>`` float64 (shape[j] + 1,) for every dimension j; ``p_low``, ``p_up``,
    ``p_up_star`` float64 (n_cells,) (NaN when unknown).

Locating a point x: outside X (any coordinate outside ``[space_lower, space_upper]``) means
leaving X. Otherwise ``i_j = min(searchsorted(breakpoints_j, x_j, side="right") - 1,
shape[j] - 1)`` (half-open intervals, the last one closed at the upper end of X) and the cell is
``ravel_multi_index(i, shape)`` (C order), as :meth:`robust_imdp.models.geometry.Partition.locate`.
Cells of different sizes (a refined ``geometry.BoxPartition``): the breakpoints are every cell
face and the ``.npz`` also holds ``cell_map`` int64 (shape): the cell is ``cell_map[i]``.

Run: ``s = delta[initial][cell_letters[q0]]``; while ``s`` is neither accepting (satisfied) nor
a sink (violated) and ``t < k``, apply ``strategy[(t,) q, s]``, observe the next state, stop as
violated if it left X, else ``s = delta[s][cell_letters[q]]``, ``t += 1``. For a k-step
strategy, reaching time ``k`` without acceptance is a violation of the bounded specification.
With ``"semantics": "safety"`` in the JSON (the safety reading; absent means reach) accepting
states decide nothing: the run is violated at a sink or on leaving X, satisfied at time ``k``,
and without a horizon it runs for ever.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from robust_imdp.errors import (DimensionError, InvalidInputError, InvalidModelError, OutsideDomainError,
                                 UnknownAtomError)

__all__ = ["Controller", "ControllerRuns", "remap_letters", "grid_of_cells", "RUNNING", "SATISFIED", "VIOLATED"]

RUNNING, SATISFIED, VIOLATED = "running", "satisfied", "violated"
FORMAT = "robust_imdp.controller"


def remap_letters(labels: Any, atoms: Sequence[str], dfa_atoms: Sequence[str]) -> np.ndarray:
    """Re-express letters over ``atoms`` as letters over ``dfa_atoms`` (extra atoms are dropped).

    Parameters
    ----------
    labels : (n,) int array
        Bit ``i`` set iff ``atoms[i]`` holds.
    atoms : sequence of str
        Atom order of ``labels`` (e.g. the partition's region names).
    dfa_atoms : sequence of str
        Target order; every name must be in ``atoms``.

    Returns
    -------
    (n,) int64 array, bit ``j`` set iff ``dfa_atoms[j]`` holds.

    Raises
    ------
    UnknownAtomError
        If a DFA atom is not among ``atoms`` (names them and lists the known labels).
    """
    atoms = tuple(atoms)
    index = {a: i for i, a in enumerate(atoms)}
    unknown = [a for a in dfa_atoms if a not in index]
    if unknown:
        raise UnknownAtomError(
            f"the formula uses atoms {unknown} that no region defines; known labels are {list(atoms)}"
        )
    lab = np.asarray(labels, dtype=np.int64)
    out = np.zeros(lab.shape, dtype=np.int64)
    for j, a in enumerate(dfa_atoms):  # loop over atoms (a handful), vectorised over cells
        out |= ((lab >> index[a]) & 1) << j
    return out


#: What :meth:`Controller.from_tables` reads of a saved result.
_TABLES = ("cells_lower", "cells_upper", "label_letters", "dfa_atoms", "dfa_delta", "dfa_initial", "dfa_accepting",
           "strategy", "space_lower", "space_upper", "modes")


def _input_table(inputs: Any, names: Sequence[str] | None) -> tuple:
    """``(inputs (M, m) float array or None, names tuple or None)`` from an input grid or an array."""
    if inputs is None:
        return None, None
    if hasattr(inputs, "points"):  # a models.inputs.InputGrid (numpy-only here: read by duck type)
        names = getattr(inputs, "names", None) if names is None else names
        inputs = inputs.points
    table = np.array(inputs, dtype=np.float64)
    if table.ndim == 1:
        table = table[:, None]
    if table.ndim != 2 or table.shape[0] == 0 or not np.all(np.isfinite(table)):
        raise DimensionError(f"inputs must be a finite (n_modes, m) array of the modes' input vectors; got shape "
                             f"{np.shape(inputs)}")
    names = tuple(f"u{j + 1}" for j in range(table.shape[1])) if names is None else tuple(names)
    if len(names) != table.shape[1]:
        raise DimensionError(f"input_names must name the {table.shape[1]} inputs; got {list(names)}")
    table.setflags(write=False)
    return table, names


def grid_of_cells(cells_lower: Any, cells_upper: Any) -> tuple:
    """The breakpoint grid of a set of box cells and the cell of each of its boxes.

    Parameters
    ----------
    cells_lower, cells_upper : (n_cells, d) float arrays
        Cells that tile a box (a ``Partition``'s or a refined ``BoxPartition``'s cells).

    Returns
    -------
    breakpoints : list of d increasing 1-D float arrays
        Per dimension, every cell face.
    cell_map : int64 array of shape ``tuple(len(b) - 1 for b in breakpoints)``, or None
        The cell of each box of the grid; None when the cells are the grid's boxes in C order
        (``ravel_multi_index``, as ``Partition.locate``).

    Raises
    ------
    InvalidInputError
        If a box of the grid belongs to no cell (the cells do not tile it).
    """
    lo = np.asarray(cells_lower, dtype=np.float64)
    up = np.asarray(cells_upper, dtype=np.float64)
    if lo.ndim != 2 or lo.shape != up.shape or lo.shape[0] == 0:
        raise DimensionError(f"cells_lower and cells_upper must be (n_cells, d) arrays of one shape; got "
                             f"{lo.shape} and {up.shape}")
    d = lo.shape[1]
    bps = [np.unique(np.concatenate([lo[:, j], up[:, j]])) for j in range(d)]
    shape = tuple(len(b) - 1 for b in bps)
    lo_idx = np.stack([np.searchsorted(bps[j], lo[:, j]) for j in range(d)])
    hi_idx = np.stack([np.searchsorted(bps[j], up[:, j]) for j in range(d)])
    single = bool(np.all(hi_idx - lo_idx == 1))
    if single and lo.shape[0] == int(np.prod(shape)):
        flat = np.ravel_multi_index(tuple(lo_idx), shape)
        if np.array_equal(flat, np.arange(lo.shape[0])):
            return bps, None
    cell_map = np.full(shape, -1, dtype=np.int64)
    if single:
        cell_map[tuple(lo_idx)] = np.arange(lo.shape[0])
    else:
        for q in range(lo.shape[0]):  # set-up only, once per result: cells of different sizes
            cell_map[tuple(slice(lo_idx[j, q], hi_idx[j, q]) for j in range(d))] = q
    if np.any(cell_map < 0):
        box = np.argwhere(cell_map < 0)[0]
        raise InvalidInputError(f"the cells must tile their bounding box; the grid box at "
                                f"{[float(bps[j][box[j]]) for j in range(d)]} belongs to no cell")
    return bps, cell_map


def _sinks(delta: np.ndarray, accepting: np.ndarray) -> np.ndarray:
    """(S,) bool: states from which no accepting state is reachable (backward fixed point)."""
    good = accepting.copy()
    while True:
        new = good | good[delta].any(axis=1)
        if (new == good).all():
            return ~good
        good = new


class Controller:
    """Refined switching controller: locate the cell, track the DFA, look the mode up.

    Parameters
    ----------
    strategy : (n_cells, S) or (k, n_cells, S) int array
        Mode index per (cell, DFA state) (per time step for a k-step horizon).
    dfa_delta : (S, 2**len(atoms)) int array
    dfa_initial : int
    dfa_accepting : (S,) bool array
    atoms : sequence of str
        DFA atom order (bit ``i`` of a letter is ``atoms[i]``).
    cell_letters : (n_cells,) int array
        Letter of every cell over ``atoms``.
    breakpoints : sequence of 1-D float arrays
        Per dimension, the increasing cell boundaries; ``n_cells = prod(len(b) - 1)``.
    space_lower, space_upper : (d,) float arrays
        The compact set X.
    modes : sequence of str, optional
        Mode names returned by :meth:`act` (indices when omitted; :meth:`act_index` always
        returns indices).
    threshold : float, optional
    p_low, p_up, p_up_star : (n_cells,) float arrays, optional
        Bounds of the synthesis, kept for inspection and saving.
    cell_map : int array of shape ``tuple(len(b) - 1 for b in breakpoints)``, optional
        Cells of different sizes: the cell of each box of the breakpoint grid (every cell is a
        union of such boxes; ``BoxPartition.grid_index``). Default: the boxes are the cells.
    metadata : dict, optional
        JSON-serialisable information (formula, ...).
    periodic : sequence of d bool, optional
        Periodic dimensions (states are wrapped into X there).
    semantics : {"reach", "safety"}
        The reading the strategy was computed for: "reach", the run is satisfied once the DFA accepts;
        "safety", it is violated by a bad prefix or by leaving X and satisfied at the horizon (never
        decided without one: :meth:`act` keeps returning modes).
    inputs : (n_modes, m) float array or models.inputs.InputGrid, optional
        The input vector of each mode (an input grid's points): :meth:`act_input` returns it.
    input_names : sequence of m str, optional
        The inputs' names (default: the grid's, else ``u1..um``).

    Attributes
    ----------
    mode_names : tuple of str or None
        The names given as ``modes`` (None when omitted).
    status : {"running", "satisfied", "violated"}
    cell : int (-1 after leaving X)
    dfa_state : int
    time : int
        Number of steps observed since :meth:`reset`.
    """

    def __init__(
        self,
        strategy: Any,
        dfa_delta: Any,
        dfa_initial: int,
        dfa_accepting: Any,
        atoms: Sequence[str],
        cell_letters: Any,
        breakpoints: Sequence[Any],
        space_lower: Any,
        space_upper: Any,
        *,
        modes: Sequence[str] | None = None,
        threshold: float | None = None,
        p_low: Any = None,
        p_up: Any = None,
        p_up_star: Any = None,
        metadata: dict | None = None,
        cell_map: Any = None,
        periodic: Sequence[bool] | None = None,
        semantics: str = "reach",
        inputs: Any = None,
        input_names: Sequence[str] | None = None,
    ):
        if semantics not in ("reach", "safety"):
            raise InvalidInputError(f"semantics must be 'reach' or 'safety'; got {semantics!r}")
        self.semantics = semantics
        self.inputs, self.input_names = _input_table(inputs, input_names)
        self.atoms = tuple(atoms)
        # periodic dimensions (docs/periodic.md): states are wrapped into X there before locating
        self.periodic = None if periodic is None or not any(periodic) else tuple(bool(v) for v in periodic)
        self.dfa_delta = np.array(dfa_delta, dtype=np.int64)
        self.dfa_accepting = np.array(dfa_accepting, dtype=bool)
        S = self.dfa_delta.shape[0] if self.dfa_delta.ndim == 2 else -1
        if self.dfa_delta.ndim != 2 or self.dfa_delta.shape[1] != 2 ** len(self.atoms):
            raise DimensionError(
                f"dfa_delta must have shape (S, {2 ** len(self.atoms)}) for atoms {list(self.atoms)}; "
                f"got {self.dfa_delta.shape}"
            )
        if self.dfa_delta.size and (self.dfa_delta.min() < 0 or self.dfa_delta.max() >= S):
            raise InvalidModelError(f"dfa_delta targets must lie in [0, {S})")
        if self.dfa_accepting.shape != (S,):
            raise DimensionError(f"dfa_accepting must have shape ({S},); got {self.dfa_accepting.shape}")
        if not 0 <= int(dfa_initial) < S:
            raise InvalidModelError(f"dfa_initial must lie in [0, {S}); got {dfa_initial!r}")
        self.dfa_initial = int(dfa_initial)
        self.dfa_sink = _sinks(self.dfa_delta, self.dfa_accepting)

        self.breakpoints = [np.array(b, dtype=np.float64) for b in breakpoints]
        for j, b in enumerate(self.breakpoints):
            if b.ndim != 1 or b.size < 2 or np.any(np.diff(b) <= 0):
                raise InvalidModelError(f"breakpoints[{j}] must be a strictly increasing 1-D array of length >= 2")
        self.shape = tuple(len(b) - 1 for b in self.breakpoints)
        self.dim = len(self.shape)
        self.n_cells = int(np.prod(self.shape))
        self.cell_map = None
        if cell_map is not None:
            self.cell_map = np.array(cell_map, dtype=np.int64)
            if self.cell_map.shape != self.shape:
                raise DimensionError(f"cell_map must have the breakpoint grid's shape {self.shape}; got "
                                     f"{self.cell_map.shape}")
            self.n_cells = int(self.cell_map.max(initial=-1)) + 1
            if self.cell_map.min(initial=0) < 0 or np.unique(self.cell_map).size != self.n_cells:
                raise InvalidModelError("cell_map must map every grid box to a cell 0 .. n_cells-1 and use every cell")
        self.space_lower = np.array(space_lower, dtype=np.float64).reshape(-1)
        self.space_upper = np.array(space_upper, dtype=np.float64).reshape(-1)
        if self.space_lower.shape != (self.dim,) or self.space_upper.shape != (self.dim,):
            raise DimensionError(
                f"space_lower and space_upper must have shape ({self.dim},); got "
                f"{self.space_lower.shape} and {self.space_upper.shape}"
            )
        self.cell_letters = np.array(cell_letters, dtype=np.int64)
        if self.cell_letters.shape != (self.n_cells,):
            raise DimensionError(
                f"cell_letters must have shape (n_cells,) = ({self.n_cells},); got {self.cell_letters.shape}"
            )
        if np.any((self.cell_letters < 0) | (self.cell_letters >= 2 ** len(self.atoms))):
            raise InvalidModelError(f"cell_letters must be letters in [0, {2 ** len(self.atoms)})")
        self.strategy = np.array(strategy, dtype=np.int64)
        if self.strategy.ndim == 2:
            self.horizon = None
        elif self.strategy.ndim == 3:
            self.horizon = int(self.strategy.shape[0])
        else:
            raise DimensionError(f"strategy must be (n_cells, S) or (k, n_cells, S); got {self.strategy.shape}")
        if self.strategy.shape[-2:] != (self.n_cells, S):
            raise DimensionError(
                f"strategy must end with shape (n_cells, S) = ({self.n_cells}, {S}); got {self.strategy.shape}"
            )
        self.n_modes = int(self.strategy.max(initial=-1)) + 1
        self.modes = None if modes is None else tuple(modes)
        if self.modes is not None:
            if isinstance(modes, str) or len(self.modes) < self.n_modes:
                raise InvalidInputError(
                    f"modes must name at least the {self.n_modes} modes used by the strategy; got {modes!r}"
                )
            self.n_modes = len(self.modes)
        if self.inputs is not None and self.inputs.shape[0] < self.n_modes:
            raise DimensionError(f"inputs must give the input vector of each of the {self.n_modes} modes; got "
                                 f"{self.inputs.shape[0]} rows")
        self.threshold = None if threshold is None else float(threshold)
        nan = np.full(self.n_cells, np.nan)
        self.p_low = nan.copy() if p_low is None else np.array(p_low, dtype=np.float64)
        self.p_up = nan.copy() if p_up is None else np.array(p_up, dtype=np.float64)
        self.p_up_star = nan.copy() if p_up_star is None else np.array(p_up_star, dtype=np.float64)
        for name in ("p_low", "p_up", "p_up_star"):
            if getattr(self, name).shape != (self.n_cells,):
                raise DimensionError(f"{name} must have shape ({self.n_cells},); got {getattr(self, name).shape}")
        self.metadata = dict(metadata or {})
        self.status = RUNNING
        self.cell = -1
        self.dfa_state = self.dfa_initial
        self.time = 0
        self._started = False
        self._pending = False

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_result(cls, result: Any, partition: Any = None, mode_names: Sequence[str] | None = None,
                    inputs: Any = None) -> "Controller":
        """The controller of a result.

        Parameters
        ----------
        result : SynthesisResult, pipeline Result or saved result
            A :class:`~robust_imdp.synthesis.core.SynthesisResult` with the ``partition`` it was solved on;
            or, without ``partition``, a pipeline ``Result`` (its synthesis on its partition) or a saved
            result (``robust_imdp.load_result(dir)``, an ``io.result_file.ResultFile``, or anything with
            its tables: ``cells_lower``, ``cells_upper``, ``label_letters``, ``dfa_atoms``, ``dfa_delta``,
            ``dfa_initial``, ``dfa_accepting``, ``strategy``, ``strategy_by_time``, ``space_lower``,
            ``space_upper``, ``modes``; see :meth:`from_tables`).
        partition : geometry.Partition or BoxPartition, optional
        mode_names : sequence of str, optional
            Names :meth:`act` returns (default: the result's mode names where it has them).
        inputs : models.inputs.InputGrid or (n_modes, m) array, optional
            The modes' input vectors (:meth:`act_input`; a pipeline Result gives its problem's grid).

        Raises
        ------
        DimensionError, InvalidInputError
            If the partition's cells or labels do not match the result, or ``result`` is none of these.
        """
        if partition is None:
            if hasattr(result, "synthesis") and hasattr(result, "partition"):  # a pipeline Result
                return cls.from_result(result.synthesis, result.partition,
                                       result.mode_names if mode_names is None else mode_names,
                                       inputs=getattr(result.problem, "inputs", None) if inputs is None else inputs)
            missing = [a for a in _TABLES if not hasattr(result, a)]
            if missing:
                raise InvalidInputError(
                    "Controller.from_result needs a pipeline Result, a saved result (load_result(dir)) or a "
                    f"SynthesisResult with its partition; got {type(result).__name__} without a partition (it has no "
                    f"{missing[:3]})")
            return cls.from_tables(result, mode_names)
        if partition.n_cells != result.n_cells:
            raise DimensionError(
                f"partition must have the result's {result.n_cells} cells; got {partition.n_cells}"
            )
        letters = remap_letters(partition.labels, partition.atoms, result.dfa.atoms)
        if not np.array_equal(letters, result.labels):
            q = int(np.flatnonzero(letters != result.labels)[0])
            raise InvalidInputError(
                f"partition labels differ from those used for synthesis (first at cell {q}); "
                "pass the partition the abstraction was built on"
            )
        dfa = result.dfa
        meta = {"formula": dfa.formula, "horizon": result.horizon}
        # cells of different sizes (geometry.BoxPartition): the grid of all cell faces and its cell map
        grid, cell_map = (partition.grid_index() if hasattr(partition, "grid_index")
                          else (partition.breakpoints, None))
        return cls(
            result.strategy, dfa.delta, dfa.initial, dfa.accepting, dfa.atoms, result.labels,
            grid, partition.space.lower, partition.space.upper, cell_map=cell_map,
            modes=mode_names, threshold=result.threshold, p_low=result.p_low, p_up=result.p_up,
            p_up_star=result.p_up_star, metadata=meta, periodic=getattr(partition, "periodic", None),
            semantics=getattr(result, "semantics", "reach"), inputs=inputs,
        )

    @classmethod
    def from_tables(cls, res: Any, mode_names: Sequence[str] | None = None) -> "Controller":
        """The controller of a saved result's tables (``result.json`` read back: ``ResultFile``).

        The same controller as the live ``Result.controller()``: the grid is every cell face
        (:func:`grid_of_cells`; the cells of a regular grid in C order need no cell map), the letters
        are the cells' labels over the DFA's atoms, the strategy is the time-varying table of a
        k-step result.
        """
        breakpoints, cell_map = grid_of_cells(res.cells_lower, res.cells_upper)
        by_time = getattr(res, "strategy_by_time", None)
        return cls(
            res.strategy if by_time is None else by_time, res.dfa_delta, res.dfa_initial, res.dfa_accepting,
            res.dfa_atoms, res.label_letters, breakpoints, res.space_lower, res.space_upper, cell_map=cell_map,
            modes=tuple(res.modes) if mode_names is None else mode_names, threshold=getattr(res, "threshold", None),
            p_low=getattr(res, "p_low", None), p_up=getattr(res, "p_up", None),
            p_up_star=getattr(res, "p_up_star", None),
            metadata={"formula": getattr(res, "formula", None), "horizon": getattr(res, "horizon", None)},
            periodic=getattr(res, "periodic", None), inputs=getattr(res, "inputs", None),
            # the reading of the bounds, only where it is not the default (reach)
            **({"semantics": res.semantics} if getattr(res, "semantics", "reach") != "reach" else {}),
        )

    # ------------------------------------------------------------------ running
    def locate(self, x: Any) -> "int | np.ndarray":
        """The cell of a state, or of each state of a batch; ``-1`` outside X (``Partition.locate``'s convention).

        Parameters
        ----------
        x : (d,) float array (one state; a number when d = 1) or (k, d) float array (a batch)

        Returns
        -------
        int for one state; (k,) int64 array for a batch
        """
        one = np.ndim(x) <= 1
        cells = self._locate_batch(x)
        return int(cells[0]) if one else cells

    def _locate_batch(self, x: Any) -> np.ndarray:
        """:meth:`locate` of ``(k, d)`` or ``(d,)`` points, always as a ``(k,)`` int64 array."""
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise DimensionError(f"x must have shape (k, {self.dim}) or ({self.dim},); got {np.shape(x)}")
        if np.any(np.isnan(x)):
            raise InvalidInputError("x must not contain NaN")
        if self.periodic is not None:
            x = self._wrap(x)
        inside = np.all((x >= self.space_lower) & (x <= self.space_upper), axis=1)
        multi = np.empty(x.shape, dtype=np.int64)
        for j, bp in enumerate(self.breakpoints):  # loop over dimensions, vectorised over points
            multi[:, j] = np.clip(np.searchsorted(bp, x[:, j], side="right") - 1, 0, len(bp) - 2)
        out = np.full(x.shape[0], -1, dtype=np.int64)
        if np.any(inside):
            out[inside] = np.ravel_multi_index(tuple(multi[inside].T), self.shape)
            if self.cell_map is not None:  # cells of different sizes
                out[inside] = self.cell_map.reshape(-1)[out[inside]]
        return out

    def _wrap(self, x: np.ndarray) -> np.ndarray:
        """``x`` with each periodic coordinate moved into ``[lower_j, upper_j)`` (as ``geometry.wrap_points``)."""
        x = np.array(x, dtype=np.float64)
        for j in np.flatnonzero(self.periodic):
            lo, hi = float(self.space_lower[j]), float(self.space_upper[j])
            w = lo + np.mod(x[:, j] - lo, hi - lo)
            x[:, j] = np.where((w >= hi) | (w < lo), lo, w)
        return x

    def _locate_one(self, x: Any) -> int:
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (self.dim,):
            raise DimensionError(f"x must have shape ({self.dim},); got {x.shape}")
        return int(self._locate_batch(x)[0])

    def _update_status(self) -> None:
        if self.semantics == "safety":
            if self.dfa_sink[self.dfa_state]:
                self.status = VIOLATED  # a bad prefix: acceptance is no longer reachable
            elif self.horizon is not None and self.time >= self.horizon:
                self.status = SATISFIED  # k-step safety: no bad prefix within the horizon
            else:
                self.status = RUNNING  # an accepting DFA state decides nothing under the safety reading
            return
        if self.dfa_accepting[self.dfa_state]:
            self.status = SATISFIED  # accepting product states are absorbing targets
        elif self.dfa_sink[self.dfa_state]:
            self.status = VIOLATED  # acceptance is no longer reachable
        elif self.horizon is not None and self.time >= self.horizon:
            self.status = VIOLATED  # k-step objective: not accepted within the horizon
        else:
            self.status = RUNNING

    def reset(self, x0: Any) -> "Controller":
        """Start a run in ``x0``: locate its cell and read its label (``s = delta(s0, L(q0))``).

        Raises
        ------
        OutsideDomainError
            If ``x0`` is outside X.
        """
        q = self._locate_one(x0)
        if q < 0:
            raise OutsideDomainError(
                f"x0 must lie in X = [{self.space_lower.tolist()}, {self.space_upper.tolist()}]; "
                f"got {np.asarray(x0).tolist()}"
            )
        self.cell = q
        self.time = 0
        self.dfa_state = int(self.dfa_delta[self.dfa_initial, self.cell_letters[q]])
        self._started = True
        self._pending = False
        self._update_status()
        return self

    @property
    def mode_names(self) -> tuple | None:
        """The mode names (``modes``), or None when the controller was built without them."""
        return self.modes

    def act(self, x: Any):
        """Observe the current state ``x`` and return the mode to apply, or ``None`` when done.

        The first call after :meth:`reset` must be given the reset state (its cell is checked);
        every later call is taken as the state reached by applying the previously returned mode,
        so its cell's label advances the DFA. Leaving X makes the run "violated".

        Returns
        -------
        str, int or None
            The mode's name when the controller knows the names (:attr:`mode_names`), else its
            index; ``None`` once :attr:`status` is "satisfied" or "violated". :meth:`act_index`
            is the same step and always returns the index.
        """
        mode = self.act_index(x)
        return mode if mode is None or self.modes is None else self.modes[mode]

    def act_input(self, x: Any) -> np.ndarray | None:
        """As :meth:`act`, but the mode's input vector ``(m,)`` (a copy), for a controller of an input grid
        (:attr:`inputs`); ``None`` when done.

        Raises
        ------
        InvalidInputError
            If the controller has no input grid (its modes are named, not input values).
        """
        if self.inputs is None:
            raise InvalidInputError("act_input needs a controller of an input grid (inputs); this one's modes are "
                                    f"{list(self.modes) if self.modes is not None else self.n_modes}: use act")
        mode = self.act_index(x)
        return None if mode is None else self.inputs[mode].copy()

    def act_index(self, x: Any) -> int | None:
        """As :meth:`act`, but the mode as an integer index into :attr:`mode_names` (or ``None`` when done)."""
        if not self._started:
            raise InvalidInputError("act(x) called before reset(x0)")
        q = self._locate_one(x)
        if self._pending:
            self._pending = False
            self.time += 1
            if q < 0:
                self.cell = -1
                self.status = VIOLATED  # the outside-X state is absorbing and never accepting
                return None
            self.cell = q
            self.dfa_state = int(self.dfa_delta[self.dfa_state, self.cell_letters[q]])
            self._update_status()
        elif self.status == RUNNING and q != self.cell:
            raise InvalidInputError(
                f"the first act(x) after reset must be given the reset state (cell {self.cell}); "
                f"x lies in cell {q}"
            )
        if self.status != RUNNING:
            return None
        table = self.strategy if self.horizon is None else self.strategy[self.time]
        mode = int(table[self.cell, self.dfa_state])
        self._pending = True
        return mode

    def start_batch(self, x0: Any) -> "ControllerRuns":
        """Start ``k`` runs side by side, one from each row of ``x0``: the batch form of :meth:`reset` /
        :meth:`act` (:class:`ControllerRuns`; this controller's own run is not touched).

        Parameters
        ----------
        x0 : (k, d) float array of states in X

        Returns
        -------
        ControllerRuns
            ``runs.act(x (k, d))`` gives the ``k`` modes (:meth:`ControllerRuns.act`).
        """
        return ControllerRuns(self, x0)

    # ------------------------------------------------------------------ files
    def save(self, path_prefix: str | Path) -> tuple[Path, Path]:
        """Write ``<prefix>.json`` and ``<prefix>.npz`` (format in the module docstring).

        Returns
        -------
        (json_path, npz_path)
        """
        prefix = Path(path_prefix)
        json_path, npz_path = prefix.with_name(prefix.name + ".json"), prefix.with_name(prefix.name + ".npz")
        doc = {
            "format": FORMAT,
            "version": 1,
            "atoms": list(self.atoms),
            "dfa": {
                "initial": self.dfa_initial,
                "accepting": [int(s) for s in np.flatnonzero(self.dfa_accepting)],
                "delta": self.dfa_delta.tolist(),
            },
            "modes": None if self.modes is None else list(self.modes),
            "n_modes": self.n_modes,
            "threshold": self.threshold,
            "horizon": self.horizon,
            "dim": self.dim,
            "shape": list(self.shape),
            "metadata": self.metadata,
        }
        if self.periodic is not None:  # only then: files without periodic dimensions are unchanged
            doc["periodic"] = list(self.periodic)
        if self.semantics == "safety":  # only then: files of the reach reading are unchanged
            doc["semantics"] = "safety"
        if self.inputs is not None:  # only then: files of named modes are unchanged
            doc["inputs"] = {"names": list(self.input_names), "values": self.inputs.tolist()}
        arrays = {
            "strategy": self.strategy,
            "cell_letters": self.cell_letters,
            "space_lower": self.space_lower,
            "space_upper": self.space_upper,
            "p_low": self.p_low,
            "p_up": self.p_up,
            "p_up_star": self.p_up_star,
        }
        if self.cell_map is not None:
            arrays["cell_map"] = self.cell_map
        for j, b in enumerate(self.breakpoints):
            arrays[f"breakpoints_{j}"] = b
        with open(npz_path, "wb") as fh:
            np.savez(fh, **arrays)
        json_path.write_text(json.dumps(doc, indent=1))
        return json_path, npz_path

    @classmethod
    def load(cls, path_prefix: str | Path) -> "Controller":
        """Read a controller written by :meth:`save` (no pickle: ``allow_pickle=False``)."""
        prefix = Path(path_prefix)
        json_path, npz_path = prefix.with_name(prefix.name + ".json"), prefix.with_name(prefix.name + ".npz")
        doc = json.loads(json_path.read_text())
        if doc.get("format") != FORMAT or doc.get("version") != 1:
            raise InvalidInputError(
                f"{json_path} must be a '{FORMAT}' version 1 file; got format={doc.get('format')!r}, "
                f"version={doc.get('version')!r}"
            )
        with np.load(npz_path, allow_pickle=False) as z:
            arr = {k: z[k] for k in z.files}
        S = len(doc["dfa"]["delta"])
        accepting = np.zeros(S, dtype=bool)
        accepting[np.asarray(doc["dfa"]["accepting"], dtype=np.int64)] = True
        bps = [arr[f"breakpoints_{j}"] for j in range(int(doc["dim"]))]
        return cls(
            arr["strategy"], np.asarray(doc["dfa"]["delta"], dtype=np.int64).reshape(S, -1),
            doc["dfa"]["initial"], accepting, doc["atoms"], arr["cell_letters"], bps,
            arr["space_lower"], arr["space_upper"], modes=doc["modes"], threshold=doc["threshold"],
            p_low=arr["p_low"], p_up=arr["p_up"], p_up_star=arr["p_up_star"], metadata=doc["metadata"],
            cell_map=arr.get("cell_map"), periodic=doc.get("periodic"), semantics=doc.get("semantics", "reach"),
            inputs=None if doc.get("inputs") is None else np.asarray(doc["inputs"]["values"], dtype=float),
            input_names=None if doc.get("inputs") is None else doc["inputs"]["names"],
        )

    def __repr__(self) -> str:
        return (
            f"Controller(n_cells={self.n_cells}, dfa_states={self.dfa_delta.shape[0]}, "
            f"modes={self.modes or self.n_modes}, horizon={self.horizon}, status={self.status!r})"
        )


class ControllerRuns:
    """``k`` runs of one :class:`Controller` side by side (:meth:`Controller.start_batch`): the batch form of
    ``reset`` / ``act``, vectorised over the runs, with each run following :meth:`Controller.act`'s rules.

    The first :meth:`act` must be given the start states; every later call is taken as the states reached by
    applying the modes the previous call returned; a run is over once its status is "satisfied" or
    "violated" (leaving X violates), and its entries are then ``None`` (names) or ``-1`` (indices)::

        runs = ctrl.start_batch(x0)              # x0: (k, d)
        while (u := runs.act_index(x)).max() >= 0:
            x = step(x, u)                         # rows of finished runs are not read
        runs.status                                # (k,) "satisfied" / "violated" / "running"

    Attributes
    ----------
    controller : Controller
    status : (k,) str array
    cell, dfa_state, time : (k,) int64 arrays (cell -1 after leaving X)
    """

    def __init__(self, controller: Controller, x0: Any):
        self.controller = c = controller
        x0 = np.asarray(x0, dtype=np.float64)
        if x0.ndim != 2:
            raise DimensionError(f"x0 must be a (k, {c.dim}) array of start states; got shape {x0.shape}")
        q = c._locate_batch(x0)
        if np.any(q < 0):
            i = int(np.flatnonzero(q < 0)[0])
            raise OutsideDomainError(f"x0 must lie in X = [{c.space_lower.tolist()}, {c.space_upper.tolist()}]; row "
                                     f"{i} = {x0[i].tolist()} does not")
        self.cell = q
        self.time = np.zeros(q.size, dtype=np.int64)
        self.dfa_state = c.dfa_delta[c.dfa_initial, c.cell_letters[q]]  # the first label is read at the start
        self.status = self._statuses()
        self._pending = np.zeros(q.size, dtype=bool)

    def __len__(self) -> int:
        return int(self.cell.size)

    def _statuses(self) -> np.ndarray:
        """``Controller._update_status`` for every run at once."""
        c = self.controller
        s = self.dfa_state
        over = np.zeros(s.size, dtype=bool) if c.horizon is None else self.time >= c.horizon
        if getattr(c, "semantics", "reach") == "safety":  # accepting states decide nothing; the horizon satisfies
            return np.where(c.dfa_sink[s], VIOLATED, np.where(over, SATISFIED, RUNNING))
        return np.where(c.dfa_accepting[s], SATISFIED, np.where(c.dfa_sink[s] | over, VIOLATED, RUNNING))

    def act_index(self, x: Any) -> np.ndarray:
        """Observe the ``k`` current states; the mode index of each run, ``-1`` where the run is over.

        Parameters
        ----------
        x : (k, d) float array (rows of finished runs are not read)

        Returns
        -------
        (k,) int64 array of indices into ``controller.mode_names``
        """
        c = self.controller
        x = np.asarray(x, dtype=np.float64)
        if x.shape != (len(self), c.dim):
            raise DimensionError(f"x must have shape ({len(self)}, {c.dim}) like x0; got {x.shape}")
        live = self._pending | (self.status == RUNNING)
        q = np.full(len(self), -1, dtype=np.int64)
        q[live] = c._locate_batch(x[live])
        first = ~self._pending & (self.status == RUNNING) & (q != self.cell)
        if np.any(first):
            i = int(np.flatnonzero(first)[0])
            raise InvalidInputError(f"the first act(x) after start_batch must be given the start states; row {i} lies "
                                    f"in cell {int(q[i])}, its start in cell {int(self.cell[i])}")
        moved = self._pending
        self.time[moved] += 1
        left = moved & (q < 0)
        self.cell[left] = -1
        self.status[left] = VIOLATED  # the outside-X state is absorbing and never accepting
        step = moved & (q >= 0)
        self.cell[step] = q[step]
        self.dfa_state[step] = c.dfa_delta[self.dfa_state[step], c.cell_letters[q[step]]]
        self.status[step] = self._statuses()[step]
        running = self.status == RUNNING
        modes = np.full(len(self), -1, dtype=np.int64)
        rows = np.flatnonzero(running)
        if c.horizon is None:
            modes[rows] = c.strategy[self.cell[rows], self.dfa_state[rows]]
        else:
            modes[rows] = c.strategy[self.time[rows], self.cell[rows], self.dfa_state[rows]]
        self._pending = running
        return modes

    def act(self, x: Any) -> np.ndarray:
        """As :meth:`act_index`, but the modes' names (an object array, ``None`` where the run is over) when the
        controller knows them; else the indices (``-1`` where over)."""
        idx = self.act_index(x)
        if self.controller.modes is None:
            return idx
        names = np.array(list(self.controller.modes) + [None], dtype=object)
        return names[idx]  # index -1 is the appended None
