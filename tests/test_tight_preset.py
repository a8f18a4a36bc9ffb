"""The ``tight`` preset (``Problem.tightened``, ``robust-imdp run --tight``, issue 20).

The preset only chooses settings (sub-box certificates, larger pools), whose bounds are tested on their own
(test_split_option.py, test_rkhs_local.py, the mutation table); here: the rule, that a problem's own values
win, that the preset reaches the bound stage (tighter than ``SPLIT_TOL`` and still containing the true
images, by dense sampling), the GP route's refusal, and the command line's flag.
"""

import json

import numpy as np
import pytest

from robust_imdp.bounds import rkhs
from robust_imdp.casestudies.systems import get_case_study
from robust_imdp.cli import main
from robust_imdp.errors import InvalidInputError
from robust_imdp.models.system import Dataset
from robust_imdp.bounds.rkhs_model import MAX_SUB, split_counts, split_term
from robust_imdp.pipeline.problem import (LOCAL_AUTO, LOCAL_DEFAULT, TIGHT_MAX_BOXES, TIGHT_SPLIT_TOL, TIGHT_SPLIT_TOL_3D,
                                          cell_taylor_term, pool_size, tight_settings, tight_split_tol)
from robust_imdp.synthesis.advice import POOL_ALL_MAX, POOL_FACTOR

from problem_texts import ONE_D, write_one_d
from test_pipeline import tiny_gp_problem, tiny_problem
from test_split_option import _bounds

CASE = get_case_study("three_mode_linear")


def test_tight_settings_rule():
    # every mode already on all points: local_points stays None (the automatic rule keeps all points)
    assert tight_settings([40, LOCAL_AUTO], 2) == {"split_tol": TIGHT_SPLIT_TOL, "local_points": None}
    # from 3-D on the sub-boxes grow as s^d: the coarser SPLIT_TOL
    assert tight_settings([40], 3)["split_tol"] == TIGHT_SPLIT_TOL_3D == rkhs.SPLIT_TOL
    assert tight_settings([40], 4)["split_tol"] == TIGHT_SPLIT_TOL_3D
    assert tight_settings([40], 1)["split_tol"] == TIGHT_SPLIT_TOL
    # above LOCAL_AUTO and up to POOL_ALL_MAX: all points of the largest mode, so of every mode
    s = tight_settings([300, LOCAL_AUTO + 1], 2)
    assert s["local_points"] == LOCAL_AUTO + 1
    assert pool_size(s["local_points"], 300) is None and pool_size(s["local_points"], LOCAL_AUTO + 1) is None
    assert tight_settings([POOL_ALL_MAX], 3)["local_points"] == POOL_ALL_MAX
    # above POOL_ALL_MAX: POOL_FACTOR times the default pool
    assert tight_settings([POOL_ALL_MAX + 1, 10], 2)["local_points"] == POOL_FACTOR * LOCAL_DEFAULT
    # the user's values win
    assert tight_settings([5000], 3, local_points=50, split_tol=1e-3) == {"split_tol": 1e-3, "local_points": 50}
    assert TIGHT_SPLIT_TOL < rkhs.SPLIT_TOL


@pytest.mark.parametrize("dim,n_cells", [(2, 256), (2, 1024), (2, 65536), (3, 512), (3, 4096), (3, 262144),
                                          (4, 4096), (4, 65536)])
@pytest.mark.parametrize("term", [1e-4, 3e-3, 0.04, 0.5])
def test_the_preset_stays_within_its_box_budget(dim, n_cells, term):
    tol = tight_split_tol(dim, n_cells, term)
    base = TIGHT_SPLIT_TOL if dim <= 2 else TIGHT_SPLIT_TOL_3D
    if tol is None:  # not even 2 pieces per axis fit
        assert n_cells * 2 ** dim > TIGHT_MAX_BOXES
        return
    assert tol >= base
    # the bound stage's rule (split_counts, capped at MAX_SUB) on cells of that term: within the budget
    s = int(split_counts(np.array([0.01]), term / split_term(np.array([0.01]), 1.0)[0], dim, tol)[0])
    assert n_cells * s ** dim <= TIGHT_MAX_BOXES
    # and the budget binds only where it must: the base tolerance's split would not have fitted
    s_base = int(split_counts(np.array([0.01]), term / split_term(np.array([0.01]), 1.0)[0], dim, base)[0])
    if tol > base:
        assert n_cells * s_base ** dim > TIGHT_MAX_BOXES
    else:
        assert s == s_base
    assert s <= max(1, int(np.floor(MAX_SUB ** (1 / dim) + 1e-9)))


def test_cell_taylor_term_is_the_bound_stages_split_term():
    from robust_imdp._fp import up
    from robust_imdp._kernels import inv_l2_up, norm_inflation
    from robust_imdp.bounds.rkhs_model import t_max_up

    cs, ls, B = np.array([0.25, 0.5]), np.array([1.0, 2.0]), 1.5
    r = 0.5 * cs[None, :]
    want = split_term(t_max_up(r, inv_l2_up(ls, 2)), float(up(B * norm_inflation(2))))[0]
    assert cell_taylor_term(cs, ls, B) == want
    assert cell_taylor_term(cs, ls, 2 * B) > want and cell_taylor_term(cs / 2, ls, B) < want
    p = tiny_problem()
    assert p.grid_taylor_term() == cell_taylor_term(p.cell_size, 2.0, p.rkhs_bound)


def test_tightened_on_a_fine_grid_takes_fewer_sub_boxes():
    # 64 x 64 cells (4,096): 32 boxes per cell fit the budget, so at most 5 pieces per axis
    p = tiny_problem(cell_size=np.array([1 / 16, 1 / 16]))
    t = p.tightened()
    s = split_counts(np.array([0.01]), p.grid_taylor_term() / split_term(np.array([0.01]), 1.0)[0], 2,
                     t.split_tol)[0]
    assert 4096 * s ** 2 <= TIGHT_MAX_BOXES and s >= 2


def test_tightened_is_a_copy_that_keeps_the_problems_values():
    p = tiny_problem(split_tol=2e-3)
    t = p.tightened()
    assert t is not p and p.split_tol == 2e-3 and p.local_points is None
    assert t.split_tol == 2e-3 and t.local_points is None  # 40 points per mode: all points already
    assert tiny_problem().tightened().split_tol == TIGHT_SPLIT_TOL
    assert tiny_problem(local_points=7).tightened().local_points == 7


def test_tightened_counts_points_per_mode():
    # 1,200 points in mode 0 and 40 in the others: above LOCAL_AUTO, so all points (1,200) for every mode
    x, u, xn = CASE.system.sample_dataset(40, CASE.lower, CASE.upper, rng=3)
    rng = np.random.default_rng(5)
    extra = rng.uniform(CASE.lower, CASE.upper, (1160, 2))
    xe = CASE.system.step(extra, np.zeros(1160, dtype=int), rng)
    data = Dataset(np.vstack([x, extra]), np.concatenate([u, np.zeros(1160, dtype=int)]), np.vstack([xn, xe]),
                   modes=CASE.system.mode_names)
    t = tiny_problem(data=data).tightened()
    assert t.local_points == 1200 and t.split_tol == TIGHT_SPLIT_TOL


def test_tightened_on_the_gp_route_is_refused():
    with pytest.raises(InvalidInputError, match="split_tol applies to error_bound"):
        tiny_gp_problem().tightened()


@pytest.fixture(scope="module")
def bounds_pair():
    # r / l = 0.125 (cells of 0.5, lengthscale 2), B = 6: SPLIT_TOL gives 10 pieces per axis, the preset 14
    # (the 2-D cap; at lengthscale 1 both sit at the cap and give the same boxes)
    p = tiny_problem()
    return _bounds(p.replace(split_tol=rkhs.SPLIT_TOL)), _bounds(p.tightened())


def test_tight_bounds_are_tighter_than_split_tol_and_contain_the_true_images(bounds_pair):
    (part, cb_s), (_, cb_t) = bounds_pair
    w_s = cb_s.image_upper - cb_s.image_lower
    w_t = cb_t.image_upper - cb_t.image_lower
    assert np.median(w_s - w_t) > 0  # the preset's split_tol reaches the bound stage
    assert np.mean(w_t <= w_s + 1e-12) > 0.9
    rng = np.random.default_rng(12)
    lo, up = part.cells_lower, part.cells_upper
    for u in range(3):
        pts = lo[:, None, :] + rng.random((lo.shape[0], 400, 2)) * (up - lo)[:, None, :]
        img = CASE.system.g(pts.reshape(-1, 2), np.full(pts.shape[0] * pts.shape[1], u)).reshape(pts.shape)
        assert np.all(img >= cb_t.image_lower[u][:, None, :]) and np.all(img <= cb_t.image_upper[u][:, None, :])


@pytest.mark.slow
def test_run_tight_on_the_command_line(tmp_path, capsys):
    write_one_d(tmp_path)
    code = main(["run", str(tmp_path / "p.toml"), "--out", str(tmp_path / "o"), "--tight", "--no-figures"])
    _, err = capsys.readouterr()
    assert code == 0, err
    assert f"tight preset: split_tol = {TIGHT_SPLIT_TOL:g}, local_points = all points" in err
    doc = json.loads((tmp_path / "o" / "result.json").read_text())
    assert doc["parameters"]["split_tol"] == TIGHT_SPLIT_TOL
    # with the file's own split_tol the preset keeps it
    (tmp_path / "q.toml").write_text(ONE_D + "split_tol = 0.003\n")
    code = main(["run", str(tmp_path / "q.toml"), "--out", str(tmp_path / "o2"), "--tight", "--no-figures",
                 "--quiet"])
    assert code == 0
    assert json.loads((tmp_path / "o2" / "result.json").read_text())["parameters"]["split_tol"] == 0.003


def test_suggest_and_improve_take_the_flag_like_run(capsys):
    from robust_imdp.cli import _parser, _tightened

    p = _parser()
    assert p.parse_args(["suggest", "D", "--problem", "p.toml", "--budget", "1", "--tight"]).tight
    assert p.parse_args(["improve", "p.toml", "--true-system", "s", "--budget", "1", "--tight"]).tight
    assert not p.parse_args(["run", "p.toml", "--out", "o"]).tight
    prob = tiny_problem()
    args = p.parse_args(["suggest", "D", "--problem", "p.toml", "--budget", "1", "--tight"])
    assert _tightened(prob, args).split_tol == TIGHT_SPLIT_TOL
    assert "tight preset: split_tol = 0.0004, local_points = all points" in capsys.readouterr().err
    assert _tightened(prob, p.parse_args(["suggest", "D", "--problem", "p.toml", "--budget", "1"])) is prob
    # a grid too fine for sub-boxes within the budget (512 x 512 cells): the line says so
    fine = tiny_problem(cell_size=np.array([1 / 128, 1 / 128]))
    assert _tightened(fine, args).split_tol is None
    assert "split_tol = none (sub-boxes of this grid would exceed 131,072 boxes" in capsys.readouterr().err
