"""Switched stochastic systems and their data (the paper's eq. (system) and data set D).

``x_{k+1} = f_u(x_k) + g_u(x_k) + v_k``: the known part ``f_u`` is affine
(:class:`AffineMap`) or any ``known.KnownDynamics`` (both have ``dim``, ``__call__``,
``image_bounds`` and ``fingerprint``), ``g_u`` is unknown (learned by ``gp.learn`` from the residuals
``y = x_next - f_u(x)``, eq. (NewDataset)), ``v_k`` is i.i.d. noise.

* :class:`Dataset` -- validated samples ``(x_i, u_i, x_next_i)``.
* :class:`AffineMap` -- ``f(x) = A x + b``.
* :func:`residuals` -- per mode ``(x, y)`` with ``y = x_next - f_u(x)``.
* :class:`SwitchedSystem` -- the TRUE system, for simulation and data generation only.

The noise is a duck type with ``dim`` and ``sample(k, rng) -> (k, n)`` (``noise.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np

from robust_imdp.errors import DimensionError, InvalidInputError, InvalidModelError

__all__ = ["Dataset", "AffineMap", "ModeResiduals", "residuals", "SwitchedSystem"]


def _finite_matrix(name: str, a: Any) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2:
        raise DimensionError(f"{name} must be a 2-D (m, n) float array; got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(arr))[0])
        raise InvalidInputError(f"{name} must be finite; got {arr[bad]} at index {bad}")
    return arr


def _mode_index(mode: Any, names: tuple[str, ...]) -> int:
    """Mode index from an index or a name."""
    if isinstance(mode, (int, np.integer)) and not isinstance(mode, bool):
        if 0 <= int(mode) < len(names):
            return int(mode)
        raise InvalidInputError(f"mode must be an index in [0, {len(names)}) or one of {names}; got {mode!r}")
    if isinstance(mode, str) and mode in names:
        return names.index(mode)
    raise InvalidInputError(f"mode must be an index in [0, {len(names)}) or one of {names}; got {mode!r}")


# --------------------------------------------------------------------------- data
@dataclass(frozen=True)
class Dataset:
    """Samples ``(x_i, u_i, x_next_i)`` of a switched system, validated on construction.

    Parameters
    ----------
    x : (m, n) float array
        States.
    u : (m,) int or str array
        Mode of each sample: indices ``0 .. n_modes-1`` or names from ``modes``.
    x_next : (m, n) float array
        Successor states.
    modes : sequence of str, optional
        Mode names in index order. Default: ``"0", "1", ...`` up to the largest index
        for integer ``u``; the sorted distinct names for string ``u``.

    Attributes
    ----------
    u : (m,) int array
        Mode indices (names are converted).
    mode_names : tuple of str
    n_modes, dim, n_samples : int

    Raises
    ------
    DimensionError, InvalidInputError
        Wrong shapes, non-finite values, unknown modes, a mode without samples.
    """

    x: np.ndarray
    u: np.ndarray
    x_next: np.ndarray
    modes: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        x = _finite_matrix("x", self.x)
        x_next = np.asarray(self.x_next, dtype=np.float64)
        if x_next.shape != x.shape:
            raise DimensionError(
                f"x_next must have shape (m, {x.shape[1]}) like x, with m = {x.shape[0]}; got {x_next.shape}")
        x_next = _finite_matrix("x_next", x_next)
        m = x.shape[0]
        if m == 0:
            raise DimensionError("x must have at least one row; got shape (0, n)")
        u_raw = np.asarray(self.u)
        if u_raw.shape != (m,):
            raise DimensionError(f"u must have shape ({m},) like x's rows; got {u_raw.shape}")
        if self.modes is not None:
            names = tuple(str(n) for n in self.modes)
            if len(set(names)) != len(names) or not names:
                raise InvalidInputError(f"modes must be distinct non-empty names; got {self.modes!r}")
        else:
            names = None
        if u_raw.dtype.kind in "iu":
            u = u_raw.astype(np.int64)
            if names is None:
                names = tuple(str(i) for i in range(int(u.max()) + 1 if u.size else 0))
            bad = (u < 0) | (u >= len(names))
            if np.any(bad):
                i = int(np.argmax(bad))
                raise InvalidInputError(f"u must hold mode indices in [0, {len(names)}); got u[{i}] = {u[i]}")
        elif u_raw.dtype.kind in "UO":
            labels = u_raw.astype(str)
            if names is None:
                names = tuple(sorted(set(labels.tolist())))
            lookup = {n: i for i, n in enumerate(names)}
            unknown = [lab for lab in labels.tolist() if lab not in lookup]
            if unknown:
                raise InvalidInputError(f"u must hold mode names from {names}; got unknown mode {unknown[0]!r}")
            u = np.array([lookup[lab] for lab in labels.tolist()], dtype=np.int64)
        else:
            raise InvalidInputError(f"u must hold integer mode indices or mode names; got dtype {u_raw.dtype}")
        counts = np.bincount(u, minlength=len(names))
        if np.any(counts == 0):
            empty = [names[i] for i in np.flatnonzero(counts == 0)]
            raise InvalidInputError(f"every mode needs at least one sample; modes without data: {empty}")
        for name, val in (("x", x), ("x_next", x_next), ("u", u)):
            val.setflags(write=False)
            object.__setattr__(self, name, val)
        object.__setattr__(self, "modes", names)

    @property
    def mode_names(self) -> tuple[str, ...]:
        return self.modes  # type: ignore[return-value]

    @property
    def n_modes(self) -> int:
        return len(self.modes)  # type: ignore[arg-type]

    @property
    def dim(self) -> int:
        return int(self.x.shape[1])

    @property
    def n_samples(self) -> int:
        return int(self.x.shape[0])

    def by_mode(self, mode: int | str) -> tuple[np.ndarray, np.ndarray]:
        """Samples of one mode.

        Parameters
        ----------
        mode : int or str
            Index or name.

        Returns
        -------
        x : (m_u, n) float array
        x_next : (m_u, n) float array
        """
        sel = self.u == _mode_index(mode, self.mode_names)
        return self.x[sel], self.x_next[sel]


# --------------------------------------------------------------------------- known part
@dataclass(frozen=True)
class AffineMap:
    """Known dynamics ``f(x) = A x + b``.

    Parameters
    ----------
    A : (n, n) float array
    b : (n,) float array

    Example
    -------
    >>> f = AffineMap(A=[[1.0, 0.5], [0.0, 1.0]], b=[0.1, 0.0])
    >>> f.dim, f([[1.0, 2.0]]).tolist()
    (2, [[2.1, 2.0]])

    The range over the unit box, rounded outward (it contains the exact ``[0.1, 1.6] x [0, 1]``):

    >>> image = f.image_bounds([[0.0, 0.0]], [[1.0, 1.0]])
    >>> bool(image.lower[0, 0] < 0.1 < 1.6 < image.upper[0, 0]), bool(image.upper[0, 1] > 1.0)
    (True, True)
    """

    A: np.ndarray
    b: np.ndarray

    def __post_init__(self) -> None:
        A = _finite_matrix("A", self.A)
        if A.shape[0] != A.shape[1]:
            raise DimensionError(f"A must be square (n, n); got {A.shape}")
        b = np.asarray(self.b, dtype=np.float64)
        if b.shape != (A.shape[0],):
            raise DimensionError(f"b must have shape ({A.shape[0]},) like A's rows; got {b.shape}")
        if not np.all(np.isfinite(b)):
            raise InvalidInputError(f"b must be finite; got {b}")
        A.setflags(write=False)
        b.setflags(write=False)
        object.__setattr__(self, "A", A)
        object.__setattr__(self, "b", b)

    @property
    def dim(self) -> int:
        return int(self.A.shape[0])

    @classmethod
    def zero(cls, n: int) -> "AffineMap":
        """``f(x) = 0`` (everything is learned)."""
        return cls(np.zeros((n, n)), np.zeros(n))

    @classmethod
    def identity(cls, n: int) -> "AffineMap":
        """``f(x) = x`` (the GP learns the increment)."""
        return cls(np.eye(n), np.zeros(n))

    def __call__(self, x: Any) -> np.ndarray:
        """Apply to rows: ``(k, n) -> (k, n)``, ``x @ A.T + b``."""
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise DimensionError(f"x must have shape (k, {self.dim}); got {x.shape}")
        return x @ self.A.T + self.b

    def image_bounds(self, lower: Any, upper: Any):
        """Certified range of every component over boxes, rounded outward.

        ``min_{x in box} a.x + b = b + sum_j min(a_j lo_j, a_j hi_j)`` (and max likewise). Each
        product is correctly rounded (relative error u), the sum of ``n + 1`` terms adds at most
        ``gamma_n`` times the sum of their magnitudes; the bound moves out by ``gamma_{n+2}`` of
        that sum (plus 1e-300 for underflow) and one more ulp.

        Parameters
        ----------
        lower, upper : (k, n) float arrays, ``lower <= upper``

        Returns
        -------
        known.ImageBounds with ``lower``, ``upper`` (k, n) and ``leaves`` (k,) (all 1)
        """
        from robust_imdp.models.known import ImageBounds

        lo = np.asarray(lower, dtype=np.float64)
        hi = np.asarray(upper, dtype=np.float64)
        if lo.ndim != 2 or lo.shape[1] != self.dim or hi.shape != lo.shape:
            raise DimensionError(f"lower and upper must have shape (k, {self.dim}); got {lo.shape}, {hi.shape}")
        if not np.all(lo <= hi):
            r = int(np.argwhere(~(lo <= hi))[0][0])
            raise InvalidInputError(f"boxes must have lower <= upper; box {r} is {lo[r].tolist()}, {hi[r].tolist()}")
        p_lo = self.A[None, :, :] * lo[:, None, :]  # (k, n_out, n): a_ij lo_j
        p_hi = self.A[None, :, :] * hi[:, None, :]
        t_min = np.minimum(p_lo, p_hi)
        t_max = np.maximum(p_lo, p_hi)
        n = self.dim
        u = 2.0 ** -53
        gamma = (n + 2) * u / (1.0 - (n + 2) * u) * 1.01
        s_min = t_min.sum(axis=2) + self.b
        s_max = t_max.sum(axis=2) + self.b
        e_min = gamma * (np.abs(t_min).sum(axis=2) + np.abs(self.b)) + 1e-300
        e_max = gamma * (np.abs(t_max).sum(axis=2) + np.abs(self.b)) + 1e-300
        return ImageBounds(lower=np.nextafter(s_min - e_min, -np.inf), upper=np.nextafter(s_max + e_max, np.inf),
                           leaves=np.ones(lo.shape[0], dtype=np.int64))

    def residuals(self, x: Any, x_next: Any):
        """``y = fl(x_next - fl(A x + b))`` with a bound on its rounding error (``known.Residuals``).

        The certificate (eq. W of docs/rkhs_bounds.md) needs the exact residual within the data-noise
        allowance, so the float error of ``y`` joins it. ``fl(A x + b)`` is a sum of ``n + 1`` correctly
        rounded products in any order (BLAS, FMA or not): error ``<= gamma_{n+1} (|A| |x| + |b|)``; the
        subtraction adds at most half an ulp of ``|y|`` (bounded by one ``spacing``). The sum is moved
        up by ``gamma_3`` relative, 1e-300 absolute and one ulp.
        """
        from robust_imdp.models.known import Residuals

        x = np.asarray(x, dtype=np.float64)
        xn = np.asarray(x_next, dtype=np.float64)
        y = xn - self(x)
        n = self.dim
        u = 2.0 ** -53
        g = (n + 1) * u / (1.0 - (n + 1) * u)
        e = g * (np.abs(x) @ np.abs(self.A).T + np.abs(self.b)) + np.spacing(np.abs(y))
        e = np.nextafter(e * (1.0 + 4 * u) + 1e-300, np.inf)
        return Residuals(y=y, bound=e)

    def fingerprint(self) -> str:
        """A digest of ``A`` and ``b`` (cache keys)."""
        import hashlib

        return hashlib.sha256(b"AffineMap" + self.A.tobytes() + self.b.tobytes()).hexdigest()


class ModeResiduals(NamedTuple):
    """Training data of one mode: inputs ``x (m_u, n)`` and residuals ``y (m_u, n)``."""

    x: np.ndarray
    y: np.ndarray


def _check_maps(known_maps: Sequence[Callable], n_modes: int, dim: int) -> None:
    if len(known_maps) != n_modes:
        raise DimensionError(f"known_maps must have one map per mode ({n_modes}); got {len(known_maps)}")
    for i, f in enumerate(known_maps):
        d = getattr(f, "dim", dim)
        if d != dim:
            raise DimensionError(f"known_maps[{i}] must act on dimension {dim}; got dimension {d}")


def residuals(dataset: Dataset, known_maps: Sequence[Callable]) -> tuple[ModeResiduals, ...]:
    """Per mode ``(x, y)`` with ``y = x_next - f_u(x)`` (paper eq. (NewDataset)).

    Parameters
    ----------
    dataset : Dataset
    known_maps : sequence of AffineMap (or callables (k, n) -> (k, n)), one per mode

    Returns
    -------
    tuple of ModeResiduals, in mode order
    """
    _check_maps(known_maps, dataset.n_modes, dataset.dim)
    out = []
    for i in range(dataset.n_modes):
        x, xn = dataset.by_mode(i)
        out.append(ModeResiduals(x, xn - known_maps[i](x)))
    return tuple(out)


# --------------------------------------------------------------------------- true system
class SwitchedSystem:
    """The TRUE system ``x+ = f_u(x) + g_u(x) + v`` (simulation and data generation only).

    Parameters
    ----------
    known_maps : sequence of AffineMap, one per mode
    unknown_fns : sequence of callables ``(k, n) -> (k, n)``, one per mode (``g_u``)
    noise : noise model with ``dim`` and ``sample(k, rng) -> (k, n)``
    mode_names : sequence of str, optional (default ``"0", "1", ...``)
    """

    def __init__(self, known_maps: Sequence[AffineMap], unknown_fns: Sequence[Callable], noise: Any,
                 mode_names: Sequence[str] | None = None) -> None:
        if len(known_maps) == 0:
            raise InvalidModelError("known_maps must have at least one mode; got none")
        n = known_maps[0].dim
        _check_maps(known_maps, len(known_maps), n)
        if len(unknown_fns) != len(known_maps):
            raise DimensionError(
                f"unknown_fns must have one function per mode ({len(known_maps)}); got {len(unknown_fns)}")
        if getattr(noise, "dim", None) != n:
            raise DimensionError(f"noise.dim must equal the state dimension {n}; got {getattr(noise, 'dim', None)!r}")
        names = tuple(str(i) for i in range(len(known_maps))) if mode_names is None else tuple(map(str, mode_names))
        if len(names) != len(known_maps) or len(set(names)) != len(names):
            raise InvalidModelError(f"mode_names must be {len(known_maps)} distinct names; got {mode_names!r}")
        self.known_maps = tuple(known_maps)
        self.unknown_fns = tuple(unknown_fns)
        self.noise = noise
        self.mode_names = names
        self.dim = n

    @property
    def n_modes(self) -> int:
        return len(self.known_maps)

    def step(self, x: Any, mode: int | str, rng: Any = None) -> np.ndarray:
        """One step from each row of ``x``: ``(k, n) -> (k, n)``, fresh noise per row.

        Parameters
        ----------
        x : (k, n) float array
        mode : int or str
        rng : seed or Generator

        Returns
        -------
        (k, n) float array
        """
        i = _mode_index(mode, self.mode_names)
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise DimensionError(f"x must have shape (k, {self.dim}); got {x.shape}")
        gen = np.random.default_rng(rng)
        g = np.asarray(self.unknown_fns[i](x), dtype=np.float64)
        if g.shape != x.shape:
            raise DimensionError(f"unknown_fns[{i}] must return shape {x.shape}; got {g.shape}")
        v = np.asarray(self.noise.sample(x.shape[0], gen), dtype=np.float64).reshape(x.shape)
        return self.known_maps[i](x) + g + v

    def sample_dataset(self, n_per_mode: int, box_lower: Any, box_upper: Any, rng: Any = None) -> Dataset:
        """Data set with ``n_per_mode`` uniform samples of ``x`` in a box per mode.

        Parameters
        ----------
        n_per_mode : int >= 1
        box_lower, box_upper : (n,) float arrays, lower <= upper
        rng : seed or Generator

        Returns
        -------
        Dataset
            Samples grouped by mode (mode 0 first).
        """
        k = int(n_per_mode)
        if k < 1:
            raise InvalidInputError(f"n_per_mode must be a positive integer; got {n_per_mode!r}")
        lo = np.asarray(box_lower, dtype=np.float64)
        hi = np.asarray(box_upper, dtype=np.float64)
        if lo.shape != (self.dim,) or hi.shape != (self.dim,):
            raise DimensionError(f"box_lower and box_upper must have shape ({self.dim},); got {lo.shape}, {hi.shape}")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(lo <= hi)):
            raise InvalidInputError(f"box must be finite with box_lower <= box_upper; got {lo}, {hi}")
        gen = np.random.default_rng(rng)
        xs, us, xns = [], [], []
        for i in range(self.n_modes):
            x = gen.uniform(lo, hi, size=(k, self.dim))
            xs.append(x)
            xns.append(self.step(x, i, gen))
            us.append(np.full(k, i, dtype=np.int64))
        return Dataset(np.vstack(xs), np.concatenate(us), np.vstack(xns), modes=self.mode_names)
