"""The paper's case studies: true systems, regions and formulas (Jackson et al., HSCC 2021, Sec. 6).

Used by the examples, by ``robust-imdp simulate --true-system NAME`` and by the tests. The true
dynamics here are what the *data* come from; the synthesis only sees the data, the known affine
part of each mode and the noise model.

* ``three_mode_linear``: x+ = A_u x + v with A_1 = [[0.4, 0.1], [0, 0.5]],
  A_2 = [[0.4, 0.5], [0, 0.5]], A_3 = [[0.4, 0], [0.5, 0.5]], all dynamics unknown (f_u = 0);
  v ~ N(0, 0.01^2 I) truncated to [-0.01, 0.01] per dimension; 200 samples per mode.
* ``four_mode_nonlinear``: x+ = x + g_u(x) + v (f_u = identity) with g_1 = [0.5 + 0.2 sin x2,
  0.4 cos x1], g_2 = [-0.5 + 0.2 sin x2, 0.4 cos x1], g_3 = [0.4 cos x2, 0.5 + 0.2 sin x1],
  g_4 = [0.4 cos x2, -0.5 + 0.2 sin x1]; same noise; 300 samples per mode.
* ``unicycle_3d`` (not from the paper; issue 10's scale study): a unicycle (p_x, p_y, theta) on
  [0, 4]^2 x [-pi, pi] with three turning modes. Known: the heading update theta + omega_u
  (omega = +0.3, 0, -0.3) and the position itself; unknown: the motion v (cos theta, sin theta)
  (v = 0.15) plus a cross current 0.04 sin p_y along p_x. Noise N(0, 0.005^2) truncated to
  +-0.01; 10,000 samples per mode; a 64^3 grid; reach ``goal`` while avoiding ``obs``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from robust_imdp.errors import DimensionError, InvalidInputError

__all__ = ["TrueSystem", "CaseStudy", "CASE_STUDIES", "get_case_study", "true_system",
           "known_dynamics_cell_bounds"]

_A_LINEAR = np.array([
    [[0.4, 0.1], [0.0, 0.5]],
    [[0.4, 0.5], [0.0, 0.5]],
    [[0.4, 0.0], [0.5, 0.5]],
])


def _g_linear(x: np.ndarray, modes: np.ndarray) -> np.ndarray:
    return np.einsum("kij,kj->ki", _A_LINEAR[modes], x)


def _g_nonlinear(x: np.ndarray, modes: np.ndarray) -> np.ndarray:
    s1, s2 = np.sin(x[:, 0]), np.sin(x[:, 1])
    c1, c2 = np.cos(x[:, 0]), np.cos(x[:, 1])
    g = np.empty_like(x)
    # modes 0, 1: [+-0.5 + 0.2 sin x2, 0.4 cos x1]; modes 2, 3: [0.4 cos x2, +-0.5 + 0.2 sin x1]
    offset = np.where((modes == 0) | (modes == 2), 0.5, -0.5)
    horiz = modes < 2
    g[:, 0] = np.where(horiz, offset + 0.2 * s2, 0.4 * c2)
    g[:, 1] = np.where(horiz, 0.4 * c1, offset + 0.2 * s1)
    return g


# --------------------------------------------------------------------------- separable form
# The same unknown parts as sums of one-coordinate terms, for exact image boxes
# (TrueSystem.image_bounds): g_terms[u][i] = ((kind, coordinate, coefficient), ...) with kind
# "lin" (c * x_j), "sin" (c * sin x_j), "cos" (c * cos x_j) or "const" (c; coordinate -1).
# tests/test_casestudies.py checks them against g at random points.
_G_TERMS_LINEAR = tuple(
    tuple(tuple(("lin", j, float(A[i, j])) for j in range(2) if A[i, j] != 0.0) for i in range(2))
    for A in _A_LINEAR
)
_G_TERMS_NONLINEAR = (
    ((("const", -1, 0.5), ("sin", 1, 0.2)), (("cos", 0, 0.4),)),
    ((("const", -1, -0.5), ("sin", 1, 0.2)), (("cos", 0, 0.4),)),
    ((("cos", 1, 0.4),), (("const", -1, 0.5), ("sin", 0, 0.2))),
    ((("cos", 1, 0.4),), (("const", -1, -0.5), ("sin", 0, 0.2))),
)

_TERM_KINDS = ("lin", "sin", "cos", "const")
_EPS = 2.0 ** -52  # float64 machine epsilon (2 x unit round-off)
# Outward margin of image_bounds, relative to the magnitudes involved (see _term_sum_bounds).
_MARGIN_REL = 1e-12


def _trig_range(kind: str, lo: np.ndarray, hi: np.ndarray):
    """Range ``[min, max]`` of ``sin`` or ``cos`` over ``[lo, hi]`` (arrays), up to float error.

    The extremes of a smooth function over an interval are at the endpoints or at interior
    critical points: sin has its maxima at pi/2 + 2k pi and minima at -pi/2 + 2k pi, cos at
    2k pi and pi + 2k pi. A critical point c + 2k pi lies in [lo, hi] iff
    k = ceil((lo - c) / 2pi) satisfies c + 2k pi <= hi. That test is done in floats; it can
    only err for a critical point within ``delta`` (returned) of an endpoint, and then the
    endpoint value is within ``delta**2 / 2`` of +-1 (|f''| <= 1), which the caller adds to
    its margin. Where the test says "inside" the exact value +-1 is used.

    Returns
    -------
    fmin, fmax : arrays like ``lo`` (computed with libm, NOT yet rounded outward)
    delta : array like ``lo``, bound on the distance error of the critical-point test
    """
    f = np.sin if kind == "sin" else np.cos
    peak, trough = (0.5 * np.pi, -0.5 * np.pi) if kind == "sin" else (0.0, np.pi)
    two_pi = 2.0 * np.pi
    f_lo, f_hi = f(lo), f(hi)
    fmin, fmax = np.minimum(f_lo, f_hi), np.maximum(f_lo, f_hi)

    def has(c):
        k = np.ceil((lo - c) / two_pi)
        return c + k * two_pi <= hi

    fmax = np.where(has(peak), 1.0, fmax)
    fmin = np.where(has(trough), -1.0, fmin)
    # |computed c + 2k pi - exact| <= (|c| + 2|k| pi) * few eps (pi rounded, one product, one
    # sum); |k| 2 pi <= |lo| + |hi| + 2 pi + |c|; a factor 8 covers the few roundings.
    delta = 8.0 * _EPS * (np.abs(lo) + np.abs(hi) + 4.0 * np.pi + 4.0)
    return fmin, fmax, delta


def _term_sum_bounds(terms, lower: np.ndarray, upper: np.ndarray):
    """Outward-rounded ``[lo, hi]`` of ``sum_t term_t(x)`` over the boxes ``[lower, upper]``.

    ``terms``: ((kind, coordinate, coefficient), ...); boxes (k, n). Returns two (k,) arrays.

    Exactness: when every coordinate appears in at most one term, the range of the sum over a
    box is the sum of the 1-D ranges (the coordinates vary independently over a box), so the
    result is the exact range plus the margin below. When a coordinate appears twice the sum of
    ranges still CONTAINS the range of the sum (sound, possibly loose).

    Soundness of the margin (why the box is never inward). The float result differs from the
    real one by (a) at most one rounding (|error| <= eps/2 |value|) per product ``c * v``,
    (b) the libm error of sin/cos, at most a few ulp of values in [-1, 1] (glibc < 1 ulp, numpy's
    SIMD kernels <= 4 ulp), times |c|, (c) the summation of k terms, <= (k - 1) eps/2 times the
    sum of magnitudes, (d) the critical-point test of ``_trig_range``: <= delta**2 / 2 times |c|.
    With S = sum of term magnitudes and C = sum of |c| of trig terms, (a)+(c) <= (k + 1) eps S
    and (b) <= 8 eps C; we subtract/add ``1e-12 (1 + S + C) + C delta**2``, which exceeds that
    for any k < 4000 terms, and then move one more ulp outward with ``nextafter``. The same
    margin covers the float evaluation of f + g by :meth:`TrueSystem.step` (a few roundings).
    """
    k = lower.shape[0]
    lo, hi = np.zeros(k), np.zeros(k)
    mag, trig_c, trig_extra = np.zeros(k), np.zeros(k), np.zeros(k)
    for kind, j, c in terms:
        c = float(c)
        if kind == "const":
            t_lo = t_hi = np.full(k, c)
        elif kind == "lin":
            a, b = c * lower[:, j], c * upper[:, j]
            t_lo, t_hi = np.minimum(a, b), np.maximum(a, b)
        else:
            fmin, fmax, delta = _trig_range(kind, lower[:, j], upper[:, j])
            a, b = c * fmin, c * fmax
            t_lo, t_hi = np.minimum(a, b), np.maximum(a, b)
            trig_c += abs(c)
            trig_extra += abs(c) * delta ** 2
        lo += t_lo
        hi += t_hi
        mag += np.maximum(np.abs(t_lo), np.abs(t_hi))
    margin = _MARGIN_REL * (1.0 + mag + trig_c) + trig_extra
    # outward: lower bounds down, upper bounds up, plus one ulp (ARCHITECTURE: soundness direction)
    return np.nextafter(lo - margin, -np.inf), np.nextafter(hi + margin, np.inf)


@dataclass(frozen=True, eq=False)
class TrueSystem:
    """x+ = A_u x + b_u + g_u(x) + v, vectorised over rows with per-row modes.

    Attributes
    ----------
    mode_names : tuple of str
    known_A : (n_modes, n, n) float array, known_b : (n_modes, n) float array
    g : callable ``(x (k, n), modes (k,) int) -> (k, n)``, the unknown part
    sigma, bound : (n,) float arrays of the truncated Gaussian noise
    g_terms : tuple or None
        Optional separable form of ``g`` for :meth:`image_bounds`: ``g_terms[u][i]`` is a tuple
        of ``(kind, coordinate, coefficient)`` with kind ``"lin"`` (``c x_j``), ``"sin"``
        (``c sin x_j``), ``"cos"`` (``c cos x_j``) or ``"const"`` (``c``, coordinate ``-1``)
        whose sum is component ``i`` of ``g`` in mode ``u``. None: no exact images.
    """

    mode_names: tuple
    known_A: np.ndarray
    known_b: np.ndarray
    g: Callable
    sigma: np.ndarray
    bound: np.ndarray
    g_terms: tuple | None = None

    def __post_init__(self):
        if self.g_terms is None:
            return
        M, n = len(self.mode_names), len(self.sigma)
        if len(self.g_terms) != M or any(len(row) != n for row in self.g_terms):
            raise DimensionError(
                f"g_terms must have {M} modes x {n} outputs; got {[len(r) for r in self.g_terms]}")
        for u, row in enumerate(self.g_terms):
            for i, terms in enumerate(row):
                for kind, j, _c in terms:
                    if kind not in _TERM_KINDS or (kind != "const" and not 0 <= j < n):
                        raise InvalidInputError(
                            f"g_terms[{u}][{i}] must hold (kind in {_TERM_KINDS}, coordinate in "
                            f"0..{n - 1}, coefficient); got {(kind, j, _c)!r}")

    def image_bounds(self, lower, upper):
        """Certified boxes of the noise-free images ``{A_u x + b_u + g_u(x) : x in cell}``.

        Every output component of every case study is a sum of functions of single
        coordinates (the known affine part and ``g_terms``), so its range over a box is the
        sum of exact 1-D ranges (linear: the endpoints, so ``x -> A x`` gives ``A c -+ |A| h`` for
        centre c and half-widths h; sin/cos: endpoints and the interior critical points k pi/2); see ``_term_sum_bounds`` for the outward margin
        (``1e-12 (1 + magnitudes)``, far below any width that matters, always on the safe side).

        Parameters
        ----------
        lower, upper : (n_cells, n) float arrays
            Cell boxes, ``lower <= upper``.

        Returns
        -------
        image_lower, image_upper : (n_modes, n_cells, n) float arrays
            Contain the exact images, rounded outward (never inward).

        Raises
        ------
        InvalidInputError
            The system has no ``g_terms``, or the boxes are not finite with ``lower <= upper``.
        DimensionError
            ``lower`` / ``upper`` do not have shape (n_cells, n).
        """
        if self.g_terms is None:
            raise InvalidInputError(
                "image_bounds needs the separable form g_terms of the true system; this TrueSystem has g_terms=None")
        n = len(self.sigma)
        lower = np.asarray(lower, dtype=float)
        upper = np.asarray(upper, dtype=float)
        if lower.ndim != 2 or lower.shape[1] != n:
            raise DimensionError(f"lower must have shape (n_cells, {n}); got {lower.shape}")
        if upper.shape != lower.shape:
            raise DimensionError(f"upper must have shape {lower.shape} like lower; got {upper.shape}")
        if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))):
            raise InvalidInputError("lower and upper must be finite")
        bad = np.argwhere(lower > upper)
        if bad.size:
            q, j = (int(v) for v in bad[0])
            raise InvalidInputError(
                f"lower must be <= upper; got [{lower[q, j]}, {upper[q, j]}] at cell {q}, dim {j}")
        M = len(self.mode_names)
        img_lo = np.empty((M, lower.shape[0], n))
        img_hi = np.empty_like(img_lo)
        for u in range(M):
            for i in range(n):
                known = [("lin", j, float(self.known_A[u, i, j])) for j in range(n)
                         if self.known_A[u, i, j] != 0.0]
                if self.known_b[u, i] != 0.0:
                    known.append(("const", -1, float(self.known_b[u, i])))
                img_lo[u, :, i], img_hi[u, :, i] = _term_sum_bounds(
                    tuple(known) + tuple(self.g_terms[u][i]), lower, upper)
        return img_lo, img_hi

    def noise_model(self):
        """The noise as a :class:`robust_imdp.models.noise.TruncatedGaussianNoise`."""
        from robust_imdp.models.noise import TruncatedGaussianNoise

        return TruncatedGaussianNoise(self.sigma, self.bound)

    def sample_noise(self, k: int, rng) -> np.ndarray:
        """(k, n) independent N(0, sigma_i^2) components truncated to [-bound_i, bound_i]."""
        from scipy.stats import truncnorm

        rng = np.random.default_rng(rng)
        a = self.bound / self.sigma
        return truncnorm.rvs(-a, a, size=(k, len(self.sigma)), random_state=rng) * self.sigma

    def step(self, x, modes, rng) -> np.ndarray:
        """One step for every row of ``x`` (k, n) under ``modes`` (k,) int indices."""
        x = np.asarray(x, dtype=float)
        modes = np.broadcast_to(np.asarray(modes, dtype=np.int64), (x.shape[0],))
        known = np.einsum("kij,kj->ki", self.known_A[modes], x) + self.known_b[modes]
        return known + self.g(x, modes) + self.sample_noise(x.shape[0], rng)

    def sample_dataset(self, n_per_mode: int, lower, upper, rng):
        """Uniform i.i.d. states in the box, propagated once through each mode.

        Returns
        -------
        x : (n_modes * n_per_mode, n), u : (n_modes * n_per_mode,) int, x_next : like x
        """
        rng = np.random.default_rng(rng)
        lower, upper = np.asarray(lower, float), np.asarray(upper, float)
        u = np.repeat(np.arange(len(self.mode_names)), n_per_mode)
        x = lower + rng.random((u.size, lower.size)) * (upper - lower)
        return x, u, self.step(x, u, rng)


@dataclass(frozen=True)
class CaseStudy:
    """A named case study: true system, data size, regions, formulas, threshold."""

    name: str
    system: TrueSystem
    n_per_mode: int
    regions: dict  # name -> list of (lower, upper) pairs
    formulas: tuple
    threshold: float = 0.95
    lower: tuple = (-2.0, -2.0)
    upper: tuple = (2.0, 2.0)
    cell_size: tuple = (0.125, 0.125)
    # The assumption of the examples (unit-amplitude SE kernel): lengthscale, RKHS bound B and
    # misspecification tau, fixed before looking at the outputs. Why these values: README,
    # "Assumptions behind the guarantees" (not refuted by the data with a margin, and the true g
    # of each case study is within tau of a function of norm < B).
    gp: tuple = (("lengthscale", 2.0),)
    rkhs_bound: float = 6.0
    misspecification: float = 0.001
    data_format: str = "csv"


_SIGMA = np.array([0.01, 0.01])
_ZERO = np.zeros((2, 2))
_EYE = np.eye(2)

_THREE = CaseStudy(
    name="three_mode_linear",
    system=TrueSystem(("1", "2", "3"), np.stack([_ZERO] * 3), np.zeros((3, 2)), _g_linear,
                      _SIGMA, _SIGMA.copy(), _G_TERMS_LINEAR),
    n_per_mode=200,
    regions={
        "des": [((-1.0, -1.0), (0.0, 0.0)), ((0.0, 0.0), (1.0, 1.0))],
        "obs": [((-2.0, -2.0), (-1.0, -1.0)), ((-1.0, 0.0), (0.0, 1.0)),
                ((0.0, -1.0), (1.0, 0.0)), ((1.0, 1.0), (2.0, 2.0))],
    },
    formulas=("G !obs & F des",),
)

_FOUR = CaseStudy(
    name="four_mode_nonlinear",
    system=TrueSystem(("1", "2", "3", "4"), np.stack([_EYE] * 4), np.zeros((4, 2)), _g_nonlinear,
                      _SIGMA, _SIGMA.copy(), _G_TERMS_NONLINEAR),
    n_per_mode=300,
    regions={
        "des": [((-0.75, -0.75), (0.75, 0.75))],
        "d1": [((-1.25, 1.0), (0.0, 2.0)), ((-1.75, -2.0), (0.0, -1.5)),
               ((1.25, -1.75), (2.0, 0.0))],
        "d2": [((-0.75, -0.75), (0.75, 0.75))],
        "o": [((-1.75, -0.75), (-1.25, 1.0)), ((-1.0, -1.25), (-0.5, -0.75)),
              ((0.5, -1.75), (1.25, -1.25)), ((0.75, -0.5), (1.0, 0.5)),
              ((0.75, 0.75), (1.75, 1.75))],
    },
    formulas=("F des", "G !o & F d1 & F d2"),
    rkhs_bound=2.5,
)

_V, _OMEGA, _CURRENT = 0.15, 0.3, 0.04


def _g_unicycle(x: np.ndarray, modes: np.ndarray) -> np.ndarray:
    g = np.empty_like(x)
    g[:, 0] = _V * np.cos(x[:, 2]) + _CURRENT * np.sin(x[:, 1])
    g[:, 1] = _V * np.sin(x[:, 2])
    g[:, 2] = 0.0
    return g


_G_TERMS_UNICYCLE = tuple(
    ((("cos", 2, _V), ("sin", 1, _CURRENT)), (("sin", 2, _V),), (("const", -1, 0.0),)) for _ in range(3)
)
_PI = float(np.pi)

_UNICYCLE = CaseStudy(
    name="unicycle_3d",
    system=TrueSystem(("left", "straight", "right"), np.stack([np.eye(3)] * 3),
                      np.array([[0.0, 0.0, _OMEGA], [0.0, 0.0, 0.0], [0.0, 0.0, -_OMEGA]]), _g_unicycle,
                      np.full(3, 0.005), np.full(3, 0.01), _G_TERMS_UNICYCLE),
    n_per_mode=10_000,
    regions={
        "goal": [((3.0, 3.0, -_PI), (3.75, 3.75, _PI))],
        "obs": [((1.5, 1.0, -_PI), (2.5, 3.0, _PI))],
    },
    formulas=("G !obs & F goal",),
    threshold=0.9,
    lower=(0.0, 0.0, -_PI),
    upper=(4.0, 4.0, _PI),
    cell_size=(0.0625, 0.0625, _PI / 32),
    # local optimal weights from the 50 nearest of 10^4 samples per mode: at 64^3 cells 0.57 of
    # the known-dynamics Q_yes in ~8 min; local ridge weights ("error_bound", "ridge") take ~3 min
    # and reach 0.25 (benchmarks/reference.py, benchmarks/scale.py)
    gp=(("lengthscale", [4.0, 1.5, 1.5]), ("error_bound", "optimal"), ("local_points", 50)),
    rkhs_bound=1.0,
    misspecification=0.001,
    data_format="npz",
)

CASE_STUDIES = {c.name: c for c in (_THREE, _FOUR, _UNICYCLE)}


def get_case_study(name: str) -> CaseStudy:
    """The case study called ``name`` (one of ``CASE_STUDIES``)."""
    try:
        return CASE_STUDIES[name]
    except KeyError:
        raise InvalidInputError(
            f"case study must be one of {sorted(CASE_STUDIES)}; got {name!r}"
        ) from None


def true_system(name: str) -> TrueSystem:
    """The true system of case study ``name`` (for ``validate`` and ``simulate``)."""
    return get_case_study(name).system


def known_dynamics_cell_bounds(name: str, partition):
    """Exact (certified) image boxes of case study ``name``'s true dynamics over ``partition``.

    The input of the known-dynamics reference: ``abstraction.abstract(partition, bounds, noise)``
    with these bounds is the abstraction our pipeline would build if it knew ``f_u + g_u``
    exactly (no GP error), so its Q_yes is the best any learned bound can reach on that grid.

    Parameters
    ----------
    name : str
        A case study in ``CASE_STUDIES``.
    partition : geometry.Partition
        Cells ``partition.cells_lower`` / ``partition.cells_upper`` (n_cells, n).

    Returns
    -------
    abstraction.CellBounds
        ``image_lower``, ``image_upper`` (n_modes, n_cells, n) from
        :meth:`TrueSystem.image_bounds`, ``std_upper=None`` (known dynamics).
    """
    from robust_imdp.abstraction.rows import CellBounds

    system = true_system(name)
    lower = getattr(partition, "cells_lower", None)
    upper = getattr(partition, "cells_upper", None)
    if lower is None or upper is None:
        raise InvalidInputError(
            f"partition must be a Partition (with cells_lower / cells_upper); got {type(partition).__name__}")
    if np.shape(lower)[1:] != (len(system.sigma),):
        raise DimensionError(
            f"partition must have dimension {len(system.sigma)} like case study {name!r}; got cells of shape "
            f"{np.shape(lower)}")
    lo, hi = system.image_bounds(lower, upper)
    return CellBounds(lo, hi, None)


def _toml_list(v) -> str:
    return "[" + ", ".join(_toml_list(e) if np.ndim(e) else repr(float(e)) for e in v) + "]"


def problem_toml(case: CaseStudy, formula: str, data_path: str, *, rkhs_bound: float | None = None,
                 eta=None) -> str:
    """The TOML problem file text for ``case`` with ``formula`` (see :mod:`robust_imdp.io.files`)."""
    rkhs_bound = case.rkhs_bound if rkhs_bound is None else rkhs_bound
    lines = [
        f"# {case.name}: generated by robust_imdp.casestudies (Jackson et al., HSCC 2021, Sec. 6)",
        "[space]",
        f"lower = {_toml_list(case.lower)}",
        f"upper = {_toml_list(case.upper)}",
        f"cell_size = {_toml_list(case.cell_size)}",
        "",
    ]
    for name, boxes in case.regions.items():
        for lo, up in boxes:
            lines += [f"[[regions.{name}]]", f"lower = {_toml_list(lo)}", f"upper = {_toml_list(up)}"]
    lines += ["", "[spec]", f"formula = {formula!r}".replace("'", '"'),
              f"threshold = {case.threshold!r}", "", "[data]", f'path = "{data_path}"', ""]
    sysm = case.system
    for i, m in enumerate(sysm.mode_names):
        lines += [f'[modes."{m}"]', f"A = {_toml_list(sysm.known_A[i])}",
                  f"b = {_toml_list(sysm.known_b[i])}"]
    lines += ["", "[noise]", 'kind = "truncated_gaussian"', f"sigma = {_toml_list(sysm.sigma)}",
              f"bound = {_toml_list(sysm.bound)}", "", "[gp]", f"rkhs_bound = {float(rkhs_bound)!r}"]
    for key, value in case.gp:
        if isinstance(value, str):
            lines.append(f'{key} = "{value}"')
        elif np.ndim(value):
            lines.append(f"{key} = {_toml_list(value)}")
        else:
            lines.append(f"{key} = {value!r}")
    if case.misspecification:
        lines.append(f"misspecification = {float(case.misspecification)!r}")
    if eta is not None:
        lines += ["", "[abstraction]", f"eta = {_toml_list(np.broadcast_to(eta, sysm.sigma.shape))}"]
    return "\n".join(lines) + "\n"


def write_problem_files(name: str, directory, *, seed: int = 0, formula: str | None = None,
                        rkhs_bound: float | None = None, eta=None):
    """Generate the case study's data (fixed seed) and problem file into ``directory``.

    Returns
    -------
    Path
        The problem file ``<directory>/<name>.toml`` (data in ``<name>_data.csv``).
    """
    from pathlib import Path

    from robust_imdp.io.files import write_data_file

    case = get_case_study(name)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    x, u, x_next = case.system.sample_dataset(case.n_per_mode, case.lower, case.upper, seed)
    data_name = f"{name}_data.{case.data_format}"
    write_data_file(directory / data_name, x, u, x_next, modes=case.system.mode_names)
    path = directory / f"{name}.toml"
    path.write_text(problem_toml(case, formula or case.formulas[0], data_name, rkhs_bound=rkhs_bound, eta=eta))
    return path


# =========================================================================== assumption certificate
# Why the shipped assumption (lengthscale, rkhs_bound B, misspecification tau) is honest for the
# TRUE unknown parts: for every mode u and output i we exhibit an h = sum_j alpha_j k(., z_j) and
# certify, in floating point with outward rounding, ||h||_H <= norm_upper and
# sup_X |g_u^(i) - h| <= sup_error_upper. Then g_u^(i) is within tau of a function of norm <= B
# whenever sup_error_upper <= tau and norm_upper <= B. The certificate (certify_expansion) does
# not depend on how alpha was found; the fit (_min_norm_fit) only proposes it.

_U = 2.0 ** -53  # unit round-off of float64 (half of _EPS)
_SQRT3_UP = float(np.nextafter(np.sqrt(3.0), np.inf))  # >= sqrt(3): sqrt is correctly rounded
#: Eigenvalues of the centres' kernel matrix below this fraction of the largest are dropped by
#: the fit (a proposal only; the certificate uses the resulting alpha as it is).
_FIT_EIG_REL_TOL = 1e-9
_CHUNK = 4096  # check-grid points per kernel block (memory: _CHUNK x n_centres floats)


def _gamma(n: float) -> float:
    """``gamma_n = n u / (1 - n u)``: relative error bound of n roundings (Higham, ASNA, Lemma 3.1)."""
    return n * _U / (1.0 - n * _U)


def _up_rounded(x, n_ops: int):
    """Upper bound of the exact value of a NON-NEGATIVE expression evaluated in floats as ``x``.

    If the evaluation took at most ``n_ops`` roundings of non-negative intermediates, the exact
    value is ``<= x (1 + gamma_n) <= x (1 + 2 n u)`` (n u << 1). The product
    ``x * (1 + 2 (n + 1) u)`` (the factor is exact) is itself rounded, by at most ``(1 - u)``, and
    ``(1 + 2 (n + 1) u)(1 - u) >= 1 + 2 n u``; one more ulp up with ``nextafter`` for good measure.
    """
    return np.nextafter(np.asarray(x, float) * (1.0 + 2.0 * (n_ops + 1) * _U), np.inf)


def _check_lengthscale(lengthscale, d: int) -> np.ndarray:
    ls = np.asarray(lengthscale, dtype=float)
    if ls.ndim == 0:
        ls = np.full(d, float(ls))
    if ls.shape != (d,):
        raise DimensionError(f"lengthscale must be a float or have shape ({d},); got shape {ls.shape}")
    if not np.all(np.isfinite(ls) & (ls > 0)):
        raise InvalidInputError(f"lengthscale must be positive and finite; got {ls.tolist()}")
    return ls


def _se_kernel(A: np.ndarray, B: np.ndarray, lengthscale: np.ndarray):
    """Unit-amplitude SE kernel matrix ``exp(-sum_a (A_a - B_a)^2 / (2 l_a^2))`` and its error.

    Returns ``K`` (p, q) and ``rel`` with ``|K_computed - K_exact| <= rel K_exact`` entrywise.

    Error analysis (``z = sum_a (A_a - B_a)^2 inv_l2_a``, the exponent is ``-z/2``):
    per term one rounding for the difference (squared: 2), one for the square, two for
    ``inv_l2 = 1 / (l * l)`` and one for the product: 6; plus ``d - 1`` for the sum, so the
    computed ``z' = z (1 + t)``, ``|t| <= gamma_{d+5}``, and the exponent is off by at most
    ``gamma_{d+5} zmax / 2`` (halving is exact). ``exp`` of a float is accurate to a few ulp (we
    allow 4 ulp = 8u relative, the bound numpy documents for its SIMD kernels; glibc is < 1 ulp).
    Hence ``rel = (1 + 8u) e^{gamma zmax/2} - 1 <= (expm1(gamma zmax/2) + 8u)(1 + 1e-6)``, rounded up.
    Results stay normal floats (relative error bound valid) because ``zmax <= 1400`` is enforced.
    """
    inv_l2 = 1.0 / (lengthscale * lengthscale)
    z = np.zeros((A.shape[0], B.shape[0]))
    for a in range(A.shape[1]):
        diff = A[:, a, None] - B[None, :, a]
        z += (diff * diff) * inv_l2[a]
    zmax = float(z.max()) if z.size else 0.0
    if zmax > 1400.0:
        # exp(-z/2) < e^-700 could be subnormal (below 2.2e-308 ~ e^-708), where exp's error is
        # not relative any more; such far-apart points contribute nothing useful, so refuse.
        raise InvalidInputError(
            f"points and centres must be within sqrt(1400) ~ 37 lengthscales of each other; got sum_a "
            f"(dx_a / l_a)^2 = {zmax:.4g}")
    expo = _gamma(A.shape[1] + 6) * zmax / 2.0  # d + 6 >= d + 5: one spare rounding
    rel = float(_up_rounded((np.expm1(expo) + 8 * _U) * (1.0 + 1e-6), 4))
    return np.exp(-0.5 * z), rel


def rkhs_norm_upper(centres, alpha, lengthscale) -> float:
    """Certified upper bound of ``||sum_j alpha_j k(., z_j)||_H`` (unit-amplitude SE kernel).

    ``||h||^2 = alpha^T K alpha`` (reproducing property). In floats, with ``K'`` the computed
    matrix (``|K' - K| <= rel K`` entrywise, :func:`_se_kernel`) and ``N' = fl(alpha . fl(K' alpha))``::

        |N' - alpha^T K' alpha| <= gamma_{2n} |alpha|^T K' |alpha|      (n-term dot products, twice)
        |alpha^T K' alpha - alpha^T K alpha| <= rel |alpha|^T K |alpha| <= rel / (1 - rel) |alpha|^T K' |alpha|

    and ``|alpha|^T K' |alpha| <= W' / (1 - gamma_{2n})`` for its float value ``W'`` (all terms
    >= 0). So ``||h||^2 <= max(N', 0) + (gamma_{2n} + rel / (1 - rel)) W' / (1 - gamma_{2n})``;
    the error is added BEFORE the square root (where cancellation in ``N'`` hurts), the sum is
    rounded up (:func:`_up_rounded`) and ``sqrt`` (correctly rounded) moved one ulp up.

    Parameters
    ----------
    centres : (n, d) float array
    alpha : (n,) float array
    lengthscale : float or (d,) float array

    Returns
    -------
    float
    """
    Z = np.ascontiguousarray(centres, dtype=float)
    alpha = np.ascontiguousarray(alpha, dtype=float)
    if Z.ndim != 2 or Z.shape[0] < 1:
        raise DimensionError(f"centres must have shape (n, d) with n >= 1; got {Z.shape}")
    if alpha.shape != (Z.shape[0],):
        raise DimensionError(f"alpha must have shape ({Z.shape[0]},) like centres' rows; got {alpha.shape}")
    if not (np.all(np.isfinite(Z)) and np.all(np.isfinite(alpha))):
        raise InvalidInputError("centres and alpha must be finite")
    K, rel = _se_kernel(Z, Z, _check_lengthscale(lengthscale, Z.shape[1]))
    n = Z.shape[0]
    N = float(alpha @ (K @ alpha))
    a = np.abs(alpha)
    W = float(a @ (K @ a))
    g = _gamma(2 * n + 2)  # 2n + 2 >= the 2n roundings of the nested dot products
    # (g + rel/(1-rel)) W / (1-g): a handful of roundings of non-negative values -> _up_rounded
    err = _up_rounded((g + rel / (1.0 - rel)) * W / (1.0 - g), 6)
    N_up = _up_rounded(max(N, 0.0) + float(err), 1)  # ||h||^2 <= max(N', 0) + err (one addition)
    return float(np.nextafter(np.sqrt(N_up), np.inf))  # sqrt correctly rounded: one ulp up suffices


def _terms_values(terms, P: np.ndarray):
    """Values of ``sum_t term_t`` (a ``g_terms`` entry) at the points ``P`` (k, d), with error bounds.

    Per term: ``c`` (const) is exact; ``fl(c x_j)`` has one rounding; ``fl(c fl(sin x_j))``:
    libm/numpy sin and cos are within 4 ulp <= 8u (absolute, values in [-1, 1]), times ``|c|``,
    plus the product's rounding. The recursive sum of T terms adds ``gamma_T sum |t|``. So
    ``err <= (u + gamma_T) S + 8u (1 + u) C`` with S the sum of |term values| and C of the trig
    ``|c|``; we return ``2 ((gamma_{T+1}) S + 9u C)``, rounded up (a factor 2 of slack).
    """
    val = np.zeros(P.shape[0])
    S = np.zeros(P.shape[0])
    C = 0.0
    for kind, j, c in terms:
        c = float(c)
        if kind == "const":
            t = np.full(P.shape[0], c)
        elif kind == "lin":
            t = c * P[:, j]
        elif kind in ("sin", "cos"):
            t = c * (np.sin(P[:, j]) if kind == "sin" else np.cos(P[:, j]))
            C += abs(c)
        else:
            raise InvalidInputError(f"terms must have kinds in {_TERM_KINDS}; got {kind!r}")
        val = val + t
        S = S + np.abs(t)
    err = _up_rounded(2.0 * (_gamma(len(terms) + 1) * S + 9.0 * _U * C), 4 + len(terms))
    return val, err


def _terms_second_derivative_bounds(terms, d: int) -> np.ndarray:
    """Upper bounds ``G_a >= sup |d^2 g / dx_a^2|`` of a ``g_terms`` entry, (d,) array.

    const and lin terms have no second derivative; ``(c sin x_j)'' = -c sin x_j`` and
    ``(c cos x_j)'' = -c cos x_j`` are bounded by ``|c|`` and only along axis j. Rounded up.
    """
    G = np.zeros(d)
    for kind, j, c in terms:
        if kind in ("sin", "cos"):
            G[j] += abs(float(c))
    return _up_rounded(G, len(terms))


def _axis_grid(lo: float, hi: float, spacing: float, name: str):
    """Points ``lo = p_0 < ... < p_n = hi`` (floats, endpoints exact) with gaps ``<= spacing``.

    Returns the points and an upper bound of their largest gap (float differences rounded up).
    """
    if not (np.isfinite(spacing) and spacing > 0):
        raise InvalidInputError(f"{name} must be positive and finite; got {spacing!r}")
    n = max(1, int(np.ceil((hi - lo) / spacing)))
    pts = lo + (hi - lo) * (np.arange(n + 1) / n)
    pts[0], pts[-1] = lo, hi  # the grid covers [lo, hi] exactly
    gaps = np.diff(pts)
    if not np.all(gaps > 0):
        raise InvalidInputError(f"{name} = {spacing!r} is too fine for the box [{lo!r}, {hi!r}] in float64")
    # |fl(p - q) - (p - q)| <= u |p - q|: one rounding per gap, so round the largest up
    return pts, float(_up_rounded(gaps.max(), 1))


def _tensor_points(axes) -> np.ndarray:
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(axes))


def certify_expansion(terms, centres, alpha, lengthscale, lower, upper, *, check_spacing=1.0 / 64.0) -> dict:
    """Certified ``||h||_H`` and ``sup_X |g - h|`` for ``h = sum_j alpha_j k(., z_j)`` and ``g = sum terms``.

    ``k`` is the unit-amplitude SE kernel with ``lengthscale``; ``g`` is a ``g_terms`` entry
    (a sum of ``const``, ``c x_j``, ``c sin x_j``, ``c cos x_j`` terms, see :class:`TrueSystem`);
    ``X = [lower, upper]``.

    Method (every step rounded outward; ``e = g - h``)
        1. ``||h|| <= norm_upper`` by :func:`rkhs_norm_upper`.
        2. ``e`` at the points of a tensor grid covering X exactly (endpoints included, gaps
           ``<= s_a`` per axis), each with a bound of its float error: ``g`` by
           :func:`_terms_values`; ``h`` as ``fl(K' alpha)`` with
           ``|fl(K' alpha) - K alpha| <= (rel / (1 - rel) + gamma_n) S / (1 - gamma_n)``, ``S =
           fl(K' |alpha|)`` (kernel error ``rel`` of :func:`_se_kernel`, n-term dot product);
           the subtraction adds ``u |e'|``. Hence ``|e(p)| <= E_grid`` at every grid point.
        3. Between grid points, on each grid cell (a box with widths ``h_a <= s_a``), with ``I e``
           the multilinear interpolant of ``e`` at the cell's ``2^d`` vertices::

               |e(x)| <= |I e(x)| + |e(x) - I e(x)| <= max_vertices |e| + sum_a (s_a^2 / 8) sup |d^2 e / dx_a^2|.

           ``|I e(x)| <= max_vertices |e|`` since ``I e(x)`` is a convex combination of the vertex
           values. The remainder: with ``L_a`` linear interpolation along axis a (other
           coordinates fixed), ``I = L_1 ... L_d`` and, telescoping,
           ``e - I e = sum_a L_1 ... L_{a-1} (e - L_a e)``; every ``L_b`` is a convex combination of
           point values, so ``||L_b f||_inf <= ||f||_inf`` on the cell, and the 1-D bound
           ``|f(t) - L f(t)| = |f''(xi)| (t - t_0)(t_1 - t) / 2 <= h^2 / 8 sup |f''|`` (Atkinson, An
           Introduction to Numerical Analysis, 2nd ed., Thm 3.2 with n = 1) gives the sum of 1-D
           bounds. ``|d^2 e/dx_a^2| <= |d^2 g/dx_a^2| + |d^2 h/dx_a^2|``; the first is bounded by
           :func:`_terms_second_derivative_bounds`; for the second the derivative reproducing
           property (Zhou, J. Comput. Appl. Math. 2008, Thm 1; Steinwart & Christmann 2008,
           Cor. 4.36) gives ``d^2_a h(x) = <h, d^2_a k(x, .)>``, so
           ``|d^2_a h(x)| <= ||h|| ||d^2_a k(x, .)||_H = ||h|| sqrt(3) / l_a^2``: ``||d^2_a k(x, .)||^2 =
           d^2_{x_a} d^2_{x'_a} k(x, x')|_{x = x'} = phi''''(0)`` for ``phi(r) = e^{-r^2/(2 l_a^2)} =
           1 - r^2/(2 l_a^2) + r^4/(8 l_a^4) - ...`` (the other factors of the product kernel are 1
           at ``x = x'``), i.e. ``4! / (8 l_a^4) = 3 / l_a^4``.

        So ``sup_X |g - h| <= E_grid + sum_a (s_a^2 / 8)(G_a + norm_upper sqrt(3) / l_a^2) = sup_error_upper``.

    Parameters
    ----------
    terms : tuple of (kind, coordinate, coefficient)
        The function g (one entry of ``TrueSystem.g_terms``).
    centres : (n, d) float array
    alpha : (n,) float array
    lengthscale : float or (d,) float array
    lower, upper : (d,) float arrays
        The box X.
    check_spacing : float or (d,) float array
        Largest gap of the check grid per axis (smaller: tighter and slower).

    Returns
    -------
    dict with ``norm_upper``, ``sup_error_upper``, ``grid_max_error`` (``E_grid``, including the
    evaluation errors), ``eval_error`` (largest evaluation-error bound on the grid),
    ``interp_remainder``, ``check_spacing`` ((d,) upper bounds of the grid gaps), ``n_check``.
    """
    return _certify_batch([terms], centres, np.asarray(alpha, dtype=float)[None, :], lengthscale, lower, upper,
                          check_spacing)[0]


def _certify_batch(terms_list, centres, alphas, lengthscale, lower, upper, check_spacing) -> list:
    """:func:`certify_expansion` of several ``(terms, alpha)`` pairs on the same centres and grid.

    ``alphas`` (m, n); the kernel blocks of the check grid are computed once for all m.
    Returns a list of m dicts (see :func:`certify_expansion`).
    """
    Z = np.ascontiguousarray(centres, dtype=float)
    if Z.ndim != 2 or Z.shape[0] < 1:
        raise DimensionError(f"centres must have shape (n, d) with n >= 1; got {Z.shape}")
    n, d = Z.shape
    alphas = np.asarray(alphas, dtype=float)
    if alphas.ndim != 2 or alphas.shape[1] != n or alphas.shape[0] != len(terms_list):
        raise DimensionError(f"alpha must have shape ({n},) like centres' rows; got {alphas.shape[1:]}")
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    if lower.shape != (d,) or upper.shape != (d,):
        raise DimensionError(f"lower and upper must have shape ({d},) like centres' columns; got {lower.shape}, "
                             f"{upper.shape}")
    if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper)) and np.all(lower < upper)):
        raise InvalidInputError(f"lower must be < upper and both finite; got {lower.tolist()}, {upper.tolist()}")
    ls = _check_lengthscale(lengthscale, d)
    spacing = np.broadcast_to(np.asarray(check_spacing, dtype=float), (d,))
    norms = [rkhs_norm_upper(Z, alpha, ls) for alpha in alphas]  # also validates each alpha

    axes, gaps = [], np.empty(d)
    for a in range(d):
        pts, gaps[a] = _axis_grid(float(lower[a]), float(upper[a]), float(spacing[a]), "check_spacing")
        axes.append(pts)
    P = _tensor_points(axes)
    m = alphas.shape[0]
    gam = _gamma(n + 1)  # n-term dot products (one spare rounding)
    grid_max = np.zeros(m)
    eval_max = np.zeros(m)
    abs_alphas = np.abs(alphas)
    for start in range(0, P.shape[0], _CHUNK):
        Pc = P[start:start + _CHUNK]
        K, rel = _se_kernel(Pc, Z, ls)
        H = K @ alphas.T  # (chunk, m): h'(p) = fl(K' alpha)
        S = K @ abs_alphas.T  # fl(K' |alpha|)
        err_H = _up_rounded((rel / (1.0 - rel) + gam) * S / (1.0 - gam), 6)
        for k, terms in enumerate(terms_list):
            g, err_g = _terms_values(terms, Pc)
            e = np.abs(g - H[:, k])
            err = _up_rounded(err_g + err_H[:, k] + _U * e * (1.0 + 2 * _U), 4)
            bound = _up_rounded(e + err, 1)  # |e(p)| <= |e'| + err (one addition)
            grid_max[k] = max(grid_max[k], float(bound.max()))
            eval_max[k] = max(eval_max[k], float(err.max()))

    out = []
    for k, terms in enumerate(terms_list):
        # sup |d^2 e / dx_a^2| <= G_a + norm_upper sqrt(3) / l_a^2 (certify_expansion, step 3)
        M = _terms_second_derivative_bounds(terms, d) + norms[k] * _SQRT3_UP / (ls * ls)
        remainder = float(_up_rounded(np.sum(gaps * gaps / 8.0 * M), 8 + 2 * d))
        sup_error = float(_up_rounded(grid_max[k] + remainder, 1))
        out.append({"norm_upper": norms[k], "sup_error_upper": sup_error, "grid_max_error": float(grid_max[k]),
                    "eval_error": float(eval_max[k]), "interp_remainder": remainder, "check_spacing": gaps.copy(),
                    "n_check": P.shape[0]})
    return out


def _fit_basis(K_fz: np.ndarray, K_zz: np.ndarray):
    """``T = V_r diag(lambda_r)^{-1/2}`` (eigenvalues of ``K_zz`` above ``_FIT_EIG_REL_TOL`` x max) and ``K_fz T``."""
    lam, V = np.linalg.eigh((K_zz + K_zz.T) / 2.0)
    keep = lam > _FIT_EIG_REL_TOL * lam.max()
    T = V[:, keep] / np.sqrt(lam[keep])
    return T, K_fz @ T


def _min_norm_fit(T: np.ndarray, A: np.ndarray, y: np.ndarray, tol: float, what: str) -> np.ndarray:
    """Weights ``alpha`` of a small-norm kernel expansion within ``tol`` of ``y`` at the fit points.

    Program (a second-order cone program, solved by cvxpy + Clarabel)::

        minimise over beta in R^r   ||beta||_2
        subject to                  -tol <= K_fz T beta - y <= tol,      alpha = T beta

    (``A = K_fz T``) with ``T = V_r diag(lambda_r)^{-1/2}`` from the eigenvalues of ``K_zz`` above
    ``_FIT_EIG_REL_TOL`` times the largest (:func:`_fit_basis`), so that ``alpha^T K_zz alpha = ||beta||^2``: the
    smallest RKHS norm among expansions on these centres (restricted to the well-conditioned
    eigen-directions) that fit the data points within ``tol``. Its optimum need not bound
    anything: ``alpha`` is only a proposal, and :func:`certify_expansion` certifies norm and
    sup error of whatever comes back (an inaccurate solve costs tightness, never soundness).

    Test-support exception to the house rule "cvxpy only in robust_imdp.solvers.lp": this program is
    used only to certify the case studies' assumption (tests, README), so it lives next to
    them; cvxpy is imported lazily, and the library never calls it.
    """
    import cvxpy as cp

    from robust_imdp.errors import ConvergenceError

    beta = cp.Variable(T.shape[1])
    prob = cp.Problem(cp.Minimize(cp.norm(beta)), [A @ beta - y <= tol, y - A @ beta <= tol])
    try:
        prob.solve(solver=cp.CLARABEL)
    except cp.error.SolverError as exc:
        raise ConvergenceError(f"CLARABEL failed on the fit SOCP of {what}: {exc}") from None
    if prob.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or beta.value is None:
        raise ConvergenceError(
            f"CLARABEL did not solve the fit SOCP of {what} (tolerance {tol:g}): status {prob.status!r}; "
            "try a larger tau, more centres or a larger centre_margin")
    return T @ np.asarray(beta.value, dtype=float)


def assumption_certificate(name: str, lengthscale=2.0, tau: float = 0.002, *, fit_spacing: float = 0.2,
                           check_spacing: float = 1.0 / 64.0, centre_spacing: float = 0.5,
                           centre_margin: float = 1.0, fit_fraction: float = 0.8) -> list:
    """Certify that every true unknown component of case study ``name`` is within ``tau`` of an RKHS function.

    For every mode u and output i, ``g = g_u^(i)`` (``TrueSystem.g_terms``, i.e. ``x_next - f_u(x)``
    without noise) is fitted by ``h = sum_j alpha_j k(., z_j)`` (unit-amplitude SE kernel with
    ``lengthscale``, centres ``z_j`` on a tensor grid over X widened by ``centre_margin``, gaps
    ``<= centre_spacing``) by :func:`_min_norm_fit` with tolerance ``fit_fraction * tau`` on a fit
    grid of gaps ``<= fit_spacing``; then :func:`certify_expansion` certifies
    ``||h||_H <= norm_upper`` and ``sup_X |g - h| <= sup_error_upper`` rigorously (outward
    rounding, interpolation remainder between the check-grid points of gaps ``<= check_spacing``).
    If ``sup_error_upper <= tau``, then ``g`` satisfies the assumption "within tau (sup norm on X)
    of a function of RKHS norm <= B" for every ``B >= norm_upper``. Components with the same
    terms are fitted once.

    Parameters
    ----------
    name : str
        A case study in ``CASE_STUDIES``.
    lengthscale : float or (d,) float array
    tau : float > 0
        The misspecification allowance to certify.
    fit_spacing, check_spacing, centre_spacing : float > 0
    centre_margin : float >= 0
    fit_fraction : float in (0, 1]
        The fit's tolerance as a fraction of ``tau`` (room for the error between fit points and
        the interpolation remainder of the certificate).

    Returns
    -------
    list of dict, one per (mode, output) in mode order
        ``mode`` (name), ``output`` (0-based), ``terms``, ``lengthscale``, ``tau``, ``tau_fit``,
        ``norm_upper``, ``sup_error_upper``, ``certified`` (``sup_error_upper <= tau``),
        ``grid_max_error``, ``eval_error``, ``interp_remainder``, ``check_spacing``, ``n_check``,
        ``n_centres``, ``centres`` (n, d), ``alpha`` (n,).

    Raises
    ------
    InvalidInputError
        Unknown case study or a parameter out of range (the message names it).
    ConvergenceError
        The fit SOCP failed (no certificate can be given with these settings).
    """
    case = get_case_study(name)
    system = case.system
    lower = np.asarray(case.lower, dtype=float)
    upper = np.asarray(case.upper, dtype=float)
    d = lower.size
    ls = _check_lengthscale(lengthscale, d)
    tau = float(tau)
    if not (np.isfinite(tau) and tau > 0):
        raise InvalidInputError(f"tau must be positive and finite; got {tau!r}")
    if not (0 < float(fit_fraction) <= 1):
        raise InvalidInputError(f"fit_fraction must be in (0, 1]; got {fit_fraction!r}")
    if not (np.isfinite(centre_margin) and centre_margin >= 0):
        raise InvalidInputError(f"centre_margin must be finite and >= 0; got {centre_margin!r}")
    if system.g_terms is None:
        raise InvalidInputError(f"case study {name!r} has no g_terms (the separable form of g); cannot certify")
    centre_axes = [_axis_grid(float(lower[a] - centre_margin), float(upper[a] + centre_margin),
                              float(centre_spacing), "centre_spacing")[0] for a in range(d)]
    Z = _tensor_points(centre_axes)
    fit_axes = [_axis_grid(float(lower[a]), float(upper[a]), float(fit_spacing), "fit_spacing")[0]
                for a in range(d)]
    Pf = _tensor_points(fit_axes)
    K_zz = _se_kernel(Z, Z, ls)[0]
    K_fz = _se_kernel(Pf, Z, ls)[0]
    tau_fit = fit_fraction * tau
    T, A = _fit_basis(K_fz, K_zz)
    keys = list(dict.fromkeys(tuple(terms) for row in system.g_terms for terms in row))  # distinct, in order
    alphas = np.stack([_min_norm_fit(T, A, _terms_values(key, Pf)[0], tau_fit, f"terms {key}") for key in keys])
    certs = dict(zip(keys, zip(alphas, _certify_batch(keys, Z, alphas, ls, lower, upper, check_spacing))))
    out = []
    for u, mode in enumerate(system.mode_names):
        for i, terms in enumerate(system.g_terms[u]):
            alpha, cert = certs[tuple(terms)]
            out.append({"mode": mode, "output": i, "terms": tuple(terms), "lengthscale": ls, "tau": tau,
                        "tau_fit": tau_fit, **cert, "certified": cert["sup_error_upper"] <= tau,
                        "n_centres": Z.shape[0], "centres": Z, "alpha": alpha})
    return out


__all__ += ["rkhs_norm_upper", "certify_expansion", "assumption_certificate"]
