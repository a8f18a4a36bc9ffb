"""Calibration (bounds/calibrate.py, `robust-imdp calibrate`): the statistics against independent references,
the suggestion on a function of known norm, the held-out evidence's two directions, the trend check, the
problem-file shapes of the suggestion, the command's files and its errors (docs/calibration.md)."""

import json
import tomllib

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy import stats

from robust_imdp.bounds import calibrate as cal
from robust_imdp.bounds.assumptions import check_modes, resolve
from robust_imdp.bounds.rkhs import unit_kernel
from robust_imdp.errors import DimensionError, InvalidInputError
from robust_imdp.models.noise import GaussianNoise, TruncatedGaussianNoise, UniformNoise

from problem_texts import write_one_d


# --------------------------------------------------------------------------- a function of known norm
def _expansion(seed=0, ell=1.0, norm=0.3, n_centres=8, lo=-3.0, hi=3.0):
    """``g = sum_j a_j k_l(., c_j)`` (1-D) scaled to RKHS norm ``norm`` at lengthscale ``ell``."""
    rng = np.random.default_rng(seed)
    c = rng.uniform(lo, hi, (n_centres, 1))
    a = rng.standard_normal(n_centres)
    a *= norm / np.sqrt(a @ unit_kernel(c, c, ell) @ a)
    return c, a


def _g(x, c, a, ell):
    return unit_kernel(x, c, ell) @ a


def _norm_at(c, a, ell, lp):
    """``||g||`` at lengthscale ``lp`` (1-D closed form, benchmarks/calibration.py's norm_at); inf for lp >= sqrt(2) ell."""
    if lp >= np.sqrt(2) * ell:
        return np.inf
    s2 = 2 * ell ** 2 - lp ** 2
    G = ell ** 2 / (lp * np.sqrt(s2)) * np.exp(-0.5 * (c - c.T) ** 2 / s2)
    return float(np.sqrt(a @ G @ a))


def test_norm_at_closed_form_is_the_limit_of_minimum_norm_interpolants():
    # The closed form the checks below use, against the min-norm interpolant at lp of g on 80 points of [-8, 8]
    # (norm sqrt(y K^-1 y), a lower bound that converges to ||g||_lp). 1e-8 relative: measured 2e-10 at
    # lp = 1.15 (the interpolant converges slowly near sqrt(2) l), 4e-16 below; a wrong power of l'/l or a wrong
    # width of the Gaussian in the formula is off by percents.
    c, a = _expansion()
    for lp in (0.6, 0.85, 1.15):
        x = np.linspace(-8, 8, 80)[:, None]
        K = unit_kernel(x, x, lp)
        y = _g(x, c, a, 1.0)
        alpha = np.linalg.lstsq(K, y, rcond=1e-14)[0]
        assert_allclose(np.sqrt(alpha @ K @ alpha), _norm_at(c, a, 1.0, lp), rtol=1e-8)
    assert _norm_at(c, a, 1.0, 1.0) == pytest.approx(0.3, rel=1e-12)  # the scaling
    assert _norm_at(c, a, 1.0, np.sqrt(2.0)) == np.inf  # a sum of bumps is not in H_l' for l' >= sqrt(2) l


@pytest.fixture(scope="module")
def known_norm():
    """80 samples of g (l = 1, norm 0.3) on [-3, 3] with uniform noise 0.02, and its calibration."""
    c, a = _expansion()
    rng = np.random.default_rng(1)
    X = rng.uniform(-3, 3, (80, 1))
    y = _g(X, c, a, 1.0) + rng.uniform(-0.02, 0.02, 80)
    r = cal.calibrate_component(X, y, noise_bound=0.02, noise_variance=0.02 ** 2 / 3, lower=[-3.0], upper=[3.0],
                                rng=0)
    return {"c": c, "a": a, "X": X, "y": y, "r": r}


def test_suggestion_on_a_function_of_known_norm(known_norm):
    r, c, a = known_norm["r"], known_norm["c"], known_norm["a"]
    # the optima of both curves near the generating lengthscale 1 (within a factor 2: the benchmark's target)
    assert 0.5 <= r.curves.cv <= 2.0
    assert 0.5 <= r.curves.ml <= 2.0
    # the rule: 0.75 x the smaller optimum, rounded down to 2 significant digits
    assert r.lengthscale <= cal.LENGTHSCALE_SHRINK * min(r.curves.ml, r.curves.cv) + 1e-12
    assert r.lengthscale >= cal.LENGTHSCALE_SHRINK * min(r.curves.ml, r.curves.cv) * 0.9
    # B is at least the certified minimum norm (B_MARGIN x it, rounded up) ...
    assert r.rkhs_bound >= cal.B_MARGIN * r.min_norm
    assert r.min_norm > 0
    # ... and at least the true norm at the suggested lengthscale (which is finite: lp < sqrt(2) l)
    truth = _norm_at(c, a, 1.0, r.lengthscale)
    assert np.isfinite(truth) and r.rkhs_bound >= truth
    # the minimum norm is a lower bound of the truth (certified)
    assert r.min_norm <= truth
    assert not r.trend.detected


def test_held_out_evidence_has_no_violation_at_the_true_norm_and_some_far_below(known_norm):
    X, y, c, a = known_norm["X"], known_norm["y"], known_norm["c"], known_norm["a"]
    folds = cal.kfold(80, 5, 0)
    # At the true lengthscale and B = the true norm, g is admissible: every held-out residual lies within the
    # certified pointwise bound +- the noise bound (a soundness property of the bound; no tolerance).
    ev = cal.held_out_evidence(X, y, 1.0, noise_bound=0.02, rkhs_bounds=[0.3 * (1 + 1e-9)], folds=folds,
                               stop=False)
    assert ev.violations.tolist() == [0] and ev.smallest == pytest.approx(0.3)
    # teeth: at a quarter of the data's minimum norm the training folds cannot explain the held-out points
    r = known_norm["r"]
    low = cal.held_out_evidence(X, y, 1.0, noise_bound=0.02, rkhs_bounds=[0.25 * r.min_norm], folds=folds)
    assert low.violations[0] > 0 and low.smallest is None and low.cp_upper is None


def test_held_out_smallest_b_never_exceeds_the_minimum_norm_on_the_same_points(known_norm):
    # 80 points <= MAX_POINTS and <= MIN_NORM_POINTS: the evidence and the minimum norm see the same data, and the
    # minimum-norm function fits every fold, so the grid's first value above the minimum norm has no violation
    r = known_norm["r"]
    assert r.n_used == 80 and r.min_norm_points == 80
    assert r.held_out.smallest is not None
    assert r.held_out.smallest <= cal.B_GRID_ABOVE * r.min_norm * (1 + 1e-12)
    k = r.held_out.evaluated
    assert np.all(r.held_out.violations[k:] == 0)  # not evaluated: 0 by monotonicity
    assert r.held_out.cp_upper == pytest.approx(cal.clopper_pearson_upper(0, 80, cal.CONFIDENCE))


def test_trend_is_flagged_and_its_tau_is_the_affine_part_s_largest_magnitude(known_norm):
    X, y = known_norm["X"], known_norm["y"]
    yt = y + 0.5 + 0.3 * X[:, 0]
    r = cal.calibrate_component(X, yt, noise_bound=0.02, noise_variance=0.02 ** 2 / 3, lower=[-3.0], upper=[3.0],
                                rng=0)
    t = r.trend
    assert t.detected and t.min_norm_detrended <= cal.TREND_FACTOR * t.min_norm
    # least squares is linear: the fit of y + trend is the fit of y (g's own affine part) plus the trend
    base = np.linalg.lstsq(np.hstack([X, np.ones((80, 1))]), y, rcond=None)[0]
    assert_allclose([t.slope[0], t.offset], base + [0.3, 0.5], rtol=1e-9)
    # tau = max over X = [-3, 3] of |slope x + offset| (at an end), against a dense grid
    xs = np.linspace(-3, 3, 10001)
    assert t.tau == pytest.approx(np.max(np.abs(t.slope[0] * xs + t.offset)), rel=1e-9)
    assert t.rkhs_bound_detrended >= cal.B_MARGIN * t.min_norm_detrended
    # the table to paste says what to do
    res = cal.Calibration((r,), ("a",), 1, np.array([[r.rkhs_bound]]), np.array([[[r.lengthscale]]]),
                          np.zeros((1, 1)), cal.EVIDENCE, {"folds": 5, "confidence": 0.95}, 0.0)
    assert "known part" in res.learning_table() and "misspecification" in res.learning_table()


def test_tau_of_a_2d_affine_part_against_the_box_vertices():
    rng = np.random.default_rng(3)
    X = rng.uniform([-1, 0], [2, 5], (60, 2))
    y = 0.7 - 0.4 * X[:, 0] + 0.2 * X[:, 1]
    t = cal.trend_check(X, y, 1.0, noise_bound=0.01, lower=[-1, 0], upper=[2, 5], min_norm=1.0)
    V = np.array([[-1, 0], [-1, 5], [2, 0], [2, 5]], float)
    assert t.tau == pytest.approx(np.max(np.abs(V @ t.slope + t.offset)), rel=1e-12)
    assert_allclose(t.slope, [-0.4, 0.2], atol=1e-9)  # exact affine data: least squares recovers it


# --------------------------------------------------------------------------- statistics
@pytest.mark.parametrize("k,n,conf", [(0, 1, 0.95), (0, 40, 0.95), (1, 40, 0.95), (3, 17, 0.9), (10, 300, 0.99),
                                      (49, 50, 0.95), (5, 1000, 0.5)])
def test_clopper_pearson_against_the_beta_quantile(k, n, conf):
    # the one-sided upper bound is the conf quantile of Beta(k + 1, n - k) (scipy.stats.beta); ours bisects the
    # binomial CDF to 1e-15 relative, scipy's quantile is accurate to ~1e-12: 1e-9 relative
    p = cal.clopper_pearson_upper(k, n, conf)
    assert p == pytest.approx(stats.beta.ppf(conf, k + 1, n - k), rel=1e-9)
    # and it is the boundary: P[Bin(n, p) <= k] = 1 - conf (1e-6 relative steps either side)
    assert stats.binom.cdf(k, n, p * (1 + 1e-6)) < 1 - conf < stats.binom.cdf(k, n, p * (1 - 1e-6))


def test_clopper_pearson_edges_and_bad_input():
    assert cal.clopper_pearson_upper(7, 7) == 1.0
    assert cal.clopper_pearson_upper(0, 300, 0.95) == pytest.approx(1 - 0.05 ** (1 / 300), rel=1e-12)
    for args, what in (((5, 4), "violations <= n"), ((0, 0), "n >= 1"), ((-1, 4), "violations <= n"),
                       ((1.5, 4), "violations must be an integer"), ((True, 4), "violations must be an integer")):
        with pytest.raises(InvalidInputError, match=what):
            cal.clopper_pearson_upper(*args)
    with pytest.raises(InvalidInputError, match="confidence"):
        cal.clopper_pearson_upper(0, 4, 1.0)


def test_noise_variance_against_closed_forms():
    # midpoint rule on 20,000 quantiles: the Gaussian's unbounded tail is the worst case (measured 2.3e-4
    # relative); bounded noise is far more accurate. Tolerances 1e-3 and 1e-6.
    assert_allclose(cal.noise_variance(GaussianNoise([0.3, 0.05])), [0.09, 0.0025], rtol=1e-3)
    assert_allclose(cal.noise_variance(UniformNoise([0.2])), [0.2 ** 2 / 3], rtol=1e-6)
    tn = TruncatedGaussianNoise([0.1, 0.1], [0.15, 0.05])
    ref = [stats.truncnorm(-b / 0.1, b / 0.1, scale=0.1).var() for b in (0.15, 0.05)]
    assert_allclose(cal.noise_variance(tn), ref, rtol=1e-6)
    with pytest.raises(InvalidInputError, match="noise model"):
        cal.noise_variance(0.1)


def test_kfold_partitions_the_samples():
    f = cal.kfold(23, 5, rng=4)
    assert sorted(np.concatenate(f).tolist()) == list(range(23))
    assert [len(v) for v in f] == [5, 5, 5, 4, 4]
    assert [v.tolist() for v in cal.kfold(23, 5, rng=4)] == [v.tolist() for v in f]  # seeded
    with pytest.raises(InvalidInputError, match="folds"):
        cal.kfold(23, 1)
    with pytest.raises(InvalidInputError, match="at least 10 samples"):
        cal.kfold(9, 5)


def test_bad_component_inputs_name_the_argument():
    X = np.linspace(0, 1, 20)[:, None]
    y = np.sin(X[:, 0])
    kw = dict(noise_bound=0.01, noise_variance=1e-4, lower=[0.0], upper=[1.0])
    with pytest.raises(DimensionError, match="y must have shape"):
        cal.calibrate_component(X, y[:5], **kw)
    with pytest.raises(InvalidInputError, match="finite"):
        cal.calibrate_component(X, np.where(X[:, 0] > 0.5, np.nan, y), **kw)
    with pytest.raises(InvalidInputError, match="noise_variance"):
        cal.calibrate_component(X, y, **dict(kw, noise_variance=0.0))
    with pytest.raises(DimensionError, match="lower and upper"):
        cal.calibrate_component(X, y, **dict(kw, lower=[1.0]))
    with pytest.raises(InvalidInputError, match="rkhs_bounds"):
        cal.held_out_evidence(X, y, 1.0, noise_bound=0.01, rkhs_bounds=[0.2, 0.1], folds=cal.kfold(20, 2))


# --------------------------------------------------------------------------- the suggestion's shapes
def _fake(B, L, tau=None, names=("east", "west")):
    """A Calibration with hand-set suggestions (no components): only the shapes are under test."""
    B = np.asarray(B, float)
    M, n = B.shape
    L = np.asarray(L, float)
    L = np.broadcast_to(L[..., None] if L.ndim == 2 else L, (M, n, n)).copy()
    tau = np.zeros((M, n)) if tau is None else np.asarray(tau, float)
    return cal.Calibration((), tuple(names), n, B, L, tau, cal.EVIDENCE, {"folds": 5, "confidence": 0.95}, 0.0)


@pytest.mark.parametrize("B,L", [
    ([[0.4, 0.4], [0.4, 0.4]], [[1.0, 1.0], [1.0, 1.0]]),          # one value for all
    ([[0.4, 0.3], [0.4, 0.3]], [[1.0, 0.5], [1.0, 0.5]]),          # per component, same in every mode
    ([[0.4, 0.3], [0.2, 0.2]], [[1.0, 0.5], [0.7, 0.7]]),          # per mode
    ([[0.4, 0.0], [0.2, 0.2]], [[[1.0, 2.0], [1.0, 1.0]], [[0.7, 0.7], [0.7, 0.7]]]),  # a known one, ARD kept
])
def test_suggested_values_resolve_to_the_same_settings(B, L):
    res = _fake(B, L)
    s = res.suggested
    st = resolve(s["rkhs_bound"], s["lengthscale"], s["misspecification"], res.mode_names, 2)
    assert_allclose(st.rkhs_bound, res.rkhs_bound, rtol=0)
    assert_allclose(st.lengthscale, res.lengthscale, rtol=0)
    assert_allclose(st.misspecification, res.misspecification, rtol=0)
    # the pasted TOML reads back as the same values
    table = tomllib.loads(res.learning_table())["learning"]
    assert table == {k: s[k] for k in ("rkhs_bound", "lengthscale", "misspecification")}


def test_collapsed_forms_and_quoted_mode_names():
    res = _fake([[0.4, 0.4], [0.4, 0.4]], [[1.0, 1.0], [1.0, 1.0]])
    assert res.suggested == {"rkhs_bound": 0.4, "lengthscale": 1.0, "misspecification": 0.0}
    res = _fake([[0.4, 0.3], [0.2, 0.2]], [[1.0, 1.0], [1.0, 1.0]], names=("go east", "b"))
    assert res.suggested["rkhs_bound"] == {"go east": [0.4, 0.3], "b": 0.2}
    assert '"go east" = [0.4, 0.3]' in res.learning_table()


def test_round_sig_moves_b_up_and_the_lengthscale_down():
    assert cal._round_sig(0.4137, 2, up=True) == 0.42
    assert cal._round_sig(0.42, 2, up=True) == 0.42
    assert cal._round_sig(0.6378, 2, up=False) == 0.63
    assert cal._round_sig(1234.0, 2, up=True) == 1300.0
    for v in np.random.default_rng(0).uniform(1e-4, 1e3, 200):
        assert cal._round_sig(v, 2, up=True) >= v >= cal._round_sig(v, 2, up=False)


# --------------------------------------------------------------------------- Problem.calibrate and the command
@pytest.fixture(scope="module")
def one_d(tmp_path_factory):
    folder = tmp_path_factory.mktemp("calibrate")
    return write_one_d(folder)


def test_problem_calibrate_suggests_a_b_the_assumption_check_accepts(one_d):
    from robust_imdp.bounds.rkhs import noise_bound_at_confidence
    from robust_imdp.io.files import load_problem

    problem = load_problem(one_d)
    res = problem.calibrate(workers=1)
    assert [c.mode for c in res.components] == [0] and res.mode_names == ("a",)
    s = res.suggested
    st = resolve(s["rkhs_bound"], s["lengthscale"], s["misspecification"], problem.mode_names, 1)
    x, xn = problem.data.by_mode(0)
    y = xn - problem.maps[0](x)
    nb, _ = noise_bound_at_confidence(problem.noise, x.shape[0], 0.01)
    checks = check_modes([(x, y)], st, np.asarray(nb).reshape(1, 1), mode_names=problem.mode_names)
    assert checks[0].minimum <= st.rkhs_bound[0, 0]  # the suggestion is not refuted by the data
    assert problem.rkhs_bound == 1.0  # the problem is not changed


def test_cli_writes_calibration_json_and_prints_the_table(one_d, tmp_path, capsys):
    from robust_imdp.cli import main

    before = one_d.read_bytes()
    out = tmp_path / "cal"
    assert main(["calibrate", str(one_d), "--out", str(out), "--quiet"]) == 0
    text = capsys.readouterr().out
    doc = json.loads((out / "calibration.json").read_text())
    assert doc["format"] == "robust_imdp.calibration/1" and "evidence, not proof" in doc["statement"]
    assert set(doc["suggested"]) == {"rkhs_bound", "lengthscale", "misspecification"}
    comp = doc["components"][0]
    assert comp["mode"] == "a" and comp["suggested"]["rkhs_bound"] >= comp["min_norm"]["value"]
    assert (out / "calibration.png").stat().st_size > 0
    # the table to paste is printed and reads as the JSON's suggestion
    assert "[learning]" in text and "evidence, not proof" in text and "B sugg" in text
    table = tomllib.loads(text[text.index("[learning]"):text.index("\nwrote ")])["learning"]
    assert table == doc["suggested"]
    assert one_d.read_bytes() == before  # never edits the user's file


def test_cli_failure_leaves_the_previous_calibration(one_d, tmp_path, monkeypatch, capsys):
    from robust_imdp import plotting
    from robust_imdp.cli import main

    out = tmp_path / "cal"
    out.mkdir()
    (out / "calibration.json").write_text("previous")

    def broken(*a, **k):
        raise OSError(28, "No space left on device", "calibration.png")

    monkeypatch.setattr(plotting, "save_calibration_figure", broken)
    assert main(["calibrate", str(one_d), "--out", str(out), "--quiet"]) == 1
    assert (out / "calibration.json").read_text() == "previous"  # the new JSON was staged, never swapped in
    assert sorted(p.name for p in out.iterdir()) == ["calibration.json"]  # no staging folder left behind
    assert "No space left" in capsys.readouterr().err


def test_cli_bad_inputs(one_d, tmp_path, capsys):
    from robust_imdp.cli import main

    with pytest.raises(SystemExit) as e:
        main(["calibrate", str(one_d), "--folds", "1"])
    assert e.value.code == 2 and "--folds" in capsys.readouterr().err
    # 30 samples cannot be cut into 20 folds of 2 and more: the mode is named, nothing is written
    out = tmp_path / "none"
    assert main(["calibrate", str(one_d), "--out", str(out), "--folds", "20", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "mode 'a' has 30 samples" in err and "40" in err
    assert not out.exists()
    assert main(["calibrate", str(tmp_path / "missing.toml"), "--out", str(out)]) == 1


def test_plot_calibration_draws_one_row_per_component(one_d, tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    from robust_imdp.io.files import load_problem
    from robust_imdp.plotting import plot_calibration, save_calibration_figure

    res = load_problem(one_d).calibrate(workers=1)
    fig = plot_calibration(res)
    # 3 panels per component plus the likelihood's twin axis
    assert len(fig.axes) == 4 * len(res.components)
    path = tmp_path / "c.json"
    path.write_text(json.dumps(res.to_dict()))
    assert save_calibration_figure(path, tmp_path / "c.png").stat().st_size > 0
    with pytest.raises(InvalidInputError, match="calibration"):
        plot_calibration(3)


def test_keep_lengthscale_calibrates_b_at_the_problem_s_lengthscale(one_d):
    from robust_imdp.bounds.rkhs_check import min_rkhs_norm
    from robust_imdp.io.files import load_problem

    problem = load_problem(one_d)
    problem = problem.replace(gp_options={**problem.gp_options, "lengthscale": 0.7})
    res = problem.calibrate(workers=1, keep_lengthscale=True)
    c = res.components[0]
    assert res.suggested["lengthscale"] == 0.7 and c.lengthscale_rule == "kept from the problem"
    # the minimum norm is the assumption check's at that lengthscale (same points, same allowance)
    x, xn = problem.data.by_mode(0)
    y = (xn - problem.maps[0](x))[:, 0]
    assert c.min_norm == min_rkhs_norm(x, y, 0.7, c.noise_bound, 0.0)["minimum"]
    assert c.rkhs_bound >= cal.B_MARGIN * c.min_norm
