"""The factored (orthogonally decoupled) interval MDP: one interval vector per axis and (mode, cell).

On a uniform grid (a :class:`~robust_imdp.models.geometry.Partition`'s ``shape``, cells in C
order, flat index ``np.ravel_multi_index(idx, shape)``) the next state's axes are independent
when the image of a cell is a box and the noise is a product: from cell q under mode u the law
of the next cell is ``p = p_0 x p_1 x ... x p_{d-1}``, where ``p_i`` is the law of axis i's next
interval, extended by two more outcomes, "outside X's range on axis i" and "an in-grid interval
that is not listed".  :class:`AxisMarginals` stores per (mode, cell) the bounds of ``p_i``:

* ``lower[u, q, j] <= p_i(interval start[u, q] + j) <= upper[u, q, j]`` for the ``k`` listed
  intervals (periodic axes: index ``(start + j) mod n``; non-periodic: positions past ``n - 1``
  are not intervals and carry ``lower = upper = 0``);
* ``out_lower <= p_i(outside) <= out_upper`` (0 on a periodic axis);
* ``p_i(every in-grid interval not listed, in total) <= rest_upper`` (lower bound 0);
* ``sum(p_i) = 1``.

The joint law is the product; a joint outcome with any axis outside is the absorbing outside
state ``n_cells`` (docs/ARCHITECTURE.md's convention).  :class:`FactoredIMDP` holds one
:class:`AxisMarginals` per axis; its solver is :mod:`robust_imdp.solvers.factored`, the theory
is in docs/factored.md.  A row stores ``sum_i (2 k_i + 4)`` numbers (start, k lowers, k uppers,
the two outside bounds, the rest bound) instead of one interval per joint successor.

Invalid objects cannot exist: the constructors validate shapes, ``0 <= lower <= upper <= 1``
and each axis's feasibility ``sum(lower) + out_lower <= 1 <= sum(upper) + out_upper +
rest_upper`` (up to :data:`~robust_imdp.models.imdp.ROW_SUM_TOL`), naming the (mode, cell, axis)
and the amounts.  Nothing is repaired.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robust_imdp.errors import DimensionError, InvalidIntervalError, InvalidModelError, ResourceError
from robust_imdp.models.imdp import IMDP, ROW_SUM_TOL

__all__ = ["AxisMarginals", "FactoredIMDP", "MAX_JOINT_ENTRIES", "AXIS_ARRAYS", "save_npz"]

#: Largest number of stored entries :meth:`FactoredIMDP.to_joint` builds (about 1.2 GB of
#: arrays); beyond it the joint model is refused with a ``ResourceError`` rather than swapping.
MAX_JOINT_ENTRIES = 50_000_000

_U = 2.0 ** -53  # unit round-off of float64


def _gamma(n: int) -> float:
    """Higham's gamma_n = n u / (1 - n u): relative error of n roundings (ASNA, Lemma 3.1)."""
    return n * _U / (1.0 - n * _U)


def _down(x, rel):
    """A lower bound of the real ``x (1 + t)``, ``|t| <= rel``, for ``x >= 0``: one more ulp down."""
    return np.nextafter(np.asarray(x, float) * (1.0 - rel), -np.inf).clip(min=0.0)


def _up(x, rel):
    """An upper bound of the real ``x (1 + t)``, ``|t| <= rel``, for ``x >= 0``: one more ulp up."""
    return np.nextafter(np.asarray(x, float) * (1.0 + rel), np.inf)


def _frozen(a) -> np.ndarray:
    a = np.array(a, copy=True, order="C")
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class AxisMarginals:
    """Per (mode, cell) interval bounds of the marginal law of ONE axis of the next state.

    Attributes
    ----------
    n : int
        Grid intervals on this axis (``Partition.shape[i]``).
    periodic : bool
    start : (n_modes, n_cells) int64
        First listed grid interval on the axis, in ``[0, n)``.
    lower, upper : (n_modes, n_cells, k) float64
        Bounds of ``P(x'_i in interval (start + j))``, ``j < k``.  Non-periodic: ``start + j`` may
        run past ``n - 1``; such entries must have ``lower = upper = 0``.  Periodic: the interval
        is ``(start + j) mod n`` and ``k <= n`` (listed intervals distinct).
    out_lower, out_upper : (n_modes, n_cells) float64
        Bounds of ``P(x'_i outside X's range on axis i)``; both 0 on a periodic axis.
    rest_upper : (n_modes, n_cells) float64
        Upper bound of the TOTAL probability of the in-grid intervals not listed (their lower
        bounds are 0).
    axis : int, optional
        The axis these marginals belong to; only named in error messages (and checked by
        :class:`FactoredIMDP` when given).

    Raises
    ------
    DimensionError, InvalidModelError, InvalidIntervalError
        Naming the axis (when given), the array, the (mode, cell) and the amounts.
    """

    n: int
    periodic: bool
    start: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    out_lower: np.ndarray
    out_upper: np.ndarray
    rest_upper: np.ndarray
    axis: int | None = None

    def __post_init__(self):
        if self.axis is None:
            self._validate()
            return
        try:
            self._validate()
        except (DimensionError, InvalidModelError, InvalidIntervalError) as exc:
            raise type(exc)(f"axis {self.axis}: {exc}") from None

    def _validate(self):
        n = self.n
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise InvalidModelError(f"n (grid intervals on the axis) must be an int >= 1; got {n!r}")
        if not isinstance(self.periodic, (bool, np.bool_)):
            raise InvalidModelError(f"periodic must be a bool; got {self.periodic!r}")
        object.__setattr__(self, "n", int(n))
        object.__setattr__(self, "periodic", bool(self.periodic))
        lower = np.asarray(self.lower)
        if lower.ndim != 3:
            raise DimensionError(f"lower must have shape (n_modes, n_cells, k); got {lower.shape}")
        M, N, k = lower.shape
        arrays = {}
        for name in ("lower", "upper"):
            a = np.asarray(getattr(self, name))
            if a.shape != (M, N, k):
                raise DimensionError(f"{name} must have shape (n_modes, n_cells, k) = {(M, N, k)} like lower; "
                                     f"got {a.shape}")
            arrays[name] = a
        for name in ("start", "out_lower", "out_upper", "rest_upper"):
            a = np.asarray(getattr(self, name))
            if a.shape != (M, N):
                raise DimensionError(f"{name} must have shape (n_modes, n_cells) = {(M, N)}; got {a.shape}")
            arrays[name] = a
        st = arrays["start"]
        if st.size and not np.issubdtype(st.dtype, np.integer):
            raise InvalidModelError(f"start must hold integers; got dtype {st.dtype}")
        for name in ("lower", "upper", "out_lower", "out_upper", "rest_upper"):
            a = arrays[name]
            if a.size and not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
                raise InvalidIntervalError(f"{name} must hold real numbers; got dtype {a.dtype}")
            arrays[name] = a.astype(np.float64)
        arrays["start"] = st.astype(np.int64)
        for name, a in arrays.items():
            object.__setattr__(self, name, _frozen(a))
        _check_axis(self)

    # ------------------------------------------------------------------ shape
    @property
    def n_modes(self) -> int:
        return int(self.lower.shape[0])

    @property
    def n_cells(self) -> int:
        return int(self.lower.shape[1])

    @property
    def k(self) -> int:
        """Listed intervals per (mode, cell)."""
        return int(self.lower.shape[2])

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays."""
        return int(sum(getattr(self, a).nbytes for a in AXIS_ARRAYS))

    def positions(self) -> np.ndarray:
        """(n_modes, n_cells, k) int64: grid interval of every listed entry (``(start + j) mod n`` on a
        periodic axis); ``-1`` where a non-periodic position runs past ``n - 1``."""
        p = self.start[..., None] + np.arange(self.k)
        if self.periodic:
            return p % self.n
        return np.where(p < self.n, p, -1)


#: The arrays of every axis of a model, in AxisMarginals' field order (what the files store per axis).
AXIS_ARRAYS = ("start", "lower", "upper", "out_lower", "out_upper", "rest_upper")


def _where(flat: int, N: int) -> str:
    u, q = divmod(int(flat), N)
    return f"(mode {u}, cell {q})"


def _check_axis(ax: AxisMarginals) -> None:
    """The checks of :class:`AxisMarginals` (module docstring); raises naming the (mode, cell)."""
    M, N, k = ax.lower.shape
    n = ax.n
    lo, up = ax.lower.reshape(M * N, k), ax.upper.reshape(M * N, k)
    st = ax.start.reshape(-1)
    bad = np.flatnonzero((st < 0) | (st >= n))
    if bad.size:
        r = int(bad[0])
        raise InvalidModelError(f"start{_where(r, N)} = {int(st[r])} is not a grid interval in [0, {n})")
    if ax.periodic and k > n:
        raise InvalidModelError(f"a periodic axis lists k <= n distinct intervals; got k = {k} > n = {n}")
    for name in ("lower", "upper"):
        a = getattr(ax, name).reshape(M * N, k)
        bad = np.argwhere(~np.isfinite(a))
        if bad.size:
            r, j = (int(x) for x in bad[0])
            raise InvalidIntervalError(f"{name}{_where(r, N)}[{j}] = {float(a[r, j])} is not finite")
    bad = np.argwhere((lo < 0) | (lo > up) | (up > 1))
    if bad.size:
        r, j = (int(x) for x in bad[0])
        raise InvalidIntervalError(f"{_where(r, N)}, listed entry {j} (interval start + {j}): [{float(lo[r, j])!r}, "
                                   f"{float(up[r, j])!r}] violates 0 <= lower <= upper <= 1")
    if not ax.periodic:
        past = st[:, None] + np.arange(k) >= n
        bad = np.argwhere(past & (up > 0))
        if bad.size:
            r, j = (int(x) for x in bad[0])
            raise InvalidIntervalError(f"{_where(r, N)}, listed entry {j}: position start + {j} = {int(st[r]) + j} "
                                       f"is past the last interval {n - 1} of a non-periodic axis and must have "
                                       f"lower = upper = 0; got upper {float(up[r, j])!r}")
    ol, ou, ru = (getattr(ax, a).reshape(-1) for a in ("out_lower", "out_upper", "rest_upper"))
    for name, a in (("out_lower", ol), ("out_upper", ou), ("rest_upper", ru)):
        bad = np.flatnonzero(~np.isfinite(a) | (a < 0) | (a > 1))
        if bad.size:
            r = int(bad[0])
            raise InvalidIntervalError(f"{name}{_where(r, N)} = {float(a[r])!r} must be a finite number in [0, 1]")
    bad = np.flatnonzero(ol > ou)
    if bad.size:
        r = int(bad[0])
        raise InvalidIntervalError(f"{_where(r, N)}: out_lower {float(ol[r])!r} > out_upper {float(ou[r])!r}")
    if ax.periodic:
        bad = np.flatnonzero(ou > 0)
        if bad.size:
            r = int(bad[0])
            raise InvalidIntervalError(f"{_where(r, N)}: a periodic axis has no outside; out_upper must be 0, got "
                                       f"{float(ou[r])!r}")
    s_lo = lo.sum(axis=1) + ol
    bad = np.flatnonzero(s_lo > 1.0 + ROW_SUM_TOL)
    if bad.size:
        r = int(bad[0])
        raise InvalidIntervalError(f"{_where(r, N)}: sum of lower bounds {float(s_lo[r])!r} (listed + out_lower) > 1 "
                                   f"(excess {s_lo[r] - 1:.3g})")
    s_up = up.sum(axis=1) + ou + ru
    bad = np.flatnonzero(s_up < 1.0 - ROW_SUM_TOL)
    if bad.size:
        r = int(bad[0])
        raise InvalidIntervalError(f"{_where(r, N)}: sum of upper bounds {float(s_up[r])!r} (listed + out_upper + "
                                   f"rest_upper) < 1 (deficit {1 - s_up[r]:.3g})")


@dataclass(frozen=True, eq=False)
class FactoredIMDP:
    """An interval MDP on a uniform grid whose transition laws are products of per-axis laws.

    States: the cells ``0 .. n_cells - 1`` (C order over ``shape``) and the absorbing outside
    state ``n_cells``; every cell has one choice per mode (choice index = mode index).

    Parameters
    ----------
    shape : tuple of int
        Grid intervals per axis (``Partition.shape``); ``n_cells = prod(shape)``.
    axes : sequence of AxisMarginals
        One per axis, ``axes[i].n == shape[i]``, all of the same ``(n_modes, n_cells)``.
    n_modes, n_cells : int, optional
        Checked against the arrays when given.

    Raises
    ------
    DimensionError, InvalidModelError, InvalidIntervalError
        Naming the axis, the (mode, cell) and the amounts.

    Example
    -------
    A 1-D grid of 2 cells, one mode: from every cell the next interval is 0 with probability
    in [0.5, 0.7], interval 1 in [0.2, 0.4], outside in [0, 0.1]:

    >>> import numpy as np
    >>> ax = AxisMarginals(n=2, periodic=False, start=np.zeros((1, 2), int),
    ...                    lower=np.tile([0.5, 0.2], (1, 2, 1)), upper=np.tile([0.7, 0.4], (1, 2, 1)),
    ...                    out_lower=np.zeros((1, 2)), out_upper=np.full((1, 2), 0.1), rest_upper=np.zeros((1, 2)))
    >>> m = FactoredIMDP(shape=(2,), axes=(ax,))
    >>> m.n_states, m.entries_per_row, m.to_joint().n_states
    (3, 3, 3)
    """

    shape: tuple
    axes: tuple
    n_modes: int | None = None
    n_cells: int | None = None

    def __post_init__(self):
        try:
            shape = tuple(int(s) for s in self.shape)
        except (TypeError, ValueError):
            raise InvalidModelError(f"shape must be a tuple of ints (grid intervals per axis); got {self.shape!r}") from None
        if not shape or min(shape) < 1:
            raise InvalidModelError(f"shape must be a non-empty tuple of ints >= 1; got {shape}")
        axes = tuple(self.axes)
        if len(axes) != len(shape):
            raise DimensionError(f"axes must hold one AxisMarginals per axis of shape {shape} ({len(shape)}); "
                                 f"got {len(axes)}")
        N = int(np.prod(shape))
        M = None
        for i, ax in enumerate(axes):
            if not isinstance(ax, AxisMarginals):
                raise InvalidModelError(f"axes[{i}] must be an AxisMarginals; got {type(ax).__name__}")
            if ax.axis is not None and ax.axis != i:
                raise InvalidModelError(f"axes[{i}] says it is the marginals of axis {ax.axis}")
            if ax.n != shape[i]:
                raise DimensionError(f"axes[{i}].n = {ax.n} must equal shape[{i}] = {shape[i]}")
            if ax.n_cells != N:
                raise DimensionError(f"axes[{i}] must cover n_cells = prod(shape) = {N} cells; got {ax.n_cells}")
            if M is None:
                M = ax.n_modes
            elif ax.n_modes != M:
                raise DimensionError(f"axes[{i}] has {ax.n_modes} modes; axes[0] has {M}")
        if M < 1:
            raise DimensionError("a FactoredIMDP needs at least one mode; got n_modes = 0")
        for name, want in (("n_modes", M), ("n_cells", N)):
            got = getattr(self, name)
            if got is not None and int(got) != want:
                raise DimensionError(f"{name} = {got!r} disagrees with the arrays ({want})")
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "axes", axes)
        object.__setattr__(self, "n_modes", int(M))
        object.__setattr__(self, "n_cells", N)

    # ------------------------------------------------------------------ sizes
    @property
    def dim(self) -> int:
        return len(self.shape)

    @property
    def n_states(self) -> int:
        """Cells plus the outside state."""
        return self.n_cells + 1

    @property
    def outside_state(self) -> int:
        return self.n_cells

    @property
    def periodic(self) -> tuple:
        return tuple(ax.periodic for ax in self.axes)

    @property
    def k(self) -> tuple:
        """Listed intervals per axis."""
        return tuple(ax.k for ax in self.axes)

    @property
    def entries_per_row(self) -> int:
        """``sum_i (k_i + 1)``: interval entries per (cell, mode), listed ones plus "outside" (the
        count the odIMDP literature reports, e.g. 28 on BAS-4D)."""
        return int(sum(ax.k + 1 for ax in self.axes))

    @property
    def numbers_per_row(self) -> int:
        """``sum_i (2 k_i + 4)``: stored numbers per (cell, mode) (start, lowers, uppers, the two
        outside bounds, the rest bound)."""
        return int(sum(2 * ax.k + 4 for ax in self.axes))

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays."""
        return int(sum(ax.nbytes for ax in self.axes))

    def __repr__(self) -> str:
        return (f"FactoredIMDP(shape={self.shape}, n_modes={self.n_modes}, k={self.k}, periodic={self.periodic}, "
                f"memory={self.nbytes / 2**20:.1f} MiB)")

    # ------------------------------------------------------------------ joint expansion
    def joint_entries(self) -> int:
        """Number of stored entries :meth:`to_joint` would build (listed in-grid box entries and the
        outside entry of every row, plus the outside state's self-loop)."""
        R = self.n_modes * self.n_cells
        valid = np.ones(R, dtype=np.int64)
        for ax in self.axes:
            valid = valid * (ax.positions() >= 0).reshape(R, -1).sum(axis=1)
        return int(valid.sum() + R + 1)

    def to_joint(self, max_entries: int = MAX_JOINT_ENTRIES) -> IMDP:
        """The joint interval MDP whose rows contain every product law of this model.

        Row (cell q, mode u) lists every in-grid joint successor of the listed box and the outside
        state; the other cells are unlisted with the row's ``floor``.  The outside state
        ``n_cells`` has one self-loop row.  Each bound is sound, i.e. holds for every product
        ``p = p_0 x ... x p_{d-1}`` of per-axis laws in this model's sets (docs/factored.md):

        * listed cell ``z``: ``p(z) = prod_i p_i(z_i)`` with ``lower_i <= p_i(z_i) <= upper_i``, so
          ``prod_i lower_i <= p(z) <= prod_i upper_i`` (products of non-negative bounds are
          monotone), rounded down / up by ``gamma(d)``;
        * outside: ``p(outside) = 1 - prod_i P(in_i)`` with ``P(in_i) = 1 - p_i(outside)``, and
          ``P(in_i)`` is the listed plus the unlisted mass, so ``max(1 - out_upper_i,
          sum lower_i) <= P(in_i) <= min(1 - out_lower_i, sum upper_i + rest_upper_i)``; then
          ``1 - prod(in_hi) <= p(outside) <= 1 - prod(in_lo)`` (each sum and product rounded
          outward, the subtraction one ulp outward);
        * unlisted cell ``z`` (some axis i has ``z_i`` not listed): ``p_i(z_i) <= rest_upper_i``
          (one unlisted interval holds at most the unlisted total) and ``p_j(z_j) <= m_j`` for
          the others, ``m_j`` the largest listed upper bound or ``rest_upper_j``; so the floor
          ``max_i rest_upper_i prod_{j != i} m_j`` (over axes that have unlisted intervals,
          rounded up by ``gamma(d)``) bounds every unlisted cell.

        Clamps to [0, 1] are safe: every bound is a bound of a probability.

        Parameters
        ----------
        max_entries : int
            Refuse (``ResourceError``) models with more stored entries than this.

        Returns
        -------
        IMDP
            ``n_cells + 1`` states, ``n_modes`` choices per cell in mode order.
        """
        entries = self.joint_entries()
        if entries > max_entries:
            raise ResourceError(f"the joint expansion of this FactoredIMDP has {entries:,} entries (> max_entries = "
                                f"{max_entries:,}); solve it factored (robust_imdp.solvers.factored)")
        d, M, N = self.dim, self.n_modes, self.n_cells
        R = M * N  # rows in mode-major order here; reordered to cell-major below
        g_rel = _gamma(d + 1)
        pos, lo, up, inlo, inhi, m_side, has_rest = [], [], [], [], [], [], []
        for ax in self.axes:
            p = ax.positions().reshape(R, ax.k)
            l = np.where(p >= 0, ax.lower.reshape(R, ax.k), 0.0)
            h = np.where(p >= 0, ax.upper.reshape(R, ax.k), 0.0)
            pos.append(p)
            lo.append(l)
            up.append(h)
            ol, ou, ru = (getattr(ax, a).reshape(R) for a in ("out_lower", "out_upper", "rest_upper"))
            # P(in_i) bounds (see the docstring): sums of k non-negative terms err by gamma(k) relatively
            s_lo = _down(l.sum(axis=1), _gamma(ax.k + 1))
            s_hi = _up(h.sum(axis=1) + ru, _gamma(ax.k + 2))
            inlo.append(np.clip(np.maximum(np.nextafter(1.0 - ou, -np.inf), s_lo), 0.0, 1.0))
            inhi.append(np.clip(np.minimum(np.nextafter(1.0 - ol, np.inf), s_hi), 0.0, 1.0))
            n_listed = (p >= 0).sum(axis=1) if not ax.periodic else np.full(R, ax.k)
            unl = (n_listed < ax.n) & (ru > 0)  # the axis has unlisted in-grid intervals that may get mass
            has_rest.append(unl)
            m_side.append(np.maximum(h.max(axis=1, initial=0.0), np.where(unl, ru, 0.0)))
        # listed box: outer products over the axes, shape (R, k_0, ..., k_{d-1})
        col = np.zeros((R,) + (1,) * d, dtype=np.int64)
        valid = np.ones((R,) + (1,) * d, dtype=bool)
        plo = np.ones((R,) + (1,) * d)
        phi = np.ones((R,) + (1,) * d)
        strides = np.cumprod((1,) + self.shape[::-1])[:-1][::-1]  # C-order strides of the grid
        for i in range(d):
            view = [R] + [1] * d
            view[i + 1] = self.k[i]
            p = pos[i].reshape(view)
            col = col + np.maximum(p, 0) * int(strides[i])
            valid = valid & (p >= 0)
            plo = plo * lo[i].reshape(view)
            phi = phi * up[i].reshape(view)
        full = (R,) + self.k
        col = np.broadcast_to(col, full).reshape(R, -1)
        valid = np.broadcast_to(valid, full).reshape(R, -1)
        plo = np.broadcast_to(_down(plo, g_rel), full).reshape(R, -1)
        phi = np.broadcast_to(np.minimum(_up(phi, g_rel), 1.0), full).reshape(R, -1)
        # outside: 1 - prod(in_hi) <= p(out) <= 1 - prod(in_lo)
        prod_hi = _up(np.prod(np.stack(inhi), axis=0), g_rel).clip(max=1.0)
        prod_lo = _down(np.prod(np.stack(inlo), axis=0), g_rel)
        out_lo = np.clip(np.nextafter(1.0 - prod_hi, -np.inf), 0.0, 1.0)
        out_hi = np.clip(np.nextafter(1.0 - prod_lo, np.inf), 0.0, 1.0)
        # floor of the unlisted cells
        floor = np.zeros(R)
        for i in range(d):
            others = np.ones(R)
            for j in range(d):
                if j != i:
                    others = others * m_side[j]
            ru = self.axes[i].rest_upper.reshape(R)
            floor = np.maximum(floor, np.where(has_rest[i], ru * others, 0.0))
        floor = np.minimum(_up(floor, g_rel), 1.0) * (floor > 0)
        # rows in cell-major order (state q has its modes' rows in mode order)
        order = np.arange(R).reshape(M, N).T.reshape(-1)
        col, valid, plo, phi = col[order], valid[order], plo[order], phi[order]
        out_lo, out_hi, floor = out_lo[order], out_hi[order], floor[order]
        cnt = valid.sum(axis=1) + 1
        row_ptr = np.zeros(R + 2, dtype=np.int64)
        np.cumsum(np.r_[cnt, 1], out=row_ptr[1:])
        rr, jj = np.nonzero(valid)
        # per row: the listed cells (in box order), then the outside entry
        c_all = np.empty(row_ptr[-1], dtype=np.int64)
        l_all = np.empty(row_ptr[-1])
        h_all = np.empty(row_ptr[-1])
        within = np.arange(rr.size) - np.repeat(np.r_[0, np.cumsum(cnt - 1)][:-1], cnt - 1)
        dest = row_ptr[rr] + within
        c_all[dest], l_all[dest], h_all[dest] = col[rr, jj], plo[rr, jj], phi[rr, jj]
        last = row_ptr[1:R + 1] - 1
        c_all[last], l_all[last], h_all[last] = N, out_lo, out_hi
        c_all[-1], l_all[-1], h_all[-1] = N, 1.0, 1.0  # the outside state's self-loop
        state_ptr = np.r_[np.arange(0, R + 1, M), R + 1].astype(np.int64)
        return IMDP.from_csr(state_ptr, row_ptr, c_all, l_all, h_all, floor=np.r_[floor, 0.0],
                             actions=np.r_[np.tile(np.arange(M), N), 0])

    # ------------------------------------------------------------------ files
    def save(self, path) -> None:
        """Write the model to an ``.npz`` file (no pickle), atomically: a temporary file in the
        same folder renamed into place, so a failure leaves an older file as it was."""
        save_npz(path, self.npz_arrays())

    def npz_arrays(self) -> dict:
        """The arrays :meth:`save` writes (and :meth:`load` reads): format, shape, periodic, every axis's arrays."""
        arrays = {"format": np.array("robust_imdp.FactoredIMDP/1"), "shape": np.array(self.shape, dtype=np.int64),
                  "periodic": np.array(self.periodic, dtype=bool)}
        for i, ax in enumerate(self.axes):
            for a in AXIS_ARRAYS:
                arrays[f"axis{i}_{a}"] = getattr(ax, a)
        return arrays

    @classmethod
    def load(cls, path) -> "FactoredIMDP":
        """Read a file written by :meth:`save` (validated like the constructor).

        Raises
        ------
        InvalidModelError
            If the file is not such a file (the message names the file and what is missing).
        """
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except (OSError, ValueError) as exc:
            raise InvalidModelError(f"{path}: not a readable .npz file of a FactoredIMDP ({exc})") from None
        if "format" not in data or str(data["format"]) != "robust_imdp.FactoredIMDP/1":
            raise InvalidModelError(f"{path}: not a FactoredIMDP file (format 'robust_imdp.FactoredIMDP/1' expected; "
                                    f"got {str(data['format']) if 'format' in data else 'no format key'!r})")
        shape = tuple(int(s) for s in data["shape"])
        periodic = data["periodic"]
        axes = []
        for i in range(len(shape)):
            missing = [a for a in AXIS_ARRAYS if f"axis{i}_{a}" not in data]
            if missing:
                raise InvalidModelError(f"{path}: axis {i} lacks {', '.join(missing)}")
            try:
                axes.append(AxisMarginals(n=shape[i], periodic=bool(periodic[i]), axis=i,
                                          **{a: data[f"axis{i}_{a}"] for a in AXIS_ARRAYS}))
            except (InvalidModelError, InvalidIntervalError, DimensionError) as exc:
                raise type(exc)(f"{path}: {exc}") from None
        return cls(shape=shape, axes=tuple(axes))


def save_npz(path, arrays: dict) -> None:
    """``np.savez`` of ``arrays`` to ``path`` atomically: a temporary file in the same folder, flushed to disk and
    renamed into place, so a failure leaves an older file as it was."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent or ".")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
