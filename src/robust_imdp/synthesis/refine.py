"""Adaptive refinement of undecided cells (see docs/refinement.md): split, re-bound the new cells, re-abstract, re-solve.

Refining a uniform grid everywhere spends almost all of its cells where nothing is undecided.
:func:`refine` starts from an abstraction on a :class:`~robust_imdp.models.geometry.BoxPartition` (an
unsplit one is the rectilinear grid, bit for bit) and repeats, round by round:

1. **select** the cells whose splitting can most change the class of an open cell -- one that
   can still become Q_yes: Q_?, or Q_no with ``p_up_star >= threshold`` (``focus="open"``, the
   default), or Q_? only (``focus="undecided"``) -- (:func:`select_cells`): an open cell q,
   weighted by its volume, points at itself and at every successor c its chosen mode can reach
   (upper bound > 0), in proportion to ``upper(q, u, c)``; each candidate's score is that
   weight times its own error ``p_up_star - p_low`` (cells whose value is already exact, such
   as obstacles, score 0);
2. **split** the best ones (bisect the longest side, or every side) within the round's share of
   the cell budget and above ``min_cell_size``;
3. **bound** only the new cells (``bound_cells``, e.g. the certified RKHS bounds of
   ``rkhs.bound_chunk``: a pure function of the cell boxes, the learned model does not change)
   and intersect each child's image box with its parent's (both contain the child's image);
4. **re-abstract** only the affected rows: the new cells' rows and the rows that listed a split
   cell. Every other row is kept as it is: its listed targets, their bounds and its floor
   depend only on its own image box and on the boxes of the cells it lists, none of which
   changed, and the children of an unlisted cell are separated from ``Im ⊕ e_f`` like their
   parent, so they are covered by the same floor. The assembled IMDP is therefore exactly the
   one :func:`~robust_imdp.abstraction.rows.abstract` builds from scratch (tested);
5. **re-solve** the product (``synthesis.synthesize``; the solver takes no initial values, so
   there is no warm start: the state space changes every round anyway).

It stops when no cell is open (undecided), at the cell budget (``max_cells``), after ``max_rounds``,
when the time budget is spent, or when no undecided cell can be split further
(``min_cell_size``). Each round's cells, Q_yes / Q_no / Q_? volume shares and times are recorded
(:class:`RefineRound`).

Soundness is that of the abstraction: every bound holds for every point of every cell whatever
its size (the bounds are per cell), and the labels are exact (children inherit them).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from robust_imdp.abstraction.factored import is_factored
from robust_imdp.abstraction.rows import AbstractionRows, CellBounds, abstract_rows, assemble_abstraction, join_rows, \
    select_rows
from robust_imdp.errors import DimensionError, InvalidInputError, ResourceError
from robust_imdp.models.factored import MAX_JOINT_ENTRIES
from robust_imdp.models.geometry import BoxPartition, Partition

__all__ = ["RefineOptions", "RefineRound", "RefineResult", "refine", "select_cells", "focus_cells", "class_shares"]

SPLITS = ("longest", "all")
FOCUS = ("open", "undecided")


@dataclass(frozen=True)
class RefineOptions:
    """Settings of the refinement loop (the problem file's ``[refine]`` table).

    Attributes
    ----------
    max_cells : int
        Cell budget: no round makes the partition larger than this.
    max_rounds : int
        Rounds of split / bound / abstract / solve (default 8).
    min_cell_size : float or (d,) float array or None
        No cell is bisected along an axis where its halves would be narrower than this
        (default: the base grid's smallest cell width / 16).
    time_budget : float or None
        Seconds (wall clock, counted from the start of :func:`refine`); no round starts after it.
    split : {"longest", "all"}
        Bisect a cell along its longest side relative to the base cell (a k-d tree; two
        children), or along every side (a quad/oct-tree step; ``2**d`` children).
    growth : float in (0, 1]
        A round adds at most ``growth * n_cells`` cells (a few rounds, each aimed at the cells
        the last solve found undecided).
    focus : {"open", "undecided"}
        Which cells refinement tries to decide (:func:`select_cells`): every cell that can still
        become Q_yes (default), or the Q_? cells only.
    """

    max_cells: int
    max_rounds: int = 8
    min_cell_size: object = None
    time_budget: float | None = None
    split: str = "longest"
    growth: float = 0.35
    focus: str = "open"

    def __post_init__(self):
        if isinstance(self.max_cells, bool) or not isinstance(self.max_cells, (int, np.integer)) or self.max_cells < 1:
            raise InvalidInputError(f"[refine].max_cells must be a positive integer; got {self.max_cells!r}")
        if isinstance(self.max_rounds, bool) or not isinstance(self.max_rounds, (int, np.integer)) \
                or self.max_rounds < 0:
            raise InvalidInputError(f"[refine].max_rounds must be an integer >= 0; got {self.max_rounds!r}")
        if self.min_cell_size is not None:
            m = np.asarray(self.min_cell_size, dtype=float)
            if m.ndim > 1 or not np.all(np.isfinite(m)) or np.any(m <= 0):
                raise InvalidInputError(
                    f"[refine].min_cell_size must be a positive float or a list of them; got {self.min_cell_size!r}")
        if self.time_budget is not None and not (float(self.time_budget) > 0):
            raise InvalidInputError(f"[refine].time_budget must be a positive number of seconds; got {self.time_budget!r}")
        if self.split not in SPLITS:
            raise InvalidInputError(f"[refine].split must be one of {SPLITS}; got {self.split!r}")
        if self.focus not in FOCUS:
            raise InvalidInputError(f"[refine].focus must be one of {FOCUS}; got {self.focus!r}")
        if not (0 < float(self.growth) <= 1):
            raise InvalidInputError(f"[refine].growth must lie in (0, 1]; got {self.growth!r}")

    KEYS = ("max_cells", "max_rounds", "min_cell_size", "time_budget", "split", "growth", "focus")

    @classmethod
    def from_dict(cls, d) -> "RefineOptions":
        """From the ``[refine]`` table (unknown keys are errors naming the valid ones)."""
        if isinstance(d, RefineOptions):
            return d
        if not isinstance(d, dict):
            raise InvalidInputError(f"[refine] must be a table; got {type(d).__name__}")
        unknown = sorted(set(d) - set(cls.KEYS))
        if unknown:
            raise InvalidInputError(f"[refine] has unknown keys {unknown}; valid keys are {list(cls.KEYS)}")
        if "max_cells" not in d:
            raise InvalidInputError("[refine] needs max_cells (the cell budget; refinement is on when [refine] is given)")
        return cls(**d)

    def to_dict(self) -> dict:
        m = self.min_cell_size
        return {"max_cells": int(self.max_cells), "max_rounds": int(self.max_rounds),
                "min_cell_size": None if m is None else np.asarray(m, float).tolist(),
                "time_budget": None if self.time_budget is None else float(self.time_budget),
                "split": self.split, "growth": float(self.growth), "focus": self.focus}


@dataclass(frozen=True)
class RefineRound:
    """Progress of one round (round 0: the unrefined partition).

    Attributes
    ----------
    round, n_cells, n_split : int
        Round number, cells after the round, cells split in it.
    counts : dict ``{"yes", "no", "maybe"} -> int`` (cells)
    shares : dict ``{"yes", "no", "maybe"} -> float`` (fractions of the volume of X)
    rows_rebuilt : int
        Cells whose IMDP rows were recomputed (the others were kept).
    seconds : dict ``{"bound", "abstract", "solve", "select", "total"}`` -> float
        Times of the round; ``elapsed`` is the time since the refinement started.
    elapsed : float
    """

    round: int
    n_cells: int
    n_split: int
    counts: dict
    shares: dict
    rows_rebuilt: int
    seconds: dict
    elapsed: float

    def line(self) -> str:
        s = self.shares
        return (f"round {self.round}: {self.n_cells} cells ({self.n_split} split, {self.rows_rebuilt} rows rebuilt); "
                f"area Q_yes {s['yes']:.4f}  Q_no {s['no']:.4f}  Q_? {s['maybe']:.4f}; "
                f"{self.seconds['total']:.1f} s (bound {self.seconds['bound']:.1f}, abstract "
                f"{self.seconds['abstract']:.2f}, solve {self.seconds['solve']:.1f}), {self.elapsed:.1f} s so far")

    def to_dict(self) -> dict:
        return {"round": self.round, "n_cells": self.n_cells, "n_split": self.n_split, "counts": dict(self.counts),
                "shares": dict(self.shares), "rows_rebuilt": self.rows_rebuilt, "seconds": dict(self.seconds),
                "elapsed": self.elapsed}


@dataclass(frozen=True, eq=False)
class RefineResult:
    """Output of :func:`refine`.

    Attributes
    ----------
    partition : geometry.BoxPartition
    cell_bounds : abstraction.CellBounds
        Image boxes of every cell of ``partition`` (``std_upper=None``).
    abstraction : abstraction.Abstraction
    synthesis : synthesis.SynthesisResult
    rounds : tuple of RefineRound
        Round 0 is the starting partition.
    stopped : str
        Why the loop ended ("no undecided cells", "cell budget", "max_rounds", "time budget",
        "nothing to split").
    """

    partition: BoxPartition
    cell_bounds: CellBounds
    abstraction: object
    synthesis: object
    rounds: tuple
    stopped: str
    options: RefineOptions = field(repr=False, default=None)


# --------------------------------------------------------------------------- helpers
def class_shares(classes, volumes) -> tuple[dict, dict]:
    """Cells per class and the classes' fractions of the total volume."""
    classes = np.asarray(classes)
    volumes = np.asarray(volumes, dtype=float)
    total = float(volumes.sum())
    counts = {c: int(np.sum(classes == c)) for c in ("yes", "no", "maybe")}
    shares = {c: float(volumes[classes == c].sum() / total) for c in ("yes", "no", "maybe")}
    return counts, shares


def _min_size(options: RefineOptions, partition: BoxPartition) -> np.ndarray:
    if options.min_cell_size is None:
        w = partition.base.cells_upper - partition.base.cells_lower
        return np.full(partition.dim, float(w.min()) / 16.0)
    return np.broadcast_to(np.asarray(options.min_cell_size, dtype=float), (partition.dim,)).copy()


def focus_cells(synthesis, focus: str = "open") -> np.ndarray:
    """``(n_cells,)`` bool: the cells refinement tries to decide (see :class:`RefineOptions`)."""
    classes = np.asarray(synthesis.classes)
    if focus == "undecided":
        return classes == "maybe"
    return (classes == "maybe") | ((classes == "no") & (np.asarray(synthesis.p_up_star) >= synthesis.threshold))


def select_cells(partition: BoxPartition, imdp, synthesis, n_modes: int, focus: str = "open"):
    """Scores of every cell for splitting (see the module docstring, step 1).

    Parameters
    ----------
    partition : BoxPartition
    imdp : IMDP
        The abstraction's IMDP (row ``q * n_modes + u`` is cell q under mode u).
    synthesis : SynthesisResult
        ``classes``, ``error``, ``strategy`` and ``initial_dfa_state`` of the last solve.
    n_modes : int
    focus : {"open", "undecided"}
        The cells whose class refinement tries to change: the undecided ones (Q_?), or every cell
        that can still become Q_yes (Q_? and the Q_no cells whose optimistic bound ``p_up_star``
        reaches the threshold: their strategy's ``p_up`` is below it, the best strategy's is not).

    Returns
    -------
    (n_cells,) float array: 0 for cells whose splitting cannot change an undecided cell.
    """
    N = partition.n_cells
    vol = partition.volumes()
    err = np.asarray(synthesis.error, dtype=float)
    maybe = np.flatnonzero(focus_cells(synthesis, focus))
    weight = np.zeros(N)
    weight[maybe] += vol[maybe]
    if maybe.size:
        strat = np.asarray(synthesis.strategy)
        table = strat if strat.ndim == 2 else strat[0]
        u = table[maybe, np.asarray(synthesis.initial_dfa_state)[maybe]]
        r = maybe * n_modes + u
        ptr = imdp.row_ptr
        lens = ptr[r + 1] - ptr[r]
        idx = np.repeat(ptr[r], lens) + np.arange(int(lens.sum())) - np.repeat(np.cumsum(lens) - lens, lens)
        src = np.repeat(maybe, lens)
        c = imdp.col[idx]
        ok = c < N  # the outside state is not a cell
        np.add.at(weight, c[ok], vol[src[ok]] * imdp.upper[idx][ok])
    return weight * err


def _split_axes(partition: BoxPartition, cells, min_size, split: str):
    """Per cell: the axis to bisect (-1: none allowed), or all-axes feasibility for ``split="all"``."""
    w = (partition.cells_upper - partition.cells_lower)[cells]
    ok = 0.5 * w >= min_size  # halves no narrower than min_cell_size
    if split == "all":
        return np.where(np.all(ok, axis=1), 0, -1)
    base_w = (partition.base.cells_upper - partition.base.cells_lower)[partition.base_cell[cells]]
    rel = np.where(ok, w / base_w, -np.inf)  # longest side relative to the base cell's
    ax = np.argmax(rel, axis=1)
    return np.where(np.any(ok, axis=1), ax, -1)


def _bound_new(bound_cells, partition: BoxPartition, new, parent, cell_bounds: CellBounds):
    """Image boxes of the new cells, intersected with their parents' (both contain the image)."""
    lo, hi = bound_cells(partition.cells_lower[new], partition.cells_upper[new])
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    M, d = cell_bounds.n_modes, cell_bounds.dim
    if lo.shape != (M, new.size, d) or hi.shape != lo.shape:
        raise DimensionError(f"bound_cells must return two ({M}, {new.size}, {d}) arrays; got {lo.shape}, {hi.shape}")
    plo, phi = cell_bounds.image_lower[:, parent], cell_bounds.image_upper[:, parent]
    # Both boxes contain {f(x) : x in child} (a non-empty set), so the intersection does and
    # max(lower) <= min(upper) holds; max/min are exact in floating point.
    return np.maximum(lo, plo), np.minimum(hi, phi)


def _rebuild_rows(partition: BoxPartition, rows: AbstractionRows, old_n: int, split: np.ndarray,
                  image_lower, image_upper, noise, options: dict):
    """Rows of the refined partition: recompute new cells' rows and rows listing a split cell."""
    N, M = partition.n_cells, rows.n_modes
    ptr = np.zeros(rows.row_len.size + 1, dtype=np.int64)
    np.cumsum(rows.row_len, out=ptr[1:])
    was_split = np.zeros(old_n + 1, dtype=bool)
    was_split[split] = True
    hit_entry = was_split[rows.col]
    hit_row = np.add.reduceat(hit_entry.astype(np.int64), ptr[:-1]) > 0 if rows.col.size else np.zeros(0, bool)
    touched = np.zeros(N, dtype=bool)
    touched[:old_n] = hit_row.reshape(old_n, M).any(axis=1)
    touched[split] = True
    touched[old_n:] = True
    redo = np.flatnonzero(touched)
    keep = np.flatnonzero(~touched)
    new_rows = abstract_rows(partition, CellBounds(image_lower[:, redo], image_upper[:, redo], None), noise, None,
                             **options)
    kept_rows = select_rows(rows, keep)
    # cell indices are stable under BoxPartition.split, the outside state's is not: old_n -> N
    kept_rows = dataclasses.replace(kept_rows, col=np.where(kept_rows.col == old_n, N, kept_rows.col))
    joined = join_rows([kept_rows, new_rows])
    order = np.empty(N, dtype=np.int64)
    order[np.concatenate([keep, redo])] = np.arange(N)
    return select_rows(joined, order), int(redo.size)


# --------------------------------------------------------------------------- the loop
def refine(partition, cell_bounds: CellBounds, bound_cells: Callable, noise, dfa, *, threshold: float,
           horizon=None, options: RefineOptions, abstraction_options: dict | None = None, synthesize=None,
           abstraction=None, synthesis=None, progress: Callable[[str], None] | None = None) -> RefineResult:
    """Refine the undecided cells round by round (see the module docstring).

    Parameters
    ----------
    partition : geometry.Partition or geometry.BoxPartition
        The starting cells (a ``Partition`` is taken as the unsplit ``BoxPartition``).
    cell_bounds : CellBounds
        ``(n_modes, n_cells, d)`` image boxes of the starting cells, ``std_upper=None`` (known
        dynamics, or the learning error already folded in, as the pipeline's default route).
    bound_cells : callable ``(lower (k, d), upper (k, d)) -> (image_lower, image_upper)``
        Certified ``(n_modes, k, d)`` image boxes of new cells (a pure function of the boxes).
    noise : NoiseModel
    dfa : DFA
    threshold : float
    horizon : int or None
    options : RefineOptions
    abstraction_options : dict, optional
        ``eta``, ``eps_rule``, ``combine``, ``floor_tol`` of :func:`~robust_imdp.abstraction.rows.abstract_rows`.
    synthesize : callable ``(abstraction, partition) -> SynthesisResult``, optional
        Default: ``synthesis.synthesize(imdp, partition.labels, partition.atoms, dfa, threshold=...,
        horizon=..., outside_state=partition.outside_state)``.
    abstraction, synthesis : optional
        The starting abstraction (on ``partition``, with these bounds) and its synthesis result,
        when already computed (e.g. by the pipeline); they are rebuilt from ``cell_bounds`` if
        not given. A factored abstraction (``abstraction.factored``; docs/factored.md) is not kept:
        refined cells are boxes, not a grid, so the rounds work on joint rows (``abstraction_options``'
        transitions), built from ``cell_bounds`` for the whole grid and re-solved in round 0; where
        those rows would exceed :data:`MAX_JOINT_ENTRIES` the refinement is refused.
    progress : callable ``(str) -> None``, optional
        Receives one line per round.

    Returns
    -------
    RefineResult
    """
    from robust_imdp.synthesis.core import synthesize as _synthesize

    t_start = time.perf_counter()
    options = RefineOptions.from_dict(options) if isinstance(options, dict) else options
    partition = _check_start(partition, cell_bounds)
    abs_opts = dict(abstraction_options or {})
    M = cell_bounds.n_modes
    if is_factored(abstraction):
        _check_joint_size(abstraction)
        if progress:
            progress(f"refinement: the grid's factored abstraction becomes joint rows (refined cells are boxes, not "
                     f"a grid; about {abstraction.joint_entries():,} entries); round 0 re-solves them")
        abstraction, synthesis = None, None

    def solve(ab, part):
        if synthesize is not None:
            return synthesize(ab, part)
        return _synthesize(ab.imdp, part.labels, part.atoms, dfa, threshold=threshold, horizon=horizon,
                           outside_state=part.outside_state)

    # -- round 0: the starting abstraction and its solution
    t0 = time.perf_counter()
    rows = abstract_rows(partition, cell_bounds, noise, None, **abs_opts)
    if abstraction is None or abstraction.partition.n_cells != partition.n_cells:
        abstraction = assemble_abstraction(partition, [rows])
        synthesis = None
    t_abs = time.perf_counter() - t0
    t0 = time.perf_counter()
    if synthesis is None:
        synthesis = solve(abstraction, partition)
    t_solve = time.perf_counter() - t0
    counts, shares = class_shares(synthesis.classes, partition.volumes())
    rounds = [RefineRound(0, partition.n_cells, 0, counts, shares, partition.n_cells,
                          {"select": 0.0, "bound": 0.0, "abstract": t_abs, "solve": t_solve,
                           "total": t_abs + t_solve}, time.perf_counter() - t_start)]
    if progress:
        progress(rounds[-1].line())
    min_size = _min_size(options, partition)
    per_child = (2 ** partition.dim - 1) if options.split == "all" else 1
    stopped = "max_rounds"
    for rnd in range(1, options.max_rounds + 1):
        stopped = _budget_stop(partition, synthesis, options, per_child, t_start)
        if stopped is not None:
            break
        # -- 1. select
        t0 = time.perf_counter()
        split, axes = _pick_cells(partition, abstraction, synthesis, M, options, min_size, per_child)
        if split.size == 0:
            stopped = "nothing to split"
            break
        t_sel = time.perf_counter() - t0
        # -- 2. split, 3. bound the new cells only
        old_n = partition.n_cells
        partition = partition.split(split, None if options.split == "all" else axes)
        t0 = time.perf_counter()
        cell_bounds = _bound_children(bound_cells, partition, cell_bounds, split, old_n, per_child)
        t_bound = time.perf_counter() - t0
        # -- 4. rebuild the affected rows
        t0 = time.perf_counter()
        rows, n_rebuilt = _rebuild_rows(partition, rows, old_n, split, cell_bounds.image_lower,
                                        cell_bounds.image_upper, noise, abs_opts)
        abstraction = assemble_abstraction(partition, [rows])
        t_abs = time.perf_counter() - t0
        # -- 5. solve
        t0 = time.perf_counter()
        synthesis = solve(abstraction, partition)
        t_solve = time.perf_counter() - t0
        counts, shares = class_shares(synthesis.classes, partition.volumes())
        secs = {"select": t_sel, "bound": t_bound, "abstract": t_abs, "solve": t_solve}
        secs["total"] = sum(secs.values())
        rounds.append(RefineRound(rnd, partition.n_cells, int(split.size), counts, shares, n_rebuilt, secs,
                                  time.perf_counter() - t_start))
        if progress:
            progress(rounds[-1].line())
    else:
        stopped = "max_rounds" if focus_cells(synthesis, options.focus).any() else "no undecided cells"
    return RefineResult(partition=partition, cell_bounds=cell_bounds, abstraction=abstraction, synthesis=synthesis,
                        rounds=tuple(rounds), stopped=stopped, options=options)


def _check_joint_size(abstraction) -> None:
    """Refuse (``ResourceError``) a refinement whose joint rows of the grid would exceed :data:`MAX_JOINT_ENTRIES`
    (the entries of the factored model's joint expansion: the exact joint rows list at most these)."""
    entries = abstraction.joint_entries()
    if entries > MAX_JOINT_ENTRIES:
        raise ResourceError(
            f"refinement works on joint rows (refined cells are boxes, not a grid), and the joint rows of this "
            f"{abstraction.partition.n_cells:,}-cell grid would hold about {entries:,} entries (> {MAX_JOINT_ENTRIES:,}): "
            "drop [refine] and keep the factored result, or use a coarser grid")


def _check_start(partition, cell_bounds) -> BoxPartition:
    """The starting cells as a ``BoxPartition`` (a ``Partition`` is its unsplit one), after checking the bounds."""
    if isinstance(partition, Partition):
        partition = BoxPartition(partition)
    if not isinstance(partition, BoxPartition):
        raise InvalidInputError(f"partition must be a Partition or a BoxPartition; got {type(partition).__name__}")
    if not isinstance(cell_bounds, CellBounds) or cell_bounds.std_upper is not None:
        raise InvalidInputError("cell_bounds must be a CellBounds with std_upper=None (image boxes with the "
                                "learning error folded in)")
    if cell_bounds.n_cells != partition.n_cells or cell_bounds.dim != partition.dim:
        raise DimensionError(f"cell_bounds must have shape (n_modes, {partition.n_cells}, {partition.dim}); got "
                             f"{cell_bounds.image_lower.shape}")
    return partition


def _budget_stop(partition, synthesis, options: RefineOptions, per_child: int, t_start: float):
    """Why the loop stops before a round (no open cell, cell budget, time budget), or None."""
    if not focus_cells(synthesis, options.focus).any():
        return "no undecided cells"
    if partition.n_cells + per_child > options.max_cells:
        return "cell budget"
    if options.time_budget is not None and time.perf_counter() - t_start >= float(options.time_budget):
        return "time budget"
    return None


def _pick_cells(partition, abstraction, synthesis, n_modes, options: RefineOptions, min_size, per_child):
    """The cells to split this round and their axes: the best scores that can still be split, within the
    round's share of the cell budget (``growth``) and the room left (``max_cells``); empty if none."""
    score = select_cells(partition, abstraction.imdp, synthesis, n_modes, options.focus)
    cand = np.flatnonzero(score > 0)
    axes = _split_axes(partition, cand, min_size, options.split)
    cand, axes = cand[axes >= 0], axes[axes >= 0]
    if cand.size == 0:
        return cand, axes
    order = np.lexsort((cand, -score[cand]))  # best first; ties by index (deterministic)
    room = options.max_cells - partition.n_cells
    k = min(cand.size, room // per_child, max(1, int(options.growth * partition.n_cells) // per_child))
    pick = order[:k]
    return cand[pick], axes[pick]


def _bound_children(bound_cells, partition: BoxPartition, cell_bounds: CellBounds, split, old_n: int,
                    per_child: int) -> CellBounds:
    """Image boxes of every cell after ``split``: the split cells (now their first child) and the new
    cells ``old_n..`` bounded by ``bound_cells`` within their parents' boxes; every other cell's kept."""
    new = np.concatenate([split, np.arange(old_n, partition.n_cells)])
    parent = np.concatenate([split, np.repeat(split, per_child)])
    nlo, nhi = _bound_new(bound_cells, partition, new, parent, cell_bounds)
    ilo = np.concatenate([cell_bounds.image_lower, nlo[:, split.size:]], axis=1)
    ihi = np.concatenate([cell_bounds.image_upper, nhi[:, split.size:]], axis=1)
    ilo[:, split], ihi[:, split] = nlo[:, :split.size], nhi[:, :split.size]
    return CellBounds(ilo, ihi, None)
