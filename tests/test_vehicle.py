"""The 4-D vehicle case study (``casestudies/vehicle.py``): its exact image boxes and its problem.

The image boxes are the known-dynamics reference's input (``benchmarks/vehicle_4d.py``), so they must be
sound (never inward) and exact up to the 1e-12 margin. The extremes of every output over a box are
attained at known points (corners of the (v, theta) box, the critical headings of sin/cos inside it, the
critical speeds +-k/(2c) of the speed map), so the tests evaluate the true step at exactly those points
plus dense random points: any inward shrink of a term by 0.1 % of its size is caught.
"""

from __future__ import annotations

import numpy as np
import pytest

from robust_imdp.casestudies.vehicle import VEHICLE, VEHICLE_CASE, VehicleSystem, drag_map_range, trig_range
from robust_imdp.errors import DimensionError, InvalidInputError

PI = np.pi


def _random_boxes(rng, k, *, theta_span=2.0, v_lo=-0.2, v_hi=1.0):
    """k random boxes in R^4: positions anywhere, headings of any width up to ``theta_span`` (rad)."""
    c = np.column_stack([rng.uniform(-5, 5, k), rng.uniform(-5, 5, k), rng.uniform(-7, 7, k),
                         rng.uniform(v_lo, v_hi, k)])
    h = np.column_stack([rng.uniform(0, 0.5, k), rng.uniform(0, 0.5, k), rng.uniform(0, theta_span / 2, k),
                         rng.uniform(0, 0.2, k)])
    return c - h, c + h


def _extreme_points(system, lo, hi):
    """Per box, the points where an output can be extremal: the 16 corners, and for (theta, v) the
    corners combined with the critical headings k pi/2 inside and the critical speeds inside. (m, 4)
    arrays per box, as a list."""
    out = []
    for a, b in zip(lo, hi):
        th = [a[2], b[2]] + [t for t in np.arange(np.ceil(a[2] / (PI / 2)), np.floor(b[2] / (PI / 2)) + 1) * (PI / 2)
                             if a[2] <= t <= b[2]]
        vs = [a[3], b[3]]
        for k in np.unique(system.speed_factor):
            if system.drag > 0:
                vs += [v for v in (k / (2 * system.drag), -k / (2 * system.drag)) if a[3] <= v <= b[3]]
        P = np.array([[px, py, t, v] for px in (a[0], b[0]) for py in (a[1], b[1]) for t in th for v in vs])
        out.append(P)
    return out


def _check_contains(system, lo, hi, rng, n_random=2000):
    """Max violation (> 0: unsound) and min slack of the sampled extremes (tightness), over all boxes."""
    ilo, ihi = system.image_bounds(lo, hi)
    worst_violation, worst_gap = -np.inf, 0.0
    extremes = _extreme_points(system, lo, hi)
    for q in range(lo.shape[0]):
        x = np.concatenate([lo[q] + rng.random((n_random, 4)) * (hi[q] - lo[q]), extremes[q]])
        for u in range(len(system.mode_names)):
            y = system.mean_step(x, np.full(x.shape[0], u))
            worst_violation = max(worst_violation, np.max(ilo[u, q] - y.min(0)), np.max(y.max(0) - ihi[u, q]))
            worst_gap = max(worst_gap, np.max(y.min(0) - ilo[u, q]), np.max(ihi[u, q] - y.max(0)))
    return worst_violation, worst_gap


# --------------------------------------------------------------------------- image boxes
def test_image_bounds_contain_dense_samples_and_are_exact():
    """400 random boxes (headings up to 2 rad wide, speeds of both signs), 2000 uniform points + the
    extreme points each, 4 modes: no sample outside (soundness), and the sampled extremes reach the box
    up to 1e-10 (the margin 1e-12 (1 + magnitudes) with magnitudes < 20; the extreme points are exact)."""
    rng = np.random.default_rng(0)
    lo, hi = _random_boxes(rng, 400)
    violation, gap = _check_contains(VEHICLE, lo, hi, rng)
    assert violation <= 0.0
    assert gap < 1e-10


def test_image_bounds_with_interior_critical_speeds():
    """A vehicle whose speed map has its critical speeds +-k/(2c) inside the boxes (c = 1: +-0.5, +-0.375):
    the maximum of k v + a - c v|v| is interior there; sound and exact as above."""
    system = VehicleSystem(drag=1.0)
    rng = np.random.default_rng(1)
    lo, hi = _random_boxes(rng, 200, v_lo=-0.8, v_hi=0.8)
    lo[:, 3], hi[:, 3] = np.minimum(lo[:, 3], -0.6), np.maximum(hi[:, 3], 0.6)  # holds +-0.5 and +-0.375
    violation, gap = _check_contains(system, lo, hi, rng)
    assert violation <= 0.0 and gap < 1e-10


@pytest.mark.parametrize("component", [0, 1, 2, 3])
def test_shrunk_box_is_caught(component):
    """Sensitivity: the box of one output moved inward by 0.1 % of its width on each side is flagged by the
    same extreme points in almost every (mode, box); so the check above would catch such a bug."""
    rng = np.random.default_rng(2)
    lo, hi = _random_boxes(rng, 100)
    ilo, ihi = VEHICLE.image_bounds(lo, hi)
    w = ihi[..., component] - ilo[..., component]
    caught = np.zeros((4, 100), bool)
    for q, P in enumerate(_extreme_points(VEHICLE, lo, hi)):
        for u in range(4):
            y = VEHICLE.mean_step(P, np.full(P.shape[0], u))[:, component]
            caught[u, q] = (y.min() < ilo[u, q, component] + 1e-3 * w[u, q]) or (
                y.max() > ihi[u, q, component] - 1e-3 * w[u, q])
    assert caught.mean() > 0.99


def test_point_boxes():
    """Degenerate boxes [x, x]: the box holds the float step and is at most 1e-10 wide."""
    x = np.random.default_rng(3).uniform(VEHICLE_CASE["lower"], VEHICLE_CASE["upper"], (500, 4))
    lo, hi = VEHICLE.image_bounds(x, x)
    for u in range(4):
        y = VEHICLE.mean_step(x, np.full(500, u))
        assert np.all(lo[u] <= y) and np.all(y <= hi[u])
    assert np.max(hi - lo) < 1e-10


def test_hand_computed_box():
    """Box [0, 0.25] x [1, 1.25] x [0, pi/4] x [0.5, 0.6] under accelerate (a = 0.08, k = 1, c = 0.25):
    p_x' in [0 + 0.5 cos(pi/4), 0.25 + 0.6] (cos in [cos pi/4, 1]), p_y' in [1 + 0, 1.25 + 0.6 sin(pi/4)],
    theta' = theta, v' in [0.5 + 0.08 - 0.25 * 0.25, 0.6 + 0.08 - 0.25 * 0.36] (increasing on [0, 2])."""
    lo, hi = VEHICLE.image_bounds(np.array([[0.0, 1.0, 0.0, 0.5]]), np.array([[0.25, 1.25, PI / 4, 0.6]]))
    want_lo = [0.5 * np.cos(PI / 4), 1.0, 0.0, 0.5175]
    want_hi = [0.85, 1.25 + 0.6 * np.sin(PI / 4), PI / 4, 0.59]
    np.testing.assert_allclose(lo[0, 0], want_lo, rtol=0, atol=1e-11)
    np.testing.assert_allclose(hi[0, 0], want_hi, rtol=0, atol=1e-11)
    assert np.all(lo[0, 0] <= want_lo) and np.all(hi[0, 0] >= want_hi)  # outward


def test_trig_range_critical_points_and_wide():
    """sin over [1, 2] holds pi/2 (max 1); cos over [3, 3.5] holds pi (min -1); over [-7, -6.2] cos holds -2pi
    (max 1); a 2 pi wide interval is [-1, 1]; an interval without critical points gets its end values."""
    lo = np.array([1.0, 3.0, -7.0, 0.0, 0.1])
    hi = np.array([2.0, 3.5, -6.2, 2 * PI, 0.2])
    smin, smax = trig_range("sin", lo, hi)
    cmin, cmax = trig_range("cos", lo, hi)
    assert smax[0] == 1.0 and cmin[1] == -1.0 and cmax[2] == 1.0
    assert (smin[3], smax[3], cmin[3], cmax[3]) == (-1.0, 1.0, -1.0, 1.0)
    np.testing.assert_allclose([smin[4], smax[4]], [np.sin(0.1), np.sin(0.2)], rtol=0, atol=0)
    np.testing.assert_allclose([cmin[4], cmax[4]], [np.cos(0.2), np.cos(0.1)], rtol=0, atol=0)


def test_drag_map_range_interior_maximum():
    """phi(v) = v - v|v| (k = 1, a = 0, c = 1) on [0, 1]: maximum 1/4 at v = 1/2, minimum 0 at both ends;
    on [-1, 0]: minimum -1/4 at v = -1/2."""
    fmin, fmax, _ = drag_map_range(1.0, 0.0, 1.0, np.array([0.0, -1.0]), np.array([1.0, 0.0]))
    np.testing.assert_allclose(fmax, [0.25, 0.0], atol=1e-15)
    np.testing.assert_allclose(fmin, [0.0, -0.25], atol=1e-15)


def test_image_bounds_errors():
    with pytest.raises(DimensionError, match="lower"):
        VEHICLE.image_bounds(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(DimensionError, match="upper"):
        VEHICLE.image_bounds(np.zeros((2, 4)), np.zeros((3, 4)))
    with pytest.raises(InvalidInputError, match="lower must be <= upper"):
        VEHICLE.image_bounds(np.ones((1, 4)), np.zeros((1, 4)))
    with pytest.raises(InvalidInputError, match="finite"):
        VEHICLE.image_bounds(np.full((1, 4), np.nan), np.zeros((1, 4)))
    with pytest.raises(DimensionError, match="accel"):
        VehicleSystem(accel=np.zeros(3))
    with pytest.raises(InvalidInputError, match="drag"):
        VehicleSystem(drag=-1.0)
    with pytest.raises(InvalidInputError, match="speed_factor"):
        VehicleSystem(speed_factor=np.array([1.0, -0.5, 1.0, 1.0]))
    with pytest.raises(DimensionError, match="sigma"):
        VehicleSystem(sigma=np.zeros(4))
    with pytest.raises(DimensionError, match="x must have shape"):
        VEHICLE.mean_step(np.zeros((2, 3)), 0)


# --------------------------------------------------------------------------- the model and its problem
def test_known_part_plus_drag_is_the_true_step():
    """The problem's known f (expressions, parsed by KnownDynamics) plus the learned drag on v equals the
    true noise-free step; and the affine split (known_A x + known_b + g) does too."""
    from robust_imdp.models.known import KnownDynamics

    x = np.random.default_rng(4).uniform(VEHICLE_CASE["lower"], VEHICLE_CASE["upper"], (1000, 4))
    for u, exprs in enumerate(VEHICLE.known_f()):
        f = KnownDynamics(list(exprs)).evaluate(x)
        f[:, 3] += VEHICLE.drag_term(x)
        want = VEHICLE.mean_step(x, np.full(1000, u))
        np.testing.assert_allclose(f, want, rtol=0, atol=1e-14)
        split = x @ VEHICLE.known_A[u].T + VEHICLE.known_b[u] + VEHICLE.g(x, np.full(1000, u))
        np.testing.assert_allclose(split, want, rtol=0, atol=1e-14)


def test_reference_boxes_inside_certified_known_ranges():
    """Both are sound, ours is exact: our box of every output lies inside KnownDynamics' certified range
    of the full true expression (kinematics + drag) up to 1e-11, on 64 random cells of the case study."""
    from robust_imdp.models.known import KnownDynamics

    rng = np.random.default_rng(5)
    L, U, h = (np.array(VEHICLE_CASE[k]) for k in ("lower", "upper", "cell_size"))
    idx = rng.integers(0, np.round((U - L) / h).astype(int), (64, 4))
    lo, hi = L + idx * h, L + (idx + 1) * h
    ilo, ihi = VEHICLE.image_bounds(lo, hi)
    for u, exprs in enumerate(VEHICLE.known_f()):
        full = list(exprs[:3]) + [f"{exprs[3]} - {VEHICLE.drag!r}*x4*abs(x4)"]
        b = KnownDynamics(full).image_bounds(lo, hi)
        assert np.all(ilo[u] >= b.lower - 1e-11) and np.all(ihi[u] <= b.upper + 1e-11)


def test_turn_never_meets_its_own_heading_cell():
    """The turn of 0.5 rad exceeds one heading cell plus the noise bound on the 16^4 and 20^4 grids and is
    below two cells minus it, so Thm 1 lets a turn land in the next one or two heading cells only."""
    for k in (16, 20):
        c = 2 * PI / k
        w = float(VEHICLE.omega[2])
        assert c + VEHICLE.bound[2] < w < 2 * c - VEHICLE.bound[2]
        assert VEHICLE.omega[3] == -w


def test_problem_file_states_the_vehicle():
    """The problem file: f per mode, periodic heading, B = [0, 0, 0, B] (only v learned)."""
    from robust_imdp.casestudies.systems import CaseStudy, problem_toml

    case = CaseStudy(system=VEHICLE, **VEHICLE_CASE)
    text = problem_toml(case, case.formulas[0], "data.npz")
    assert "periodic = [false, false, true, false]" in text
    assert 'f = ["x1 + x4*cos(x3)", "x2 + x4*sin(x3)", "x3", "x4 + 0.08"]' in text  # accelerate
    assert 'f = ["x1 + x4*cos(x3)", "x2 + x4*sin(x3)", "x3 + 0.5", "x4"]' in text  # left
    assert 'f = ["x1 + x4*cos(x3)", "x2 + x4*sin(x3)", "x3", "0.75*x4"]' in text  # brake
    assert "rkhs_bound = [0.0, 0.0, 0.0, 0.5]" in text


def test_pipeline_end_to_end_small_grid(tmp_path):
    """4^4 cells, 400 samples per mode: the learned problem runs end to end, its Q_yes is at least the goal
    cells' share it must have, and Monte-Carlo containment holds (100 cells x 20 runs, validate's Wilson
    test at its default confidence)."""
    from robust_imdp.casestudies.systems import CaseStudy, problem_toml
    from robust_imdp.io.files import load_problem, write_data_file
    from robust_imdp.models.geometry import wrap_points
    from robust_imdp.pipeline.run import synthesize_from_data
    from robust_imdp.validate import validate

    case = CaseStudy(system=VEHICLE, **{**VEHICLE_CASE, "n_per_mode": 400})
    x, u, xn = VEHICLE.sample_dataset(case.n_per_mode, case.lower, case.upper, 0)
    xn = wrap_points(xn, np.asarray(case.lower), np.asarray(case.upper), case.periodic)
    write_data_file(tmp_path / "d.npz", x, u, xn, modes=VEHICLE.mode_names)
    (tmp_path / "p.toml").write_text(problem_toml(case, case.formulas[0], "d.npz"))
    problem = load_problem(tmp_path / "p.toml")
    problem = problem.replace(cell_size=(problem.space_upper - problem.space_lower) / 4)
    result = synthesize_from_data(problem, progress=False, advice=False)
    assert result.partition.n_cells == 256
    assert np.count_nonzero(result.synthesis.p_low >= 0.9) >= 64  # the goal band y in [3, 4]: 1/4 of the cells
    rep = validate(result, VEHICLE, n_per_cell=20, max_steps=200, rng=0,
                   cells=np.random.default_rng(0).choice(256, 100, replace=False))
    assert rep.passed


def test_shipped_drag_assumption_is_honest():
    """The case study's assumption for v (SE kernel, lengthscale (100, 100, 100, 0.5), B = 0.5, tau = 0.001)
    holds for the true drag g(x) = -c v|v|: h(x) = sum_j alpha_j k(x, z_j) with centres z_j = (2, 2, 0, v_j)
    has a certified norm (certificate.rkhs_norm_upper) <= 0.5 and sup_X |g - h| <= 0.001.

    Sup error: h(x) = phi(p, theta) h_v(v), phi = exp(-((p_x-2)^2 + (p_y-2)^2 + theta^2) / (2 100^2)) in
    [phi_min, 1] over X, so |g - h| <= |g - h_v| + (1 - phi_min) |h_v|. On v in [0, 0.8], |g - h_v| is bounded
    from a grid of spacing s: between grid points e = g - h_v with |e''| <= M is within M s^2 / 8 of the larger
    end value, M = 2c + sum_j |alpha_j| / l^2 (|k''| <= 1/l^2 for the SE kernel). Float error of the
    evaluation (< 1e-12 here) is covered by adding 1e-9."""
    from robust_imdp.casestudies.certificate import rkhs_norm_upper

    ls = np.array([100.0, 100.0, 100.0, 0.5])
    B, tau = VEHICLE_CASE["rkhs_bound"][3], VEHICLE_CASE["misspecification"]
    assert tuple(VEHICLE_CASE["gp"][0][1]) == tuple(ls)
    c, l_v = VEHICLE.drag, ls[3]
    v_lo, v_hi = VEHICLE_CASE["lower"][3], VEHICLE_CASE["upper"][3]
    z = np.linspace(v_lo - 0.05, v_hi + 0.05, 20)
    K = np.exp(-(z[:, None] - z[None, :]) ** 2 / (2 * l_v ** 2))
    alpha = np.linalg.solve(K + 1e-4 * np.eye(20), -c * z * np.abs(z))  # a proposal; certified below
    centres = np.column_stack([np.full(20, 2.0), np.full(20, 2.0), np.zeros(20), z])
    norm = rkhs_norm_upper(centres, alpha, ls)
    s = 1e-5
    v = np.linspace(v_lo, v_hi, int(round((v_hi - v_lo) / s)) + 1)
    h_v = np.exp(-(v[:, None] - z[None, :]) ** 2 / (2 * l_v ** 2)) @ alpha
    e = np.abs(-c * v * np.abs(v) - h_v)
    M = 2 * c + np.sum(np.abs(alpha)) / l_v ** 2
    sup_e = e.max() + M * s ** 2 / 8 + 1e-9
    L, U = np.array(VEHICLE_CASE["lower"]), np.array(VEHICLE_CASE["upper"])
    far = max(2.0 - L[0], U[0] - 2.0) ** 2 + max(2.0 - L[1], U[1] - 2.0) ** 2 + max(-L[2], U[2]) ** 2
    phi_min = np.exp(-far / (2 * 100.0 ** 2))
    sup_err = sup_e + (1 - phi_min) * np.abs(h_v).max() * (1 + 1e-9)
    assert norm <= B and sup_err <= tau, (norm, sup_err)
    assert norm > 0.2  # the fit is not trivial (||g|| is of this size): 0.2 < ~0.32 <= B = 0.5
