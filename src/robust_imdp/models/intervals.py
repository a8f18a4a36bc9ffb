"""Outward-rounded interval arithmetic over the expression tapes of ``models.known``.

Every operation takes ``(lo, hi)`` arrays of its arguments and rounds the result outward
(``np.nextafter`` of the round-to-nearest value, at most half an ulp from the exact one).
Transcendentals (sin cos tan exp log tanh and non-square powers) are first widened by
``MARGIN_ULP`` ulps of the result: this module's own rule, not ``robust_imdp._fp``'s error
bounds, because numpy documents no correctly-rounded transcendentals (margins and their check
against mpmath: ``docs/known_dynamics.md``).  ``_interval_eval`` runs a whole tape over boxes
(natural interval extension); ``_point_eval`` runs it in plain floats at points.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["MARGIN_ULP"]

#: Ulps by which every transcendental result is widened (then one more nextafter).  numpy's
#: AVX-512 SVML paths document up to 4 ulp; twice that covers |impl(t) - exact(t)| and the
#: distance of any other <= 4-ulp implementation's value from ours.
MARGIN_ULP = 8

_TWO_PI = 2.0 * math.pi                         # used only inside slack-protected tests
_MAX_INT_EXPONENT = 1024                        # integer powers handled exactly up to this order


# --------------------------------------------------------------------------- rounding helpers
def _dn(x):
    """Round-to-nearest result moved one ulp towards -inf (a sound lower bound)."""
    return np.nextafter(x, -np.inf)


def _up(x):
    """Round-to-nearest result moved one ulp towards +inf (a sound upper bound)."""
    return np.nextafter(x, np.inf)


def _widen(r):
    """``[r - MARGIN_ULP ulp(r), r + MARGIN_ULP ulp(r)]`` rounded outward: encloses the exact value
    of a transcendental whose computed value is ``r`` (implementation error <= 4 ulp)."""
    s = MARGIN_ULP * np.spacing(np.abs(r))
    return _dn(r - s), _up(r + s)


def _is_int_point(c):
    value, lo, hi = c
    return lo == hi == value and value == int(value) and abs(value) <= _MAX_INT_EXPONENT


# --------------------------------------------------------------------------- interval operations
# Each takes (lo, hi) arrays of its arguments and returns (lo, hi, bad) with bad a boolean array
# (the operation is undefined somewhere on the argument interval) or None.
def _i_add(al, ah, bl, bh):
    return _dn(al + bl), _up(ah + bh), None


def _i_sub(al, ah, bl, bh):
    return _dn(al - bh), _up(ah - bl), None


def _i_mul(al, ah, bl, bh):
    p = (al * bl, al * bh, ah * bl, ah * bh)
    return _dn(np.minimum(np.minimum(p[0], p[1]), np.minimum(p[2], p[3]))), \
        _up(np.maximum(np.maximum(p[0], p[1]), np.maximum(p[2], p[3]))), None


def _i_div(al, ah, bl, bh):
    bad = (bl <= 0) & (bh >= 0)
    bl, bh = np.where(bad, 1.0, bl), np.where(bad, 1.0, bh)
    q = (al / bl, al / bh, ah / bl, ah / bh)
    return _dn(np.minimum(np.minimum(q[0], q[1]), np.minimum(q[2], q[3]))), \
        _up(np.maximum(np.maximum(q[0], q[1]), np.maximum(q[2], q[3]))), bad


def _i_sq(al, ah):
    # x^2 is decreasing on x <= 0, increasing on x >= 0: minimum 0 when 0 is inside
    lo2, hi2 = al * al, ah * ah
    inside = (al <= 0) & (ah >= 0)
    lo = np.where(inside, 0.0, _dn(np.minimum(lo2, hi2)))
    return np.maximum(lo, 0.0), _up(np.maximum(lo2, hi2)), None  # x^2 >= 0: clamp is exact


def _i_abs(al, ah):
    inside = (al <= 0) & (ah >= 0)
    m = np.maximum(np.abs(al), np.abs(ah))
    return np.where(inside, 0.0, np.minimum(np.abs(al), np.abs(ah))), m, None  # exact


def _i_sqrt(al, ah):
    bad = al < 0
    # sqrt is correctly rounded (IEEE 754): one nextafter suffices; sqrt >= 0 makes the clamp safe
    return np.maximum(_dn(np.sqrt(np.where(bad, 0.0, al))), 0.0), _up(np.sqrt(np.where(bad, 0.0, ah))), bad


def _i_monotone(fun, al, ah, lower_limit=None, upper_limit=None):
    """Increasing ``fun``: ``[fun(al), fun(ah)]`` widened by the transcendental margin."""
    lo, _ = _widen(fun(al))
    _, hi = _widen(fun(ah))
    if lower_limit is not None:  # the exact function is >= lower_limit: the clamp is safe
        lo = np.maximum(lo, lower_limit)
    if upper_limit is not None:
        hi = np.minimum(hi, upper_limit)
    return lo, hi


def _i_exp(al, ah):
    return (*_i_monotone(np.exp, al, ah, lower_limit=0.0), None)


def _i_tanh(al, ah):
    return (*_i_monotone(np.tanh, al, ah, -1.0, 1.0), None)


def _i_log(al, ah):
    bad = al <= 0
    lo, hi = _i_monotone(np.log, np.where(bad, 1.0, al), np.where(bad, 1.0, ah))
    return lo, hi, bad


def _grid_hit(al, ah, phase, period):
    """Does ``[al, ah]`` possibly contain a point ``phase + k period`` (k integer)?

    ``q = (t - phase)/period`` is computed with a relative error of a few ulps; the slack
    ``1e-13 (1 + |q|)`` is far larger, so a wrong answer can only be "yes" (which is sound: an
    extremum or a pole is assumed inside).
    """
    qa = (al - phase) / period
    qb = (ah - phase) / period
    return np.ceil(qa - 1e-13 * (1.0 + np.abs(qa))) <= np.floor(qb + 1e-13 * (1.0 + np.abs(qb)))


def _i_trig(fun, al, ah, phase_max, phase_min):
    """sin/cos: endpoints widened; 1 / -1 where a maximum / minimum may lie inside."""
    la, ua = _widen(fun(al))
    lb, ub = _widen(fun(ah))
    lo, hi = np.minimum(la, lb), np.maximum(ua, ub)
    full = (ah - al) >= 6.28  # at least (almost) a period: both extrema inside
    hi = np.where(full | _grid_hit(al, ah, phase_max, _TWO_PI), 1.0, hi)
    lo = np.where(full | _grid_hit(al, ah, phase_min, _TWO_PI), -1.0, lo)
    # sin, cos take values in [-1, 1]: the clamps are safe
    return np.maximum(lo, -1.0), np.minimum(hi, 1.0), None


def _i_sin(al, ah):
    return _i_trig(np.sin, al, ah, 0.5 * math.pi, -0.5 * math.pi)


def _i_cos(al, ah):
    return _i_trig(np.cos, al, ah, 0.0, math.pi)


def _i_tan(al, ah):
    bad = ((ah - al) >= 3.14) | _grid_hit(al, ah, 0.5 * math.pi, math.pi)
    lo, hi = _i_monotone(np.tan, np.where(bad, 0.0, al), np.where(bad, 0.0, ah))
    return lo, hi, bad


def _i_sign(al, ah):
    return np.sign(al), np.sign(ah), None  # non-decreasing, exact


def _i_min(al, ah, bl, bh):
    return np.minimum(al, bl), np.minimum(ah, bh), None  # exact


def _i_max(al, ah, bl, bh):
    return np.maximum(al, bl), np.maximum(ah, bh), None  # exact


def _i_powi(al, ah, n):
    """``x^n`` for an integer ``n >= 1``: even n has its minimum at 0 when 0 is inside."""
    if n == 1:
        return al, ah
    pl, ph = np.power(al, float(n)), np.power(ah, float(n))
    l1, u1 = _widen(pl)
    l2, u2 = _widen(ph)
    if n % 2:  # odd: increasing
        return l1, u2
    inside = (al <= 0) & (ah >= 0)
    lo = np.where(inside, 0.0, np.minimum(l1, l2))
    return np.maximum(lo, 0.0), np.maximum(u1, u2)  # x^(2k) >= 0: clamp is safe


def _i_pow(al, ah, bl, bh, int_exponent):
    """``x^y``: integer point exponents exactly (x^-n = 1/x^n); else a positive base.

    For ``x > 0``, ``x^y = exp(y log x)`` with ``y log x`` bilinear in ``(y, log x)``, so its
    extremes over a box are at the four corners; ``0^y = 0`` for ``y > 0`` extends this to x = 0.
    """
    if int_exponent is not None:
        n = int_exponent
        if n == 0:
            return np.ones_like(al), np.ones_like(al), None
        lo, hi = _i_powi(al, ah, abs(n))
        if n > 0:
            return lo, hi, None
        return _i_div(np.ones_like(lo), np.ones_like(hi), lo, hi)
    bad = ~((al > 0) | ((al >= 0) & (bl > 0)))
    al, ah = np.where(bad, 1.0, al), np.where(bad, 1.0, ah)
    los, his = [], []
    for x in (al, ah):
        for y in (bl, bh):
            lo, hi = _widen(np.power(x, y))
            los.append(lo)
            his.append(hi)
    return np.maximum(np.minimum.reduce(los), 0.0), np.maximum.reduce(his), bad  # x^y >= 0 here


_UNARY_I = {"neg": lambda al, ah: (-ah, -al, None), "sq": _i_sq, "abs": _i_abs, "sqrt": _i_sqrt,
            "exp": _i_exp, "log": _i_log, "tanh": _i_tanh, "sin": _i_sin, "cos": _i_cos, "tan": _i_tan,
            "sign": _i_sign, "twice": lambda al, ah: (2.0 * al, 2.0 * ah, None),
            "inv": lambda al, ah: _i_div(np.ones_like(al), np.ones_like(ah), al, ah)}
_BINARY_I = {"add": _i_add, "sub": _i_sub, "mul": _i_mul, "div": _i_div, "min": _i_min, "max": _i_max}

_WHY = {"div": "division by an interval that holds 0", "inv": "division by an interval that holds 0",
        "sqrt": "sqrt of an interval reaching below 0", "log": "log of an interval reaching 0 or below",
        "tan": "tan of an interval that may hold a pole (pi/2 + k pi)",
        "pow": "a power x^y undefined on the interval (non-integer y: the base reaches 0 or below; "
               "y = -n: the base holds 0)",
        "overflow": "the enclosure overflows the double range"}


def _interval_eval(tape, consts, lo, hi):
    """Interval values of ``tape``'s outputs over boxes ``[lo, hi]`` ((k, n) arrays).

    Returns ``(out_lo, out_hi, bad, why)``: ``(k, n_outputs)`` arrays, ``bad`` (k,) True where
    some operation is undefined on its argument interval or overflows, ``why`` ``(op, first box)``
    of the first such operation (or None).  Bad boxes carry placeholder values downstream.
    """
    k = lo.shape[0]
    rl, rh = [], []
    bad = np.zeros(k, dtype=bool)
    why = None
    with np.errstate(all="ignore"):
        for op, a, b in tape.instrs:
            if op == "var":
                vl, vh, nb = lo[:, a], hi[:, a], None
            elif op == "const":
                c = consts[a]
                vl, vh, nb = np.full(k, c[1]), np.full(k, c[2]), None
            elif op == "pow":
                e_op, e_a, _ = tape.instrs[b]
                n = int(consts[e_a][0]) if e_op == "const" and _is_int_point(consts[e_a]) else None
                vl, vh, nb = _i_pow(rl[a], rh[a], rl[b], rh[b], n)
            elif op == "mul" and a == b:
                vl, vh, nb = _i_sq(rl[a], rh[a])
            elif op in _BINARY_I:
                vl, vh, nb = _BINARY_I[op](rl[a], rh[a], rl[b], rh[b])
            else:
                vl, vh, nb = _UNARY_I[op](rl[a], rh[a])
            over = ~(np.isfinite(vl) & np.isfinite(vh))
            if nb is not None or over.any():
                new = (over if nb is None else (nb | over)) & ~bad
                if new.any():
                    if why is None:
                        first = int(np.flatnonzero(new)[0])
                        why = (op if nb is not None and nb[first] else "overflow", first)
                    bad |= new
                vl, vh = np.where(bad, 0.0, vl), np.where(bad, 0.0, vh)
            rl.append(vl)
            rh.append(vh)
    out_lo = np.stack([rl[r] for _, r in tape.outputs], axis=1) if tape.outputs else np.zeros((k, 0))
    out_hi = np.stack([rh[r] for _, r in tape.outputs], axis=1) if tape.outputs else np.zeros((k, 0))
    return out_lo, out_hi, bad, why


def _point_eval(tape, consts, x):
    """Floating-point values of ``tape``'s outputs at points ``x`` ((m, n) -> (m, n_outputs))."""
    m = x.shape[0]
    r = []
    with np.errstate(all="ignore"):
        for op, a, b in tape.instrs:
            if op == "var":
                v = x[:, a]
            elif op == "const":
                v = np.full(m, consts[a][0])
            elif op == "pow":
                v = np.power(r[a], r[b])
            else:
                A = r[a]
                B = r[b] if b >= 0 else None
                v = {"add": np.add, "sub": np.subtract, "mul": np.multiply, "div": np.divide,
                     "min": np.minimum, "max": np.maximum}[op](A, B) if op in _BINARY_I else \
                    {"neg": np.negative, "sq": lambda t: t * t, "abs": np.abs, "sqrt": np.sqrt, "exp": np.exp,
                     "log": np.log, "tanh": np.tanh, "sin": np.sin, "cos": np.cos, "tan": np.tan,
                     "sign": np.sign, "twice": lambda t: 2.0 * t, "inv": lambda t: 1.0 / t}[op](A)
            r.append(v)
    return np.stack([r[reg] for _, reg in tape.outputs], axis=1)
