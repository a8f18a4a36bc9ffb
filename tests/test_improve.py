"""The sampling loop (robust_imdp.improve) on a tiny 2-D robot with a known simulator.

Oracles: the true images of every cell on a dense grid of states (the boxes must contain them after
every round), the previous round's boxes (kept cells unchanged, re-bounded ones only tighter), the
data file read back (round column, complete after an interrupt), and hand-made bad simulators.
"""

import numpy as np
import pytest

from robust_imdp.errors import DimensionError, InvalidInputError, ProblemFileError
from robust_imdp.improve import DATA_FILE, improve

STEPS = {"east": [0.4, 0.0], "north": [0.0, 0.4]}


def g(x):
    return 0.05 * np.sin(x[:, ::-1])


class Robot:
    mode_names = ("east", "north")

    def step(self, x, modes, rng):
        s = np.array([STEPS[m] for m in self.mode_names])[modes]
        return x + s + g(x) + rng.uniform(-0.01, 0.01, x.shape)


def _problem(**kw):
    from robust_imdp import Problem, TruncatedGaussianNoise

    rng = np.random.default_rng(3)
    xs, us, xn = [], [], []
    for i, name in enumerate(STEPS):
        x = rng.uniform(0, 3, (12, 2))
        xs.append(x)
        us += [name] * 12
        xn.append(Robot().step(x, np.full(12, i), rng))
    return Problem.from_arrays(
        np.vstack(xs), np.array(us), np.vstack(xn), lower=[0, 0], upper=[3, 3], cell_size=0.5,
        regions={"goal": ([2, 2], [3, 3])}, formula="F goal", threshold=0.9,
        modes={k: (np.eye(2), v) for k, v in STEPS.items()},
        noise=TruncatedGaussianNoise([0.005, 0.005], [0.01, 0.01]), rkhs_bound=0.3, lengthscale=1.0,
        misspecification=0.001, **kw)


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    out = tmp_path_factory.mktemp("improve")
    return improve(_problem(), Robot(), 12, rounds=3, out=out, progress=False, allow_outside=True,
                   keep_history=True), out


def test_rounds_are_recorded_in_the_result_and_the_data_file(loop):
    import json

    from robust_imdp.io.data_file import read_data_file, read_rounds

    res, out = loop
    assert [r.round for r in res.rounds] == [0, 1, 2, 3] and [r.added for r in res.rounds] == [0, 4, 4, 4]
    doc = json.loads((out / "result.json").read_text())
    assert [r["round"] for r in doc["diagnostics"]["improve"]["rounds"]] == [0, 1, 2, 3]
    assert "chosen from earlier data" in doc["diagnostics"]["statement"]
    assert (out / DATA_FILE).read_text().splitlines()[0].endswith(",round")
    assert read_rounds(out / DATA_FILE).tolist() == [0] * 24 + [1] * 4 + [2] * 4 + [3] * 4
    x, u, xn, _ = read_data_file(out / DATA_FILE, ["east", "north"], 2)  # the pipeline reads it (round ignored)
    assert x.shape == (36, 2)


def test_every_round_s_boxes_contain_the_true_images_and_kept_boxes_are_unchanged(loop):
    res, _ = loop
    part = res.result.partition
    t = np.linspace(0, 1, 9)
    grid = np.stack(np.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
    shifts = np.array([STEPS[m] for m in Robot.mode_names])
    for k, (lo, hi) in enumerate(res.history):
        for q in range(part.n_cells):
            pts = part.cells_lower[q] + grid * (part.cells_upper[q] - part.cells_lower[q])
            for u in range(2):
                img = pts + shifts[u] + g(pts)  # the noise-free image f_u + g_u
                assert np.all(img >= lo[u, q] - 1e-12) and np.all(img <= hi[u, q] + 1e-12), (k, q, u)
        if k:
            plo, phi = res.history[k - 1]
            assert np.all(lo >= plo) and np.all(hi <= phi)  # re-bounded boxes only tighten
            same = np.all((lo == plo) & (hi == phi), axis=2)
            assert same.sum() == same.size - res.rounds[k].rebound  # every other box kept bit for bit


def test_the_last_result_passes_monte_carlo_validation(loop):
    from robust_imdp.validate import validate

    rep = validate(loop[0].result, Robot(), n_per_cell=30, rng=11)
    assert rep.passed


def test_interrupt_in_the_simulator_keeps_the_data_file_complete_and_resumes(tmp_path):
    from robust_imdp.io.data_file import read_rounds

    class Stops(Robot):
        calls = 0

        def step(self, x, modes, rng):
            Stops.calls += 1
            if Stops.calls == 2:
                raise KeyboardInterrupt
            return super().step(x, modes, rng)

    with pytest.raises(KeyboardInterrupt):
        improve(_problem(), Stops(), 8, rounds=2, out=tmp_path, progress=False, allow_outside=True)
    assert read_rounds(tmp_path / DATA_FILE).tolist() == [0] * 24 + [1] * 4  # round 1 complete, round 2 not started
    assert not (tmp_path / (DATA_FILE + ".tmp")).exists()
    again = improve(_problem(), Robot(), 8, rounds=2, out=tmp_path, progress=False, allow_outside=True)
    assert [r.round for r in again.rounds] == [0, 1, 2]
    assert read_rounds(tmp_path / DATA_FILE).tolist() == [0] * 24 + [1] * 4 + [2] * 4


class _Bad(Robot):
    def __init__(self, what):
        self.what = what

    def step(self, x, modes, rng):
        y = super().step(x, modes, rng)
        if self.what == "raise":
            raise RuntimeError("sensor offline")
        if self.what == "nan":
            y[1, 0] = np.nan
        if self.what == "shape":
            return y[:, :1]
        if self.what == "outside":
            y[0] = [5.0, 5.0]
        return y


@pytest.mark.parametrize("what,err,text", [
    ("raise", InvalidInputError, r"improve round 1: the true system's step raised RuntimeError: sensor offline"),
    ("nan", InvalidInputError, r"improve round 1: the true system returned NaN or inf for 1 of 4 requests \(first: "
                               r"request 2 "),
    ("shape", DimensionError, r"improve round 1: .* \(4, 2\) float array, one row per request; got ndarray of shape "
                              r"\(4, 1\)"),
    ("outside", InvalidInputError, r"improve round 1: the true system returned states outside X .* request 1 "),
])
def test_bad_simulators_name_the_round_and_request_and_keep_the_previous_result(tmp_path, what, err, text):
    from robust_imdp.io.data_file import read_rounds

    with pytest.raises(err, match=text):
        improve(_problem(), _Bad(what), 4, rounds=1, out=tmp_path, progress=False)
    assert read_rounds(tmp_path / DATA_FILE).tolist() == [0] * 24  # nothing of the failed round written
    assert (tmp_path / "result.json").exists()  # round 0's result stays


def test_iid_route_is_refused_for_adaptive_data(tmp_path):
    with pytest.raises(InvalidInputError, match="iid_noise = true assumes the inputs were chosen independently"):
        improve(_problem(iid_noise=True), Robot(), 4, progress=False)
    from robust_imdp.io.data_file import refuse_adaptive_iid, write_data_file

    p = _problem()
    write_data_file(tmp_path / "d.csv", p.data.x, p.data.u, p.data.x_next, modes=p.mode_names,
                    rounds=np.r_[np.zeros(20, int), np.ones(4, int)])
    refuse_adaptive_iid(tmp_path / "d.csv", False)
    with pytest.raises(ProblemFileError, match="4 samples of rounds > 0: iid_noise = true assumes"):
        refuse_adaptive_iid(tmp_path / "d.csv", True)


def test_cli_improve_prints_rounds(tmp_path, capsys):
    from robust_imdp.cli import main
    from robust_imdp.io.files import write_data_file
    from test_suggest import PROBLEM_TOML

    p = _problem()
    write_data_file(tmp_path / "d.csv", p.data.x, p.data.u, p.data.x_next, modes=p.mode_names)
    (tmp_path / "p.toml").write_text(PROBLEM_TOML)
    (tmp_path / "robot.py").write_text("import numpy as np\n"
                                       "class Robot:\n    mode_names = ('east', 'north')\n"
                                       "    def step(self, x, modes, rng):\n"
                                       "        s = np.array([[0.4, 0.0], [0.0, 0.4]])[modes]\n"
                                       "        return x + s + 0.05 * np.sin(x[:, ::-1])\n"
                                       "class Pushed(Robot):\n"
                                       "    def step(self, x, modes, rng):\n"
                                       "        return super().step(x, modes, rng) + [0.5, 0.0]\n")
    args = ["improve", str(tmp_path / "p.toml"), "--budget", "4", "--rounds", "2", "--quiet", "--allow-outside"]
    assert main(args + ["--true-system", f"{tmp_path / 'robot.py'}:Robot", "--out", str(tmp_path / "o")]) == 0
    text = capsys.readouterr().out
    assert "round 2: +2 samples" in text and "Q_yes" in text and (tmp_path / "o" / "result.json").exists()
    # a push the model does not know (0.5 east, above B = 0.3 plus the noise anywhere the new samples are taken):
    # the new samples refute B, and the all-data check of the round says so
    assert main(args + ["--true-system", f"{tmp_path / 'robot.py'}:Pushed", "--out", str(tmp_path / "c")]) == 1
    assert "is refuted by the data" in capsys.readouterr().err


def test_a_re_bounded_box_is_exactly_the_intersection_of_the_kept_and_the_new_box():
    # Oracle: the new box of the same cells from the same data, bounded alone (previous box +-1e300); the loop's
    # box must be max / min of it and the kept box, bit for bit (both contain the image, so does their
    # intersection; anything smaller is unsound, anything larger wastes the kept box)
    from robust_imdp.abstraction.rows import CellBounds
    from robust_imdp.improve import _affected, _append, _rebound
    from robust_imdp.models.geometry import Box, Partition
    from robust_imdp.pipeline.bound_stage import _learn_and_bound
    from robust_imdp.pipeline.preflight import _region_objects
    from robust_imdp.pipeline.runtime import _Log, _Run

    p0 = _problem()
    part = Partition(Box(p0.space_lower, p0.space_upper), p0.cell_size, _region_objects(p0))
    log, run = _Log(False), _Run(workers=None)
    try:
        kept, _, _ = _learn_and_bound(p0, part, log, run, None)
        rng = np.random.default_rng(9)
        xs = rng.uniform(0, 3, (8, 2))
        us = np.arange(8) % 2
        data = _append(p0.data, xs, us, Robot().step(xs, us, rng))
        p1 = p0.replace(data=data)
        cells = _affected(p1, part, data, p0.data.u.shape[0])
        assert sum(c.size for c in cells) > 0
        new, n = _rebound(p1, part, kept, cells, log, run)
        inf = np.full_like(kept.image_lower, 1e300)  # CellBounds must be finite: 1e300 stands for R
        alone, _ = _rebound(p1, part, CellBounds(-inf, inf, None), cells, log, run)
    finally:
        run.close()
    tighter_new = 0
    for u, q in enumerate(cells):
        np.testing.assert_array_equal(new.image_lower[u, q], np.maximum(kept.image_lower[u, q], alone.image_lower[u, q]))
        np.testing.assert_array_equal(new.image_upper[u, q], np.minimum(kept.image_upper[u, q], alone.image_upper[u, q]))
        tighter_new += int(np.sum(alone.image_lower[u, q] > kept.image_lower[u, q]))
    assert tighter_new > 0  # the new data tighten some sides: the test sees the new box
    others = np.ones(kept.image_lower.shape[:2], bool)
    for u, q in enumerate(cells):
        others[u, q] = False
    np.testing.assert_array_equal(new.image_lower[others], kept.image_lower[others])  # not re-bounded: kept
    np.testing.assert_array_equal(new.image_upper[others], kept.image_upper[others])


def test_the_incremental_check_reports_a_lower_and_an_upper_bound_of_the_minimum_norm(loop):
    import json

    _, out = loop
    a = json.loads((out / "result.json").read_text())["diagnostics"]["assumption"]
    inc = a["incremental_check"]
    assert "lower bound" in inc["note"] and "upper bound" in inc["note"]
    assert [(r["mode"], r["component"]) for r in inc["components"]] == [(r["mode"], r["component"])
                                                                        for r in a["min_norm"]]
    assert {r["how"] for r in inc["components"]} <= {"witness kept", "witness refitted", "full check"}
    for r, m in zip(inc["components"], a["min_norm"]):
        if r["witness_norm_upper"] is not None:  # certified lower <= minimum norm <= witness's norm <= B
            assert m["minimum"] <= r["witness_norm_upper"] <= r["rkhs_bound"]
