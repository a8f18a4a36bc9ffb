"""A 4-D planar vehicle ``(p_x, p_y, theta, v)``: known kinematics, periodic heading, learned drag.

The true system, one step of length 1 under mode ``u``::

    p_x' = p_x + v cos(theta)                     + w_1
    p_y' = p_y + v sin(theta)                     + w_2
    theta' = theta + omega_u                      + w_3      (heading periodic on [-pi, pi))
    v'   = k_u v + a_u - c_d v |v|                + w_4      (c_d v |v|: the unknown drag)

with the modes ``accelerate`` (a = +0.08), ``brake`` (k = 0.75), ``left`` and ``right``
(omega = +-0.5 rad, coasting) and the noise ``w`` a truncated Gaussian (sigma 0.005, bound 0.01 per
component). What the problem file states as known (``[modes.NAME] f``) is everything but the drag:
``f_u = (x1 + x4 cos x3, x2 + x4 sin x3, x3 + omega_u, k_u x4 + a_u)``; ``p_x``, ``p_y`` and
``theta`` are known components (``rkhs_bound = 0``) and only ``g_u^(4) = -c_d v |v|`` is learned
from the data (``rkhs_bound = [0, 0, 0, B]``, lengthscale long in every coordinate but ``v``).

:class:`VehicleSystem` duck-types ``casestudies.systems.TrueSystem`` (``mode_names``, ``sigma``,
``bound``, ``known_A``, ``known_b``, ``g``, ``g_terms = None``, ``step``, ``sample_noise``,
``sample_dataset``, ``noise_model``, ``image_bounds``) so ``validate``/``simulate``, the problem files
and the known-dynamics reference (``systems.known_dynamics_cell_bounds("vehicle_4d", partition)``)
take it as they are; ``systems`` registers it as ``CASE_STUDIES["vehicle_4d"]``. Its kinematics are
not a sum of one-coordinate terms (``v cos theta``), so it has its own certified image boxes
(:meth:`VehicleSystem.image_bounds`, eq. V1-V4 there).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from robust_imdp.errors import DimensionError, InvalidInputError

__all__ = ["VehicleSystem", "VEHICLE", "VEHICLE_CASE", "trig_range", "drag_map_range"]

_PI = float(np.pi)
#: Turn per step (rad). Between one and two heading cells (pi/8 at 16, pi/10 at 20 cells per turn) plus
#: the noise bound, so a turn's image never meets its own heading cell (Thm 1's upper bound is 1 on any
#: cell the expanded image meets: a turn of exactly one cell could be undone by the adversary).
_OMEGA = 0.5
_TWO_PI = 2.0 * _PI
#: Outward margin of image_bounds, relative to the magnitudes involved (see ``_outward``).
_MARGIN_REL = 1e-12
#: Slack of the critical-point test of ``trig_range``, relative to (1 + |argument|): far above the
#: few-ulp error of ``(t - phase) / 2pi`` in floats (see trig_range).
_CRIT_SLACK = 1e-12


def trig_range(kind: str, lo, hi):
    """Ranges ``[min, max]`` of ``sin`` or ``cos`` over the intervals ``[lo, hi]`` (arrays), sound.

    The extremes of ``sin``/``cos`` over an interval are at its ends or at interior critical
    points (sin: maxima pi/2 + 2k pi, minima -pi/2 + 2k pi; cos: 0 + 2k pi and pi + 2k pi). A
    critical point ``c + 2k pi`` lies in ``[lo, hi]`` iff ``floor((hi - c) / 2pi) >= (lo - c) / 2pi``;
    the test is made in floats with a slack of ``1e-12 (1 + |lo| + |hi|)`` in favour of "inside", so a
    float error can only add a critical point (bound +-1: a superset, sound), never drop one. The end
    values come from libm (<= 4 ulp, docs/known_dynamics.md), covered by the caller's margin.
    An interval at least 2 pi wide gets ``[-1, 1]``.

    Returns
    -------
    fmin, fmax : float arrays like ``lo`` (end values not yet rounded outward)
    """
    lo = np.asarray(lo, dtype=float)
    hi = np.asarray(hi, dtype=float)
    f = np.sin if kind == "sin" else np.cos
    peak, trough = (0.5 * _PI, -0.5 * _PI) if kind == "sin" else (0.0, _PI)
    f_lo, f_hi = f(lo), f(hi)
    fmin, fmax = np.minimum(f_lo, f_hi), np.maximum(f_lo, f_hi)
    slack = _CRIT_SLACK * (1.0 + np.abs(lo) + np.abs(hi))

    def has(c):
        # some integer k with lo - slack <= c + 2k pi <= hi + slack
        return np.floor((hi + slack - c) / _TWO_PI) >= (lo - slack - c) / _TWO_PI

    wide = (hi - lo) >= _TWO_PI
    fmax = np.where(has(peak) | wide, 1.0, fmax)
    fmin = np.where(has(trough) | wide, -1.0, fmin)
    return fmin, fmax


def drag_map_range(k, a, c, lo, hi):
    """Range of ``phi(v) = k v + a - c v |v|`` over ``[lo, hi]`` (arrays), ``k >= 0``, ``c >= 0``.

    ``phi`` is C^1 and piecewise quadratic: ``phi'(v) = k - 2 c |v|``, zero only at ``v = +-k / (2c)``
    (``c > 0``). Its extremes over an interval are at the ends or at those critical points where
    they lie inside; all candidates are evaluated (exact range up to the float error of a few
    operations, covered by the caller's margin). A critical point is taken when it lies inside up to
    a relative slack, in favour of inside (a superset of candidates: sound).

    Returns
    -------
    fmin, fmax : float arrays like ``lo`` (not yet rounded outward)
    mag : float array, a bound on the magnitudes of the terms (for the margin)
    """
    lo = np.asarray(lo, dtype=float)
    hi = np.asarray(hi, dtype=float)

    def phi(v):
        return k * v + a - c * v * np.abs(v)

    f_lo, f_hi = phi(lo), phi(hi)
    fmin, fmax = np.minimum(f_lo, f_hi), np.maximum(f_lo, f_hi)
    if c > 0.0:
        slack = _CRIT_SLACK * (1.0 + np.abs(lo) + np.abs(hi))
        for vc in (k / (2.0 * c), -k / (2.0 * c)):
            inside = (lo - slack <= vc) & (vc <= hi + slack)
            val = phi(vc)
            fmin = np.where(inside, np.minimum(fmin, val), fmin)
            fmax = np.where(inside, np.maximum(fmax, val), fmax)
    vmax = np.maximum(np.abs(lo), np.abs(hi))
    mag = abs(k) * vmax + abs(a) + c * vmax * vmax
    return fmin, fmax, mag


def _outward(lo, hi, mag):
    """``[lo - m, hi + m]`` moved one more ulp outward, ``m = 1e-12 (1 + mag)``.

    Why it is never inward: each bound of :meth:`VehicleSystem.image_bounds` is a float expression of
    at most ~8 operations on the cell's corners, each correctly rounded (<= eps/2 relative) except
    sin/cos (<= 4 ulp of a value in [-1, 1], numpy SVML; glibc < 1 ulp), so its error is below
    ``16 eps (1 + mag) < 4e-15 (1 + mag)`` with ``mag`` a bound on the magnitudes of the terms; the
    margin is 250 times that. It also covers the float evaluation of :meth:`VehicleSystem.step`.
    """
    m = _MARGIN_REL * (1.0 + mag)
    return np.nextafter(lo - m, -np.inf), np.nextafter(hi + m, np.inf)


@dataclass(frozen=True, eq=False)
class VehicleSystem:
    """The planar vehicle, vectorised over rows with per-row modes (see the module docstring).

    Attributes
    ----------
    mode_names : tuple of str
    accel, speed_factor, omega : (n_modes,) float arrays
        ``a_u``, ``k_u`` (>= 0) and ``omega_u`` of the mode.
    drag : float
        ``c_d >= 0`` of the unknown drag ``-c_d v |v|``.
    sigma, bound : (4,) float arrays of the truncated Gaussian noise
    """

    mode_names: tuple = ("accelerate", "brake", "left", "right")
    accel: np.ndarray = field(default_factory=lambda: np.array([0.08, 0.0, 0.0, 0.0]))
    speed_factor: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.75, 1.0, 1.0]))
    omega: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, _OMEGA, -_OMEGA]))
    drag: float = 0.25
    sigma: np.ndarray = field(default_factory=lambda: np.full(4, 0.005))
    bound: np.ndarray = field(default_factory=lambda: np.full(4, 0.01))

    def __post_init__(self):
        M = len(self.mode_names)
        for name in ("accel", "speed_factor", "omega"):
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.shape != (M,) or not np.all(np.isfinite(arr)):
                raise DimensionError(f"{name} must be {M} finite floats (one per mode); got {arr.tolist()}")
            object.__setattr__(self, name, arr)
        if np.any(self.speed_factor < 0):
            raise InvalidInputError(f"speed_factor must be >= 0; got {self.speed_factor.tolist()}")
        if not (np.isfinite(self.drag) and self.drag >= 0):
            raise InvalidInputError(f"drag must be a finite float >= 0; got {self.drag!r}")
        for name in ("sigma", "bound"):
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.shape != (4,) or not np.all(np.isfinite(arr) & (arr > 0)):
                raise DimensionError(f"{name} must be 4 positive floats; got {arr.tolist()}")
            object.__setattr__(self, name, arr)

    # ------------------------------------------------------------------ the model
    def known_f(self) -> tuple:
        """The known part per mode as expression strings in ``x1..x4`` (everything but the drag)."""
        out = []
        for u in range(len(self.mode_names)):
            k, a, w = (float(self.speed_factor[u]), float(self.accel[u]), float(self.omega[u]))
            heading = "x3" if w == 0.0 else f"x3 {'+' if w > 0 else '-'} {abs(w)!r}"
            speed = ("x4" if k == 1.0 else f"{k!r}*x4") + ("" if a == 0.0 else f" {'+' if a > 0 else '-'} {abs(a)!r}")
            out.append(("x1 + x4*cos(x3)", "x2 + x4*sin(x3)", heading, speed))
        return tuple(out)

    @property
    def known_A(self) -> np.ndarray:
        """(n_modes, 4, 4): ``diag(1, 1, 1, k_u)``, the affine part of ``TrueSystem``'s decomposition."""
        A = np.tile(np.eye(4), (len(self.mode_names), 1, 1))
        A[:, 3, 3] = self.speed_factor
        return A

    @property
    def known_b(self) -> np.ndarray:
        """(n_modes, 4): ``(0, 0, omega_u, a_u)``."""
        b = np.zeros((len(self.mode_names), 4))
        b[:, 2], b[:, 3] = self.omega, self.accel
        return b

    #: No separable form (``v cos theta`` is a product); :meth:`image_bounds` is the system's own.
    g_terms = None

    def g(self, x, modes) -> np.ndarray:
        """The non-affine rest ``(v cos theta, v sin theta, 0, -c_d v |v|)`` at the rows of ``x`` (k, 4).

        As in ``TrueSystem``, ``known_A x + known_b + g`` is the noise-free step; this split is the
        true system's, not the problem's (whose known part is :meth:`known_f`: all but the drag).
        ``modes`` is unused (the rest does not depend on the mode).
        """
        x = np.asarray(x, dtype=float)
        out = np.zeros_like(x)
        out[:, 0] = x[:, 3] * np.cos(x[:, 2])
        out[:, 1] = x[:, 3] * np.sin(x[:, 2])
        out[:, 3] = self.drag_term(x)
        return out

    def drag_term(self, x) -> np.ndarray:
        """The unknown part of the problem, ``-c_d v |v|`` (component ``v``), at the rows of ``x`` (k, 4)."""
        x = np.asarray(x, dtype=float)
        return -self.drag * x[:, 3] * np.abs(x[:, 3])

    def noise_model(self):
        """The noise as a :class:`robust_imdp.models.noise.TruncatedGaussianNoise`."""
        from robust_imdp.models.noise import TruncatedGaussianNoise

        return TruncatedGaussianNoise(self.sigma, self.bound)

    def sample_noise(self, k: int, rng) -> np.ndarray:
        """(k, 4) independent N(0, sigma_i^2) components truncated to [-bound_i, bound_i]."""
        from scipy.stats import truncnorm

        rng = np.random.default_rng(rng)
        a = self.bound / self.sigma
        return truncnorm.rvs(-a, a, size=(k, 4), random_state=rng) * self.sigma

    def mean_step(self, x, modes) -> np.ndarray:
        """The noise-free step ``f_u(x) + g_u(x)`` for every row of ``x`` (k, 4) under ``modes`` (k,)."""
        x = np.asarray(x, dtype=float)
        if x.ndim != 2 or x.shape[1] != 4:
            raise DimensionError(f"x must have shape (k, 4); got {x.shape}")
        modes = np.broadcast_to(np.asarray(modes, dtype=np.int64), (x.shape[0],))
        px, py, th, v = x.T
        out = np.empty_like(x)
        out[:, 0] = px + v * np.cos(th)
        out[:, 1] = py + v * np.sin(th)
        out[:, 2] = th + self.omega[modes]
        out[:, 3] = self.speed_factor[modes] * v + self.accel[modes] - self.drag * v * np.abs(v)
        return out

    def step(self, x, modes, rng) -> np.ndarray:
        """One step for every row of ``x`` (k, 4) under ``modes`` (k,) int indices (heading not wrapped)."""
        nxt = self.mean_step(x, modes)
        return nxt + self.sample_noise(nxt.shape[0], rng)

    def sample_dataset(self, n_per_mode: int, lower, upper, rng):
        """Uniform i.i.d. states in the box, propagated once through each mode.

        Returns
        -------
        x : (n_modes * n_per_mode, 4), u : (n_modes * n_per_mode,) int, x_next : like x
        """
        rng = np.random.default_rng(rng)
        lower, upper = np.asarray(lower, float), np.asarray(upper, float)
        u = np.repeat(np.arange(len(self.mode_names)), n_per_mode)
        x = lower + rng.random((u.size, lower.size)) * (upper - lower)
        return x, u, self.step(x, u, rng)

    # ------------------------------------------------------------------ exact image boxes
    def image_bounds(self, lower, upper):
        """Certified boxes of the noise-free images ``{f_u(x) + g_u(x) : x in cell}``, per mode.

        Over a box the four inputs vary independently, and each output is exact as an interval
        expression in which every input appears once:

        * (V1) ``p_x + v cos(theta)``: ``[p_x] + [v] * [cos theta]``, the product of two independent
          intervals attaining its extremes at the corners, ``[cos theta]`` by :func:`trig_range`;
        * (V2) ``p_y + v sin(theta)``: likewise with sin;
        * (V3) ``theta + omega_u``: a shift;
        * (V4) ``k_u v + a_u - c_d v |v|``: one-variable, :func:`drag_map_range`.

        So the boxes are the exact images up to float error, moved outward by ``_outward``
        (``1e-12 (1 + magnitudes)`` then one ulp: never inward).

        Parameters
        ----------
        lower, upper : (n_cells, 4) float arrays
            Cell boxes, ``lower <= upper``.

        Returns
        -------
        image_lower, image_upper : (n_modes, n_cells, 4) float arrays
        """
        lower = np.asarray(lower, dtype=float)
        upper = np.asarray(upper, dtype=float)
        if lower.ndim != 2 or lower.shape[1] != 4:
            raise DimensionError(f"lower must have shape (n_cells, 4); got {lower.shape}")
        if upper.shape != lower.shape:
            raise DimensionError(f"upper must have shape {lower.shape} like lower; got {upper.shape}")
        if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))):
            raise InvalidInputError("lower and upper must be finite")
        bad = np.argwhere(lower > upper)
        if bad.size:
            q, j = (int(v) for v in bad[0])
            raise InvalidInputError(
                f"lower must be <= upper; got [{lower[q, j]}, {upper[q, j]}] at cell {q}, dim {j}")
        M, K = len(self.mode_names), lower.shape[0]
        img_lo = np.empty((M, K, 4))
        img_hi = np.empty_like(img_lo)
        vl, vh = lower[:, 3], upper[:, 3]
        vmag = np.maximum(np.abs(vl), np.abs(vh))
        for pos, kind in ((0, "cos"), (1, "sin")):
            tl, th = trig_range(kind, lower[:, 2], upper[:, 2])
            corners = np.stack([vl * tl, vl * th, vh * tl, vh * th])  # (V1)/(V2): product of intervals
            lo = lower[:, pos] + corners.min(axis=0)
            hi = upper[:, pos] + corners.max(axis=0)
            mag = np.maximum(np.abs(lower[:, pos]), np.abs(upper[:, pos])) + vmag
            lo, hi = _outward(lo, hi, mag)
            img_lo[:, :, pos], img_hi[:, :, pos] = lo, hi
        for u in range(M):
            w = float(self.omega[u])
            mag = np.maximum(np.abs(lower[:, 2]), np.abs(upper[:, 2])) + abs(w)
            img_lo[u, :, 2], img_hi[u, :, 2] = _outward(lower[:, 2] + w, upper[:, 2] + w, mag)  # (V3)
            fmin, fmax, mag = drag_map_range(float(self.speed_factor[u]), float(self.accel[u]), float(self.drag),
                                             vl, vh)  # (V4)
            img_lo[u, :, 3], img_hi[u, :, 3] = _outward(fmin, fmax, mag)
        return img_lo, img_hi


#: The true vehicle of case study ``vehicle_4d``.
VEHICLE = VehicleSystem()

#: The case study's settings (``casestudies.systems.CaseStudy`` keyword arguments but ``system``);
#: the region boxes leave theta and v free.
VEHICLE_CASE = dict(
    name="vehicle_4d",
    n_per_mode=5_000,
    regions={
        "goal": [((0.0, 3.0, -_PI, 0.0), (4.0, 4.0, _PI, 0.8))],
        "obs": [((1.0, 1.0, -_PI, 0.0), (3.0, 2.0, _PI, 0.8))],
    },
    formulas=("G !obs & F goal",),
    threshold=0.9,
    lower=(0.0, 0.0, -_PI, 0.0),
    upper=(4.0, 4.0, _PI, 0.8),
    cell_size=(0.25, 0.25, _PI / 8, 0.05),
    # the drag depends on v alone: long lengthscales elsewhere let the local points spread along
    # p_x, p_y, theta and average the noise; only v is learned (B = 0: known components)
    gp=(("lengthscale", [100.0, 100.0, 100.0, 0.5]), ("error_bound", "optimal"), ("local_points", 50)),
    rkhs_bound=(0.0, 0.0, 0.0, 0.5),
    misspecification=0.001,
    data_format="npz",
    known_f=VEHICLE.known_f(),
    periodic=(False, False, True, False),
)
