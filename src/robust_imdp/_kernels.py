"""The squared-exponential (SE) kernel and the bounds of its floating-point error: the one home of the kernel.

Three evaluations exist, each kept bit for bit as its users computed it (their results are
compared byte for byte across releases):

* :func:`se_kernel` -- ``sf2 * exp(-0.5 * sum_j ((a_j - b_j) / l_j)^2)`` (numpy): the GP route
  (``bounds.gp``); no error bound (the GP route does not certify the kernel's rounding);
* :func:`kernel_matrix` -- ``exp(-z/2)``, ``z = sum_a (A_a - B_a)^2 inv_l2_a`` (numba), with the
  rounded-up inverse squares :func:`inv_l2_up`, the relative error bound :func:`kernel_rel_err`
  (and its numba twin :func:`kernel_rel_err_nb`) and the norm inflation :func:`norm_inflation`
  that the rounding of the lengthscales costs: the RKHS route (``bounds.rkhs*``);
* :func:`se_kernel_with_error` -- the same ``z`` in numpy with plain ``1 / (l * l)`` and numpy's
  ``exp``, and its own relative error bound (numpy's documented 4-ulp exp): the case studies'
  assumption certificate (``casestudies.certificate``).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from robust_imdp._fp import U, gamma, up, up_rounded
from robust_imdp.errors import DimensionError, InvalidInputError

__all__ = ["se_kernel", "check_lengthscale", "kernel_matrix", "kernel_rel_err", "kernel_rel_err_nb", "inv_l2_up",
           "norm_inflation", "se_kernel_with_error"]


def check_lengthscale(lengthscale, d: int, name: str = "lengthscale") -> np.ndarray:
    """The lengthscales as a (d,) float array: a float is broadcast; each must be positive and finite."""
    ls = np.asarray(lengthscale, float)
    if ls.ndim == 0:
        ls = np.full(d, float(ls))
    if ls.shape != (d,):
        raise DimensionError(f"{name} must be a float or have shape ({d},); got shape {ls.shape}")
    if not np.all(np.isfinite(ls) & (ls > 0)):
        raise InvalidInputError(f"{name} must be positive and finite; got {ls.tolist()}")
    return ls


def se_kernel(A: np.ndarray, B: np.ndarray, lengthscale: np.ndarray, signal_variance: float) -> np.ndarray:
    """Squared-exponential kernel ``sf2 * exp(-0.5 * sum_j ((a_j - b_j) / l_j)^2)``.

    Parameters
    ----------
    A : (p, d) float array
    B : (q, d) float array
    lengthscale : (d,) float array
    signal_variance : float

    Returns
    -------
    (p, q) float array
    """
    sq = np.zeros((A.shape[0], B.shape[0]))
    # Coordinate-wise differences (no |a|^2 + |b|^2 - 2ab cancellation): O(p q) memory per dim.
    for j in range(A.shape[1]):
        diff = (A[:, j, None] - B[None, :, j]) / lengthscale[j]
        sq += diff * diff
    return signal_variance * np.exp(-0.5 * sq)


def se_gram(A: np.ndarray, B: np.ndarray, inv_l2: np.ndarray) -> np.ndarray:
    """Unit-amplitude SE kernel ``exp(-0.5 * sum_j (a_j - b_j)^2 inv_l2_j)``, (p, q), in plain numpy: the
    data-fitted function and the sample suggestions' power function (diagnostics, not bounds, so no
    error bound; the certified evaluations are :func:`kernel_matrix` and :func:`se_kernel_with_error`)."""
    return np.exp(-0.5 * np.sum((A[:, None, :] - B[None, :, :]) ** 2 * inv_l2, axis=2))


@numba.njit(cache=True)
def kernel_matrix(A, B, inv_l2):  # pragma: no cover - compiled
    """``exp(-z/2)``, ``z = sum_a (A_a - B_a)^2 inv_l2_a``, and the largest ``z`` met."""
    p, q, d = A.shape[0], B.shape[0], A.shape[1]
    K = np.empty((p, q))
    zmax = 0.0
    for i in range(p):
        for j in range(q):
            z = 0.0
            for a in range(d):
                diff = A[i, a] - B[j, a]
                z += diff * diff * inv_l2[a]
            if z > zmax:
                zmax = z
            K[i, j] = math.exp(-0.5 * z)
    return K, zmax


def kernel_rel_err(zmax: float, d: int) -> float:
    """Relative error bound of every computed kernel value ``exp(-z/2)`` with ``z <= zmax``.

    ``z`` is a sum of d products of rounded differences: relative error ``<= (d + 3) u``
    (difference, square, product with ``inv_l2`` and ``d - 1`` additions), i.e. an absolute
    error ``<= (d + 3) u z / 2`` in the exponent, a relative error ``<= e^{(d+3) u z/2} - 1`` of the
    exact exponential; exp itself is accurate to 1 ulp in glibc/LLVM (we allow 2, and the
    inverse lengthscales' own rounding, 3 u relative in ``z``, is covered by using ``d + 6``).
    """
    x = (d + 6) * U * zmax / 2.0
    return float((math.expm1(x) + 2 * U) * (1 + 1e-6) + 4 * U)


def inv_l2_up(lengthscale, d: int, name: str = "lengthscale") -> np.ndarray:
    """``1 / l_a^2`` per axis, rounded up (the RKHS route's kernel: lengthscales l' <= l)."""
    ls = check_lengthscale(lengthscale, d, name)
    # Rounded UP: the kernel actually evaluated has lengthscales l' <= l, and for SE kernels
    # H_l ⊆ H_l' with ||f||_l' <= prod_a (l_a/l'_a)^{1/2} ||f||_l (Steinwart & Christmann 2008,
    # Prop. 4.46), so the assumption carries over with B inflated by :func:`norm_inflation`.
    return up((1.0 / (ls * ls)) * (1.0 + 4 * U))


def norm_inflation(d: int) -> float:
    """Factor covering ``prod_a (l_a / l'_a)^{1/2}`` for the rounded-up inverse squares (<= 1 + 8u per axis)."""
    return 1.0 + (4 * d + 8) * U



@numba.njit(cache=True)
def kernel_rel_err_nb(zmax, d):  # pragma: no cover - compiled
    """Numba twin of :func:`kernel_rel_err` (same formula; tested equal)."""
    x = (d + 6) * U * zmax / 2.0
    return (math.expm1(x) + 2 * U) * (1 + 1e-6) + 4 * U


def se_kernel_with_error(A: np.ndarray, B: np.ndarray, lengthscale: np.ndarray):
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
    expo = gamma(A.shape[1] + 6) * zmax / 2.0  # d + 6 >= d + 5: one spare rounding
    rel = float(up_rounded((np.expm1(expo) + 8 * U) * (1.0 + 1e-6), 4))
    return np.exp(-0.5 * z), rel
