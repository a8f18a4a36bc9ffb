"""Outward rounding: the one home of the helpers that turn a float result into a sound bound.

Every bound the library prints is a float computed in round-to-nearest arithmetic. The helpers
below move such a float outward by an explicit bound on its error, and then one more ulp with
``np.nextafter``, so that the returned float is on the safe side of the real value:

* ``up(x, err)`` >= every real within ``err`` of ``x``; ``down(x, err)`` <= every such real;
* ``outward(x, err, up)`` does the same but leaves ``x`` unchanged where ``err == 0`` (the value
  was computed exactly);
* ``gamma(n)`` is Higham's ``gamma_n = n u / (1 - n u)`` (ASNA, Lemma 3.1): ``n`` roundings of a
  product or of a sum of ``n + 1`` terms have relative error at most ``gamma_n``;
* ``up_rounded(x, n)`` bounds a non-negative expression evaluated with ``n`` roundings.

Where a module needs a different rule (the relative margin of the noise probabilities, the
8-ulp margins of transcendental functions in ``models.known``), it says why next to its own code.
"""

from __future__ import annotations

import numba
import numpy as np

#: Unit round-off of float64 (half the machine epsilon).
U = 2.0 ** -53


def gamma(n: float) -> float:
    """``gamma_n = n u / (1 - n u)``: relative error bound of ``n`` roundings (Higham, ASNA, Lemma 3.1)."""
    return n * U / (1.0 - n * U)


#: From this many elements on, :func:`up` and :func:`down` take their ulp step in a compiled loop
#: (:func:`_next_float`: the same floats as ``np.nextafter``, which calls libm per element: 6-22 ns an element
#: against about 1; the exact rows spent a quarter of their time there); below it, ``np.nextafter``.
_COMPILED_FROM = 64


@numba.njit(cache=True, nogil=True)
def _next_float(v, upward):  # pragma: no cover - compiled
    """``np.nextafter(v, +inf)`` (``upward``) or ``np.nextafter(v, -inf)`` of a 1-D contiguous float64 array, bit
    for bit (tests/test_fp.py): one step of the IEEE-754 bit pattern away from or towards zero; NaN stays NaN, the
    infinity in the direction stays, a zero steps to the smallest subnormal of the direction's sign."""
    out = np.empty_like(v)
    vi = v.view(np.int64)
    oi = out.view(np.int64)
    sign = 1 if upward else -1
    for i in range(v.size):
        x = v[i]
        if 0.0 < abs(x) < np.inf:  # a positive float grows with its bits, a negative one (sign bit set) shrinks
            oi[i] = vi[i] + (sign if vi[i] >= 0 else -sign)
        elif x == 0.0:
            out[i] = 5e-324 * sign
        elif x != x or x == sign * np.inf:  # NaN, and the infinity in the direction, stay
            out[i] = x
        else:  # the other infinity: the largest float of its sign
            oi[i] = vi[i] - 1
    return out


def _step(v: np.ndarray, upward: bool):
    """``np.nextafter(v, +-inf)``, compiled for arrays of :data:`_COMPILED_FROM` elements or more."""
    if v.ndim == 0 or v.size < _COMPILED_FROM:
        return np.nextafter(v, np.inf if upward else -np.inf)
    return _next_float(np.ascontiguousarray(v).reshape(-1), upward).reshape(v.shape)


def up(x, err=0.0):
    """Upper bound of a real known to lie within ``err`` of the float ``x`` (one more ulp up)."""
    return _step(np.asarray(np.asarray(x, float) + err), True)


def down(x, err=0.0):
    """Lower bound of a real known to lie within ``err`` of the float ``x`` (one more ulp down)."""
    return _step(np.asarray(np.asarray(x, float) - err), False)


def outward(x, err, upward: bool):
    """Move ``x`` by the error bound ``err`` (>= 0) and one ulp outward, except where ``err == 0``
    (the value was computed exactly and is returned unchanged)."""
    x = np.asarray(x, dtype=float)
    err = np.broadcast_to(np.asarray(err, dtype=float), x.shape)
    moved = _step(np.asarray(x + err if upward else x - err), upward)
    return np.where(err > 0, moved, x)


def up_rounded(x, n_ops: int):
    """Upper bound of the exact value of a NON-NEGATIVE expression evaluated in floats as ``x``.

    If the evaluation took at most ``n_ops`` roundings of non-negative intermediates, the exact
    value is ``<= x (1 + gamma_n) <= x (1 + 2 n u)`` (n u << 1). The product
    ``x * (1 + 2 (n + 1) u)`` (the factor is exact) is itself rounded, by at most ``(1 - u)``, and
    ``(1 + 2 (n + 1) u)(1 - u) >= 1 + 2 n u``; one more ulp up with ``nextafter`` for good measure.
    """
    return np.nextafter(np.asarray(x, float) * (1.0 + 2.0 * (n_ops + 1) * U), np.inf)


def complement_down(x):
    """A lower bound of ``1 - x`` for floats ``x`` in [0, 1]: ``fl(1 - x)``, one ulp down only where it
    rounded up.

    The rounding error of ``s = fl(1 - x)`` is exact in floats (Fast2Sum, Dekker 1971: ``|1| >= |x|``):
    ``e = (-x) - (s - 1)`` equals ``(1 - x) - s``, so ``e < 0`` says ``s`` lies above the real ``1 - x``.
    """
    x = np.asarray(x, float)
    s = 1.0 - x
    e = (-x) - (s - 1.0)
    return np.where(e < 0, np.nextafter(s, -np.inf), s)


def complement_up(x):
    """An upper bound of ``1 - x`` for floats ``x`` in [0, 1] (:func:`complement_down`'s mirror image)."""
    x = np.asarray(x, float)
    s = 1.0 - x
    e = (-x) - (s - 1.0)
    return np.where(e > 0, np.nextafter(s, np.inf), s)
