"""The tight route end to end (issue 9): refusal of a refuted assumption, the stated confidence,
unbounded noise, the diagnostics in result.json, and Monte-Carlo containment on a problem whose
data come from a function of exactly known RKHS norm."""

from __future__ import annotations

import json

import numpy as np
import pytest

from robust_imdp.casestudies.systems import get_case_study, problem_toml
from robust_imdp.cli import main
from robust_imdp.errors import AssumptionError
from robust_imdp.io.files import write_data_file
from robust_imdp.models.noise import GaussianNoise, UniformNoise
from robust_imdp.pipeline.problem import Problem
from robust_imdp.pipeline.run import synthesize_from_data
from robust_imdp.models.system import AffineMap, Dataset
from robust_imdp.validate import validate


def _coarse_case(tmp_path, *, rkhs_bound=None, n=40, edit=None):
    case = get_case_study("three_mode_linear")
    x, u, xn = case.system.sample_dataset(n, case.lower, case.upper, rng=1)
    if edit is not None:
        edit(x, u, xn)
    write_data_file(tmp_path / "d.csv", x, u, xn, modes=case.system.mode_names)
    text = problem_toml(case, "G !obs & F des", "d.csv", rkhs_bound=rkhs_bound).replace(
        "cell_size = [0.125, 0.125]", "cell_size = [0.5, 0.5]")
    (tmp_path / "p.toml").write_text(text)
    return tmp_path / "p.toml"


def _run(argv, capsys):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def test_refuted_rkhs_bound_exits_1_before_any_result(tmp_path, capsys):
    # B = 2: every sample alone is possible (|residual| <= 1.29 + noise), but jointly the data
    # need an RKHS norm of about 3 (the SOCP certificate of the assumption check).
    problem = _coarse_case(tmp_path, rkhs_bound=2.0)
    out = tmp_path / "out"
    out.mkdir()
    (out / "result.json").write_text("{}")  # an old result stays as it was (issue 33: a failed re-run keeps it)
    code, stdout, err = _run(["run", str(problem), "--out", str(out), "--quiet"], capsys)
    assert code == 1
    assert "[learning].rkhs_bound = 2 is refuted by the data" in err and "component" in err
    assert "needs an RKHS norm of at least" in err and "Traceback" not in err
    assert err.count("\n") == 1  # one message
    assert (out / "result.json").read_text() == "{}" and sorted(p.name for p in out.iterdir()) == ["cache",
                                                                                                    "result.json"]


def test_impossible_sample_is_named(tmp_path, capsys):
    def spike(x, u, xn):
        xn[5, 1] = 99.0

    problem = _coarse_case(tmp_path, edit=spike)
    code, _, err = _run(["run", str(problem), "--out", str(tmp_path / "out"), "--quiet"], capsys)
    assert code == 1
    # checked when the data are read: sample 5 is on line 7 of the CSV (1-based, after the header)
    assert "line 7" in err and "component 2 is impossible under the assumption" in err


@pytest.mark.slow
def test_result_json_carries_the_diagnostics(tmp_path, capsys):
    problem = _coarse_case(tmp_path)
    out = tmp_path / "out"
    code, stdout, err = _run(["run", str(problem), "--out", str(out), "--no-figures"], capsys)
    assert code == 0, err
    assert "error radius eps" in stdout and "holds with probability 1" in stdout
    doc = json.loads((out / "result.json").read_text())
    diag = doc["diagnostics"]
    assert diag["confidence"] == 1.0 and diag["error_bound"] == "optimal"
    assert {r["mode"] for r in diag["eps"]} == {"1", "2", "3"}
    assert all(r["max"] >= r["median"] > 0 for r in diag["eps"])
    assert diag["cell_half_width"] == [0.25, 0.25]
    assert diag["assumption"]["rkhs_bound"] == 6.0 and diag["assumption"]["misspecification"] == 0.001
    assert all(0 < r["minimum"] < 6.0 for r in diag["assumption"]["min_norm"])
    assert diag["successors_per_row"] >= 1


# --------------------------------------------------------------------------- known-norm system
class KernelSystem:
    """x+ = x + h_u(x) + v with h_u a finite SE-kernel expansion of known norm (the assumption holds
    exactly: tau = 0), for validate()."""

    def __init__(self, rng, noise, norm=0.4, ls=1.5, n_modes=2):
        self.mode_names = tuple(str(i) for i in range(n_modes))
        self.noise = noise
        self.ls = ls
        self.Z = rng.uniform(-2, 2, (n_modes, 2, 8, 2))
        self.c = rng.standard_normal((n_modes, 2, 8))
        for u in range(n_modes):
            for i in range(2):
                Z = self.Z[u, i]
                K = np.exp(-0.5 * np.sum((Z[:, None] - Z[None]) ** 2, -1) / ls ** 2)
                self.c[u, i] *= norm * (1 - 1e-9) / np.sqrt(self.c[u, i] @ K @ self.c[u, i])
        self.drift = np.array([[0.35, 0.0], [-0.35, 0.0], [0.0, 0.35]])[:n_modes]

    def g(self, x, modes):
        out = np.empty_like(x)
        for i in range(2):
            Z, c = self.Z[modes, i], self.c[modes, i]  # (k, 8, 2), (k, 8)
            k = np.exp(-0.5 * np.sum((x[:, None, :] - Z) ** 2, -1) / self.ls ** 2)
            out[:, i] = np.sum(k * c, axis=1)
        return out

    def step(self, x, modes, rng):
        x = np.asarray(x, float)
        modes = np.broadcast_to(np.asarray(modes, np.int64), (x.shape[0],))
        return x + self.drift[modes] + self.g(x, modes) + self.noise.sample(x.shape[0], rng)


def _kernel_problem(noise, rng, *, iid=False, m=150):
    sysm = KernelSystem(rng, noise)
    u = np.repeat(np.arange(2), m)
    x = rng.uniform(-2, 2, (u.size, 2))
    xn = sysm.step(x, u, rng)
    problem = Problem(
        space_lower=np.array([-2.0, -2.0]), space_upper=np.array([2.0, 2.0]), cell_size=np.array([0.5, 0.5]),
        regions={"goal": [((0.5, -0.5), (1.5, 0.5))]}, formula="F goal", threshold=0.9, horizon=None,
        data=Dataset(x, u, xn, modes=sysm.mode_names), mode_names=sysm.mode_names,
        maps=tuple(AffineMap(np.eye(2), sysm.drift[k]) for k in range(2)), noise=noise, rkhs_bound=0.5,
        gp_options={"lengthscale": 1.5}, iid_noise=iid)
    return problem, sysm


@pytest.mark.slow
def test_end_to_end_containment_with_informative_brackets():
    # The three-mode linear system (its g is certified to satisfy the shipped assumption, see
    # test_assumption_certificate.py) with wider truncated noise (sigma 0.05, bound 0.1) on a 0.25
    # grid: 26 of 256 cells get p_low strictly inside (0.02, 0.98). Every bracket must contain the
    # Monte-Carlo frequency (99.9 % Wilson intervals, 256 cells: a correct result is flagged with
    # probability <= 256 x 1e-3 = 26 % per seed -- the seed is fixed, and the flagged count must be 0).
    from robust_imdp.casestudies.systems import TrueSystem
    from robust_imdp.io.files import result_to_dict
    from robust_imdp.validate import ResultFile

    case = get_case_study("three_mode_linear")
    s0 = case.system
    sysm = TrueSystem(s0.mode_names, s0.known_A, s0.known_b, s0.g, np.array([0.05, 0.05]), np.array([0.1, 0.1]),
                      s0.g_terms)
    x, u, xn = sysm.sample_dataset(100, case.lower, case.upper, 3)
    problem = Problem(
        space_lower=np.array(case.lower), space_upper=np.array(case.upper), cell_size=np.array([0.25, 0.25]),
        regions=case.regions, formula="G !obs & F des", threshold=0.9, horizon=None,
        data=Dataset(x, u, xn, modes=sysm.mode_names), mode_names=sysm.mode_names,
        maps=tuple(AffineMap.zero(2) for _ in range(3)), noise=sysm.noise_model(), rkhs_bound=case.rkhs_bound,
        gp_options=dict(case.gp), misspecification=case.misspecification)
    res = synthesize_from_data(problem, progress=False)
    p_low = res.synthesis.p_low
    assert np.sum((p_low > 0.02) & (p_low < 0.98)) >= 20
    rep = validate(ResultFile.from_dict(result_to_dict(res)), sysm, n_per_cell=400, max_steps=80, rng=4,
                   confidence=0.999)
    assert rep.outside.size == 0, rep.summary()


def test_unbounded_noise_states_its_confidence():
    # Gaussian noise: the deterministic bound runs on the event max |noise| <= sigma z (union bound over
    # all samples) and the result says with which confidence; with iid_noise the budget is split.
    rng = np.random.default_rng(22)
    problem, _ = _kernel_problem(GaussianNoise([0.02, 0.02]), rng, m=60)
    problem = problem.replace(cell_size=np.array([1.0, 1.0]))
    res = synthesize_from_data(problem, progress=False)
    assert res.diagnostics["confidence"] == pytest.approx(0.99)
    assert "probability >= 0.99 over the data" in res.diagnostics["statement"]
    iid = synthesize_from_data(problem.replace(iid_noise=True), progress=False)
    assert iid.diagnostics["confidence"] == pytest.approx(0.99)
    assert "sub-Gaussian bound of independent noise" in iid.diagnostics["statement"]


def test_refusal_in_the_library_names_the_mode():
    rng = np.random.default_rng(23)
    problem, _ = _kernel_problem(UniformNoise([0.01, 0.01]), rng, m=60)
    with pytest.raises(AssumptionError, match=r"rkhs_bound = 0\.01 is refuted.*mode '[01]'"):
        synthesize_from_data(problem.replace(rkhs_bound=0.01), progress=False)
