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
* ``unicycle_3d`` (not from the paper; the 3-D scale study of benchmarks/scale.py): a unicycle (p_x, p_y, theta) on
  [0, 4]^2 x [-pi, pi] with three turning modes. Known: the heading update theta + omega_u
  (omega = +0.3, 0, -0.3) and the position itself; unknown: the motion v (cos theta, sin theta)
  (v = 0.15) plus a cross current 0.04 sin p_y along p_x. Noise N(0, 0.005^2) truncated to
  +-0.01; 10,000 samples per mode; a 64^3 grid; reach ``goal`` while avoiding ``obs``.
* ``unicycle_3d_known``: the same robot, data and regions, modelled as a robot: the kinematics
  and heading update are the known part f_u (expressions), the heading is periodic (data wrapped
  into [-pi, pi)), p_y and theta are known components (B = 0) and only the cross current
  0.04 sin p_y along p_x is learned (benchmarks/unicycle_known.py compares the two).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from robust_imdp.casestudies import vehicle as _vehicle
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
    misspecification: float = 0.001  # or a tuple per component
    data_format: str = "csv"
    # Optional, for case studies with a nonlinear known part (``[modes.NAME] f``) and periodic
    # dimensions (docs/known_dynamics.md, docs/periodic.md); None writes A/b and no periodic key.
    # ``rkhs_bound`` may then be a list per component (0 = a known component).
    known_f: tuple | None = None  # per mode, n expression strings in x1..xn
    periodic: tuple | None = None  # n bools


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

# The same robot with its kinematics known: f_u = (p_x + v cos theta, p_y + v sin theta, theta + omega_u)
# written as expressions, the heading periodic (its data wrapped into [-pi, pi)), and only the cross
# current 0.04 sin p_y along p_x learned. p_y and theta are known components (B = 0, image = certified
# range of f + tau). The drift depends on p_y alone, so its lengthscale is long in p_x and theta: the
# 50 local points then spread along those dimensions and average the noise.
# The assumption is honest (tests/test_unicycle_known.py certifies it): h(x) = h_y(p_y) k_100(p_x, 2)
# k_100(theta, 0), with h_y = sum_j alpha_j k_1.5(., z_j) fitted to 0.04 sin on [0, 4], has
# ||h|| = ||h_y|| <= 0.07367 (product kernel: the norm of a product of functions of separate
# coordinates is the product of the norms, and ||k_100(., c)|| = 1) and sup_X |g - h| <=
# sup |0.04 sin - h_y| + sup |h_y| (1 - e^{-(2^2 + pi^2) / (2 100^2)}) <= 0.00016 + 0.0402 * 0.00070 <=
# 0.00019 <= tau = 0.0002. So B = 0.074, tau = 0.0002 on p_x; the known components have g = 0
# exactly (tau = 0). The first assumption (B = 0.1, tau = 0.001 everywhere) was honest but loose.
_UNICYCLE_KNOWN_F = tuple(
    ("x1 + 0.15*cos(x3)", "x2 + 0.15*sin(x3)", heading) for heading in ("x3 + 0.3", "x3", "x3 - 0.3")
)
_UNICYCLE_KNOWN = CaseStudy(
    name="unicycle_3d_known",
    system=_UNICYCLE.system,  # the same true robot; only what the problem file states as known differs
    n_per_mode=_UNICYCLE.n_per_mode,
    regions=_UNICYCLE.regions,
    formulas=_UNICYCLE.formulas,
    threshold=_UNICYCLE.threshold,
    lower=_UNICYCLE.lower,
    upper=_UNICYCLE.upper,
    cell_size=_UNICYCLE.cell_size,
    gp=(("lengthscale", [[100.0, 1.5, 100.0], 1.0, 1.0]), ("error_bound", "optimal"), ("local_points", 50)),
    rkhs_bound=(0.074, 0.0, 0.0),
    misspecification=(0.0002, 0.0, 0.0),
    data_format="npz",
    known_f=_UNICYCLE_KNOWN_F,
    periodic=(False, False, True),
)

# The 4-D vehicle (casestudies/vehicle.py: its true system has its own exact image boxes, no g_terms).
_VEHICLE = CaseStudy(system=_vehicle.VEHICLE, **_vehicle.VEHICLE_CASE)

CASE_STUDIES = {c.name: c for c in (_THREE, _FOUR, _UNICYCLE, _UNICYCLE_KNOWN, _VEHICLE)}


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


def _toml_strings(v) -> str:
    return "[" + ", ".join(f'"{e}"' for e in v) + "]"


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
    ]
    if case.periodic is not None:
        lines.append("periodic = [" + ", ".join("true" if p else "false" for p in case.periodic) + "]")
    lines.append("")
    for name, boxes in case.regions.items():
        for lo, up in boxes:
            lines += [f"[[regions.{name}]]", f"lower = {_toml_list(lo)}", f"upper = {_toml_list(up)}"]
    lines += ["", "[spec]", f"formula = {formula!r}".replace("'", '"'),
              f"threshold = {case.threshold!r}", "", "[data]", f'path = "{data_path}"', ""]
    sysm = case.system
    for i, m in enumerate(sysm.mode_names):
        if case.known_f is not None:
            lines += [f'[modes."{m}"]', f"f = {_toml_strings(case.known_f[i])}"]
        else:
            lines += [f'[modes."{m}"]', f"A = {_toml_list(sysm.known_A[i])}",
                      f"b = {_toml_list(sysm.known_b[i])}"]
    b_text = _toml_list(rkhs_bound) if np.ndim(rkhs_bound) else f"{float(rkhs_bound)!r}"
    lines += ["", "[noise]", 'kind = "truncated_gaussian"', f"sigma = {_toml_list(sysm.sigma)}",
              f"bound = {_toml_list(sysm.bound)}", "", "[learning]", f"rkhs_bound = {b_text}"]
    for key, value in case.gp:
        if isinstance(value, bool):
            lines.append(f"{key} = {'true' if value else 'false'}")
        elif isinstance(value, str):
            lines.append(f'{key} = "{value}"')
        elif isinstance(value, (list, tuple)) or np.ndim(value):
            lines.append(f"{key} = {_toml_list(value)}")
        else:
            lines.append(f"{key} = {value!r}")
    if case.misspecification:
        tau = case.misspecification
        lines.append(f"misspecification = {_toml_list(tau) if np.ndim(tau) else repr(float(tau))}")
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
    if case.periodic is not None:  # a real robot reports its heading wrapped into [-pi, pi)
        from robust_imdp.models.geometry import wrap_points

        x_next = wrap_points(x_next, np.asarray(case.lower, float), np.asarray(case.upper, float), case.periodic)
    data_name = f"{name}_data.{case.data_format}"
    write_data_file(directory / data_name, x, u, x_next, modes=case.system.mode_names)
    path = directory / f"{name}.toml"
    path.write_text(problem_toml(case, formula or case.formulas[0], data_name, rkhs_bound=rkhs_bound, eta=eta))
    return path
