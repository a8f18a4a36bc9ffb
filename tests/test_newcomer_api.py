"""What a new user met through the Python API and the command line: clear errors at construction, a
controller that answers one state with one cell, a batch form of ``act``, messages that agree with the
files they describe, figures in every dimension."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from robust_imdp.cli import main  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from test_plotting import doc_nd  # noqa: E402

# a true system for doc_nd's modes "1", "2", "3" in any dimension: contract towards the centre
CONTRACT = """
import numpy as np

class Contract:
    mode_names = ("1", "2", "3")

    def step(self, x, modes, rng):
        return 0.8 * x + rng.uniform(-0.05, 0.05, x.shape)
"""


@pytest.mark.parametrize("d", [1, 3])
def test_simulate_draws_trajectories_in_every_dimension(tmp_path, capsys, d):
    # 3-D results got no trajectories.png and no word about it (only 2-D was drawn)
    (tmp_path / "result.json").write_text(json.dumps(doc_nd(d, h=1.0)))
    (tmp_path / "sys.py").write_text(CONTRACT)
    code = main(["simulate", str(tmp_path), "--true-system", f"{tmp_path / 'sys.py'}:Contract", "--n-per-cell", "2",
                 "--max-steps", "10", "--paths", "4"])
    assert code in (0, 1), capsys.readouterr().err  # doc_nd's bounds are synthetic: the check may flag cells
    png = tmp_path / "trajectories.png"
    assert png.exists() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000


def test_trajectory_panels_project_every_pair_of_the_first_coordinates():
    import matplotlib.pyplot as plt

    from robust_imdp import plotting
    from robust_imdp.validate import Trajectories

    paths = [np.array([[0.5, 0.5, 0.5], [0.1, 0.2, 0.3]]), np.array([[-1.5, 1.0, 0.0]])]
    tr = Trajectories(paths=paths, outcome=np.array([1, 2]), steps=np.array([1, 0]))
    fig = plotting.plot_trajectory_panels(doc_nd(3, h=1.0), tr)
    axes = [ax for ax in fig.axes if ax.get_visible()]
    assert [(ax.get_xlabel(), ax.get_ylabel()) for ax in axes] == [("$x_1$", "$x_2$"), ("$x_1$", "$x_3$"),
                                                                  ("$x_2$", "$x_3$")]
    # the first panel's path segment is the (x_1, x_2) projection of the first path
    segs = [c for c in axes[0].collections if type(c).__name__ == "LineCollection"][0].get_segments()
    np.testing.assert_array_equal(segs[0], paths[0][:, [0, 1]])
    with pytest.raises(ValueError, match="pairs must be pairs"):
        plotting.plot_trajectory_panels(doc_nd(3, h=1.0), tr, pairs=[(0, 3)])
    plt.close("all")


def test_suggest_prints_the_radius_change_its_csv_holds(tmp_path, capsys):
    # it printed "radius -0.00161" while the CSV said radius_change 0.00161476
    import csv

    from problem_texts import write_one_d

    write_one_d(tmp_path)
    assert main(["run", str(tmp_path / "p.toml"), "--out", str(tmp_path / "k"), "--quiet", "--no-figures",
                 "--advice", "off"]) == 0
    capsys.readouterr()
    assert main(["suggest", str(tmp_path / "k"), "--problem", str(tmp_path / "p.toml"), "--budget", "3"]) == 0
    out = capsys.readouterr().out
    printed = [float(line.rsplit("radius_change ", 1)[1]) for line in out.splitlines() if "radius_change " in line]
    with open(tmp_path / "k" / "suggestions.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert printed and printed == [float(r["radius_change"]) for r in rows][: len(printed)]
    assert all(v > 0 for v in printed)  # a decrease of the error radius, stated as a positive change


# --------------------------------------------------------------------------- Problem.from_arrays checks at construction
def _robot_kwargs(**changes):
    from robust_imdp import TruncatedGaussianNoise

    rng = np.random.default_rng(0)
    x = rng.uniform(0, 4, (60, 2))
    u = np.where(np.arange(60) < 30, "east", "north")
    x_next = x + np.where(u[:, None] == "east", [0.3, 0.0], [0.0, 0.3])
    kw = dict(lower=[0, 0], upper=[4, 4], cell_size=0.5,
              regions={"goal": ([3, 3], [4, 4]), "obstacle": ([1.5, 1], [2.5, 3])},
              formula="G !obstacle & F goal", threshold=0.9,
              modes={"east": (np.eye(2), [0.3, 0]), "north": (np.eye(2), [0, 0.3])},
              noise=TruncatedGaussianNoise([0.01, 0.01], [0.02, 0.02]), rkhs_bound=0.2, lengthscale=1.0)
    kw.update(changes)
    return (x, u, x_next), kw


@pytest.mark.parametrize("changes,error,match", [
    # a raw AttributeError at synthesis before
    ({"noise": "gaussian"}, "InvalidInputError",
     r"noise must be a noise model: TruncatedGaussianNoise\(sigma, bound\), GaussianNoise\(sigma\) or "
     r"UniformNoise\(bound\).*got str 'gaussian'"),
    ({"noise": "UNIFORM3"}, "InvalidInputError", r"noise must be a noise model"),
    ({"cell_size": -0.5}, "InvalidInputError", r"cell_size must be a number > 0 or 2 numbers > 0.*got -0\.5"),
    ({"cell_size": [0.5, float("nan")]}, "InvalidInputError", r"cell_size must be"),
    ({"regions": {"goal": ([3, 3], [5, 4])}, "formula": "F goal"}, "InvalidInputError",
     r"regions\['goal'\] = \[\[3\.0, 3\.0\], \[5\.0, 4\.0\]\] lies outside X .* in dimension 1"),
    ({"regions": {"goal": ([3, 3], [3, 4])}, "formula": "F goal"}, "InvalidInputError",
     r"regions\['goal'\] needs finite lower < upper"),
    ({"formula": "F (goal"}, "FormulaSyntaxError", r"cannot parse formula at position 7"),
    ({"formula": "F gaol"}, "UnknownAtomError", r"formula 'F gaol' names regions \['gaol'\] that are not defined"),
])
def test_from_arrays_refuses_bad_input_at_construction(changes, error, match):
    import robust_imdp.errors as errors
    from robust_imdp import Problem

    data, kw = _robot_kwargs(**changes)
    with pytest.raises(getattr(errors, error), match=match):
        Problem.from_arrays(*data, **kw)


def test_from_arrays_accepts_a_region_across_a_periodic_seam():
    from robust_imdp import Problem

    data, kw = _robot_kwargs(regions={"goal": ([3, 3.5], [4, 4.5]), "obstacle": ([1.5, 1], [2.5, 3])},
                             periodic=(False, True))
    assert Problem.from_arrays(*data, **kw).periodic == (False, True)
    data, kw = _robot_kwargs(regions={"goal": ([3, -0.5], [4, 4.5]), "obstacle": ([1.5, 1], [2.5, 3])},
                             periodic=(False, True))
    with pytest.raises(ValueError, match=r"5 wide in dimension 2, which is periodic with period 4"):
        Problem.from_arrays(*data, **kw)


# --------------------------------------------------------------------------- counts, locate, batches
def _tiny_result():
    from robust_imdp import Problem, synthesize_from_data

    data, kw = _robot_kwargs(cell_size=1.0)
    return synthesize_from_data(Problem.from_arrays(*data, **kw), progress=False, advice=False)


@pytest.fixture(scope="module")
def tiny():
    return _tiny_result()


def test_counts_is_a_property_like_n_cells_and_still_a_call(tiny):
    c = tiny.counts
    assert isinstance(c, dict) and set(c) == {"yes", "no", "maybe"}
    assert sum(c.values()) == tiny.n_cells
    assert c == {k: int(np.sum(tiny.classes == k)) for k in ("yes", "no", "maybe")}
    assert tiny.counts() == c  # the method form of earlier versions keeps working


def test_locate_returns_an_int_for_one_state_and_an_array_for_a_batch(tiny):
    ctrl = tiny.controller()
    one = ctrl.locate(np.array([0.5, 0.5]))
    assert isinstance(one, int) and one == int(tiny.partition.locate([[0.5, 0.5]])[0])
    assert ctrl.locate([9.0, 9.0]) == -1  # outside X: -1, an int
    batch = ctrl.locate(np.array([[0.5, 0.5], [3.5, 3.5], [9.0, 9.0]]))
    assert isinstance(batch, np.ndarray) and batch.shape == (3,)
    np.testing.assert_array_equal(batch, tiny.partition.locate([[0.5, 0.5], [3.5, 3.5], [9.0, 9.0]]))
    assert ctrl.locate(np.array([[0.5, 0.5]])).shape == (1,)  # a batch of one stays a batch


def _step(x, modes):
    # east / north by 0.35, and names or indices alike (index 0 = east)
    east = np.array([m in ("east", 0) for m in modes])
    return x + np.where(east[:, None], [0.35, 0.0], [0.0, 0.35])


def test_batch_runs_make_the_same_decisions_as_single_runs(tiny):
    rng = np.random.default_rng(3)
    x0 = rng.uniform(0, 4, (40, 2))
    for horizon in (None, 5):
        res = tiny if horizon is None else __import__("robust_imdp").resynthesize(tiny, horizon=horizon,
                                                                                  progress=False)
        single = []
        for x in x0:  # the reference: one run at a time with act
            c = res.controller()
            c.reset(x)
            modes, y = [], x.copy()
            while (m := c.act(y)) is not None:
                modes.append(m)
                y = _step(y[None], [m])[0]
            single.append((modes, c.status))
        runs = res.controller().start_batch(x0)
        got = [[] for _ in x0]
        x = x0.copy()
        for _ in range(100):
            m = runs.act(x)
            if all(v is None for v in m):
                break
            for i, v in enumerate(m):
                if v is not None:
                    got[i].append(v)
            x = _step(x, m)
        assert [(g, s) for g, s in zip(got, runs.status)] == single
    idx = tiny.controller().start_batch(x0[:3]).act_index(x0[:3])
    assert idx.dtype == np.int64 and idx.shape == (3,)


def test_batch_runs_check_their_input(tiny):
    from robust_imdp.errors import DimensionError, InvalidInputError, OutsideDomainError

    ctrl = tiny.controller()
    with pytest.raises(OutsideDomainError, match=r"row 1 = \[9\.0, 9\.0\] does not"):
        ctrl.start_batch([[0.5, 0.5], [9.0, 9.0]])
    runs = ctrl.start_batch([[0.5, 0.5], [3.5, 0.5]])
    with pytest.raises(DimensionError, match=r"x must have shape \(2, 2\)"):
        runs.act([[0.5, 0.5]])
    with pytest.raises(InvalidInputError, match="row 1 lies in cell"):
        runs.act([[0.5, 0.5], [0.5, 3.5]])  # the first act must be given the start states


# --------------------------------------------------------------------------- command line, docs
def test_example_help_lists_every_case_study(capsys):
    from robust_imdp.casestudies.systems import CASE_STUDIES
    from robust_imdp.cli import CASE_STUDY_NAMES

    assert CASE_STUDY_NAMES == tuple(CASE_STUDIES)
    with pytest.raises(SystemExit):
        main(["example", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert all(name in text for name in CASE_STUDIES), text


def test_preflight_estimate_says_the_load_it_was_measured_at(monkeypatch):
    # the time estimate is a pilot's speed at the load of the moment; the line said nothing of it
    import os

    from robust_imdp.pipeline.preflight import load_text

    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    monkeypatch.setattr(os, "getloadavg", lambda: (6.0, 5.0, 4.0))
    text = load_text(2)
    assert "load average 6.0 on 2 cores (busy" in text and "holds while the load stays" in text
    monkeypatch.setattr(os, "getloadavg", lambda: (1.0, 0.5, 0.5))
    assert "load average 1.0 on 2 cores:" in load_text(2)  # not busy: no more runnable threads than cores


def test_the_bound_stage_preflight_line_carries_the_load(tmp_path, capsys):
    from problem_texts import write_one_d

    write_one_d(tmp_path)
    assert main(["run", str(tmp_path / "p.toml"), "--out", str(tmp_path / "k"), "--no-figures", "--advice", "off"]) == 0
    line = [s for s in capsys.readouterr().err.splitlines() if "cell bounds; about" in s]
    assert len(line) == 1 and "at the speed measured now" in line[0] and "on one core" in line[0], line


def test_readme_first_paragraph_names_what_a_known_part_can_be():
    text = (Path(__file__).parents[1] / "README.md").read_text()
    first = " ".join(text.split("\n\n")[2].split())
    assert "at most an affine part" not in first
    assert "expressions" in first and "periodic" in first and "A x + b" in first
