r"""The nominal model: the cells' transitions under point dynamics, to rank modes where the guarantee does not.

Where the robust lower values of several modes tie -- often at 0, wherever the adversary of the
interval MDP can always force a failure -- the guarantee says nothing about which mode to use. The
synthesis then asks a *nominal* model (:mod:`robust_imdp.synthesis.ties`): the same cells and modes,
with the certified image boxes replaced by the images ``y_u(x) = f_u(x) + g_hat_u(x)`` of the data-fitted
dynamics (known part plus the kernel-ridge fit of the residuals, :mod:`robust_imdp.bounds.fit`) or of the
known dynamics, at a few points ``x_1 .. x_S`` of every cell (:func:`cell_points`), and the noise around
them. The nominal law of a cell is the mixture over its points (a state spread evenly over the cell)::

    T_nom(z | q, u) = (1/S) sum_s P[y_u(x_s) + v in z] = (1/S) sum_s prod_i P[y_{u,i}(x_s) + v_i in z_i].

Each term is what :func:`~robust_imdp.abstraction.exact_rows.exact_rows` computes for a degenerate image
box ``Y = {y}`` (lower = upper): per axis the certified noise integrals of
:mod:`robust_imdp.abstraction.marginals`, so every entry is a narrow interval around the point
probability (its rounding, the floor ``floor_tol / 20`` of the unlisted cells, the outside state's mass).
The mixture averages the intervals (an unlisted cell counts 0 below and the floor above), rounded outward,
so they contain the mixture's probabilities and every row satisfies ``sum(lower) <= 1 <= sum(upper) +
floor x unlisted``. Periodic axes, refined :class:`~robust_imdp.models.geometry.BoxPartition` cells and
every noise model work as in the robust abstraction.

Why several points and not only the centre: a cell's states do not all move like its centre. Next to an
obstacle, a drift of a fifth of a cell per step pushes a fifth of the cell into it at every step, which
the centre alone (moved back to the centre by the abstraction at every step) never shows; with a few points
per axis the mixture does, and the ranking avoids hugging the obstacle (benchmarks/controller_quality.py
measures it: on the 16 x 16 newcomer robot the centre alone gives about 0.70 of mean empirical
satisfaction, the mixture of 4 x 4 points more).

The factored form (:class:`~robust_imdp.models.factored.FactoredIMDP`, docs/factored.md): a point image's law is
a product of per-axis laws, so with one point per cell (the centre) the per-axis marginals at ``y``
(:func:`~robust_imdp.abstraction.marginals.axis_marginals` of the degenerate box) are the nominal model exactly
(``form="factored"``); a mixture of products is no product, and the factored form takes the centre.

What it is not: a bound. Nothing about the true system is claimed from it; it only orders modes whose
guaranteed values tie, and the synthesis evaluates the chosen strategy on the robust model, so the
reported ``p_low`` and ``p_up`` stay those of the robust abstraction.
"""

from __future__ import annotations

import numpy as np

from robust_imdp._fp import down, gamma, up
from robust_imdp.abstraction.cell_bounds import CellBounds
from robust_imdp.abstraction.exact_rows import exact_rows
from robust_imdp.abstraction.marginals import AXIS_TOL, axis_marginals
from robust_imdp.abstraction.rows import AbstractionRows, assemble_abstraction
from robust_imdp.errors import DimensionError, InvalidInputError
from robust_imdp.models.factored import FactoredIMDP
from robust_imdp.models.geometry import BoxPartition, Partition
from robust_imdp.models.noise import NoiseModel

__all__ = ["NOMINAL_FORMS", "NOMINAL_POINTS", "points_per_axis", "cell_points", "row_entries",
           "nominal_abstraction"]

#: The forms of :func:`nominal_abstraction`: the joint interval MDP, or the factored per-axis marginals.
NOMINAL_FORMS = ("joint", "factored")
#: About this many points per cell by default (:func:`points_per_axis`): 4 x 4 in 2-D, 2^d in 3-D and 4-D,
#: the centre alone from 5-D on.
NOMINAL_POINTS = 16
#: Point rows' entries built at once (memory only: the rows do not depend on it).
_BLOCK_ENTRIES = 1 << 21


def points_per_axis(dim: int, budget: int = NOMINAL_POINTS) -> int:
    """Points per axis of :func:`cell_points` for a ``dim``-dimensional cell: the largest ``s >= 1`` with
    ``s ** dim <= budget``."""
    if dim < 1 or budget < 1:
        raise InvalidInputError(f"dim and budget must be >= 1; got {dim!r} and {budget!r}")
    s = max(1, int(np.floor(budget ** (1.0 / dim) + 1e-9)))
    while s ** dim > budget and s > 1:
        s -= 1
    return s


def row_entries(partition, noise: NoiseModel, per_axis: int = 1) -> int:
    """About the most entries of one row of :func:`nominal_abstraction` (an upper estimate, for memory):
    per axis the cells met by the points' spread ``(1 - 1/s)`` of the narrowest cell width plus twice the
    noise's listing radius, the product over the axes, plus the outside state."""
    lo, hi = np.asarray(partition.cells_lower, float), np.asarray(partition.cells_upper, float)
    w = np.min(hi - lo, axis=0)
    R = np.asarray(noise.listing_radius(AXIS_TOL), float)
    span = (1.0 - 1.0 / per_axis) * w + 2.0 * R
    return int(np.prod(np.floor(span / w) + 2.0)) + 1


def cell_points(partition, per_axis: int = 1) -> np.ndarray:
    """Evenly spread points of every cell: ``(n_cells, per_axis ** d, d)``.

    The midpoints of a ``per_axis^d`` grid of equal sub-boxes of the cell (offsets ``(2 i + 1) / (2 s)`` of
    its width per axis): the centre for ``per_axis = 1``, and in general the midpoint rule for the average
    over the cell.
    """
    if not isinstance(partition, (Partition, BoxPartition)):
        raise InvalidInputError(f"partition must be a Partition or a BoxPartition; got {type(partition).__name__}")
    if isinstance(per_axis, bool) or not isinstance(per_axis, (int, np.integer)) or per_axis < 1:
        raise InvalidInputError(f"per_axis must be an int >= 1; got {per_axis!r}")
    lo = np.asarray(partition.cells_lower, float)
    hi = np.asarray(partition.cells_upper, float)
    d = lo.shape[1]
    f = (2.0 * np.arange(per_axis) + 1.0) / (2.0 * per_axis)
    offs = np.stack(np.meshgrid(*[f] * d, indexing="ij"), axis=-1).reshape(-1, d)  # (S, d)
    return lo[:, None, :] + offs[None, :, :] * (hi - lo)[:, None, :]


def nominal_abstraction(partition, images, noise: NoiseModel, *, form: str = "joint", floor_tol: float = 1e-6):
    """The nominal model of ``partition``: the noise around point images, averaged over each cell's points.

    Parameters
    ----------
    partition : Partition or BoxPartition
        The robust abstraction's cells (same order): the nominal model has its states and choices.
    images : (n_modes, n_cells, n_points, d) or (n_modes, n_cells, d) float array
        The images of every cell's points (:func:`cell_points`) under every mode; the second form is one
        point per cell.
    noise : NoiseModel
        The additive noise (dimension d).
    form : {"joint", "factored"}
        An :class:`~robust_imdp.abstraction.rows.Abstraction` (its ``imdp`` has the robust IMDP's states and
        choices: cells, then the outside state, one choice per mode), or, on a grid with one point per cell, the
        :class:`~robust_imdp.models.factored.FactoredIMDP` of the per-axis marginals itself.
    floor_tol : float in (0, 1)
        As in :func:`~robust_imdp.abstraction.rows.abstract` (exact transitions: entries below
        ``floor_tol / 20`` are not listed).

    Returns
    -------
    Abstraction, or FactoredIMDP

    Raises
    ------
    DimensionError
        ``images`` does not hold the partition's cells and dimension.
    InvalidInputError
        Non-finite images, an unknown form, several points per cell with ``form="factored"``.
    """
    if form not in NOMINAL_FORMS:
        raise InvalidInputError(f"form must be one of {', '.join(NOMINAL_FORMS)}; got {form!r}")
    if not isinstance(noise, NoiseModel):
        raise InvalidInputError(f"noise must be a NoiseModel; got {type(noise).__name__}")
    y = np.array(images, dtype=np.float64)
    if y.ndim == 3:
        y = y[:, :, None, :]
    N, d = partition.n_cells, partition.dim
    if y.ndim != 4 or y.shape[1] != N or y.shape[3] != d or y.shape[0] < 1 or y.shape[2] < 1:
        raise DimensionError(f"images must have shape (n_modes, {N}, n_points, {d}) or (n_modes, {N}, {d}) (the "
                             f"point images of every mode and cell); got {np.shape(images)}")
    if not np.all(np.isfinite(y)):
        u, q, s, i = (int(v) for v in np.argwhere(~np.isfinite(y))[0])
        raise InvalidInputError(f"images must be finite; got {y[u, q, s, i]} at mode {u}, cell {q}, point {s}, "
                                f"dimension {i + 1}")
    if form == "factored":
        if y.shape[2] != 1:
            raise InvalidInputError(f"form='factored' takes one point per cell (a mixture is no product); got "
                                    f"{y.shape[2]}")
        if not isinstance(partition, Partition):
            raise InvalidInputError(f"form='factored' needs a grid (a Partition); got {type(partition).__name__}")
        return FactoredIMDP(shape=partition.shape, axes=axis_marginals(partition, y[:, :, 0], y[:, :, 0], noise))
    M, S = y.shape[0], y.shape[2]
    step = max(1, _BLOCK_ENTRIES // (M * S * row_entries(partition, noise)))
    chunks = [_mixture_chunk(partition, y[:, c0:c0 + step], noise, floor_tol) for c0 in range(0, N, step)]
    return assemble_abstraction(partition, chunks)


def _mixture_chunk(partition, y, noise, floor_tol) -> AbstractionRows:
    """The rows of a chunk of cells (images ``y`` (M, k, S, d)): per point the exact rows of the degenerate
    box, then their average (module docstring)."""
    M, k, S, d = y.shape
    parts = [exact_rows(partition, CellBounds(y[:, :, s], y[:, :, s]), noise, floor_level=floor_tol / 20)
             for s in range(S)]
    R = M * k
    if S == 1:
        ex = parts[0]
        row_len, col, lower, upper, floor = ex.row_len, ex.col, ex.lower, ex.upper, ex.floor
    else:
        n_col = partition.n_cells + 1
        rid = np.concatenate([np.repeat(np.arange(R), ex.row_len) for ex in parts])
        key = rid * n_col + np.concatenate([ex.col for ex in parts])
        keys, inv = np.unique(key, return_inverse=True)  # sorted: rows in order, columns sorted in each row
        floor_sum = np.sum([ex.floor for ex in parts], axis=0)  # (R,)
        row = keys // n_col
        # an unlisted cell of a point's row counts 0 below and that row's floor above: the mean of the upper
        # bounds is (sum of the listed uppers + sum of the floors of the points that do not list it) / S
        lo_sum = np.bincount(inv, weights=np.concatenate([ex.lower for ex in parts]), minlength=keys.size)
        up_listed = np.bincount(inv, weights=np.concatenate([ex.upper for ex in parts]), minlength=keys.size)
        fl_listed = np.bincount(inv, weights=np.concatenate([np.repeat(ex.floor, ex.row_len) for ex in parts]),
                                minlength=keys.size)
        every = np.bincount(inv, minlength=keys.size) == S  # listed at every point: no floor term
        fl_row = np.where(every, 0.0, floor_sum[row])
        up_sum = up_listed + np.maximum(fl_row - fl_listed, 0.0)
        # rounding: sums of at most S non-negative terms, one subtraction, one addition and the division by S;
        # gamma(S + 3) of the terms' magnitudes bounds every error, then one ulp outward
        lower = np.maximum(down(lo_sum / S, gamma(S + 1) * lo_sum / S), 0.0)
        upper = np.minimum(up(up_sum / S, gamma(S + 3) * (up_listed + 2.0 * fl_row) / S), 1.0)
        floor = np.where(floor_sum > 0, np.minimum(up(floor_sum / S, gamma(S + 1) * floor_sum / S), 1.0), 0.0)
        row_len = np.bincount(row, minlength=R).astype(np.int64)
        col = (keys % n_col).astype(np.int64)
    nan = np.full((M, k, d), np.nan)
    return AbstractionRows(
        row_len=row_len, col=col, lower=lower, upper=upper, floor=floor, lower_eps=nan, lower_eta=nan.copy(),
        containing=np.full((M, k), -1, dtype=np.int64), floor_eps=nan.copy(), floor_eta=nan.copy(), n_modes=M,
        eps_rule="optimized", combine="product", eta=None, floor_tol=float(floor_tol), transitions="exact")
