"""Outward rounding tested directly against exact arithmetic (issue 14, item 4).

Every rounding helper is fed adversarial floating-point inputs on which plain round-to-nearest
gives the wrong side of the exact value -- products of many factors just below 1, complements
of values below 0.5, differences, a Bellman row summing 300 small probabilities -- and is
compared with exact rational arithmetic (``fractions.Fraction`` holds every float exactly) or
mpmath at 40 digits. Each test counts violations of "lower bound <= exact" / "upper bound >=
exact", asserts 0, and asserts that the same count is > 0 when the helper's outward step is
switched off (``_fp.outward`` returning its input, the plain float result): the inputs really are
ones where rounding changes the answer.

These checks are the only ones that see the rounding of the abstraction: end to end, the noise
probabilities carry a relative margin of 1e-13 (``noise._round_down``) that hides a missing
ulp of ``_fp.outward`` from every closed-form comparison.
"""

from __future__ import annotations

from fractions import Fraction

import mpmath
import numpy as np
import pytest

from robust_imdp import _fp
from robust_imdp.abstraction import probabilities as abstraction

from robust_imdp.bounds import gp_cells as bounds

from robust_imdp.models import noise

from robust_imdp.synthesis import core as synthesis
from robust_imdp.models.imdp import IMDP
from robust_imdp.models.noise import GaussianNoise
from robust_imdp.solvers.api import _Sweeper

U = 2.0 ** -53
F = np.vectorize(Fraction, otypes=[object])  # exact value of every float


def no_outward(x, err, upward):  # the mutation "_fp.outward returns x"
    return np.asarray(x, dtype=float)


def near_one(rng, shape, bits=30):
    """Floats 1 - k 2^-53 with random k < 2^bits: products and sums of them round."""
    return 1.0 - rng.integers(1, 2**bits, size=shape) * U


# --------------------------------------------------------------------------- abstraction helpers
def test_outward_moves_past_the_error_bound(monkeypatch):
    """outward(x, err, upward) >= x + err (exactly) and != x where err > 0; down likewise; exact
    values (err == 0) are returned unchanged. A helper returning x fails the check."""
    rng = np.random.default_rng(0)
    x = rng.uniform(0.0, 1.0, 2000)
    err = np.where(rng.uniform(size=2000) < 0.2, 0.0, rng.uniform(0, 8, 2000) * U)

    def violations():
        up = _fp.outward(x, err, upward=True)
        down = _fp.outward(x, err, upward=False)
        moved = err > 0
        return int(np.sum(F(up) < F(x) + F(err)) + np.sum(F(down) > F(x) - F(err))
                   + np.sum(moved & ((up == x) | (down == x))) + np.sum(~moved & ((up != x) | (down != x))))

    assert violations() == 0
    monkeypatch.setattr(_fp, "outward", no_outward)
    assert violations() > 0


@pytest.mark.parametrize("d", [1, 2, 4, 8])
def test_combine_down_product_is_below_the_exact_product(d, monkeypatch):
    """P_g P_v of Thm 1 as a product of 2d factors just below 1 (and some in (0.5, 1)): the
    rounded-down result never exceeds the exact product; all factors 1 gives exactly 1."""
    rng = np.random.default_rng(d)
    p = near_one(rng, (1000, d))
    pv = np.where(rng.uniform(size=(1000, d)) < 0.3, rng.uniform(0.5, 1.0, (1000, d)), near_one(rng, (1000, d)))

    def violations():
        g = abstraction._combine_down(p, pv, "product")
        exact = [np.prod(F(p[k])) * np.prod(F(pv[k])) for k in range(p.shape[0])]
        return int(np.sum(F(g) > np.array(exact, dtype=object)))

    assert violations() == 0
    assert abstraction._combine_down(np.ones((1, d)), np.ones((1, d)), "product")[0] == 1.0
    monkeypatch.setattr(abstraction, "outward", no_outward)
    assert violations() > 0  # round-to-nearest lands above the exact product about half the time


@pytest.mark.parametrize("d", [2, 8])
def test_combine_down_union_is_below_the_exact_union_bound(d, monkeypatch):
    """Union bound max(0, 1 - sum(1 - p)) per factor, complements of values anywhere in (0, 1)
    (below 0.5 the complement itself rounds)."""
    rng = np.random.default_rng(10 + d)
    p = np.where(rng.uniform(size=(1000, d)) < 0.5, near_one(rng, (1000, d)), rng.uniform(0.9, 1.0, (1000, d)))
    p[:, 0] = np.where(rng.uniform(size=1000) < 0.3, rng.uniform(0.0, 0.5, 1000), p[:, 0])
    pv = near_one(rng, (1000, d))

    def exact(a):
        return max(Fraction(0), 1 - sum(1 - Fraction(v) for v in a))

    def violations():
        g = abstraction._combine_down(p, pv, "union")
        ex = [exact(p[k]) * exact(pv[k]) for k in range(p.shape[0])]
        return int(np.sum(F(g) > np.array(ex, dtype=object)))

    assert violations() == 0
    monkeypatch.setattr(abstraction, "outward", no_outward)
    assert violations() > 0


def test_complement_up_is_above_the_exact_complement(monkeypatch):
    """1 - g rounded up: exact (Sterbenz) for g >= 0.5, one error bound for g < 0.5, including
    g below 2^-54 where 1 - g rounds to 1 (clamped to 1: still >= the exact value)."""
    rng = np.random.default_rng(3)
    g = np.concatenate([rng.uniform(0.0, 0.5, 2000), rng.uniform(0.5, 1.0, 500), [0.0, 1e-17, 2.0**-54, 0.5, 1.0]])

    def violations():
        c = abstraction._complement_up(g)
        return int(np.sum(F(c) < 1 - F(g)) + np.sum(c > 1.0))

    assert violations() == 0
    np.testing.assert_array_equal(abstraction._complement_up(g[g >= 0.5]), 1.0 - g[g >= 0.5])  # exact there
    monkeypatch.setattr(abstraction, "outward", no_outward)
    assert violations() > 0


def test_down1_up1_bracket_one_correctly_rounded_operation():
    """_fp.down / _fp.up of a difference and a sum (the margins and expansions of abstract())."""
    rng = np.random.default_rng(4)
    a, b = rng.uniform(-2, 2, 5000), rng.uniform(-2, 2, 5000) * 10.0 ** rng.integers(-12, 0, 5000)
    assert np.all(F(_fp.down(a - b)) <= F(a) - F(b))
    assert np.all(F(_fp.up(a + b)) >= F(a) + F(b))
    assert np.sum(F(a - b) > F(a) - F(b)) > 0  # without the ulp: wrong side


# --------------------------------------------------------------------------- other modules
def test_bounds_rounding_helpers_move_past_the_error():
    """bounds._round_down(x, err) <= x - err and _round_up(x, err) >= x + err exactly."""
    rng = np.random.default_rng(5)
    x = rng.normal(0, 3, 3000)
    err = rng.uniform(0, 1e-12, 3000)
    assert np.all(F(bounds._round_down(x, err)) <= F(x) - F(err))
    assert np.all(F(bounds._round_up(x, err)) >= F(x) + F(err))
    assert np.sum(F(x - err) > F(x) - F(err)) > 0  # the plain float difference is on the wrong side


def test_noise_probabilities_are_below_the_exact_erf(monkeypatch):
    """P[|v| <= eta] for Gaussian noise against mpmath's erf at 40 digits: never above. With the
    rounding helper switched off (scipy's nearest-float erf) some values are above."""
    rng = np.random.default_rng(6)
    eta = rng.uniform(0.0, 0.25, (400, 1))
    gn = GaussianNoise([0.05])
    mpmath.mp.dps = 40

    def violations():
        p = gn.prob_abs_le(eta)[:, 0]
        exact = [mpmath.erf(mpmath.mpf(float(e)) / (mpmath.mpf(0.05) * mpmath.sqrt(2))) for e in eta[:, 0]]
        return int(sum(mpmath.mpf(float(v)) > x for v, x in zip(p, exact)))

    assert violations() == 0
    monkeypatch.setattr(noise, "_round_down", lambda v: np.asarray(v, dtype=float))
    assert violations() > 0


def test_synthesis_error_is_rounded_up():
    """error = p_up_star - p_low rounded up (synthesis._round_up) >= the exact difference."""
    rng = np.random.default_rng(7)
    a, b = rng.uniform(0, 1, 5000), rng.uniform(0, 1, 5000) * 1e-3
    assert np.all(F(synthesis._round_up(a - b)) >= F(a) - F(b))
    assert np.sum(F(a - b) < F(a) - F(b)) > 0


# --------------------------------------------------------------------------- solver rows
def exact_row_value(lo, up, w, maximize):
    """Ordering solution of opt p.w over {lo <= p <= up, sum p = 1} in exact rationals."""
    lo, up, w = F(lo), F(up), F(w)
    order = sorted(range(len(w)), key=lambda j: -w[j] if maximize else w[j])
    p, rem = list(lo), 1 - sum(lo)
    for j in order:
        add = min(up[j] - lo[j], rem)
        p[j] += add
        rem -= add
    return sum(pj * wj for pj, wj in zip(p, w))


def solver_row_value(lo, up, w, maximize, direction):
    """One Bellman update of a single row (state 0, k listed successors 1..k) by the solver."""
    k = lo.size
    n = k + 1
    # state 0: one row listing 1..k; states 1..k: absorbing self-loops
    m = IMDP.from_csr(np.arange(n + 1), np.r_[0, k + np.arange(n)], np.r_[np.arange(1, n), np.arange(1, n)],
                      np.r_[lo, np.ones(k)], np.r_[up, np.ones(k)])
    active = np.zeros((1, n), bool)
    active[0, 0] = True
    sw = _Sweeper(m, np.zeros((1, n), np.int64), active, 0, maximize, None)
    V, _, _ = sw.sweep(np.r_[0.0, w][None, :], direction)
    return float(V[0, 0])


@pytest.mark.parametrize("maximize", [False, True])
def test_bellman_row_of_many_small_probabilities_is_rounded_outward(maximize):
    """A row of 300 successors (15 random rows) with lower bounds ~1e-3 (sum ~0.5) and random values: the
    rounded-down / rounded-up Bellman values bracket the exact rational value; the plain
    (direction 0) float value is on the wrong side for some rows."""
    rng = np.random.default_rng(8 + maximize)
    plain_above = plain_below = 0
    for _ in range(15):
        k = 300
        lo = rng.uniform(0, 2.0 / k, k) * 0.5
        up = lo + rng.uniform(0, 2.0 / k, k)
        w = rng.uniform(0, 1, k)
        exact = exact_row_value(lo, up, w, maximize)
        assert Fraction(solver_row_value(lo, up, w, maximize, -1)) <= exact
        assert Fraction(solver_row_value(lo, up, w, maximize, +1)) >= exact
        plain = Fraction(solver_row_value(lo, up, w, maximize, 0))
        plain_above += plain > exact  # unsound as a lower bound
        plain_below += plain < exact  # unsound as an upper bound
    assert plain_above > 0 and plain_below > 0  # the inputs are ones where rounding changes the answer


def test_up_and_down_are_nextafter_bit_for_bit_on_every_path():
    """_fp.up / _fp.down take their ulp step in a compiled loop from _COMPILED_FROM elements on and with
    np.nextafter below: both paths give np.nextafter's bits, on the special values (zeros of both signs,
    subnormals, the largest floats, infinities, NaN) and on seeded floats of every magnitude, any shape."""
    from robust_imdp import _fp

    rng = np.random.default_rng(7)
    special = np.array([0.0, -0.0, 5e-324, -5e-324, 1e-320, -1e-320, np.inf, -np.inf, np.nan,
                        np.finfo(float).max, -np.finfo(float).max, np.finfo(float).tiny, -np.finfo(float).tiny,
                        1.0, -1.0, 1.0 - 2 ** -53, 2.0 ** 1023])
    wide = rng.standard_normal(3000) * 10.0 ** rng.integers(-323, 308, 3000)
    with np.errstate(over="ignore"):
        for x in (np.concatenate([special, wide]), special, wide.reshape(30, 100), wide[:5], np.float64(-0.0), 2.5):
            for f, towards in ((_fp.up, np.inf), (_fp.down, -np.inf)):
                got, want = np.asarray(f(x)), np.nextafter(np.asarray(x, float), towards)
                assert got.shape == want.shape and got.tobytes() == want.tobytes()
            # with an error bound: the step is taken from x +- err
            assert np.asarray(_fp.up(x, 1e-300)).tobytes() == np.nextafter(np.asarray(x, float) + 1e-300,
                                                                             np.inf).tobytes()
    assert np.asarray(wide).size >= _fp._COMPILED_FROM  # the compiled path is the one tested on `wide`
