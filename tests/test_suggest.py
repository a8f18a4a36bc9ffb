"""Sample requests (robust_imdp.synthesis.suggest): the power-function algebra against closed forms,
and the requests' properties on a small data-starved problem.

Oracles: the posterior covariance after adding a point, recomputed from scratch (eq. S1); the
ridge objective ``min_w ||phi_x - Phi* w||^2 + lambda ||w||^2`` in closed form (it equals the power
function, which is why the RKHS term scales with it); uniform random samples of the same number.
"""

import numpy as np
import pytest

from robust_imdp._kernels import se_gram
from robust_imdp.errors import InvalidInputError
from robust_imdp.synthesis import suggest as sg


def test_rank_one_update_equals_the_posterior_recomputed_with_the_new_point():
    rng = np.random.default_rng(0)
    data = rng.uniform(0, 2, (15, 2))
    cand = rng.uniform(0, 2, (9, 2))
    inv_l2, lam = np.array([1.0, 4.0]), 1e-3
    S = sg._posterior_cov(cand, data, inv_l2, lam)
    c = 4
    S1 = S - np.outer(S[:, c], S[:, c]) / (S[c, c] + lam)  # eq. S1
    again = sg._posterior_cov(cand, np.vstack([data, cand[c:c + 1]]), inv_l2, lam)
    # float64 Cholesky of a 16 x 16 kernel matrix (condition ~1e5 with lam = 1e-3): 1e-9 absolute
    assert np.max(np.abs(S1 - again)) < 1e-9


def test_power_function_is_the_optimal_ridge_objective():
    # P(x) = k(x,x) - k^T (K + lam I)^-1 k = min_w ||phi_x - Phi* w||^2 + lam ||w||^2 (RKHS algebra:
    # ||phi_x - Phi* w||^2 = k(x,x) - 2 w.k + w^T K w, minimised at w = (K + lam I)^-1 k)
    rng = np.random.default_rng(1)
    data = rng.uniform(-1, 1, (12, 1))
    x = np.array([[0.3]])
    inv_l2, lam = np.array([2.0]), 1e-2
    P = sg._posterior_cov(x, data, inv_l2, lam)[0, 0]
    K = se_gram(data, data, inv_l2)
    k = se_gram(data, x, inv_l2)[:, 0]
    w = np.linalg.solve(K + lam * np.eye(12), k)
    objective = 1.0 - 2 * w @ k + w @ K @ w + lam * w @ w
    assert P == pytest.approx(objective, abs=1e-12)
    # and any other weights do worse
    for _ in range(20):
        v = w + rng.normal(0, 0.05, 12)
        assert 1.0 - 2 * v @ k + v @ K @ v + lam * v @ v >= objective - 1e-12


@pytest.fixture(scope="module")
def starved():
    """A 2-D robot with 12 samples per mode: most cells undecided."""
    from robust_imdp import Problem, TruncatedGaussianNoise, synthesize_from_data

    rng = np.random.default_rng(3)
    steps = {"east": [0.4, 0.0], "north": [0.0, 0.4]}
    xs, us, xn = [], [], []
    for name, s in steps.items():
        x = rng.uniform(0, 3, (12, 2))
        xs.append(x)
        us += [name] * 12
        xn.append(x + s + 0.05 * np.sin(x[:, ::-1]) + rng.uniform(-0.01, 0.01, x.shape))
    problem = Problem.from_arrays(
        np.vstack(xs), np.array(us), np.vstack(xn), lower=[0, 0], upper=[3, 3], cell_size=0.5,
        regions={"goal": ([2, 2], [3, 3])}, formula="F goal", threshold=0.9,
        modes={k: (np.eye(2), v) for k, v in steps.items()},
        noise=TruncatedGaussianNoise([0.005, 0.005], [0.01, 0.01]), rkhs_bound=0.3, lengthscale=1.0,
        misspecification=0.001)
    return synthesize_from_data(problem, progress=False)


def test_requests_are_inside_x_for_candidate_cells_with_valid_modes(starved):
    reqs = sg.suggest_samples(starved, 10)
    cells, weights, _ = sg._candidates(starved)
    assert 0 < len(reqs) <= 10
    part = starved.partition
    for r in reqs:
        assert r.cell in set(cells.tolist())
        assert np.all(part.cells_lower[r.cell] <= r.x) and np.all(r.x <= part.cells_upper[r.cell])
        assert r.mode in starved.problem.mode_names
        assert r.radius_change > 0 and r.gain > 0
    assert np.all(np.asarray(starved.class_names)[cells] != "yes") or "reached" in " ".join(r.reason for r in reqs)


def test_suggested_samples_shrink_the_weighted_rkhs_terms_more_than_random_ones(starved):
    """The objective the requests are chosen for, measured from scratch with the augmented data."""
    n = 8
    reqs = sg.suggest_samples(starved, n)
    cells, weights, _ = sg._candidates(starved)
    part = starved.partition
    centres = 0.5 * (part.cells_lower[cells] + part.cells_upper[cells])
    B, inv_l2, floor = sg._assumption(starved.problem)
    names = list(starved.problem.mode_names)

    def objective(extra):  # sum over modes and candidates of weight * B sqrt(P)
        total = 0.0
        for u in range(len(names)):
            x = np.vstack([starved.problem.data.by_mode(u)[0]] + [e for m, e in extra if m == u])
            lam = (floor[u] / B[u]) ** 2
            P = np.maximum(np.diag(sg._posterior_cov(centres, x, inv_l2[u], lam)), 0)
            total += weights[u] @ (B[u] * np.sqrt(P))
        return total

    base = objective([])
    ours = objective([(names.index(r.mode), r.x[None]) for r in reqs])
    rng = np.random.default_rng(7)
    randoms = [objective([(int(rng.integers(0, 2)), rng.uniform(0, 3, (1, 2))) for _ in range(n)]) for _ in range(5)]
    assert ours < base
    assert base - ours > max(base - r for r in randoms)


def test_bad_n_and_nothing_undecided(starved):
    with pytest.raises(InvalidInputError, match="n .* must be an integer >= 1; got 0"):
        sg.suggest_samples(starved, 0)
    import dataclasses

    decided = dataclasses.replace(starved, class_names=np.where(starved.class_names == "maybe", "no",
                                                                starved.class_names))
    assert sg.suggest_samples(decided, 5) == []


def test_requests_csv_is_complete(tmp_path, starved):
    import csv

    reqs = sg.suggest_samples(starved, 3)
    sg.write_requests(reqs, tmp_path / "r.csv", ["x_1", "x_2"])
    rows = list(csv.reader(open(tmp_path / "r.csv")))
    assert rows[0] == ["x_1", "x_2", "mode", "cell", "radius_change", "gain", "reason"]
    assert len(rows) == len(reqs) + 1
    assert [float(v) for v in rows[1][:2]] == reqs[0].x.tolist()
    assert not (tmp_path / "r.csv.tmp").exists()


def test_result_method_and_cli_write_the_same_requests(tmp_path, starved, capsys):
    """``Result.suggest_samples`` is the module function; ``robust-imdp suggest`` re-reads a run
    from its cache and writes the same requests as CSV."""
    import csv

    from robust_imdp.cli import main
    from robust_imdp.io.files import write_data_file

    assert [r.cell for r in starved.suggest_samples(4)] == [r.cell for r in sg.suggest_samples(starved, 4)]
    p = starved.problem
    write_data_file(tmp_path / "d.csv", p.data.x, p.data.u, p.data.x_next, modes=p.mode_names)
    (tmp_path / "p.toml").write_text(PROBLEM_TOML)
    out = tmp_path / "out"
    assert main(["run", str(tmp_path / "p.toml"), "--out", str(out), "--no-figures", "--quiet", "--advice", "off"]) == 0
    assert main(["suggest", str(out), "--problem", str(tmp_path / "p.toml"), "--budget", "3"]) == 0
    err = capsys.readouterr()
    rows = list(csv.reader(open(out / "suggestions.csv")))
    assert len(rows) == 4 and "sample requests" in err.out and "did not hold" not in err.err
    assert main(["suggest", str(tmp_path), "--problem", str(tmp_path / "p.toml"), "--budget", "3"]) == 1
    assert "no result.json" in capsys.readouterr().err


PROBLEM_TOML = """[space]
lower = [0.0, 0.0]
upper = [3.0, 3.0]
cell_size = [0.5, 0.5]
[[regions.goal]]
lower = [2.0, 2.0]
upper = [3.0, 3.0]
[spec]
formula = "F goal"
threshold = 0.9
[data]
path = "d.csv"
[modes.east]
A = [[1.0, 0.0], [0.0, 1.0]]
b = [0.4, 0.0]
[modes.north]
A = [[1.0, 0.0], [0.0, 1.0]]
b = [0.0, 0.4]
[noise]
kind = "truncated_gaussian"
sigma = [0.005, 0.005]
bound = [0.01, 0.01]
[learning]
rkhs_bound = 0.3
lengthscale = 1.0
misspecification = 0.001
"""


def test_site_subset_keeps_the_full_gain_algebra(starved, monkeypatch):
    # With every candidate a site the block algorithm is the full-matrix one: the same requests as with a
    # site limit above the candidates; with fewer sites every request is one of the kept sites and the
    # block's rank-one updates equal the posterior recomputed with the requested points (eq. S1).
    all_sites = sg.suggest_samples(starved, 5)
    monkeypatch.setattr(sg, "MAX_SITES", 10 ** 6)
    assert [(r.cell, r.mode) for r in sg.suggest_samples(starved, 5)] == [(r.cell, r.mode) for r in all_sites]
    cells, weights, _ = sg._candidates(starved)
    monkeypatch.setattr(sg, "MAX_SITES", max(2, cells.size // 4))
    few = sg.suggest_samples(starved, 5)
    assert len(few) == 5 and len({(r.cell, r.mode) for r in few}) == 5
    rng = np.random.default_rng(3)
    data, cand = rng.uniform(0, 2, (15, 2)), rng.uniform(0, 2, (12, 2))
    inv_l2, lam, sites = np.array([1.0, 4.0]), 1e-3, np.array([1, 5, 8])
    S, p = sg._posterior_block(cand, data, inv_l2, lam, sites)
    full = sg._posterior_cov(cand, data, inv_l2, lam)
    assert np.max(np.abs(S - full[:, sites])) < 1e-12 and np.max(np.abs(p - np.diag(full))) < 1e-12
    c = 1  # site 5
    S1 = S - np.outer(S[:, c], S[5, :]) / (S[5, c] + lam)  # row 5: Sigma(site 5, sites)
    again = sg._posterior_cov(cand, np.vstack([data, cand[5:6]]), inv_l2, lam)
    assert np.max(np.abs(S1 - again[:, sites])) < 1e-9  # float64 Cholesky, condition ~1e5: as above


def test_the_power_function_uses_the_learned_components_lengthscales(starved):
    # component 2 known (B = 0) with a short lengthscale: the data's influence is that of component 1's
    # lengthscales (5, 0.5); a mode whose components are all known keeps the shortest over them
    p = starved.problem.replace(rkhs_bound=[0.3, 0.0], gp_options={"lengthscale": [[5.0, 0.5], [0.1, 0.1]]})
    B, inv_l2, _ = sg._assumption(p)
    np.testing.assert_array_equal(B, [0.3, 0.3])
    np.testing.assert_allclose(inv_l2, 1.0 / np.array([[5.0, 0.5], [5.0, 0.5]]) ** 2)
    p0 = starved.problem.replace(rkhs_bound=0.0, gp_options={"lengthscale": [[5.0, 0.5], [0.1, 0.2]]})
    np.testing.assert_allclose(sg._assumption(p0)[1], 1.0 / np.array([[0.1, 0.2], [0.1, 0.2]]) ** 2)


def test_beyond_max_candidates_the_frontier_of_q_yes_is_kept(starved, monkeypatch):
    # every kept undecided cell's strategy row puts upper probability on a Q_yes cell (recomputed here from
    # the abstraction's rows); among the frontier, the kept ones are at least as close to the threshold
    cells, _, _ = sg._candidates(starved)
    monkeypatch.setattr(sg, "MAX_CANDIDATES", max(1, cells.size // 3))
    kept, _, _ = sg._candidates(starved)
    c = np.asarray(starved.class_names)
    imdp, n = starved.abstraction.imdp, starved.partition.n_cells
    strategy = np.asarray(starved.synthesis.strategy)
    chosen = strategy[np.arange(n), np.asarray(starved.synthesis.initial_dfa_state)]

    def yes_mass(q):
        row = int(imdp.state_ptr[q]) + int(chosen[q])
        lo, hi = int(imdp.row_ptr[row]), int(imdp.row_ptr[row + 1])
        return sum(float(p) for t, p in zip(imdp.col[lo:hi], imdp.upper[lo:hi]) if t < n and c[t] == "yes")

    und = [q for q in kept if c[q] == "maybe"]
    assert 0 < kept.size <= sg.MAX_CANDIDATES and und
    assert all(yes_mass(q) > 0 for q in und)
    dropped = [q for q in np.setdiff1d(cells, kept) if c[q] == "maybe" and yes_mass(q) > 0]
    if dropped:
        assert min(yes_mass(q) for q in und) >= max(yes_mass(q) for q in dropped) - 1e-12


def _targets_of(result, keep_level: float, n_targets: int = 4):
    """Targets on ``n_targets`` undecided cells (evenly spread), each for its strategy's mode, keeping
    ``keep_level`` of its RKHS term."""
    maybe = np.flatnonzero(np.asarray(result.class_names) == "maybe")
    cells = maybe[np.linspace(0, maybe.size - 1, n_targets).astype(int)]
    modes = np.asarray(result.strategy)[cells, 0] if np.asarray(result.strategy).ndim == 2 else \
        np.asarray(result.strategy)[cells]
    M, N = len(result.problem.mode_names), result.partition.n_cells
    w, keep = np.zeros((M, N)), np.zeros((M, N))
    w[modes, cells] = 1.0
    keep[modes, cells] = keep_level
    return sg.Targets(w, keep, {int(q): "test" for q in cells}), cells, modes


def test_targeted_requests_stop_when_every_target_reached_its_level(starved):
    """Eq. S3: a target's gain is the share of its needed drop ``(1 - keep) sqrt(P0)``, capped at the need. With
    an easy level (keep 0.9) the greedy stops before n; recomputed from scratch with the requests as data
    (_posterior_cov, no rank-one updates), every target's sqrt(P) is at or below keep sqrt(P0), the requests are
    for target cells and modes, and the gains add up to at most the targets' total weight."""
    targets, cells, modes = _targets_of(starved, 0.9)
    reqs = sg.suggest_samples(starved, 50, targets=targets)
    assert 0 < len(reqs) < 50
    assert {r.cell for r in reqs} <= set(cells.tolist())
    names = list(starved.problem.mode_names)
    assert {names.index(r.mode) for r in reqs} <= set(modes.tolist())
    assert sum(r.gain for r in reqs) <= targets.weights.sum() * (1 + 1e-9)  # each target's share is capped at 1
    part = starved.partition
    B, inv_l2, floor = sg._assumption(starved.problem)
    for q, u in zip(cells, modes):
        c = 0.5 * (part.cells_lower[q:q + 1] + part.cells_upper[q:q + 1])
        lam = (floor[u] / B[u]) ** 2
        x0 = starved.problem.data.by_mode(u)[0]
        x1 = np.vstack([x0] + [r.x[None] for r in reqs if r.mode == names[u]])
        p0 = sg._posterior_cov(c, x0, inv_l2[u], lam)[0, 0]
        p1 = sg._posterior_cov(c, x1, inv_l2[u], lam)[0, 0]
        # the greedy stops when no target gains: each is at its level (1e-9: the rank-one updates' float error,
        # as in the eq. S1 test)
        assert np.sqrt(max(p1, 0)) <= 0.9 * np.sqrt(p0) + 1e-9


def test_a_hard_target_draws_more_requests_than_an_easy_one(starved):
    """Two targets far apart, one keeping 0.9 of its term (easy), one keeping 0 (its whole term must go): after
    the easy one is met, every further request serves the hard one (its mode, near it)."""
    maybe = np.flatnonzero(np.asarray(starved.class_names) == "maybe")
    part = starved.partition
    centres = 0.5 * (part.cells_lower + part.cells_upper)
    a = maybe[0]
    b = maybe[np.argmax(np.linalg.norm(centres[maybe] - centres[a], axis=1))]
    M, N = len(starved.problem.mode_names), part.n_cells
    w, keep = np.zeros((M, N)), np.zeros((M, N))
    w[0, [a, b]] = 1.0
    keep[0, a], keep[0, b] = 0.9, 0.0
    reqs = sg.suggest_samples(starved, 8, targets=sg.Targets(w, keep, {}))
    assert len(reqs) == 8
    near_b = [np.linalg.norm(r.x - centres[b]) < np.linalg.norm(r.x - centres[a]) for r in reqs]
    assert sum(near_b) >= 6 and near_b[-1]


def test_data_points_replace_the_problem_s_data(starved):
    """``data_points`` is the data the power function sees: the problem's own points give the same requests,
    a dense cover of X leaves almost nothing to gain."""
    names = starved.problem.mode_names
    own = [starved.problem.data.by_mode(u)[0] for u in range(len(names))]
    a, b = sg.suggest_samples(starved, 5), sg.suggest_samples(starved, 5, data_points=own)
    assert [(r.cell, r.mode) for r in a] == [(r.cell, r.mode) for r in b]
    t = np.linspace(0, 3, 31)
    dense = np.stack(np.meshgrid(t, t), -1).reshape(-1, 2)
    c = sg.suggest_samples(starved, 5, data_points=[dense] * len(names))
    assert sum(r.gain for r in c) < 0.05 * sum(r.gain for r in a)
