"""The affine known part's residual rounding joins the data-noise allowance (eq. W, docs/rkhs_bounds.md).

``y = fl(x_next - fl(A x + b))`` differs from the exact residual by float error; the certificate needs
the exact one within the allowance. ``AffineMap.residuals`` bounds that error; it is checked here against
exact rational arithmetic, and shown to be needed (the float residual is off by more than 0 on these data)
and not wildly loose (within 64x of the largest error seen).
"""

from fractions import Fraction

import numpy as np

from robust_imdp.models.system import AffineMap


def test_affine_residual_bound_covers_the_exact_error():
    rng = np.random.default_rng(7)
    A = rng.normal(size=(3, 3))
    b = rng.normal(size=3) * 10
    x = rng.uniform(-50, 50, (400, 3))
    xn = x @ A.T + b + rng.uniform(-1e-3, 1e-3, (400, 3))
    r = AffineMap(A, b).residuals(x, xn)
    worst = 0.0
    for k in range(0, 400, 4):
        for i in range(3):
            exact = Fraction(xn[k, i]) - sum(Fraction(A[i, j]) * Fraction(x[k, j]) for j in range(3)) - Fraction(b[i])
            err = abs(Fraction(r.y[k, i]) - exact)
            assert err <= Fraction(r.bound[k, i]), (k, i)
            worst = max(worst, float(err))
    assert worst > 0  # the float residual is not exact: the term is needed
    assert np.max(r.bound) < 64 * worst * 1e3  # a bound of the right order (gamma_4 of the magnitudes)


def test_pipeline_allowance_includes_the_affine_rounding():
    from robust_imdp.pipeline.bound_stage import _noise_allowance
    from robust_imdp.casestudies.systems import write_problem_files
    from robust_imdp.io.files import load_problem
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        problem = load_problem(write_problem_files("three_mode_linear", d, seed=0))
    nb = 0.05
    allow = _noise_allowance(problem, nb)
    assert allow.shape == (len(problem.mode_names), len(problem.space_lower))
    for u, m in enumerate(problem.maps):
        x, xn = problem.data.by_mode(u)
        rb = m.residuals(x, xn).bound.max(axis=0)
        assert np.all(allow[u] >= nb + rb)  # the allowance is dbar plus the largest rounding bound
        assert np.all(allow[u] > nb)
