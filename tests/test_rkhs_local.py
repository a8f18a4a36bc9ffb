"""Certified RKHS cell bounds with local weights (``bound_chunk(..., local_points=k)``).

The local path is the default for every mode with more than ``pipeline.LOCAL_AUTO`` data points
and for the 3-D case study. It has its own numba kernel (``rkhs._local_cells``: the pool's kernel
matrix, the vertex functionals, the optimal or ridge weights and their certificates) and its own
composition of the cell bound (``rkhs._local_chunk``: noise bound plus tau, the inflated norm bound,
``t_max``, eq. C), so it gets the same checks as the global path of ``test_rkhs.py``:

* **every term has teeth**: the certified cell range is compared with an independent reference
  value of (eq. C) on the same pools -- the optimal vertex values from cvxpy/clarabel
  (``lp.rkhs_vertex_socp``) for ``method="optimal"``, the 40-digit mpmath value of the certificate
  of the ridge weights for ``method="ridge"``, the Taylor remainders in mpmath, the known affine part
  exactly. The check is ``ours >= reference - tol`` (``tol`` = the reference's accuracy) and it must
  fail when the noise term, the RKHS term, the Taylor term or tau of the bound is shrunk by 0.1 %;
* **known-norm Monte Carlo**: functions of exactly known RKHS norm, three kinds of noise, known
  affine parts and misspecification, d = 1, 2, 3, both weight methods, 10,000+ cells: 0 violations.
"""

from __future__ import annotations

import mpmath as mp
import numpy as np
import pytest

from robust_imdp.bounds import rkhs
from robust_imdp.solvers.lp import rkhs_vertex_socp

from test_rkhs import count_violations, grid_cells, kern, kernel_function, samples_in_cells

SHRINK = 1e-3  # the "slightly unsound" bound: a term shrunk by 0.1 %
SOCP_TOL = 1e-7  # accuracy of clarabel's optimum (default tolerances 1e-8 on values of order 1)
RIDGE_TOL = 1e-9  # the reference's ridge weights come from numpy's solve, the code's from its own Cholesky
LAM = 1e-4  # ridge regulariser of the ridge cases (passed to bound_chunk as local_lambda)


# ----------------------------------------------------------------------------- references
def _mp_kernel(a, b, ls):
    return mp.e ** (-sum((mp.mpf(a[i]) - mp.mpf(b[i])) ** 2 / (2 * mp.mpf(ls[i]) ** 2) for i in range(len(ls))))


def _mp_ridge_vertex(Xp, yp, ls, c, v, w, noise, B):
    """(value of w.y, noise ||w||_1, B ||phi_v - Phi* w||) in mpmath, for the vertex functional
    ``phi_v = k_c + sum_a v_a dk_c/dc_a`` (``<k_x, phi_v> = k(x, c)(1 + sum_a v_a (x_a - c_a)/l_a^2)``)."""
    k = Xp.shape[0]
    d = Xp.shape[1]
    L = [1 / mp.mpf(li) ** 2 for li in ls]
    b = [_mp_kernel(Xp[i], c, ls) * (1 + sum(mp.mpf(v[a]) * (mp.mpf(Xp[i, a]) - mp.mpf(c[a])) * L[a]
                                             for a in range(d))) for i in range(k)]
    s0 = 1 + sum(mp.mpf(v[a]) ** 2 * L[a] for a in range(d))
    W = [mp.mpf(x) for x in w]
    K = [[_mp_kernel(Xp[i], Xp[j], ls) for j in range(k)] for i in range(k)]
    q = s0 - 2 * sum(W[i] * b[i] for i in range(k)) + sum(W[i] * W[j] * K[i][j] for i in range(k) for j in range(k))
    return (sum(W[i] * mp.mpf(yp[i]) for i in range(k)), mp.mpf(noise) * sum(abs(x) for x in W),
            mp.mpf(B) * mp.sqrt(max(q, 0)))


def _mp_rho(a, t):
    """``max_{0 <= s <= t} ||k_x - a phi_D||`` (eq. T for a = 1; the end points otherwise, t < 3)."""
    a, t = mp.mpf(a), mp.mpf(t)
    f_t = 1 + a ** 2 + a ** 2 * t - 2 * a * (1 + t) * mp.e ** (-t / 2)
    return mp.sqrt(max((1 - a) ** 2, f_t, 0))


def _reference(X, y, ls, lo, up, *, A, b0, B, dbar, tau, method, k, pools=None):
    """Independent value of (eq. C) on the code's pools, per cell: ``up``, ``lo`` and the size of
    every term of each side (the smallest over the vertices and both feature scalings).

    Returns dict of (n_cells,) float arrays: ``up``, ``lo`` and ``terms[side][name]`` with side in
    ("up", "lo") and name in ("noise", "rkhs", "taylor", "tau").
    """
    pools = rkhs.local_pools(X, lo, up, ls, k) if pools is None else pools
    d = X.shape[1]
    signs = rkhs.vertex_signs(d)
    nb = dbar + tau
    out = {"up": [], "lo": [], "terms": {"up": {n: [] for n in ("noise", "rkhs", "taylor", "tau")},
                                          "lo": {n: [] for n in ("noise", "rkhs", "taylor", "tau")}}}
    for q in range(lo.shape[0]):
        c = 0.5 * (lo[q] + up[q])  # dyadic cells: exact
        r = 0.5 * (up[q] - lo[q])
        P = pools[q]
        Xp, yp = X[P], y[P]
        Kp = kern(Xp, Xp, ls)
        t = sum(mp.mpf(r[a]) ** 2 / mp.mpf(ls[a]) ** 2 for a in range(d))
        vert = {"up": [], "lo": []}  # (lin_v, value of <h, phi_v> bound, noise term, rkhs term) per vertex
        for s in signs:
            v = s * r
            lin = sum(mp.mpf(A[a]) * (mp.mpf(c[a]) + mp.mpf(v[a])) for a in range(d)) + mp.mpf(b0)
            bv = kern(Xp, c[None], ls)[:, 0] * (1 + ((Xp - c) / ls ** 2) @ v)
            s0 = 1 + float(np.sum(v * v / ls ** 2))
            for side, key in ((1, "up"), (-1, "lo")):
                if method == "optimal":
                    val, w = rkhs_vertex_socp(Kp, yp, bv, s0, nb, B, side)
                    res = max(s0 - 2 * w @ bv + w @ Kp @ w, 0.0)
                    noise_t, rkhs_t = nb * np.abs(w).sum(), B * np.sqrt(res)
                    value = mp.mpf(side * val)
                else:
                    w = np.linalg.solve(Kp + LAM * np.eye(len(P)), bv)
                    wy, noise_t, rkhs_t = _mp_ridge_vertex(Xp, yp, ls, c, v, w, nb, B)
                    value = wy + side * (noise_t + rkhs_t)
                vert[key].append((lin, value, float(noise_t), float(rkhs_t)))
        for key, side in (("up", 1), ("lo", -1)):
            best, taylor_min = None, np.inf
            for a in (mp.mpf(1), mp.e ** (-t / 2)):
                rho = mp.mpf(B) * _mp_rho(a, t)
                cand = side * max(side * (lin + a * val) for lin, val, _, _ in vert[key]) + side * (rho + tau)
                best = cand if best is None else (min(best, cand) if side > 0 else max(best, cand))
                taylor_min = min(taylor_min, float(rho))
            out[key].append(float(best))
            terms = out["terms"][key]
            terms["noise"].append(min(x[2] for x in vert[key]) * float(mp.e ** (-t / 2)))
            terms["rkhs"].append(min(x[3] for x in vert[key]) * float(mp.e ** (-t / 2)))
            terms["taylor"].append(taylor_min)
            terms["tau"].append(tau)
    return {"up": np.array(out["up"]), "lo": np.array(out["lo"]),
            "terms": {s: {n: np.array(v) for n, v in out["terms"][s].items()} for s in ("up", "lo")}}


def _local_problem(seed, d, m, n_cells, r_over_l):
    """A known-norm function sampled with uniform noise, cells with dyadic centres and half-widths."""
    rng = np.random.default_rng(seed)
    ls = np.full(d, 1.0) * rng.choice([0.75, 1.0, 1.25], d)
    h = kernel_function(rng, d, 8, ls, 1.2)
    X = rng.uniform(-1, 1, (m, d))
    dbar = 0.05
    y = h(X) + rng.uniform(-dbar, dbar, m)
    r = np.ldexp(np.round(np.ldexp(r_over_l * ls, 10)), -10)  # dyadic half-widths, r/l ~ r_over_l
    c = np.ldexp(np.round(np.ldexp(rng.uniform(-0.6, 0.6, (n_cells, d)), 10)), -10)
    A = rng.standard_normal(d)
    b0 = float(np.ldexp(np.round(np.ldexp(rng.standard_normal(), 20)), -20))
    return X, y, ls, c - r, c + r, A, b0, dbar


CASES = [(1, "optimal", 0.0), (2, "optimal", 0.02), (3, "optimal", 0.0),
         (1, "ridge", 0.02), (2, "ridge", 0.0), (3, "ridge", 0.0)]


@pytest.mark.parametrize("d,method,tau", CASES)
def test_local_cell_range_is_eq_C_and_every_term_has_teeth(d, method, tau):
    # Soundness check: ours >= the reference value of (eq. C) (upper side; lower side mirrored), up to
    # the reference's accuracy tol. Teeth: for every term of the bound (noise, RKHS, Taylor remainder,
    # tau), our bound with that term shrunk by 0.1 % fails the same check on every cell -- so the check
    # sees a 0.1 % error of any one term (benchmarks/mutations.py: rkhs-local-*).
    B, k = 2.0, 20
    X, y, ls, lo, up, A, b0, dbar = _local_problem(10 * d + len(method), d, 90, 5 if d < 3 else 3, 0.15)
    kw = dict(lengthscale=ls, rkhs_bound=B, noise_bound=[dbar], misspecification=tau, method=method,
              local_points=k, local_lambda=LAM if method == "ridge" else None, split_tol=None)
    ours = rkhs.bound_chunk(X, y[:, None], A[None], np.array([b0]), lo, up, **kw)
    ref = _reference(X, y, ls, lo, up, A=A, b0=b0, B=B, dbar=dbar, tau=tau, method=method, k=k)
    tol = SOCP_TOL if method == "optimal" else RIDGE_TOL
    o_up, o_lo = ours["upper"][:, 0], ours["lower"][:, 0]
    assert np.all(o_up >= ref["up"] - tol) and np.all(o_lo <= ref["lo"] + tol)  # sound
    names = ("noise", "rkhs", "taylor") + (("tau",) if tau else ())
    for name in names:
        t_up, t_lo = ref["terms"]["up"][name], ref["terms"]["lo"][name]
        assert np.all(t_up > 0) and np.all(t_lo > 0)
        assert np.all(o_up - SHRINK * t_up < ref["up"] - tol), name  # teeth, upper side
        assert np.all(o_lo + SHRINK * t_lo > ref["lo"] + tol), name  # teeth, lower side


# ----------------------------------------------------------------------------- Monte Carlo
def _mc_local_case(rng, d, method, noise_kind, n_cells_side, known=False, tau=0.0):
    ls = rng.uniform(0.6, 2.0, d)
    B = rng.uniform(0.5, 3.0)
    dbar = rng.choice([0.005, 0.02, 0.1])
    h = kernel_function(rng, d, 8, ls, B)
    e = (lambda X: tau * np.sin(37 * X[:, 0] + 11 * X[:, -1])) if tau else (lambda X: 0.0)
    m = int(rng.integers(40, 150))
    k = int(rng.choice([8, 15, 30]))
    X = rng.uniform(-1, 1, (m, d))
    g = h(X) + e(X)
    if noise_kind == "uniform":
        noise = rng.uniform(-dbar, dbar, m)
    elif noise_kind == "signs":
        noise = dbar * rng.choice([-1.0, 1.0], m)
    else:  # adversarial: push every sample away from a smooth fit of the clean values
        Kx = kern(X, X, ls)
        mu = Kx @ np.linalg.solve(Kx + 0.5 * np.eye(m), g)
        noise = dbar * np.where(g >= mu, 1.0, -1.0)
    y = g + noise
    A = rng.standard_normal(d) if known else np.zeros(d)
    b0 = float(rng.standard_normal()) if known else 0.0
    lo, up = grid_cells(d, -1.0, 1.0, 2.0 / n_cells_side)
    out = rkhs.bound_chunk(X, y[:, None], A[None], np.array([b0]), lo, up, lengthscale=ls, rkhs_bound=B,
                           noise_bound=[dbar], misspecification=tau, method=method, local_points=k)
    P = samples_in_cells(rng, lo, up, 6)
    vals = np.stack([h(P[q]) + e(P[q]) + P[q] @ A + b0 for q in range(lo.shape[0])])
    return count_violations(vals, out["lower"][:, 0], out["upper"][:, 0]), lo.shape[0]


def test_local_cell_bounds_contain_known_norm_functions_on_10000_cells():
    # As test_rkhs.test_cell_bounds_contain_known_norm_functions_on_10000_cells, through the local
    # path (pools of 8-30 of 40-150 points). Soundness claim: zero samples outside.
    rng = np.random.default_rng(16)
    total_cells = total_viol = 0
    configs = []
    for noise_kind in ("uniform", "signs", "adversarial"):
        configs += [(1, "optimal", noise_kind, 60, False, 0.0)] * 6
        configs += [(2, "optimal", noise_kind, 16, True, 0.0)] * 6
        configs += [(2, "optimal", noise_kind, 12, False, 0.01)] * 3
        configs += [(3, "optimal", noise_kind, 5, True, 0.0)] * 3
        configs += [(1, "ridge", noise_kind, 60, True, 0.01)] * 2
        configs += [(2, "ridge", noise_kind, 16, True, 0.0)] * 3
        configs += [(3, "ridge", noise_kind, 5, False, 0.0)] * 2
    for d, method, nk, side, known, tau in configs:
        viol, n = _mc_local_case(rng, d, method, nk, side, known, tau)
        total_viol += viol
        total_cells += n
    assert total_cells >= 10_000
    assert total_viol == 0


def test_numba_kernel_error_bound_equals_the_python_one():
    # _kernel_rel_err_nb bounds the kernel values of the vertex functionals (global optimal path) and
    # of the local pools; _kernel_rel_err is checked against mpmath in test_rkhs. They must agree.
    for d in (1, 2, 3, 6):
        for z in (0.0, 1e-8, 0.5, 3.0, 40.0, 700.0, 1e4):
            assert rkhs._kernel_rel_err_nb(z, d) == rkhs._kernel_rel_err(z, d)
            assert rkhs._kernel_rel_err_nb(z, d) >= 6 * 2.0 ** -53  # exp and the inputs' rounding at least


def test_split_counts_follow_the_rule_up_to_the_cap_in_every_dimension():
    # s = ceil(sqrt(B rho(t) / tol)) (docs/rkhs_bounds.md, "Sub-boxes"): the fewest pieces with
    # B rho(t) / s^2 <= tol (the term shrinks about like t, and a sub-box of 1/s the size has t / s^2),
    # never more than floor(MAX_SUB^(1/d)) per axis.
    from robust_imdp.bounds.rkhs_model import _scaled_remainder_sqrt_up, split_term

    B, tol = 0.35, rkhs.SPLIT_TOL
    for d in (1, 2, 3, 4):
        t = d * np.linspace(0.001, 1.0, 400) ** 2  # r / l up to 1 per axis
        s = rkhs.split_counts(t, B, d, tol)
        cap = int(np.floor(rkhs.MAX_SUB ** (1.0 / d) + 1e-9))
        assert s.min() == 1 and s.max() <= cap and np.all(s ** d <= rkhs.MAX_SUB)
        assert d == 1 or s.max() == cap  # (in 1-D the rule asks for at most 16 here)
        assert np.all(np.diff(s) >= 0)  # a larger cell never gets fewer pieces
        term = B * np.minimum(rkhs.taylor_remainder_sqrt_up(t), _scaled_remainder_sqrt_up(np.exp(-0.5 * t), t))
        np.testing.assert_array_equal(term, split_term(t, B))  # the term split_counts weighs
        free = s < cap
        assert np.all(term[free] / s[free] ** 2 <= tol * (1 + 1e-12))
        assert np.all(term[s > 1] / (s[s > 1] - 1.0) ** 2 > tol)  # and one piece fewer would not do
    # the cap leaves 3-D cells at r/l 0.25 (B 0.32, the family's) the s = 6 the rule asks for
    assert int(rkhs.split_counts(np.array([3 * 0.25 ** 2]), 0.32, 3, tol)[0]) == 6


# ----------------------------------------------------------------------------- certification sub-boxes
def test_sub_boxes_cover_the_cell_exactly():
    # Union of the sub-boxes = the cell, in exact rational arithmetic, for awkward floats and s = 1..5:
    # per axis the edges start at lower, end at upper, never decrease, and neighbours share them.
    from fractions import Fraction

    rng = np.random.default_rng(17)
    lo = rng.uniform(-1e3, 1e3, (40, 2)) * rng.choice([1e-7, 1.0, 1e5], (40, 2))
    up = lo + np.abs(rng.standard_normal((40, 2))) * rng.choice([1e-12, 1e-3, 10.0], (40, 2))
    s = rng.integers(1, 6, 40)
    blo, bup, parent, starts = rkhs.sub_boxes(lo, up, s)
    assert np.all(np.diff(parent) >= 0) and np.all(starts == np.searchsorted(parent, np.arange(40)))
    for q in range(40):
        sb_lo, sb_up = blo[parent == q], bup[parent == q]
        assert sb_lo.shape[0] == s[q] ** 2 and np.all(sb_lo <= sb_up)
        axes = []
        for a in range(2):
            iv = sorted(set(zip(sb_lo[:, a], sb_up[:, a])))  # distinct intervals of this axis
            # a chain from lower to upper: each interval starts where the previous one ends (no gap)
            assert Fraction(iv[0][0]) == Fraction(lo[q, a]) and Fraction(iv[-1][1]) == Fraction(up[q, a])
            assert all(Fraction(iv[j][1]) == Fraction(iv[j + 1][0]) for j in range(len(iv) - 1))
            axes.append(iv)
        # and every combination of axis intervals is a sub-box (a product grid)
        boxes = set(zip(zip(sb_lo[:, 0], sb_up[:, 0]), zip(sb_lo[:, 1], sb_up[:, 1])))
        assert all((i0, i1) in boxes for i0 in axes[0] for i1 in axes[1])


@pytest.mark.parametrize("method", ["optimal", "ridge"])
def test_sub_box_certification_is_the_hull_of_eq_C_on_sub_boxes_with_teeth(method):
    # With a split of s = 2 per axis (dyadic sub-boxes: exact centres and half-widths), the local
    # cell range is the hull over the sub-boxes of (eq. C) on each sub-box (the cell's pool, the
    # sub-box's own Taylor remainder). Same check and teeth as above; the Taylor term named here is
    # the sub-box remainder (benchmarks/mutations.py: rkhs-split-*).
    d, B, k, tau = 2, 2.0, 20, 0.0
    X, y, ls, lo, up, A, b0, dbar = _local_problem(31 + len(method), d, 90, 3, 0.15)
    c, r = rkhs.cell_centres(lo, up)
    t = np.sum(r * r / ls ** 2, axis=1)
    rho = np.array([float(mp.mpf(B) * _mp_rho(1, v)) for v in t])
    split_tol = float(rho.min()) / 3.0  # s = ceil(sqrt(B rho / split_tol)) = 2 (rho(a) ~ 0.8 rho(1))
    s = rkhs.split_counts(t, B, d, split_tol)
    assert np.all(s == 2)
    kw = dict(lengthscale=ls, rkhs_bound=B, noise_bound=[dbar], misspecification=tau, method=method,
              local_points=k, local_lambda=LAM if method == "ridge" else None, split_tol=split_tol)
    ours = rkhs.bound_chunk(X, y[:, None], A[None], np.array([b0]), lo, up, **kw)
    blo, bup, parent, _ = rkhs.sub_boxes(lo, up, s)
    pools = rkhs.local_pools(X, lo, up, ls, k)[parent]
    ref = _reference(X, y, ls, blo, bup, A=A, b0=b0, B=B, dbar=dbar, tau=tau, method=method, k=k, pools=pools)
    tol = SOCP_TOL if method == "optimal" else RIDGE_TOL
    o_up, o_lo = ours["upper"][:, 0], ours["lower"][:, 0]
    r_up = np.array([ref["up"][parent == q].max() for q in range(lo.shape[0])])
    r_lo = np.array([ref["lo"][parent == q].min() for q in range(lo.shape[0])])
    assert np.all(o_up >= r_up - tol) and np.all(o_lo <= r_lo + tol)  # sound
    # the hull is strictly tighter than the unsplit cell range (the point of splitting)
    whole = rkhs.bound_chunk(X, y[:, None], A[None], np.array([b0]), lo, up, **dict(kw, split_tol=None))
    assert np.all(o_up < whole["upper"][:, 0]) and np.all(o_lo > whole["lower"][:, 0])
    for name in ("noise", "rkhs", "taylor"):
        # the smallest term over the sub-boxes bounds how much a shrink of it moves the hull
        t_up = np.array([ref["terms"]["up"][name][parent == q].min() for q in range(lo.shape[0])])
        t_lo = np.array([ref["terms"]["lo"][name][parent == q].min() for q in range(lo.shape[0])])
        assert np.all(o_up - SHRINK * t_up < r_up - tol), name
        assert np.all(o_lo + SHRINK * t_lo > r_lo + tol), name


@pytest.mark.parametrize("split", [False, True])
def test_global_optimal_cell_range_is_eq_C_with_teeth(split):
    # The global path (cell_ranges, all points carry weight) against the same reference with the pool
    # = all data: unsplit, and split into s = 2 sub-boxes per axis (the hull over sub-boxes).
    d, B, tau = 2, 2.0, 0.01
    X, y, ls, lo, up, A, b0, dbar = _local_problem(41 + split, d, 40, 3, 0.15)
    c, r = rkhs.cell_centres(lo, up)
    t = np.sum(r * r / ls ** 2, axis=1)
    split_tol = float(min(float(mp.mpf(B) * _mp_rho(1, v)) for v in t)) / 3.0 if split else None
    s = rkhs.split_counts(t, B, d, split_tol)
    assert np.all(s == (2 if split else 1))
    cr = rkhs.cell_ranges(rkhs.KernelModel(X, y, ls), lo, up, rkhs_bound=B, noise_bound=dbar, misspecification=tau,
                          known_row=A, known_offset=b0, split_tol=split_tol)
    blo, bup, parent, _ = rkhs.sub_boxes(lo, up, s)
    pools = np.tile(np.arange(X.shape[0]), (blo.shape[0], 1))
    ref = _reference(X, y, ls, blo, bup, A=A, b0=b0, B=B, dbar=dbar, tau=tau, method="optimal", k=X.shape[0],
                     pools=pools)
    r_up = np.array([ref["up"][parent == q].max() for q in range(lo.shape[0])])
    r_lo = np.array([ref["lo"][parent == q].min() for q in range(lo.shape[0])])
    assert np.all(cr.upper >= r_up - SOCP_TOL) and np.all(cr.lower <= r_lo + SOCP_TOL)
    for name in ("noise", "rkhs", "taylor", "tau"):
        t_up = np.array([ref["terms"]["up"][name][parent == q].min() for q in range(lo.shape[0])])
        t_lo = np.array([ref["terms"]["lo"][name][parent == q].min() for q in range(lo.shape[0])])
        assert np.all(cr.upper - SHRINK * t_up < r_up - SOCP_TOL), name
        assert np.all(cr.lower + SHRINK * t_lo > r_lo + SOCP_TOL), name


# ----------------------------------------------------------------------------- sub-box pruning and shared sums
def test_certify_with_shared_weight_sums_is_the_one_evaluator_bit_for_bit():
    # _certify_parts (the weights' O(n^2) sums computed once for many functionals: the pruning loops
    # of the optimal kernels) must give exactly _certify's bits, for random and cancelling weights.
    rng = np.random.default_rng(51)
    for trial in range(40):
        m, d = int(rng.integers(1, 30)), int(rng.integers(1, 4))
        X = rng.uniform(-1, 1, (m, d))
        model = rkhs.KernelModel(X, rng.standard_normal(m), rng.uniform(0.3, 2.0, d))
        n = int(rng.integers(0, m + 1))
        idx = np.ascontiguousarray(rng.permutation(m)[:max(n, 1)].astype(np.int64))
        w = rng.standard_normal(idx.shape[0]) * (1e6 if trial % 5 == 0 else 1.0)
        parts = np.array(rkhs._weight_parts(idx, w, n, model.K))
        vp = rkhs.vertex_problems(model, X[:1], np.full((1, d), 0.1))
        for j in range(vp["b"].shape[1]):
            for side in (1.0, -1.0):
                args = (idx, w, n, model.y, vp["b"][0, j], vp["b_err"][0, j])
                ref = rkhs._certify(*args, model.K, model.K_err, float(vp["s0"][0, j]), 0.03, 0.01, 1.3, side)
                got = rkhs._certify_parts(*args, model.K_err, float(vp["s0"][0, j]), 0.03, 0.01, 1.3, side, parts)
                assert ref[0] == got[0] and ref[1] == got[1]


def _split_problem(seed, d, m, n_cells):
    X, y, ls, lo, up, A, b0, dbar = _local_problem(seed, d, m, n_cells, 0.2)
    B = 2.0
    c, r = rkhs.cell_centres(lo, up)
    t = np.sum(r * r / ls ** 2, axis=1)
    s = np.full(lo.shape[0], 3)
    blo, bup, parent, starts = rkhs.sub_boxes(lo, up, s)
    return X, y, ls, lo, up, A, b0, dbar, B, blo, bup, parent, starts


@pytest.mark.parametrize("path", ["global", "local"])
def test_every_value_of_a_pruned_sub_box_is_a_sound_vertex_bound(path):
    # With sub-boxes (3 per axis), most sub-boxes and vertices keep the value of earlier weights
    # (pruned: they cannot move the cell's bound). Every value returned, pruned or optimised, must
    # still bound <h, phi_v> on its side: checked against the SOCP optimum of every (sub-box, vertex,
    # side) (cvxpy + clarabel, accurate to SOCP_TOL), and the optimised ones of the deciding sub-box
    # are tight (the hull equals the hull of the SOCP values within 1e-6).
    d = 2
    X, y, ls, lo, up, A, b0, dbar, B, blo, bup, parent, starts = _split_problem(61, d, 50, 3)
    c, r = rkhs.cell_centres(blo, bup)
    signs = rkhs.vertex_signs(d)
    lin, _ = rkhs._known_at_vertices(c, r, signs, A, b0)
    ptr = rkhs._blocks(lo.shape[0], starts, c.shape[0], rkhs.CELL_BLOCK)
    inv_l2 = rkhs._inv_l2(ls, d)
    if path == "global":
        model = rkhs.KernelModel(X, y, ls)
        val, _, stat = rkhs._optimal_cells(model.X, model.y, model.K, model.K_err, model.inv_l2, c, r, signs, dbar, B,
                                           X.shape[0], 2000, 1e-10, ptr, lin, True, parent)
        pools = np.tile(np.arange(X.shape[0]), (c.shape[0], 1))
        pruned = int(np.sum(stat == 6))
    else:
        k = 25
        pools = np.ascontiguousarray(rkhs.local_pools(X, lo, up, ls, k)[parent])
        v4, _ = rkhs._local_cells(rkhs._writable(X), rkhs._writable(y[:, None]), inv_l2, c, r, signs, pools, 0.0,
                                  np.array([dbar]), np.zeros(1), B, True, 2000, 1e-10, ptr, parent,
                                  np.ascontiguousarray(lin[:, :, None]))
        val = v4[:, :, 0, :]
        pruned = None
    hull = {1: np.full(lo.shape[0], -np.inf), -1: np.full(lo.shape[0], -np.inf)}
    ours = {1: np.full(lo.shape[0], -np.inf), -1: np.full(lo.shape[0], -np.inf)}
    for q in range(c.shape[0]):
        P = pools[q]
        Kp = kern(X[P], X[P], ls)
        for jv, sg in enumerate(signs):
            v = sg * r[q]
            bv = kern(X[P], c[q][None], ls)[:, 0] * (1 + ((X[P] - c[q]) / ls ** 2) @ v)
            s0 = 1 + float(np.sum(v * v / ls ** 2))
            for side, col in ((1, 0), (-1, 1)):
                opt, _ = rkhs_vertex_socp(Kp, y[P], bv, s0, dbar, B, side)
                assert side * val[q, jv, col] >= opt - SOCP_TOL, (q, jv, side)  # sound, pruned or not
                hull[side][parent[q]] = max(hull[side][parent[q]], side * lin[q, jv] + opt)
                ours[side][parent[q]] = max(ours[side][parent[q]], side * (lin[q, jv] + val[q, jv, col]))
    for side in (1, -1):
        assert np.all(np.abs(ours[side] - hull[side]) <= 1e-6), side  # the deciding vertices are optimal
    if pruned is not None:
        assert pruned > 0.5 * stat.size  # most of the 9 x 4 x 2 problems per cell are pruned


def _mc_split_case(rng, d, path, noise_kind, n_cells_side):
    ls = rng.uniform(0.3, 1.0, d)
    B = rng.uniform(0.5, 3.0)
    dbar = rng.choice([0.005, 0.02, 0.1])
    h = kernel_function(rng, d, 8, ls, B)
    m = int(rng.integers(40, 120))
    X = rng.uniform(-1, 1, (m, d))
    g = h(X)
    if noise_kind == "uniform":
        noise = rng.uniform(-dbar, dbar, m)
    elif noise_kind == "signs":
        noise = dbar * rng.choice([-1.0, 1.0], m)
    else:  # adversarial: push every sample away from a smooth fit of the clean values
        Kx = kern(X, X, ls)
        mu = Kx @ np.linalg.solve(Kx + 0.5 * np.eye(m), g)
        noise = dbar * np.where(g >= mu, 1.0, -1.0)
    y = g + noise
    A = rng.standard_normal(d)
    b0 = float(rng.standard_normal())
    lo, up = grid_cells(d, -1.0, 1.0, 2.0 / n_cells_side)
    r = 0.5 * (up[0] - lo[0])
    rho = float(rkhs.taylor_remainder_sqrt_up(np.sum(r * r / ls ** 2)))
    split_tol = B * rho / float(rng.choice([2.0, 5.0, 10.0]))  # 2 or 3 (or 4) pieces per axis
    local = int(rng.choice([10, 25])) if path == "local" else None
    out = rkhs.bound_chunk(X, y[:, None], A[None], np.array([b0]), lo, up, lengthscale=ls, rkhs_bound=B,
                           noise_bound=[dbar], local_points=local, split_tol=split_tol)
    P = samples_in_cells(rng, lo, up, 6)
    vals = np.stack([h(P[q]) + P[q] @ A + b0 for q in range(lo.shape[0])])
    return count_violations(vals, out["lower"][:, 0], out["upper"][:, 0]), lo.shape[0]


def test_split_cell_bounds_contain_known_norm_functions_on_10000_cells():
    # The known-norm Monte Carlo through the sub-box paths (global and local optimal weights, 2-4
    # pieces per axis, pruned sub-boxes): functions of exactly known norm B, three kinds of noise,
    # known affine parts, d = 1, 2, 3. Soundness claim: zero samples outside.
    rng = np.random.default_rng(62)
    total_cells = total_viol = 0
    for noise_kind in ("uniform", "signs", "adversarial"):
        for path in ("global", "local"):
            for d, side, reps in ((1, 40, 4), (2, 14, 7), (3, 5, 2)):
                for _ in range(reps):
                    viol, n = _mc_split_case(rng, d, path, noise_kind, side)
                    total_viol += viol
                    total_cells += n
    assert total_cells >= 10_000
    assert total_viol == 0
