"""Input grids: a quantised input ``u`` in R^m as the modes of the switched system.

Benchmarks state dynamics once as ``x+ = f(x, u) + v`` with ``u`` in a box quantised by a step (or in
lists of values). :class:`InputGrid` is that grid: every combination of the per-input values, in C order
(the last input varies fastest), one mode each, named by its values (``u=(17)``, ``u=(0.5, -1)``:
:func:`input_name`). :class:`InputMode` is the known part of one mode, ``f(., u_k)``: one
:class:`~robust_imdp.models.known.KnownDynamics` in ``x1..xn, u1..um`` is shared by every mode, and its
certified image over a cell is that of ``f`` over the box ``cell x {u_k}`` (the input is a point: its
interval is ``[u_k, u_k]``). ``pipeline.bound_stage.known_images`` bounds all the modes of a grid in one
vectorised call.

The input values are the floats the grid holds (``lower + k * step``, rounded to 12 significant digits of
the box's magnitude so that a decimal step gives the decimals one wrote: 0.1 * 3 is 0.3, not
0.30000000000000004, and -1 + 10 * 0.1 is 0); the
controller applies exactly these floats (:meth:`robust_imdp.synthesis.controller.Controller.act_input`),
so they are the inputs the guarantees are about.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from robust_imdp.errors import DimensionError, InvalidInputError

__all__ = ["InputGrid", "InputMode", "input_name", "input_modes", "MAX_INPUTS"]

#: Largest number of grid points (modes) a grid may have: the abstraction has a row per cell and mode.
MAX_INPUTS = 100_000


def _text(v: float) -> str:
    """A value as mode names and messages write it: 12 significant digits, no trailing zeros (17, 0.5, -1e-05)."""
    t = f"{float(v):.12g}"
    return "0" if t == "-0" else t


def input_name(u: Sequence[float]) -> str:
    """The mode name of the input vector ``u``: ``u=(17)``, ``u=(0.5, -1)``."""
    return "u=(" + ", ".join(_text(v) for v in np.atleast_1d(np.asarray(u, dtype=float))) + ")"


@dataclass(frozen=True, eq=False)
class InputGrid:
    """Every combination of per-input values: the modes of a system with a quantised input.

    Build with :meth:`from_box` (a box and a step per input) or :meth:`from_values` (a list per input).

    Attributes
    ----------
    names : tuple of m str
        The inputs' names (``u1 .. um`` unless given): for messages, figures and ``result.json``.
    values : tuple of m (k_j,) float arrays
        The values of each input, increasing.
    points : (M, m) float array, read-only
        The grid points, ``M = prod k_j``, in C order (the last input varies fastest).
    mode_names : tuple of M str
        :func:`input_name` of each point.
    """

    names: tuple
    values: tuple
    points: np.ndarray
    mode_names: tuple

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_values(cls, values: Sequence[Sequence[float]], names: Sequence[str] | None = None) -> "InputGrid":
        """The grid of the given values of each input.

        Parameters
        ----------
        values : sequence of m sequences of floats
            The values of each input (distinct, finite; sorted here).
        names : sequence of m str, optional

        Raises
        ------
        InvalidInputError, DimensionError
            Naming the input and the bad value.
        """
        if isinstance(values, (str, bytes)) or not isinstance(values, (list, tuple, np.ndarray)) or len(values) == 0:
            raise InvalidInputError(f"values must be a list with one list of values per input; got {values!r}")
        m = len(values)
        names = _names(names, m)
        per = []
        for j, v in enumerate(values):
            try:
                a = np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                a = None
            if a is None or a.ndim != 1 or a.size == 0 or not np.all(np.isfinite(a)):
                raise InvalidInputError(f"values of input {j + 1} ({names[j]}) must be a non-empty list of finite "
                                        f"numbers; got {v!r}")
            a = np.sort(a)
            dup = np.flatnonzero(np.diff(a) == 0)
            if dup.size:
                raise InvalidInputError(f"values of input {j + 1} ({names[j]}) must be distinct; {a[dup[0]]:g} appears "
                                        "twice")
            per.append(a)
        return cls._build(names, per)

    @classmethod
    def from_box(cls, lower: Sequence[float], upper: Sequence[float], step: Sequence[float] | float,
                 names: Sequence[str] | None = None) -> "InputGrid":
        """The grid ``lower_j, lower_j + step_j, ..., upper_j`` of each input.

        ``(upper - lower) / step`` must be a whole number (within 1e-9): the grid reaches ``upper``. Values are
        ``lower + k * step`` rounded to 12 significant digits (the module docstring says why).

        Raises
        ------
        InvalidInputError, DimensionError
            Naming the input whose box or step is wrong.
        """
        lo = np.atleast_1d(np.asarray(lower, dtype=float))
        hi = np.atleast_1d(np.asarray(upper, dtype=float))
        m = lo.size
        st = np.broadcast_to(np.asarray(step, dtype=float), (m,)) if np.ndim(step) == 0 else \
            np.asarray(step, dtype=float).reshape(-1)
        if lo.ndim != 1 or hi.shape != (m,) or st.shape != (m,):
            raise DimensionError(f"lower, upper and step must have one value per input ({m}); got lower {lower!r}, "
                                 f"upper {upper!r}, step {step!r}")
        names = _names(names, m)
        per = []
        for j in range(m):
            if not (np.isfinite(lo[j]) and np.isfinite(hi[j]) and np.isfinite(st[j]) and st[j] > 0 and lo[j] <= hi[j]):
                raise InvalidInputError(f"input {j + 1} ({names[j]}): need finite lower <= upper and step > 0; got "
                                        f"lower {lo[j]:g}, upper {hi[j]:g}, step {st[j]:g}")
            count = (hi[j] - lo[j]) / st[j]
            k = int(round(count))
            if abs(count - k) > 1e-9 * max(1.0, count):
                raise InvalidInputError(f"input {j + 1} ({names[j]}): (upper - lower) / step = ({_text(hi[j])} - "
                                        f"{_text(lo[j])}) / {_text(st[j])} = {count:.6g} must be a whole number (the "
                                        "grid ends at upper); change the step or the box")
            # 12 significant digits of the box's magnitude: -1 + 10 * 0.1 is 0, not 2.2e-16
            digits = 12 - int(np.ceil(np.log10(max(abs(lo[j]), abs(hi[j]), st[j]))))
            vals = np.array([round(lo[j] + i * st[j], digits) + 0.0 for i in range(k + 1)])
            vals[-1] = hi[j]
            per.append(vals)
        return cls._build(names, per)

    @classmethod
    def _build(cls, names, per) -> "InputGrid":
        M = int(np.prod([a.size for a in per]))
        if M > MAX_INPUTS:
            raise InvalidInputError(f"the input grid has {M:,} points ({' x '.join(str(a.size) for a in per)}), more "
                                    f"than {MAX_INPUTS:,}: use a coarser step")
        mesh = np.meshgrid(*per, indexing="ij")
        points = np.stack([g.reshape(-1) for g in mesh], axis=1)
        mode_names = tuple(input_name(p) for p in points)
        if len(set(mode_names)) != M:
            raise InvalidInputError("input values that differ only beyond 12 significant digits give equal mode "
                                    "names; use values that differ in the first 12 digits")
        for a in per:
            a.setflags(write=False)
        points.setflags(write=False)
        return cls(tuple(names), tuple(per), points, mode_names)

    # ------------------------------------------------------------------ queries
    @property
    def n_inputs(self) -> int:
        """m."""
        return len(self.names)

    @property
    def n_points(self) -> int:
        """M, the number of modes."""
        return int(self.points.shape[0])

    @property
    def shape(self) -> tuple:
        """Values per input."""
        return tuple(a.size for a in self.values)

    def locate(self, u: Any) -> np.ndarray:
        """The grid point (mode index) of each input vector, ``-1`` where an input is not a grid value (within
        1e-9 of the values' spacing, relative).

        Parameters
        ----------
        u : (k, m) or (m,) float array

        Returns
        -------
        (k,) int64 array
        """
        u = np.asarray(u, dtype=float)
        u2 = u.reshape(1, -1) if u.ndim == 1 else u
        if u2.ndim != 2 or u2.shape[1] != self.n_inputs:
            raise DimensionError(f"u must have {self.n_inputs} columns ({', '.join(self.names)}); got shape {u.shape}")
        idx = np.zeros(u2.shape[0], dtype=np.int64)
        ok = np.all(np.isfinite(u2), axis=1)
        for j, vals in enumerate(self.values):
            col = np.where(np.isfinite(u2[:, j]), u2[:, j], vals[0])
            pos = np.clip(np.searchsorted(vals, col), 0, vals.size - 1)
            left = np.clip(pos - 1, 0, vals.size - 1)
            near = np.where(np.abs(vals[left] - col) < np.abs(vals[pos] - col), left, pos)
            scale = max(float(np.max(np.abs(vals))) if vals.size == 1 else float(np.min(np.diff(vals))), 1e-300)
            ok &= np.abs(vals[near] - col) <= 1e-9 * scale
            idx = idx * vals.size + near
        return np.where(ok, idx, -1)

    def index(self, u: Any, *, what: str = "u") -> np.ndarray:
        """:meth:`locate`, raising where an input is not on the grid.

        Raises
        ------
        InvalidInputError
            Naming ``what``, the first such row and its input, and the grid's values.
        """
        idx = self.locate(u)
        bad = np.flatnonzero(idx < 0)
        if bad.size:
            r = int(bad[0])
            row = np.asarray(u, dtype=float).reshape(idx.size, -1)[r]
            raise InvalidInputError(f"{what}: row {r} has input {input_name(row)}, not a point of the grid "
                                    f"({self._values_text()})")
        return idx

    def _values_text(self) -> str:
        return "; ".join(f"{n} in {{{', '.join(_text(v) for v in a[:8])}{', ...' if a.size > 8 else ''}}}"
                         for n, a in zip(self.names, self.values))

    def to_dict(self) -> dict:
        """``{"names": [...], "values": [[...], ...]}`` (per input) for result files and messages."""
        return {"names": list(self.names), "values": [a.tolist() for a in self.values]}

    def fingerprint(self) -> str:
        """A digest of the names and values (cache keys)."""
        h = hashlib.sha256(b"InputGrid")
        h.update(repr(self.names).encode())
        for a in self.values:
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()

    def __repr__(self) -> str:
        parts = [f"{n} in {{{', '.join(_text(v) for v in a[:3])}{', ...' if a.size > 3 else ''}}} ({a.size})"
                 for n, a in zip(self.names, self.values)]
        return f"InputGrid({self.n_points} points: {'; '.join(parts)})"


def _names(names, m: int) -> tuple:
    if names is None:
        return tuple(f"u{j + 1}" for j in range(m))
    if isinstance(names, str) or len(names) != m or not all(isinstance(v, str) and v.strip() for v in names) \
            or len(set(names)) != m:
        raise InvalidInputError(f"names must be {m} distinct non-empty names, one per input; got {names!r}")
    return tuple(names)


class InputMode:
    """The known part ``f(., u)`` of one mode of an input grid (the known-part interface of
    ``system.AffineMap`` / ``known.KnownDynamics``: ``dim``, ``__call__``, ``image_bounds``, ``residuals``,
    ``fingerprint``).

    Parameters
    ----------
    dynamics : known.KnownDynamics
        ``f`` in ``x1..xn, u1..um`` (``n_inputs = m``), shared by every mode of the grid.
    u : (m,) float array
        The mode's input.
    """

    def __init__(self, dynamics, u):
        self.dynamics = dynamics
        self.input = np.array(u, dtype=float).reshape(-1)
        self.input.setflags(write=False)
        if self.input.size != dynamics.n_inputs:
            raise DimensionError(f"u must have {dynamics.n_inputs} values (the inputs of f); got {self.input.size}")
        self.expressions = tuple(f"{e} at {input_name(self.input)}" for e in dynamics.expressions)

    @property
    def dim(self) -> int:
        return int(self.dynamics.n_dims)

    def _with_input(self, x) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        x2 = x.reshape(1, -1) if x.ndim == 1 else x
        if x2.ndim != 2 or x2.shape[1] != self.dim:
            raise DimensionError(f"x must have shape (k, {self.dim}); got {x.shape}")
        return np.concatenate([x2, np.broadcast_to(self.input, (x2.shape[0], self.input.size))], axis=1)

    def __call__(self, x) -> np.ndarray:
        """``f(x, u)``: (k, n) -> (k, n)."""
        return self.dynamics.evaluate(self._with_input(x))

    def image_bounds(self, lower, upper, **options):
        """Certified enclosure of ``f(., u)`` over boxes: that of ``f`` over ``box x [u, u]``."""
        return self.dynamics.image_bounds(self._with_input(lower), self._with_input(upper), **options)

    def achieved_range(self, lower, upper, **options):
        """Values ``f(., u)`` attains on each box (``KnownDynamics.achieved_range`` with the input fixed); the
        argmin / argmax points are returned without the input's columns."""
        from robust_imdp.models.known import AchievedRange

        r = self.dynamics.achieved_range(self._with_input(lower), self._with_input(upper), **options)
        return AchievedRange(r.lower, r.upper, r.argmin[..., :self.dim], r.argmax[..., :self.dim])

    def residuals(self, x, x_next):
        """``y = x_next - fl(f(x, u))`` with a bound on its rounding error (``known.Residuals``)."""
        return self.dynamics.residuals(self._with_input(x), x_next)

    def fingerprint(self) -> str:
        h = hashlib.sha256(b"InputMode")
        h.update(self.dynamics.fingerprint().encode())
        h.update(self.input.tobytes())
        return h.hexdigest()

    def __repr__(self) -> str:
        return f"InputMode({list(self.dynamics.expressions)!r}, {input_name(self.input)})"


def input_modes(f, grid: InputGrid, *, name: str | None = None) -> tuple:
    """The known parts of every mode of ``grid`` for dynamics ``f(x, u)``: a tuple of :class:`InputMode`.

    Parameters
    ----------
    f : sequence of n str, or a known.KnownDynamics with ``n_inputs = grid.n_inputs``
        Expressions in ``x1..xn, u1..um`` (grammar in docs/known_dynamics.md).
    grid : InputGrid
    name : str, optional
        Prefix of the expressions' error messages (e.g. the file and table).
    """
    from robust_imdp.models.known import KnownDynamics

    if isinstance(f, KnownDynamics):
        dyn = f
        if dyn.n_inputs != grid.n_inputs:
            raise DimensionError(f"f must use the grid's {grid.n_inputs} inputs; got a KnownDynamics with n_inputs = "
                                 f"{dyn.n_inputs}")
    else:
        dyn = KnownDynamics(f, name=name, n_inputs=grid.n_inputs)
    return tuple(InputMode(dyn, p) for p in grid.points)
