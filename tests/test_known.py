"""Known nonlinear dynamics (robust_imdp.models.known): parser, certified image bounds, rounding margins.

Soundness tests compare against exact values: mpmath at 120 bits (exact to far below one ulp of
a double), ``fractions.Fraction`` for decimal constants, and ranges attained at vertices or at
known extremum points of monotone pieces.  Every random test is seeded.  The tightness tests
(``test_every_operation_is_tight_*``) use boxes whose exact range is known; a 0.1 % inward
shrink of any operation's result (or of the final enclosure) moves a bound inside that range by
1e-3 of its width, far more than the allowed rounding slack, so it fails them.
"""

from __future__ import annotations

import math
from fractions import Fraction

import mpmath
import numpy as np
import pytest

from robust_imdp.errors import DimensionError, ExpressionDomainError, ExpressionError, InvalidInputError
from robust_imdp.models.known import MARGIN_ULP, KnownDynamics, _widen

mpmath.mp.prec = 120  # exact reference: 120-bit values round to the correctly rounded double

MP = {"sin": mpmath.sin, "cos": mpmath.cos, "tan": mpmath.tan, "exp": mpmath.exp, "log": mpmath.log,
      "tanh": mpmath.tanh, "sqrt": mpmath.sqrt, "abs": abs}


def one(expr, n=1):
    """KnownDynamics with ``expr`` as the first of n components (the others identity)."""
    return KnownDynamics([expr] + [f"x{k}" for k in range(2, n + 1)])


def enclose(kd, lo, hi, form="best"):
    b = kd.image_bounds(np.atleast_2d(np.asarray(lo, float)), np.atleast_2d(np.asarray(hi, float)), form=form)
    return b.lower[0, 0], b.upper[0, 0]


# --------------------------------------------------------------------------- parser
@pytest.mark.parametrize("expr, expected", [
    ("x1 + x2", lambda a, b: a + b), ("x1 - x2", lambda a, b: a - b), ("x1 * x2", lambda a, b: a * b),
    ("x1 / x2", lambda a, b: a / b), ("x1 ^ 3", lambda a, b: a ** 3), ("x1 ** 2", lambda a, b: a ** 2),
    ("x2 ^ 0.5", lambda a, b: b ** 0.5), ("x2 ^ x1", lambda a, b: b ** a), ("-x1", lambda a, b: -a),
    ("+x1", lambda a, b: a),
    ("sin(x1)", lambda a, b: math.sin(a)), ("cos(x1)", lambda a, b: math.cos(a)),
    ("tan(x1)", lambda a, b: math.tan(a)), ("exp(x1)", lambda a, b: math.exp(a)),
    ("log(x2)", lambda a, b: math.log(b)), ("sqrt(x2)", lambda a, b: math.sqrt(b)),
    ("abs(x1)", lambda a, b: abs(a)), ("tanh(x1)", lambda a, b: math.tanh(a)),
    ("min(x1, x2)", lambda a, b: min(a, b)), ("max(x1, x2, 0.1)", lambda a, b: max(a, b, 0.1)),
    ("min(x1, x2, -1, 2*x1)", lambda a, b: min(a, b, -1, 2 * a)), ("pi * x1", lambda a, b: math.pi * a),
    ("1.5e-1 * x1 + .5", lambda a, b: 0.15 * a + 0.5),
])
def test_every_operator_and_function_evaluates_like_math(expr, expected):
    kd = KnownDynamics([expr, "x2"])
    pts = np.array([[-0.7, 1.3], [0.4, 2.5], [1.1, 0.2]])
    got = kd.evaluate(pts)[:, 0]
    want = [expected(a, b) for a, b in pts]
    np.testing.assert_allclose(got, want, rtol=1e-15, atol=0)  # the same double operations


@pytest.mark.parametrize("expr, value", [
    ("1 + 2*3", 7.0), ("2*3^2", 18.0), ("-2^2", -4.0),  # ^ binds tighter than unary minus
    ("2^3^2", 512.0), ("(2^3)^2", 64.0), ("2**3**2", 512.0),  # right-associative
    ("2^-1", 0.5), ("2^-1^2", 0.5),  # 2^(-(1^2))
    ("10 - 4 - 3", 3.0), ("64 / 4 / 2", 8.0),  # left-associative
    ("-(1 + 2) * 3", -9.0), ("--2", 2.0), ("2 * -3", -6.0), ("max(1, 2, 3, 4)", 4.0),
])
def test_precedence_and_associativity(expr, value):
    assert one(expr).evaluate(np.zeros((1, 1)))[0, 0] == value


@pytest.mark.parametrize("expr, pattern", [
    ("y + 1", r"unknown symbol 'y' at position 0 \(expected x1\.\.x3, pi or a function"),
    ("x4 + 1", r"unknown symbol 'x4' \(the state has 3 dimensions\) at position 0"),
    ("x0", r"unknown symbol 'x0'"),
    ("x1 + * 2", r"unexpected '\*' at position 5 \(expected a number, x1\.\.x3, pi, a function or '\('\)"),
    ("sin x1", r"at position 4 \(expected '\(' after the function 'sin'\)"),
    ("min(x1)", r"min takes 2 or more arguments, got 1"),
    ("sin(x1, x2)", r"sin takes 1 argument, got 2"),
    ("(x1 + 2", r"unexpected end of the expression at position 7 \(expected '\)' closing the '\(' at position 0\)"),
    ("x1 x2", r"unexpected 'x2' at position 3 \(expected an operator"),
    ("", r"empty expression"),
    ("x1 $ 2", r"unexpected character '\$' at position 3"),
    ("1e999 * x1", r"constant 1e999 is out of the double range"),
    ("__import__('os').system('true')", r"unexpected character \"'\" at position 11"),  # never eval'd
    ("__import__(x1)", r"unknown symbol '__import__' at position 0"),
    ("x1 ^", r"unexpected end of the expression at position 4"),
    ("e * x1", r"unknown symbol 'e'"),
])
def test_syntax_errors_name_the_component_position_and_expectation(expr, pattern):
    with pytest.raises(ExpressionError, match=pattern) as info:
        KnownDynamics(["x1", expr, "x3"], name='mode "left"')
    msg = str(info.value)
    assert msg.startswith(f'mode "left": f[2] = "{expr}"')
    assert isinstance(info.value, ValueError)


def test_bad_arguments_are_refused():
    with pytest.raises(InvalidInputError, match="sequence of expressions"):
        KnownDynamics("x1 + 1")
    with pytest.raises(InvalidInputError, match=r"f\[1\] = .*must be a string"):
        KnownDynamics([1.0])
    kd = KnownDynamics(["x1", "x2"])
    with pytest.raises(DimensionError, match=r"x must have shape \(m, 2\); got \(3, 3\)"):
        kd.evaluate(np.zeros((3, 3)))
    with pytest.raises(InvalidInputError, match=r"box 1 is lower \[0.0, 1.0\], upper \[1.0, 0.5\]"):
        kd.image_bounds([[0, 0], [0, 1]], [[1, 1], [1, 0.5]])


def test_decimal_constants_and_pi_are_enclosed_exactly():
    for text in ("0.1", "0.15", "1e-400", "3", "123456789.123456789", "2.5"):
        lo, hi = enclose(one(text), [0.0], [0.0], form="natural")
        assert Fraction(lo) <= Fraction(text) <= Fraction(hi), text
        assert hi - lo <= 2 * np.spacing(abs(float(text))) + 5e-324  # one neighbouring double
    lo, hi = enclose(one("pi"), [0.0], [0.0], form="natural")
    assert mpmath.mpf(lo) <= mpmath.pi <= mpmath.mpf(hi) and lo < hi


def test_casadi_sx_and_mx_inputs_match_the_parsed_expression():
    import casadi as ca

    text = ["x1 + 0.1*x3*cos(x2)", "x2 + 0.1*x3*sin(x2) - min(x1, x3)^2", "x3 - 0.05*x3*abs(x3) + tanh(x1)/3"]
    parsed = KnownDynamics(text)
    rng = np.random.default_rng(3)
    lo = rng.uniform(-2, 2, (200, 3))
    hi = lo + rng.uniform(0.01, 0.5, (200, 3))
    pts = rng.uniform(-2, 2, (50, 3))
    for sym in (ca.SX, ca.MX):
        x = sym.sym("x", 3)
        f = ca.vertcat(x[0] + 0.1 * x[2] * ca.cos(x[1]), x[1] + 0.1 * x[2] * ca.sin(x[1]) - ca.fmin(x[0], x[2]) ** 2,
                       x[2] - 0.05 * x[2] * ca.fabs(x[2]) + ca.tanh(x[0]) / 3)
        kd = KnownDynamics(f, x)
        np.testing.assert_allclose(kd.evaluate(pts), parsed.evaluate(pts), rtol=1e-14, atol=1e-15)
        # casadi's own Jacobian of the user's expression at each point
        Jf = ca.Function("J", [x], [ca.jacobian(f, x)])
        for p in pts[:10]:
            np.testing.assert_allclose(kd.jacobian(p[None])[0], np.array(Jf(p)), rtol=1e-12, atol=1e-14)
        b = kd.image_bounds(lo, hi)
        v = kd.evaluate(rng.uniform(lo, hi))
        assert np.all((b.lower <= v) & (v <= b.upper))
    with pytest.raises(ExpressionError, match="OP_ATAN is not supported"):
        x = ca.SX.sym("x", 1)
        KnownDynamics(ca.atan(x), x)
    with pytest.raises(InvalidInputError, match="needs x, a casadi symbol"):
        KnownDynamics(ca.SX.sym("y", 2))


def test_jacobian_matches_central_differences():
    kd = KnownDynamics(["x1*sin(x2) + exp(x3)/(2 + x1^2)", "sqrt(1 + x2^2) * log(2 + cos(x1))", "x1^x2 + tan(x3/3)"])
    rng = np.random.default_rng(5)
    x = np.column_stack([rng.uniform(0.5, 2, 40), rng.uniform(-1, 1, 40), rng.uniform(-1, 1, 40)])
    J = kd.jacobian(x)
    h = 1e-6
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        fd = (kd.evaluate(x + e) - kd.evaluate(x - e)) / (2 * h)
        np.testing.assert_allclose(J[:, :, j], fd, rtol=1e-6, atol=1e-7)  # O(h^2) + cancellation ~1e-10/h


# --------------------------------------------------------------------------- rounding margins vs mpmath
def _ulps(got, exact):
    """|got - exact| in ulps of the correctly rounded double of ``exact``."""
    ref = float(exact)
    return float(abs(mpmath.mpf(got) - exact) / mpmath.mpf(np.spacing(abs(ref)) if ref != 0 else 5e-324))


def _test_points(rng):
    big = np.concatenate([rng.uniform(-1e6, 1e6, 200), 10.0 ** rng.uniform(6, 22, 200) * rng.choice([-1, 1], 200),
                          [1e22, 2.0 ** 60, 1e300, -1e308]])
    near = np.concatenate([(np.arange(-40, 41) * (math.pi / 2))[:, None] + np.array([0.0, 1e-9, -1e-12])]).ravel()
    small = np.concatenate([10.0 ** rng.uniform(-300, -1, 200), [5e-324, 2.2e-308, 1e-310], -10.0 ** rng.uniform(-20, -1, 50)])
    mid = rng.uniform(-10, 10, 600)
    return {"trig": np.concatenate([big, near, small, mid]),
            "exp": np.concatenate([rng.uniform(-745, 709.7, 400), small, mid, [709.78, -744.4]]),
            "log": np.concatenate([10.0 ** rng.uniform(-307, 307, 400), 1 + rng.uniform(-1e-6, 1e-6, 200),
                                   np.abs(small), [5e-324, 1.7e308]]),
            "tanh": np.concatenate([rng.uniform(-20, 20, 400), small, [19.06, -19.07, 0.55, 700.0]]),
            "sqrt": np.concatenate([10.0 ** rng.uniform(-307, 307, 400), np.abs(small)])}


@pytest.mark.parametrize("fun", ["sin", "cos", "tan", "exp", "log", "tanh", "sqrt"])
def test_transcendental_values_within_half_the_margin_and_enclosed(fun):
    rng = np.random.default_rng({"sin": 1, "cos": 2, "tan": 3, "exp": 4, "log": 5, "tanh": 6, "sqrt": 7}[fun])
    pts = _test_points(rng)["trig" if fun in ("sin", "cos", "tan") else fun]
    got = getattr(np, fun)(pts)
    worst = 0.0
    for t, g in zip(pts, got):
        exact = MP[fun](mpmath.mpf(t))
        worst = max(worst, _ulps(g, exact))
    # numpy's implementation (libm or SIMD) is within 4 ulp; the margin is twice that
    assert worst <= MARGIN_ULP / 2, f"{fun}: {worst} ulp"
    # the interval evaluation at a degenerate box encloses the exact value (tan: away from poles)
    kd = one(f"{fun}(x1)")
    if fun == "tan":
        pts = pts[np.abs(pts) < 1e6]  # larger arguments may be refused as "near a pole" (slack 1e-13 |q|)
        pts = pts[np.abs(np.remainder(pts, math.pi) - math.pi / 2) > 1e-6]
    b = kd.image_bounds(pts[:, None], pts[:, None], form="natural")
    for t, lo, hi in zip(pts, b.lower[:, 0], b.upper[:, 0]):
        exact = MP[fun](mpmath.mpf(t))
        assert mpmath.mpf(lo) <= exact <= mpmath.mpf(hi), (fun, t, lo, hi)


def test_widening_covers_the_stated_margin():
    r = np.array([1.0, -3.5, 1e-300, 7e300, 0.1, 5e-324])
    lo, hi = _widen(r)
    for _ in range(MARGIN_ULP):  # MARGIN_ULP ulps each side, and one more
        r_lo, r_hi = np.nextafter(r if _ == 0 else r_lo, -np.inf), np.nextafter(r if _ == 0 else r_hi, np.inf)
    assert np.all(lo < r_lo) and np.all(hi > r_hi)
    assert MARGIN_ULP >= 8  # 2 x the 4 ulp documented for numpy's SVML paths (numpy PR 19478)


def test_power_values_against_mpmath():
    rng = np.random.default_rng(11)
    base = 10.0 ** rng.uniform(-3, 3, 300)
    expo = np.concatenate([rng.integers(-12, 13, 150).astype(float), rng.uniform(-5, 5, 150)])
    kd = one("x1^x2", 2)
    b = kd.image_bounds(np.column_stack([base, expo]), np.column_stack([base, expo]), form="natural")
    for x, y, lo, hi in zip(base, expo, b.lower[:, 0], b.upper[:, 0]):
        exact = mpmath.power(mpmath.mpf(x), mpmath.mpf(y))
        assert mpmath.mpf(lo) <= exact <= mpmath.mpf(hi)


# --------------------------------------------------------------------------- tightness (catches shrinks)
TIGHT = [  # (expression, box lower, box upper, exact range (lo, hi) as mpmath values)
    ("x1 + x2", [0.3, -1.7], [1.9, 2.2], lambda: (mpmath.mpf(0.3) + mpmath.mpf(-1.7), mpmath.mpf(1.9) + mpmath.mpf(2.2))),
    ("x1 - x2", [0.3, -1.7], [1.9, 2.2], lambda: (mpmath.mpf(0.3) - mpmath.mpf(2.2), mpmath.mpf(1.9) + mpmath.mpf(1.7))),
    ("x1 * x2", [-0.3, -1.7], [1.9, 2.2], lambda: (mpmath.mpf(1.9) * mpmath.mpf(-1.7), mpmath.mpf(1.9) * mpmath.mpf(2.2))),
    ("x1 / x2", [-0.3, 0.7], [1.9, 2.2], lambda: (mpmath.mpf(-0.3) / mpmath.mpf(0.7), mpmath.mpf(1.9) / mpmath.mpf(0.7))),
    ("-x1", [-0.3], [1.9], lambda: (mpmath.mpf(-1.9), mpmath.mpf(0.3))),
    ("x1^2", [-0.3], [1.9], lambda: (0, mpmath.mpf(1.9) ** 2)),
    ("x1*x1", [-0.3], [1.9], lambda: (0, mpmath.mpf(1.9) ** 2)),  # one register squared: x^2, not a product
    ("x1^3", [-1.3], [0.9], lambda: (mpmath.mpf(-1.3) ** 3, mpmath.mpf(0.9) ** 3)),
    ("x1^4", [-1.3], [0.9], lambda: (0, mpmath.mpf(-1.3) ** 4)),
    ("x1^-2", [0.4], [1.9], lambda: (mpmath.mpf(1.9) ** -2, mpmath.mpf(0.4) ** -2)),
    ("x1^-3", [-1.9], [-0.4], lambda: (mpmath.mpf(-0.4) ** -3, mpmath.mpf(-1.9) ** -3)),
    ("x1^0.7", [0.4], [1.9], lambda: (mpmath.mpf(0.4) ** mpmath.mpf(0.7), mpmath.mpf(1.9) ** mpmath.mpf(0.7))),
    ("x1^x2", [0.4, -1.2], [1.9, 0.8], lambda: (mpmath.mpf(1.9) ** mpmath.mpf(-1.2), mpmath.mpf(0.4) ** mpmath.mpf(-1.2))),
    ("sqrt(x1)", [0.0], [1.9], lambda: (0, mpmath.sqrt(mpmath.mpf(1.9)))),
    ("exp(x1)", [-0.3], [1.9], lambda: (mpmath.exp(mpmath.mpf(-0.3)), mpmath.exp(mpmath.mpf(1.9)))),
    ("log(x1)", [0.3], [1.9], lambda: (mpmath.log(mpmath.mpf(0.3)), mpmath.log(mpmath.mpf(1.9)))),
    ("tanh(x1)", [-0.3], [1.9], lambda: (mpmath.tanh(mpmath.mpf(-0.3)), mpmath.tanh(mpmath.mpf(1.9)))),
    ("tan(x1)", [-0.3], [1.4], lambda: (mpmath.tan(mpmath.mpf(-0.3)), mpmath.tan(mpmath.mpf(1.4)))),
    ("sin(x1)", [-0.3], [1.2], lambda: (mpmath.sin(mpmath.mpf(-0.3)), mpmath.sin(mpmath.mpf(1.2)))),
    ("sin(x1)", [0.3], [2.9], lambda: (mpmath.sin(mpmath.mpf(2.9)), 1)),  # maximum pi/2 inside
    ("sin(x1)", [3.5], [5.1], lambda: (-1, mpmath.sin(mpmath.mpf(3.5)))),  # minimum 3 pi/2 inside
    ("cos(x1)", [0.3], [2.9], lambda: (mpmath.cos(mpmath.mpf(2.9)), mpmath.cos(mpmath.mpf(0.3)))),
    ("cos(x1)", [-0.5], [1.2], lambda: (mpmath.cos(mpmath.mpf(1.2)), 1)),  # maximum 0 inside
    ("cos(x1)", [2.5], [3.9], lambda: (-1, mpmath.cos(mpmath.mpf(3.9)))),  # minimum pi inside
    ("abs(x1)", [-0.3], [1.9], lambda: (0, mpmath.mpf(1.9))),
    ("abs(x1)", [-2.3], [-1.9], lambda: (mpmath.mpf(1.9), mpmath.mpf(2.3))),
    ("min(x1, x2)", [-0.3, -1.7], [1.9, 0.2], lambda: (mpmath.mpf(-1.7), mpmath.mpf(0.2))),
    ("max(x1, x2)", [-0.3, -1.7], [1.9, 0.2], lambda: (mpmath.mpf(-0.3), mpmath.mpf(1.9))),
    ("0.15 * x1", [-0.3], [1.9], lambda: (mpmath.mpf(-0.3) * mpmath.mpf("0.15"), mpmath.mpf(1.9) * mpmath.mpf("0.15"))),
    ("pi * x1", [-0.3], [1.9], lambda: (mpmath.mpf(-0.3) * mpmath.pi, mpmath.mpf(1.9) * mpmath.pi)),
    ("x1 + 0.15*cos(x3)", [0.1, 0, -0.2], [0.6, 0, 0.3], lambda: (0.1 + 0.15 * mpmath.cos(mpmath.mpf(0.3)), 0.6 + mpmath.mpf("0.15"))),
    ("x1 + 0.1*x2*cos(x3)", [0.1, 0.5, 0.4], [0.6, 1.5, 0.9],
     lambda: (0.1 + mpmath.mpf("0.1") * 0.5 * mpmath.cos(mpmath.mpf(0.9)), 0.6 + mpmath.mpf("0.1") * 1.5 * mpmath.cos(mpmath.mpf(0.4)))),
]


def _check_tight(expr, lo, hi, exact, form):
    kd = one(expr, len(lo))
    L, U = enclose(kd, lo, hi, form=form)
    e_lo, e_hi = (mpmath.mpf(v) for v in exact())
    assert mpmath.mpf(L) <= e_lo and e_hi <= mpmath.mpf(U), (expr, form, L, U, e_lo, e_hi)  # sound
    slack = 64 * np.spacing(max(abs(float(e_lo)), abs(float(e_hi)), 1.0))  # rounding only
    assert float(e_lo - mpmath.mpf(L)) <= slack and float(mpmath.mpf(U) - e_hi) <= slack, (expr, form, L, U)


@pytest.mark.parametrize("expr, lo, hi, exact", TIGHT, ids=[f"{t[0]}@{t[1]}" for t in TIGHT])
@pytest.mark.parametrize("form", ["natural", "best"])
def test_every_operation_is_tight_where_the_range_is_known(expr, lo, hi, exact, form):
    _check_tight(expr, lo, hi, exact, form)


@pytest.mark.parametrize("form", ["centred", "natural", "best"])
def test_affine_maps_are_exact_up_to_rounding(form):
    rng = np.random.default_rng(17)
    A = np.round(rng.uniform(-3, 3, (3, 3)), 2)
    c = np.round(rng.uniform(-1, 1, 3), 3)
    exprs = [" + ".join(f"{A[i, j]:.2f}*x{j + 1}" for j in range(3)) + f" + {c[i]:.3f}" for i in range(3)]
    kd = KnownDynamics(exprs)
    lo = rng.uniform(-2, 2, (300, 3))
    hi = lo + rng.uniform(0.01, 0.5, (300, 3))
    b = kd.image_bounds(lo, hi, form=form)
    for r in range(0, 300, 7):
        for i in range(3):
            terms = [Fraction(f"{A[i, j]:.2f}") * Fraction(lo[r, j] if A[i, j] > 0 else hi[r, j]) for j in range(3)]
            e_lo = sum(terms) + Fraction(f"{c[i]:.3f}")
            terms = [Fraction(f"{A[i, j]:.2f}") * Fraction(hi[r, j] if A[i, j] > 0 else lo[r, j]) for j in range(3)]
            e_hi = sum(terms) + Fraction(f"{c[i]:.3f}")
            assert Fraction(b.lower[r, i]) <= e_lo and e_hi <= Fraction(b.upper[r, i])
            slack = Fraction(32 * np.spacing(8.0))  # a few roundings of values below 8
            assert e_lo - Fraction(b.lower[r, i]) <= slack and Fraction(b.upper[r, i]) - e_hi <= slack


def test_centred_form_is_sound_and_second_order():
    kd = one("x1 - 0.2*x1^2 + 0.1*sin(x1)*x1")
    f = lambda t: t - 0.2 * t * t + 0.1 * math.sin(t) * t  # noqa: E731
    excess = []
    for w in (0.4, 0.1, 0.025):
        lo, hi = np.array([[0.8]]), np.array([[0.8 + w]])
        b = kd.image_bounds(lo, hi, form="centred")
        vals = [f(s) for s in np.linspace(0.8, 0.8 + w, 201)]  # f is monotone here: range at the ends
        assert b.lower[0, 0] <= min(vals) and max(vals) <= b.upper[0, 0]
        excess.append((b.upper[0, 0] - b.lower[0, 0]) - (max(vals) - min(vals)))
    # quadratic convergence of the mean-value form: excess(w/4) ~ excess(w)/16 (first order: /4)
    assert excess[1] <= excess[0] / 10 and excess[2] <= excess[1] / 10, excess


# --------------------------------------------------------------------------- containment on random expressions
def random_expression(rng, depth, n):
    """A random expression over the whole grammar that is defined on every box (guarded arguments)."""
    if depth == 0 or rng.random() < 0.2:
        r = rng.random()
        if r < 0.65:
            return f"x{rng.integers(1, n + 1)}"
        if r < 0.8:
            return "pi"
        return f"({rng.uniform(-3, 3):.3f})"
    e = lambda: random_expression(rng, depth - 1, n)  # noqa: E731
    forms = [
        lambda: f"({e()} + {e()})", lambda: f"({e()} - {e()})", lambda: f"({e()} * {e()})",
        lambda: f"({e()} / (1.5 + cos({e()})))", lambda: f"(-{e()})", lambda: f"sin({e()})", lambda: f"cos({e()})",
        lambda: f"tan(0.7*tanh({e()}))", lambda: f"exp(1.5*sin({e()}))", lambda: f"log(1 + ({e()})^2)",
        lambda: f"log(2.5 + cos({e()}))", lambda: f"sqrt(abs({e()}))", lambda: f"sqrt(1 + ({e()})^2)",
        lambda: f"abs({e()})", lambda: f"tanh({e()})", lambda: f"min({e()}, {e()})",
        lambda: f"max({e()}, {e()}, {e()})", lambda: f"(({e()})^2)", lambda: f"(({e()})**3)",
        lambda: f"((2 + sin({e()}))^-2)", lambda: f"((1.5 + tanh({e()}))^0.5)",
        lambda: f"((2 + cos({e()}))^(0.3*sin({e()})))",
        lambda: f"(0.5*{e()} + 0.25*{e()})",
    ]
    return forms[rng.integers(len(forms))]()


def random_boxes(rng, k, n):
    centre = rng.uniform(-3, 3, (k, n))
    half = 10.0 ** rng.uniform(-3, -0.3, (k, n)) / 2
    return centre - half, centre + half


def test_containment_over_100k_random_expression_cell_pairs():
    rng = np.random.default_rng(2021)
    n, n_objects, n_cells, n_samples = 3, 100, 340, 24  # 100 x 3 expressions x 340 cells = 102,000 pairs
    pairs = violations = 0
    for _ in range(n_objects):
        exprs = [random_expression(rng, 3, n) for _ in range(n)]  # depth 4 in the tests below
        kd = KnownDynamics(exprs)
        lo, hi = random_boxes(rng, n_cells, n)
        b = kd.image_bounds(lo, hi)
        u = rng.random((n_cells, n_samples, n))
        pts = np.minimum(lo[:, None] + u * (hi - lo)[:, None], hi[:, None])
        corners = ((np.arange(2 ** n)[:, None] >> np.arange(n)) & 1).astype(bool)
        pts = np.concatenate([pts, np.where(corners[None], hi[:, None], lo[:, None])], axis=1)
        v = kd.evaluate(pts.reshape(-1, n)).reshape(n_cells, -1, n)
        # a computed value at a point of the box lies in the enclosure (margins cover it: module doc)
        bad = (v < b.lower[:, None]) | (v > b.upper[:, None])
        violations += int(bad.any(axis=1).sum())
        pairs += n_cells * n
    assert pairs >= 100_000
    assert violations == 0


@pytest.mark.parametrize("form", ["natural", "centred"])
def test_each_form_alone_contains_samples(form):
    rng = np.random.default_rng(7 if form == "natural" else 8)
    for _ in range(60):
        kd = KnownDynamics([random_expression(rng, 4, 2) for _ in range(2)])
        lo, hi = random_boxes(rng, 30, 2)
        b = kd.image_bounds(lo, hi, form=form)
        pts = rng.uniform(lo[:, None], hi[:, None], (30, 40, 2))
        v = kd.evaluate(pts.reshape(-1, 2)).reshape(30, 40, 2)
        assert np.all((b.lower[:, None] <= v) & (v <= b.upper[:, None]))


def test_exact_values_at_sampled_points_are_enclosed():
    # mpmath evaluation of the random expressions at points: the exact f(x), not only fl(f(x))
    rng = np.random.default_rng(99)
    for _ in range(40):
        expr = random_expression(rng, 3, 2)
        kd = one(expr, 2)
        lo, hi = random_boxes(rng, 5, 2)
        b = kd.image_bounds(lo, hi)
        for r in range(5):
            x = rng.uniform(lo[r], hi[r])
            exact = _mp_eval(expr, x)
            assert mpmath.mpf(b.lower[r, 0]) <= exact <= mpmath.mpf(b.upper[r, 0]), expr


def _mp_eval(expr, x):
    """The exact value of ``expr`` at the doubles ``x`` (mpmath, constants as exact decimals)."""
    import ast

    def ev(node):
        if isinstance(node, ast.BinOp):
            a, b = ev(node.left), ev(node.right)
            op = type(node.op)
            return {ast.Add: lambda: a + b, ast.Sub: lambda: a - b, ast.Mult: lambda: a * b,
                    ast.Div: lambda: a / b, ast.Pow: lambda: a ** b}[op]()
        if isinstance(node, ast.UnaryOp):
            return -ev(node.operand) if isinstance(node.op, ast.USub) else ev(node.operand)
        if isinstance(node, ast.Constant):
            return mpmath.mpf(repr(node.value)) if isinstance(node.value, float) else mpmath.mpf(node.value)
        if isinstance(node, ast.Name):
            return mpmath.pi if node.id == "pi" else mpmath.mpf(float(x[int(node.id[1:]) - 1]))
        if isinstance(node, ast.Call):
            args = [ev(a) for a in node.args]
            name = node.func.id
            if name in ("min", "max"):
                return (min if name == "min" else max)(args)
            return MP[name](args[0])
        raise AssertionError(ast.dump(node))

    return ev(ast.parse(expr.replace("^", "**"), mode="eval").body)


# --------------------------------------------------------------------------- undefined on a box
@pytest.mark.parametrize("expr, lo, hi, why", [
    ("log(x1)", [-1, 0], [0.5, 1], r"log of an interval reaching 0"),
    ("log(x1)", [0, 0], [0.5, 1], r"log of an interval reaching 0"),
    ("sqrt(x1 - 1)", [0.5, 0], [2, 1], r"sqrt of an interval reaching below 0"),
    ("x2 / x1", [-1, 0], [0.5, 1], r"division by an interval that holds 0"),
    ("tan(x1)", [1, 0], [2, 1], r"tan of an interval that may hold a pole"),
    ("x1^0.5", [-1, 0], [0.5, 1], r"a power x\^y undefined on the interval \(non-integer y: the base reaches 0"),
    ("x1^-2", [-1, 0], [0.5, 1], r"a power x\^y undefined on the interval .* y = -n: the base holds 0\)"),
    ("x2^x1", [-1, -1], [0.5, 1], r"a power x\^y undefined on the interval"),
    ("exp(x1)", [700, 0], [800, 1], r"the enclosure overflows the double range"),
])
def test_undefined_on_a_box_names_component_box_and_operation(expr, lo, hi, why):
    kd = KnownDynamics(["x1", expr], name='mode "turn"')
    lows = np.array([[1.2, 0.2], lo], float)  # box 0 is fine, box 1 is reported
    highs = np.array([[1.3, 0.3], hi], float)
    box = r"\[%g, %g\] x \[%g, %g\]" % (lo[0], hi[0], lo[1], hi[1])
    with pytest.raises(ExpressionDomainError, match=r'mode "turn": f\[2\] = "%s" is undefined on the box %s: %s'
                       % (re_escape(expr), box, why)):
        kd.image_bounds(lows, highs)


def re_escape(s):
    import re

    return re.escape(s)


def test_undefined_at_a_point_is_an_error():
    kd = KnownDynamics(["log(x1)"])
    with pytest.raises(ExpressionDomainError, match=r'f\[1\] = "log\(x1\)" is undefined or overflows at the point '
                       r'x = \(-1\) \(row 1\)'):
        kd.evaluate(np.array([[1.0], [-1.0]]))


def test_centred_form_falls_back_where_the_jacobian_is_unbounded():
    kd = one("sqrt(x1) + x1")  # d/dx sqrt(x) is unbounded at 0: the natural extension is used there
    L, U = enclose(kd, [0.0], [1.0])
    assert L <= 0.0 and U >= 2.0 and U - L <= 2.0 + 1e-12


# --------------------------------------------------------------------------- residual rounding bounds
def test_residual_rounding_bound_holds_against_mpmath():
    rng = np.random.default_rng(4)
    exprs = ["x1 + 0.15*cos(x3)", "x2 + 0.15*sin(x3)*x1^3 - exp(x2/3)", "x3 + 0.1*tan(x1/4) - log(1 + x2^2)/7"]
    kd = KnownDynamics(exprs)
    x = rng.uniform(-3, 3, (300, 3))
    x[:20] *= 1e-8  # near 0 (cancellation-free), and large values
    x[20:40] *= 30
    v = kd.evaluate(x)
    bound = kd.residual_rounding_bound(x)
    worst = 0.0
    for r in range(len(x)):
        for i, e in enumerate(exprs):
            err = abs(mpmath.mpf(v[r, i]) - _mp_eval(e, x[r]))
            assert err <= mpmath.mpf(bound[r, i]), (e, x[r])
            worst = max(worst, float(bound[r, i] / (np.finfo(float).eps * max(1.0, abs(v[r, i])))))
    assert worst < 1e3  # informative: measured <= 61 eps max(1, |f|) here (cancellation near 0 is absolute)


def test_residuals_bound_the_exact_difference():
    rng = np.random.default_rng(6)
    kd = KnownDynamics(["x1 + 0.1*cos(x2)", "x2 - 0.3*sin(x1)"])
    x = rng.uniform(-2, 2, (200, 2))
    x_next = kd.evaluate(x) + rng.normal(0, 0.01, (200, 2))
    res = kd.residuals(x, x_next)
    exprs = ["x1 + 0.1*cos(x2)", "x2 - 0.3*sin(x1)"]
    for r in range(200):
        for i in range(2):
            exact = mpmath.mpf(x_next[r, i]) - _mp_eval(exprs[i], x[r])
            assert abs(mpmath.mpf(res.y[r, i]) - exact) <= mpmath.mpf(res.bound[r, i])
    with pytest.raises(DimensionError, match=r"x_next must have shape \(200, 2\) like x"):
        kd.residuals(x, x_next[:, :1])


# --------------------------------------------------------------------------- achieved range, tightness target
def test_achieved_range_lies_inside_the_certified_range():
    rng = np.random.default_rng(12)
    for _ in range(12):
        kd = KnownDynamics([random_expression(rng, 3, 2) for _ in range(2)])
        lo, hi = random_boxes(rng, 6, 2)
        b = kd.image_bounds(lo, hi)
        a = kd.achieved_range(lo, hi, n_samples=16)
        assert np.all((b.lower <= a.lower) & (a.upper <= b.upper))
        assert np.all((a.argmin >= lo[:, None]) & (a.argmin <= hi[:, None]))
        assert np.all(a.gap_to(b) >= 0)


CASE_STUDY_KIND = [  # unicycle and planar-vehicle kinematics (issue's item 1), x = (px, py, theta, v)
    "x1 + 0.15*cos(x3)", "x2 + 0.15*sin(x3)", "x1 + 0.1*x4*cos(x3)", "x2 + 0.1*x4*sin(x3)",
    "x3 + 0.1*x4*tan(0.3)", "x4 - 0.1*(0.2*x4 + 0.05*x4*abs(x4))",
]


@pytest.mark.parametrize("width", [0.05, 0.1, 0.25, 0.5])
def test_case_study_expressions_within_one_percent_of_the_cell_width(width):
    rng = np.random.default_rng(int(width * 1000))
    kd = KnownDynamics(CASE_STUDY_KIND[:4])  # 4 components in x1..x4
    kd2 = KnownDynamics(CASE_STUDY_KIND[2:])
    k = 12
    lo = np.column_stack([rng.uniform(-2, 2, k), rng.uniform(-2, 2, k), rng.uniform(-math.pi, math.pi - width, k),
                          rng.uniform(-1, 2, k)])
    hi = lo + width
    for model in (kd, kd2):
        b = model.image_bounds(lo, hi)
        a = model.achieved_range(lo, hi, n_samples=32)
        gap = a.gap_to(b)
        assert np.all(gap <= max(0.01 * width, 1e-3)), gap.max()
