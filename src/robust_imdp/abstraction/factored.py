r"""The factored abstraction: per (mode, cell, axis) interval vectors of the next state's marginal on a grid.

``[abstraction].form = "factored"`` (docs/factored.md, "In the pipeline"): instead of one joint interval per
(cell, mode, successor cell), the abstraction stores the exact per-axis bounds of
:mod:`robust_imdp.abstraction.marginals` as a :class:`~robust_imdp.models.factored.FactoredIMDP`, solved by
:mod:`robust_imdp.solvers.factored`. It applies when

* the cells are a rectilinear grid (a :class:`~robust_imdp.models.geometry.Partition`; refined
  ``BoxPartition`` cells are no product of per-axis intervals),
* the transition bounds are the exact per-axis integrals (``transitions = "exact"``; Thm 1's containment
  events are joint),
* the noise's components are independent (``combine = "product"``; every ``NoiseModel`` is, but
  ``"union"`` asks for no independence, and then only Frechet's joint bounds hold),
* the image boxes are deterministic (known dynamics, the RKHS route, or the GP route with its error
  folded into the boxes, ``guarantee = "confidence"``): with ``guarantee = "paper"`` the GP error event
  ``E_g`` mixes two laws, which is no product.

Why the product set is sound there: for ``x`` in cell q the next state is ``y + v`` with ``y = f_u(x)`` in the
image box ``Y = prod_i Y_i`` and ``v`` with independent components, so its law is ``prod_i law(y_i + v_i)``
and each factor lies in the interval set ``P_i(u, q)`` of :func:`~robust_imdp.abstraction.marginals.axis_data`
(the min and max over ``Y_i``). :func:`factored_reason` says why the form does not apply, in words.

Chunks. The rows of a cell depend only on its own image box, the grid and one listed length ``k_i`` per axis
(every row lists ``k_i`` intervals: its own run, widened inside the grid). :func:`axis_lengths` computes the
``k_i`` over all cells first (cheap: the runs only), then :func:`factored_rows` computes any chunk of cells
with them and :func:`assemble_factored` concatenates the chunks: the same bytes as
:func:`~robust_imdp.abstraction.marginals.axis_marginals` in one pass (tested).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robust_imdp._fp import down, up
from robust_imdp.abstraction.cell_bounds import CellBounds
from robust_imdp.abstraction.marginals import AXIS_TOL, axis_data, axis_runs
from robust_imdp.errors import DimensionError, InvalidInputError, InvalidModelError
from robust_imdp.models.factored import AXIS_ARRAYS, AxisMarginals, FactoredIMDP, save_npz
from robust_imdp.models.geometry import Partition, partition_from_dict
from robust_imdp.models.noise import NoiseModel

__all__ = ["FORMS", "FactoredAbstraction", "FactoredRows", "factored_reason", "row_sizes", "axis_lengths",
           "factored_rows", "assemble_factored", "replace_cells", "abstract_factored", "abstraction_model",
           "is_factored", "is_factored_file"]

#: ``[abstraction].form``: the factored model where it applies ("auto"), always ("factored"), or never ("joint").
FORMS = ("auto", "factored", "joint")
#: Format of :meth:`FactoredAbstraction.save`'s meta record (the arrays are those of ``FactoredIMDP.save``).
_META_FORMAT = "robust_imdp.FactoredAbstraction/1"


def factored_reason(partition, noise, *, transitions: str = "exact", combine: str = "product",
                    error_models=None) -> str | None:
    """Why the factored form does not apply to these inputs, or None when it does (module docstring).

    Parameters
    ----------
    partition : Partition or BoxPartition
    noise : NoiseModel
    transitions : {"thm1", "exact"}
    combine : {"product", "union"}
    error_models : optional
        The GP route's error models that the abstraction mixes in (``guarantee = "paper"``); None when the
        image boxes hold the whole error.

    Returns
    -------
    str or None
        A sentence naming the setting that rules the form out.
    """
    if not isinstance(partition, Partition):
        return (f"the cells are a {type(partition).__name__} (refined boxes), not a grid: a refined cell's successors "
                "are no product of per-axis intervals")
    if transitions != "exact":
        return (f"transitions = {transitions!r}: Thm 1's bounds are containment events of the joint image, not "
                "per-axis marginals (the factored form needs transitions = 'exact')")
    if combine != "product":
        return (f"combine = {combine!r} assumes no independence between the noise's components: only Frechet's "
                "joint bounds hold, not a product of per-axis laws")
    if not isinstance(noise, NoiseModel):
        return f"the noise model {type(noise).__name__} does not state independent components"
    if error_models is not None:
        return ("the GP route with guarantee = 'paper' mixes the laws on and off the GP error event (the P_g "
                "mixture), which is no product of per-axis laws")
    return None


def row_sizes(space_lower, space_upper, cell_size, noise, *, tol: float = AXIS_TOL,
              floor_level: float = 5e-8) -> tuple:
    """``(joint entries, factored numbers)`` per row, estimated on one cell before any bound is known.

    A cell of ``cell_size`` whose image is a box of the same size, on grid intervals of ``cell_size`` around it
    (``pipeline.preflight.exact_successors``' model): the joint exact rows list the successors whose product of
    per-axis upper bounds exceeds the rows' least floor ``floor_level`` (``floor_tol / 20`` at the default
    ``floor_tol``; counted axis by axis, since a product of factors <= 1 stays below the floor once a partial
    product is), capped by the grid; the factored rows store ``sum_i (2 k_i + 4)`` numbers, ``k_i`` the intervals
    meeting the image widened by the listing radius of ``tol`` on each side (at its worst against the grid).
    """
    from robust_imdp.abstraction.marginals import interval_bounds

    h = np.asarray(cell_size, float).reshape(-1)
    lo, hi = np.asarray(space_lower, float).reshape(-1), np.asarray(space_upper, float).reshape(-1)
    h = np.broadcast_to(h, lo.shape)
    R_f = np.asarray(noise.listing_radius(floor_level), float)
    R_k = np.asarray(noise.listing_radius(tol), float)
    partial = np.ones(1)
    numbers = 0
    for j in range(lo.size):
        n_j = max(int(round((hi[j] - lo[j]) / h[j])), 1)
        K = int(min(np.ceil(R_f[j] / h[j]) + 2, n_j))
        t = np.arange(-K, K + 1)
        _, up_j = interval_bounds(noise, j, 0.0, h[j], t * h[j], (t + 1) * h[j])
        up_j = np.sort(up_j)[::-1][:n_j]
        prod = (partial[:, None] * up_j[None, :]).ravel()
        partial = prod[prod > floor_level] if partial.size else partial
        numbers += 2 * int(min(n_j, np.ceil((h[j] + 2 * R_k[j]) / h[j]) + 1)) + 4
    return int(max(partial.size, 1)), int(numbers)


def is_factored(abstraction) -> bool:
    """Whether ``abstraction`` is a :class:`FactoredAbstraction` (else a joint ``abstraction.rows.Abstraction``)."""
    return isinstance(abstraction, FactoredAbstraction)


def abstraction_model(abstraction):
    """The model an abstraction's synthesis solves: the ``FactoredIMDP`` of a factored abstraction, the ``IMDP``
    of a joint one."""
    return abstraction.model if is_factored(abstraction) else abstraction.imdp


# --------------------------------------------------------------------------- the abstraction
@dataclass(frozen=True, eq=False)
class FactoredAbstraction:
    """The factored abstraction of a grid (the counterpart of ``abstraction.rows.Abstraction``).

    Attributes
    ----------
    model : FactoredIMDP
        States: the grid's cells (C order), then the outside state ``n_cells``; choice = mode.
    partition : Partition
        The grid (``model.shape == partition.shape``).
    tol : float
        The listing tolerance of the marginals (``marginals.AXIS_TOL``).
    combine, transitions : str
        Always ``"product"`` and ``"exact"`` (what the form needs; kept for the code that reads them from
        either kind of abstraction).
    """

    model: FactoredIMDP
    partition: Partition
    tol: float = AXIS_TOL
    combine: str = "product"
    transitions: str = "exact"

    form = "factored"

    def __post_init__(self):
        if not isinstance(self.model, FactoredIMDP):
            raise InvalidInputError(f"model must be a FactoredIMDP; got {type(self.model).__name__}")
        if not isinstance(self.partition, Partition):
            raise InvalidInputError(f"partition must be a Partition (a grid); got {type(self.partition).__name__}")
        if tuple(self.model.shape) != tuple(self.partition.shape):
            raise DimensionError(f"model.shape {tuple(self.model.shape)} must equal the partition's shape "
                                 f"{tuple(self.partition.shape)}")
        if tuple(self.model.periodic) != tuple(self.partition.periodic or (False,) * self.partition.dim):
            raise DimensionError(f"model.periodic {self.model.periodic} must equal the partition's periodic axes "
                                 f"{self.partition.periodic}")

    @property
    def n_modes(self) -> int:
        return int(self.model.n_modes)

    @property
    def numbers_per_row(self) -> int:
        """Stored numbers per (cell, mode): ``sum_i (2 k_i + 4)``."""
        return self.model.numbers_per_row

    @property
    def entries_per_row(self) -> int:
        """Interval entries per (cell, mode): ``sum_i (k_i + 1)`` (the count the odIMDP literature reports)."""
        return self.model.entries_per_row

    @property
    def nnz_per_row(self) -> np.ndarray:
        """(n_choices,) int: :attr:`entries_per_row` for every cell's rows, 1 for the outside state's (the
        counterpart of ``Abstraction.nnz_per_row``, which the advice's cost model and the diagnostics sum)."""
        M, N = self.model.n_modes, self.model.n_cells
        return np.r_[np.full(M * N, self.entries_per_row, dtype=np.int64), np.ones(M, dtype=np.int64)]

    def joint_entries(self) -> int:
        """Stored entries of the joint expansion (:meth:`FactoredIMDP.to_joint`)."""
        return self.model.joint_entries()

    def to_joint(self, max_entries: int | None = None):
        """The joint ``IMDP`` containing every product law of the model (:meth:`FactoredIMDP.to_joint`: refused
        with a ``ResourceError`` above ``max_entries``)."""
        return self.model.to_joint() if max_entries is None else self.model.to_joint(max_entries)

    def row_upper(self, cell: int, mode: int, max_entries: int = 1_000_000):
        """``(cols, upper)``: the listed in-grid successors of row (cell, mode), each with the product of its
        per-axis upper bounds (an upper bound of its probability, as in :meth:`FactoredIMDP.to_joint`), then
        the outside state ``n_cells`` with ``1 - prod_i (1 - out_upper_i)`` (a float estimate; used to rank,
        e.g. by ``synthesis.suggest``). Refuses rows of more than ``max_entries`` joint entries."""
        m = self.model
        M, N = m.n_modes, m.n_cells
        if not (0 <= int(cell) < N and 0 <= int(mode) < M):
            raise InvalidInputError(f"(cell, mode) must lie in [0, {N}) x [0, {M}); got ({cell}, {mode})")
        size = int(np.prod(m.k))
        if size > max_entries:
            raise InvalidInputError(f"row ({cell}, {mode}) lists {size:,} joint successors (> max_entries = "
                                    f"{max_entries:,})")
        col = np.zeros(1, dtype=np.int64)
        upp = np.ones(1)
        ok = np.ones(1, dtype=bool)
        strides = np.cumprod((1,) + tuple(m.shape[::-1]))[:-1][::-1]
        out_in = 1.0
        for i, ax in enumerate(m.axes):
            pos = ax.positions()[mode, cell]
            col = (col[:, None] + np.maximum(pos, 0)[None, :] * int(strides[i])).ravel()
            upp = (upp[:, None] * ax.upper[mode, cell][None, :]).ravel()
            ok = (ok[:, None] & (pos >= 0)[None, :]).ravel()
            out_in *= 1.0 - float(ax.out_upper[mode, cell])
        return np.r_[col[ok], N], np.r_[np.minimum(upp[ok], 1.0), 1.0 - out_in]

    def __repr__(self) -> str:
        return (f"FactoredAbstraction({self.partition.n_cells} cells x {self.n_modes} modes, "
                f"{self.numbers_per_row} numbers per row, {self.model.nbytes / 2**20:.1f} MiB)")

    # ------------------------------------------------------------------ files
    def save(self, path) -> None:
        """Write an ``.npz`` file (no pickle): the model's arrays (as ``FactoredIMDP.save`` writes them, so
        ``FactoredIMDP.load`` reads the model back) and a JSON record of the partition; written beside the
        target and renamed into place."""
        meta = {"format": _META_FORMAT, "partition": self.partition.to_dict(), "tol": self.tol,
                "combine": self.combine, "transitions": self.transitions}
        save_npz(path, {**self.model.npz_arrays(), "abstraction_meta": np.array(json.dumps(meta))})

    @classmethod
    def load(cls, path) -> "FactoredAbstraction":
        """Read a file written by :meth:`save` (the model validated like its constructor).

        Raises
        ------
        InvalidModelError
            Naming the file when it is no factored abstraction (e.g. a joint ``Abstraction`` file).
        """
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z["abstraction_meta"])) if "abstraction_meta" in z.files else None
        except (OSError, ValueError) as exc:
            raise InvalidModelError(f"{path}: not a readable .npz file ({exc})") from None
        if meta is None or meta.get("format") != _META_FORMAT:
            raise InvalidModelError(f"{path}: not a factored abstraction (no '{_META_FORMAT}' record)")
        model = FactoredIMDP.load(path)
        return cls(model=model, partition=partition_from_dict(meta["partition"]), tol=float(meta["tol"]),
                   combine=meta["combine"], transitions=meta["transitions"])


def is_factored_file(path) -> bool:
    """Whether the ``.npz`` file at ``path`` holds a :class:`FactoredAbstraction` (reads only its key list)."""
    try:
        with np.load(Path(path), allow_pickle=False) as z:
            return "abstraction_meta" in z.files
    except (OSError, ValueError):
        return False


# --------------------------------------------------------------------------- building it, chunk by chunk
@dataclass(frozen=True, eq=False)
class FactoredRows:
    """The per-axis marginals of a chunk of cells (all modes): the unit of :func:`assemble_factored`.

    ``axes[j]`` is ``(start (M, c), lower (M, c, k_j), upper, out_lower (M, c), out_upper, rest_upper)`` for
    the chunk's ``c`` cells in cell order.
    """

    axes: tuple
    n_modes: int
    n_cells: int
    k: tuple
    tol: float


def _check(partition, cell_bounds, noise, tol):
    if not isinstance(partition, Partition):
        raise InvalidInputError(f"partition must be a Partition (a grid) for the factored form; got "
                                f"{type(partition).__name__}")
    if not isinstance(cell_bounds, CellBounds):
        raise InvalidInputError(f"cell_bounds must be a CellBounds; got {type(cell_bounds).__name__}")
    if cell_bounds.std_upper is not None:
        raise InvalidInputError("cell_bounds must have std_upper=None for the factored form (image boxes holding "
                                "the whole error; the GP route's P_g mixture is no product)")
    if cell_bounds.dim != partition.dim:
        raise DimensionError(f"cell_bounds must have dimension {partition.dim}; got {cell_bounds.dim}")
    if not isinstance(noise, NoiseModel) or noise.dim != partition.dim:
        raise InvalidInputError(f"noise must be a NoiseModel of dimension {partition.dim}; got "
                                f"{type(noise).__name__} of dimension {getattr(noise, 'dim', None)}")
    if not 0.0 < float(tol) < 1.0:
        raise InvalidInputError(f"tol must lie in (0, 1); got {tol!r}")


def _periodic(partition, j) -> bool:
    return partition.periodic is not None and bool(partition.periodic[j])


def _runs(partition, j, a, b, R):
    """``(first, count)`` of the listed run of axis ``j`` for image intervals ``[a, b]`` (the listing radius ``R``)."""
    return axis_runs(partition, j, down(a - R), up(b + R))


def axis_lengths(partition: Partition, cell_bounds: CellBounds, noise: NoiseModel, *, tol: float = AXIS_TOL) -> tuple:
    """The listed length ``k_j`` of every axis: the longest run over the cells and modes of ``cell_bounds``
    (``marginals.axis_marginals``' rule; at least 1). Give it the image boxes of ALL cells, then the same
    ``k`` to every chunk's :func:`factored_rows`."""
    _check(partition, cell_bounds, noise, tol)
    R = noise.listing_radius(tol)
    lo, hi = np.asarray(cell_bounds.image_lower, float), np.asarray(cell_bounds.image_upper, float)
    return tuple(int(max(1, _runs(partition, j, lo[:, :, j], hi[:, :, j], R[j])[1].max(initial=1)))
                 for j in range(partition.dim))


def factored_rows(partition: Partition, cell_bounds: CellBounds, noise: NoiseModel, k, *, tol: float = AXIS_TOL,
                  block_size: int = 65536) -> FactoredRows:
    """The per-axis marginals of the cells whose image boxes ``cell_bounds`` holds (a chunk), with listed
    lengths ``k`` (:func:`axis_lengths` of all cells).

    A pure function of its arguments: a row's start is its run widened to ``k_j`` inside the grid (to the left
    where it would pass the grid's end; ``marginals.axis_marginals``' rule), its bounds those of
    ``marginals.axis_data`` for that run (every bound sound for any listing, docs/abstraction.md).

    Raises
    ------
    InvalidInputError
        A run longer than its ``k_j`` (``k`` not from all the cells) or wrong inputs.
    """
    _check(partition, cell_bounds, noise, tol)
    k = tuple(int(v) for v in k)
    if len(k) != partition.dim or min(k) < 1:
        raise InvalidInputError(f"k must hold one listed length >= 1 per axis ({partition.dim}); got {k}")
    R = noise.listing_radius(tol)
    lo_all, hi_all = np.asarray(cell_bounds.image_lower, float), np.asarray(cell_bounds.image_upper, float)
    M, C, d = lo_all.shape
    axes = []
    for j in range(d):
        n, kj = partition.shape[j], k[j]
        if kj > n:
            raise InvalidInputError(f"k[{j}] = {kj} exceeds the {n} intervals of axis {j}")
        a, b = lo_all[:, :, j], hi_all[:, :, j]
        first, count = _runs(partition, j, a, b, R[j])
        if count.size and int(count.max()) > kj:
            raise InvalidInputError(f"axis {j}: a listed run of {int(count.max())} intervals exceeds k[{j}] = {kj} "
                                    "(pass the axis_lengths of all the cells)")
        start = first if _periodic(partition, j) else np.where(count > 0, np.minimum(first, n - kj),
                                                               np.clip(first, 0, n - kj))
        parts = [np.empty((M, C, kj)), np.empty((M, C, kj)), np.empty((M, C)), np.empty((M, C)), np.empty((M, C))]
        for c0 in range(0, C, block_size):
            sl = slice(c0, min(C, c0 + block_size))
            for arr, val in zip(parts, axis_data(partition, j, a[:, sl], b[:, sl], noise, start[:, sl],
                                                 np.full(start[:, sl].shape, kj), kj)):
                arr[:, sl] = val
        axes.append((start.astype(np.int64),) + tuple(parts))
    return FactoredRows(axes=tuple(axes), n_modes=M, n_cells=C, k=k, tol=float(tol))


def assemble_factored(partition: Partition, chunks) -> FactoredAbstraction:
    """Concatenate :func:`factored_rows` chunks (in cell order, covering every cell once) into the abstraction."""
    chunks = list(chunks)
    if not chunks:
        raise InvalidInputError("chunks must hold at least one FactoredRows; got none")
    first = chunks[0]
    if any(c.k != first.k or c.n_modes != first.n_modes for c in chunks):
        raise InvalidInputError("chunks must share the listed lengths k and the modes (k from axis_lengths of all "
                                f"cells); got {sorted({c.k for c in chunks})}")
    N = sum(c.n_cells for c in chunks)
    if N != partition.n_cells:
        raise DimensionError(f"chunks must cover the {partition.n_cells} cells of the partition once; got {N}")
    axes = []
    for j in range(partition.dim):
        arrays = {name: (np.concatenate([c.axes[j][t] for c in chunks], axis=1) if len(chunks) > 1
                         else first.axes[j][t]) for t, name in enumerate(AXIS_ARRAYS)}
        axes.append(AxisMarginals(n=partition.shape[j], periodic=_periodic(partition, j), axis=j, **arrays))
    return FactoredAbstraction(model=FactoredIMDP(shape=partition.shape, axes=tuple(axes)), partition=partition,
                               tol=first.tol)


def replace_cells(rows: FactoredRows, cells, new: FactoredRows) -> FactoredRows:
    """``rows`` (all cells of a grid) with the rows of ``cells`` (sorted indices) replaced by ``new`` (their
    :func:`factored_rows` with the same listed lengths): a row depends only on its own image box, so the result is
    what :func:`factored_rows` gives for all cells with the new boxes (the incremental loop, ``improve``)."""
    cells = np.asarray(cells, dtype=np.int64)
    if new.k != rows.k or new.n_modes != rows.n_modes or new.n_cells != cells.size:
        raise InvalidInputError(f"new must hold the rows of the {cells.size} cells with the same k {rows.k} and modes; "
                                f"got {new.n_cells} cells, k {new.k}")
    axes = []
    for old_ax, new_ax in zip(rows.axes, new.axes):
        arrays = [a.copy() for a in old_ax]
        for a, b in zip(arrays, new_ax):
            a[:, cells] = b
        axes.append(tuple(arrays))
    return FactoredRows(axes=tuple(axes), n_modes=rows.n_modes, n_cells=rows.n_cells, k=rows.k, tol=rows.tol)


def abstract_factored(partition: Partition, cell_bounds: CellBounds, noise: NoiseModel, *, tol: float = AXIS_TOL,
                      block_size: int = 65536) -> FactoredAbstraction:
    """The factored abstraction of a grid in one pass (:func:`axis_lengths`, :func:`factored_rows`,
    :func:`assemble_factored`)."""
    k = axis_lengths(partition, cell_bounds, noise, tol=tol)
    return assemble_factored(partition, [factored_rows(partition, cell_bounds, noise, k, tol=tol,
                                                       block_size=block_size)])
