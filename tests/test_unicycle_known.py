"""Case study ``unicycle_3d_known``: the 3-D unicycle with its kinematics known (f expressions),
a periodic heading and only the cross current learned (benchmarks/unicycle_known.py)."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from robust_imdp.casestudies.systems import get_case_study, problem_toml, write_problem_files
from robust_imdp.io.files import load_problem
from robust_imdp.models.known import KnownDynamics

NAME = "unicycle_3d_known"
CURRENT = 0.04  # the drift: 0.04 sin p_y along p_x, nothing along p_y and theta


def _drift(x):
    d = np.zeros_like(x)
    d[:, 0] = CURRENT * np.sin(x[:, 1])
    return d


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    return load_problem(write_problem_files(NAME, tmp_path_factory.mktemp("uni")))


def test_problem_file_states_the_robot(problem):
    """Known f per mode, heading periodic, only p_x's drift learned (B = [B, 0, 0]), long lengthscales."""
    assert problem.periodic == (False, False, True)
    assert tuple(problem.mode_names) == ("left", "straight", "right")
    assert all(isinstance(m, KnownDynamics) for m in problem.maps)
    B = np.asarray(problem.rkhs_bound, float)
    assert B[0] > 0 and B[1] == 0 and B[2] == 0
    ls = problem.gp_options["lengthscale"][0]
    assert ls[0] > 10 * ls[1] and ls[2] > 10 * ls[1]  # the drift does not depend on p_x or theta


def test_true_system_is_the_known_part_plus_the_drift(problem):
    """The problem's f_u plus 0.04 sin p_y along p_x is the true system's noise-free step."""
    case = get_case_study(NAME)
    system = case.system
    x = np.random.default_rng(3).uniform(case.lower, case.upper, (2000, 3))
    for u, f in enumerate(problem.maps):
        truth = np.einsum("ij,kj->ki", system.known_A[u], x) + system.known_b[u] + system.g(x, np.full(len(x), u))
        np.testing.assert_allclose(f.evaluate(x) + _drift(x), truth, rtol=0, atol=1e-14)


def test_data_heading_wrapped_and_residuals_are_drift_plus_noise(problem):
    """The data's heading lies in [-pi, pi); residuals modulo 2 pi are drift + noise (|noise| <= 0.01)."""
    d = problem.data
    assert np.all(d.x_next[:, 2] >= -np.pi) and np.all(d.x_next[:, 2] < np.pi)
    wrapped = np.sum(np.abs(d.x[:, 2] - d.x_next[:, 2]) > 1.0)
    assert wrapped > 0  # some steps do cross the seam
    for u, f in enumerate(problem.maps):
        sel = d.u == u
        y = d.x_next[sel] - f.evaluate(d.x[sel])
        y[:, 2] -= np.round(y[:, 2] / (2 * np.pi)) * 2 * np.pi
        assert np.max(np.abs(y - _drift(d.x[sel]))) <= 0.01 + 1e-12


def test_old_case_studies_problem_text_unchanged():
    """The writer's new branches (f, periodic, per-component B) leave the old case studies' files as they were."""
    expected = {
        "three_mode_linear": "a3e09ac72f6f4dedb00a9b0b168d396f399461f747ea98493e644502764c5c1b",
        "four_mode_nonlinear": "0d9e0870d1138471d611788ff23a9e5e16b5306ec5214932d7a73a76721f4dad",
        "unicycle_3d": "ddc689163619fd2e474d3258330ed9a996b8484676ff1967ed2740045e2fde01",
    }
    for name, digest in expected.items():
        c = get_case_study(name)
        assert hashlib.sha256(problem_toml(c, c.formulas[0], "d.csv").encode()).hexdigest() == digest, name


def test_shipped_assumption_is_certified_for_the_true_drift():
    """B and tau of p_x hold for the true drift 0.04 sin p_y (the note at systems._UNICYCLE_KNOWN).

    h(x) = h_y(p_y) k_lx(p_x, 2) k_lt(theta, 0): a product of functions of separate coordinates, so
    ||h|| = ||h_y|| ||k_lx(., 2)|| ||k_lt(., 0)|| = ||h_y|| (unit-amplitude kernels), and
    |g - h| <= |0.04 sin - h_y| + |h_y| (1 - k_lx k_lt) with 1 - k_lx k_lt <= (2^2 / lx^2 + pi^2 / lt^2) / 2
    on X = [0, 4] x [0, 4] x [-pi, pi] (1 - e^-s <= s). ||h_y|| and sup |0.04 sin - h_y| on [0, 4] are
    certified by casestudies.certificate (outward rounding, interpolation remainder).
    """
    from robust_imdp.casestudies import certificate as C
    from robust_imdp._kernels import se_kernel_with_error

    case = get_case_study(NAME)
    B, tau = float(case.rkhs_bound[0]), float(case.misspecification[0])
    assert tuple(case.rkhs_bound[1:]) == (0.0, 0.0) and tuple(case.misspecification[1:]) == (0.0, 0.0)
    lx, ly, lt = dict(case.gp)["lengthscale"][0]
    terms = (("sin", 0, CURRENT),)
    Z = C._tensor_points([C._axis_grid(-2.0, 6.0, 0.2, "c")[0]])
    P = C._tensor_points([C._axis_grid(0.0, 4.0, 0.02, "f")[0]])
    T, A = C._fit_basis(se_kernel_with_error(P, Z, np.array([ly]))[0], se_kernel_with_error(Z, Z, np.array([ly]))[0])
    alpha = C._min_norm_fit(T, A, C._terms_values(terms, P)[0], 0.8 * tau, "0.04 sin")
    cert = C.certify_expansion(terms, Z, alpha, [ly], [0.0], [4.0], check_spacing=1 / 512)
    factor = 0.5 * (2.0 ** 2 / lx ** 2 + np.pi ** 2 / lt ** 2) * (1 + 1e-12)
    sup_err = (cert["sup_error_upper"] + (CURRENT + cert["sup_error_upper"]) * factor) * (1 + 1e-12)
    assert cert["norm_upper"] <= B, (cert["norm_upper"], B)
    assert sup_err <= tau, (sup_err, tau)
    # tight: the certified norm is within 1 % of B (B was tuned, not guessed)
    assert cert["norm_upper"] >= 0.99 * B
