"""The interval Markov decision process (IMDP) data type.

An IMDP has states ``0 .. n-1``; each state has one or more *choices* (state, action),
stored as rows of a CSR matrix grouped by state (the layout of Storm's sparse matrices):

* ``state_ptr`` (n+1,): the rows of state ``s`` are ``state_ptr[s] .. state_ptr[s+1]-1``;
* ``row_ptr`` (R+1,): the stored entries of row ``r`` are ``row_ptr[r] .. row_ptr[r+1]-1``;
* ``col``, ``lower``, ``upper`` (nnz,): successor state and its probability interval;
  lower and upper share one index structure;
* ``floor`` (R,): an upper bound that holds for every state *not* listed in the row (whose
  lower bound is 0).  This is the GP abstraction's shape: a few near successors plus a tiny
  uniform upper bound to every other state, at O(listed) memory instead of O(n).

Row ``r`` therefore describes the set of distributions
``{p : lower[j] <= p[col[j]] <= upper[j] for listed j, 0 <= p[q] <= floor[r] otherwise,
sum(p) = 1}``.  It is non-empty iff ``sum(lower) <= 1 <= sum(upper) + floor * n_unlisted``.

Invalid objects cannot exist: the constructors validate everything (vectorised, so they run
on 100k-state models) and raise errors from :mod:`robust_imdp.errors` that name the row,
the state and the amounts.  Nothing is repaired.
"""

from __future__ import annotations

import numpy as np

from robust_imdp.errors import DimensionError, InvalidIntervalError, InvalidModelError

#: Absolute tolerance of the two row-sum checks ``sum(lower) <= 1`` and
#: ``1 <= sum(upper) + floor * n_unlisted`` (and only of those).  Row sums of bounds that
#: were computed in floating point carry rounding errors of a few ulps per entry; 1e-12
#: accepts them for rows of up to ~10^3 entries while rejecting every real modelling error.
#: The solver never relies on the exact feasibility of a row: its sound error bounds treat a
#: negative remaining mass ``1 - sum(lower)`` as zero extra mass (see ``solve.py``).
ROW_SUM_TOL = 1e-12

_INDEX = np.int64


def _as_index_array(a, name: str) -> np.ndarray:
    arr = np.asarray(a)
    if arr.ndim != 1:
        raise DimensionError(f"{name} must be a 1-D integer array; got shape {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        if np.issubdtype(arr.dtype, np.floating) and np.all(np.isfinite(arr)) and np.all(arr == np.round(arr)):
            pass  # integral floats (e.g. from JSON) are accepted, not rounded
        else:
            raise InvalidModelError(f"{name} must hold integers; got dtype {arr.dtype}")
    return np.ascontiguousarray(arr, dtype=_INDEX)


def _as_float_array(a, name: str, length: int) -> np.ndarray:
    arr = np.asarray(a)
    if arr.ndim != 1 or arr.shape[0] != length:
        raise DimensionError(f"{name} must have shape ({length},); got {arr.shape}")
    if arr.size and not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise InvalidIntervalError(f"{name} must hold real numbers; got dtype {arr.dtype}")
    return np.ascontiguousarray(arr, dtype=np.float64)


def _check_ptr(ptr: np.ndarray, name: str, total: int, total_name: str, strict: bool) -> None:
    if ptr.shape[0] < 1 or ptr[0] != 0:
        raise InvalidModelError(f"{name} must start with 0; got {ptr[:1].tolist()}")
    if ptr[-1] != total:
        raise InvalidModelError(f"{name}[-1] must equal {total_name} = {total}; got {int(ptr[-1])}")
    d = np.diff(ptr)
    bad = np.flatnonzero(d <= 0) if strict else np.flatnonzero(d < 0)
    if bad.size:
        i = int(bad[0])
        if strict:
            raise InvalidModelError(
                f"{name} must be strictly increasing (every state needs at least one choice); "
                f"state {i} has {int(d[i])} choices"
            )
        raise InvalidModelError(f"{name} must be non-decreasing; {name}[{i + 1}] = {int(ptr[i + 1])} < {name}[{i}] = {int(ptr[i])}")


def _segment_sum(x: np.ndarray, ptr: np.ndarray) -> np.ndarray:
    """Sum of ``x[ptr[i]:ptr[i+1]]`` for every i (empty segments give 0), vectorised."""
    if ptr.shape[0] == 1:
        return np.zeros(0)
    padded = np.append(x, 0.0)  # reduceat needs valid start indices, also for trailing empty rows
    out = np.add.reduceat(padded, ptr[:-1])
    out[ptr[1:] == ptr[:-1]] = 0.0  # reduceat returns x[start] for an empty segment
    return out


class _Cached:
    """Slots for values derived from an :class:`IMDP`'s read-only arrays, filled on first use. They live in a base
    class so that ``IMDP.__slots__`` stays the model's fields (what :meth:`IMDP.__reduce__` pickles)."""

    __slots__ = ("_has_floor",)


class IMDP(_Cached):
    """An interval MDP with rows grouped by state and an optional per-row floor.

    Build it with :meth:`from_csr` or :meth:`from_dense`; all arrays are read-only.

    Attributes
    ----------
    n_states : int
    n_choices : int
        Number of rows R (choices summed over states).
    state_ptr : (n_states + 1,) int64
    row_ptr : (R + 1,) int64
    col : (nnz,) int64
        Successor state of each stored entry.
    lower, upper : (nnz,) float64
    floor : (R,) float64
        Upper bound of every state not listed in the row (0 when the row lists all support).
    actions : (R,) int64
        Action label of each row (default: index of the row within its state).
    row_state : (R,) int64
        State owning each row.
    n_unlisted : (R,) int64
        ``n_states - (number of entries of the row)``.

    Example
    -------
    Two states with one choice each: state 0 stays with probability in [0.5, 0.7] and moves to
    state 1 with probability in [0.3, 0.5]; state 1 is absorbing:

    >>> m = IMDP.from_dense(lower=[[[0.5, 0.3]], [[0.0, 1.0]]], upper=[[[0.7, 0.5]], [[0.0, 1.0]]])
    >>> m.n_states, m.n_choices, m.nnz
    (2, 2, 3)
    >>> m.col.tolist(), m.lower.tolist(), m.upper.tolist()
    ([0, 1, 1], [0.5, 0.3, 1.0], [0.7, 0.5, 1.0])
    >>> m.upper[0] = 1.0
    Traceback (most recent call last):
    ...
    ValueError: assignment destination is read-only
    """

    __slots__ = (
        "n_states", "n_choices", "state_ptr", "row_ptr", "col", "lower", "upper",
        "floor", "actions", "row_state", "n_unlisted",
    )

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_csr(cls, state_ptr, row_ptr, col, lower, upper, floor=None, actions=None) -> "IMDP":
        """Build and validate an IMDP from CSR arrays.

        Parameters
        ----------
        state_ptr : (n + 1,) int array
            Rows of state ``s`` are ``state_ptr[s] .. state_ptr[s+1]-1``; every state needs >= 1.
        row_ptr : (R + 1,) int array
            Entries of row ``r`` are ``row_ptr[r] .. row_ptr[r+1]-1``.
        col : (nnz,) int array
            Successor states, in ``0 .. n-1``, no duplicate within a row (any order).
        lower, upper : (nnz,) float arrays
            ``0 <= lower <= upper <= 1``.
        floor : (R,) float array or None
            Upper bound for the unlisted states of each row, in [0, 1]; zeros when None.
        actions : (R,) int array or None
            Action label of each row; default the index of the row within its state.

        Raises
        ------
        DimensionError, InvalidModelError, InvalidIntervalError
            With a message naming the array, the row/state and the amounts.
        """
        state_ptr = _as_index_array(state_ptr, "state_ptr")
        row_ptr = _as_index_array(row_ptr, "row_ptr")
        col = _as_index_array(col, "col")
        if state_ptr.shape[0] < 2:
            raise InvalidModelError(f"state_ptr must have length n_states + 1 >= 2; got length {state_ptr.shape[0]}")
        n = state_ptr.shape[0] - 1
        R = row_ptr.shape[0] - 1
        nnz = col.shape[0]
        _check_ptr(state_ptr, "state_ptr", R, "n_choices (len(row_ptr) - 1)", strict=True)
        _check_ptr(row_ptr, "row_ptr", nnz, "nnz (len(col))", strict=False)
        lower = _as_float_array(lower, "lower", nnz)
        upper = _as_float_array(upper, "upper", nnz)
        floor = np.zeros(R) if floor is None else _as_float_array(floor, "floor", R)
        row_len = np.diff(row_ptr)
        row_state = np.repeat(np.arange(n, dtype=_INDEX), np.diff(state_ptr))
        if actions is None:
            actions = np.arange(R, dtype=_INDEX) - np.repeat(state_ptr[:-1], np.diff(state_ptr))
        else:
            actions = _as_index_array(actions, "actions")
            if actions.shape[0] != R:
                raise DimensionError(f"actions must have shape ({R},) (one per row); got {actions.shape}")
        entry_row = np.repeat(np.arange(R, dtype=_INDEX), row_len)

        def where(r: int) -> str:
            return f"row {r} (state {int(row_state[r])}, action {int(actions[r])})"

        # --- indices in range
        bad = np.flatnonzero((col < 0) | (col >= n))
        if bad.size:
            j = int(bad[0])
            raise InvalidModelError(f"col[{j}] = {int(col[j])} in {where(int(entry_row[j]))} is not a state index in [0, {n})")
        # --- no duplicate successor within a row (fast path: rows sorted by col)
        if nnz > 1:
            same_row = entry_row[1:] == entry_row[:-1]
            if np.any(same_row & (col[1:] <= col[:-1])):
                key = entry_row * n + col  # < R * n <= 2**63 for any model that fits in memory
                order = np.argsort(key, kind="stable")
                ks = key[order]
                dup = np.flatnonzero(ks[1:] == ks[:-1])
                if dup.size:
                    j = int(order[dup[0]])
                    raise InvalidModelError(f"{where(int(entry_row[j]))} lists successor {int(col[j])} twice")
        # --- finite numbers and 0 <= lower <= upper <= 1
        for name, arr in (("lower", lower), ("upper", upper)):
            bad = np.flatnonzero(~np.isfinite(arr))
            if bad.size:
                j = int(bad[0])
                raise InvalidIntervalError(f"{name}[{j}] = {float(arr[j])} in {where(int(entry_row[j]))} is not finite")
        bad = np.flatnonzero(~np.isfinite(floor) | (floor < 0) | (floor > 1))
        if bad.size:
            r = int(bad[0])
            raise InvalidIntervalError(f"floor[{r}] = {float(floor[r])} of {where(r)} must be a finite number in [0, 1]")
        bad = np.flatnonzero((lower < 0) | (lower > upper) | (upper > 1))
        if bad.size:
            j = int(bad[0])
            raise InvalidIntervalError(
                f"{where(int(entry_row[j]))}, successor {int(col[j])}: interval [{float(lower[j])!r}, {float(upper[j])!r}] "
                "violates 0 <= lower <= upper <= 1"
            )
        # --- row sums (the only place with a tolerance, ROW_SUM_TOL)
        n_unlisted = n - row_len
        sum_low = _segment_sum(lower, row_ptr)
        bad = np.flatnonzero(sum_low > 1.0 + ROW_SUM_TOL)
        if bad.size:
            r = int(bad[0])
            raise InvalidIntervalError(f"{where(r)}: sum of lower bounds {float(sum_low[r])!r} > 1 (excess {sum_low[r] - 1:.3g})")
        sum_up = _segment_sum(upper, row_ptr) + floor * n_unlisted
        bad = np.flatnonzero(sum_up < 1.0 - ROW_SUM_TOL)
        if bad.size:
            r = int(bad[0])
            raise InvalidIntervalError(
                f"{where(r)}: sum of upper bounds {float(sum_up[r])!r} (listed {float(sum_up[r] - floor[r] * n_unlisted[r])!r} "
                f"+ floor {float(floor[r])!r} x {int(n_unlisted[r])} unlisted) < 1 (deficit {1 - sum_up[r]:.3g})"
            )

        self = object.__new__(cls)
        arrays = dict(state_ptr=state_ptr, row_ptr=row_ptr, col=col, lower=lower, upper=upper,
                      floor=floor, actions=actions, row_state=row_state, n_unlisted=n_unlisted.astype(_INDEX))
        for k, v in arrays.items():
            # own copies: the caller's arrays may be views we must not freeze or alias
            v = np.array(v, copy=True, order="C")
            v.flags.writeable = False
            object.__setattr__(self, k, v)
        object.__setattr__(self, "n_states", int(n))
        object.__setattr__(self, "n_choices", int(R))
        return self

    @classmethod
    def from_dense(cls, lower, upper, actions=None) -> "IMDP":
        """Build an IMDP from dense ``(n, a, n)`` interval arrays (small models and tests).

        Every state gets ``a`` choices; row ``(s, u)`` lists the successors with ``upper > 0``
        (those with ``upper == 0`` have the interval [0, 0], which is what "unlisted with floor
        0" means).  ``lower`` and ``upper`` are validated like :meth:`from_csr`.
        """
        lo = np.asarray(lower, dtype=np.float64)
        up = np.asarray(upper, dtype=np.float64)
        if lo.ndim != 3 or lo.shape[0] != lo.shape[2]:
            raise DimensionError(f"lower must have shape (n, a, n); got {lo.shape}")
        if up.shape != lo.shape:
            raise DimensionError(f"upper must have the shape of lower {lo.shape}; got {up.shape}")
        n, a, _ = lo.shape
        lo2 = lo.reshape(n * a, n)
        up2 = up.reshape(n * a, n)
        # list every entry that is not exactly [0, 0] (NaN and negative entries are kept so
        # that from_csr reports them instead of dropping them silently)
        mask = ~((lo2 == 0) & (up2 == 0))
        rows, cols = np.nonzero(mask)
        row_ptr = np.zeros(n * a + 1, dtype=_INDEX)
        np.cumsum(np.bincount(rows, minlength=n * a), out=row_ptr[1:])
        state_ptr = np.arange(0, n * a + 1, a, dtype=_INDEX)
        return cls.from_csr(state_ptr, row_ptr, cols, lo2[rows, cols], up2[rows, cols], actions=actions)

    # ------------------------------------------------------------------ accessors
    def __setattr__(self, name, value):  # invalid objects cannot exist: no mutation
        raise AttributeError(f"IMDP is immutable; cannot set {name!r}")

    def __reduce__(self):
        """Pickled as its arrays (a side-lane helper or a Dask worker sends models back): the copy is the same
        validated model, read-only like the original (the default pickling would set the slots one by one)."""
        return _unpickle_imdp, (type(self), {k: getattr(self, k) for k in self.__slots__})

    @property
    def nnz(self) -> int:
        """Number of stored entries."""
        return int(self.col.shape[0])

    @property
    def has_floor(self) -> bool:
        """True when some row has a positive floor on unlisted states."""
        try:
            return self._has_floor
        except AttributeError:  # first call: computed once (floor and n_unlisted are read-only, set when built)
            value = bool(np.any(self.floor[self.n_unlisted > 0] > 0))
            object.__setattr__(self, "_has_floor", value)
            return value

    def choices_of(self, state: int) -> range:
        """Row indices of the choices of ``state``."""
        s = int(state)
        if not 0 <= s < self.n_states:
            raise InvalidModelError(f"state must be in [0, {self.n_states}); got {state}")
        return range(int(self.state_ptr[s]), int(self.state_ptr[s + 1]))

    def n_choices_of(self) -> np.ndarray:
        """(n_states,) number of choices of every state."""
        return np.diff(self.state_ptr)

    def to_dense(self) -> tuple[np.ndarray, np.ndarray]:
        """Dense ``(lower, upper)``, each of shape ``(n_choices, n_states)``, floor expanded.

        Unlisted states of row ``r`` get the interval ``[0, floor[r]]``.  Memory is R x n.
        """
        R, n = self.n_choices, self.n_states
        entry_row = np.repeat(np.arange(R), np.diff(self.row_ptr))
        lo = np.zeros((R, n))
        up = np.repeat(self.floor[:, None], n, axis=1)
        lo[entry_row, self.col] = self.lower
        up[entry_row, self.col] = self.upper
        return lo, up

    @property
    def memory_bytes(self) -> int:
        """Bytes held by the arrays of this model."""
        return int(sum(getattr(self, k).nbytes for k in (
            "state_ptr", "row_ptr", "col", "lower", "upper", "floor", "actions", "row_state", "n_unlisted")))

    def __repr__(self) -> str:
        fl = f", floor rows={int(np.count_nonzero(self.floor))}" if self.has_floor else ""
        return (f"IMDP(n_states={self.n_states}, n_choices={self.n_choices}, nnz={self.nnz}{fl}, "
                f"memory={self.memory_bytes / 2**20:.1f} MiB)")


__all__ = ["IMDP", "ROW_SUM_TOL"]


def _unpickle_imdp(cls, fields: dict):
    """The model :meth:`IMDP.__reduce__` pickled: its fields as they were (validated when it was built), the arrays
    read-only."""
    self = object.__new__(cls)
    for k, v in fields.items():
        if isinstance(v, np.ndarray):
            v.flags.writeable = False
        object.__setattr__(self, k, v)
    return self
