"""``split_tol`` (``[learning].split_tol``): sub-box certification through the pipeline.

The bound itself (eq. C on sub-boxes, its hull, pruning) is tested in test_rkhs_local.py; here: the
option reaches the bound stage (boxes inside the unsplit ones, strictly tighter somewhere), the true
images stay inside (dense sampling), refinement's and the grid's bounds use it alike, the cache key
is unchanged without it, and bad values are refused with a message naming the key.
"""

import numpy as np
import pytest

from robust_imdp.bounds import rkhs
from robust_imdp.casestudies.systems import get_case_study
from robust_imdp.errors import InvalidInputError, ProblemFileError
from robust_imdp.io.problem_file import load_problem
from robust_imdp.models.geometry import Box, Partition
from robust_imdp.pipeline import bound_stage, preflight, runtime
from robust_imdp.pipeline.cache import bounds_key
from robust_imdp.pipeline.problem import Problem

from test_pipeline import tiny_gp_problem, tiny_problem

CASE = get_case_study("three_mode_linear")


def _bounds(problem):
    part = Partition(Box(problem.space_lower, problem.space_upper), problem.cell_size,
                     preflight._region_objects(problem))
    cb, _, _ = bound_stage._learn_and_bound(problem, part, runtime._Log(False), runtime._Run(workers=1))
    return part, cb


@pytest.fixture(scope="module")
def pair():
    # lengthscale 1 on cells of 0.5: r / l = 0.25, where the Taylor remainder is a large part of the radius
    p0 = tiny_problem(gp_options={"lengthscale": 1.0})
    p1 = p0.replace(split_tol=rkhs.SPLIT_TOL)
    return (p0, *_bounds(p0)), (p1, *_bounds(p1))


def test_split_boxes_lie_inside_the_unsplit_ones_and_are_tighter(pair):
    (_, part, cb0), (_, _, cb1) = pair
    # both are sound hulls of eq. C; the split one is the hull over sub-boxes (each at most the cell's)
    assert np.all(cb1.image_lower >= cb0.image_lower - 1e-12)
    assert np.all(cb1.image_upper <= cb0.image_upper + 1e-12)
    w0 = cb0.image_upper - cb0.image_lower
    w1 = cb1.image_upper - cb1.image_lower
    assert np.median(w0 - w1) > 0.05 * np.median(w0)  # the option really reaches the bound stage


def test_split_boxes_contain_the_true_images(pair):
    (_, part, _), (_, _, cb1) = pair
    rng = np.random.default_rng(11)
    lo, up = part.cells_lower, part.cells_upper
    for u in range(3):
        pts = lo[:, None, :] + rng.random((lo.shape[0], 300, 2)) * (up - lo)[:, None, :]
        corners = np.stack([np.where(np.array(s)[None, :], up, lo) for s in ((0, 0), (0, 1), (1, 0), (1, 1))], 1)
        pts = np.concatenate([pts, corners], axis=1)
        img = CASE.system.g(pts.reshape(-1, 2), np.full(pts.shape[0] * pts.shape[1], u)).reshape(pts.shape)
        assert np.all(img >= cb1.image_lower[u][:, None, :]) and np.all(img <= cb1.image_upper[u][:, None, :])


def test_cache_key_and_parameters():
    p0 = tiny_problem()
    assert bounds_key(p0) == bounds_key(p0.replace(split_tol=None))  # unchanged without the option
    assert bounds_key(p0) != bounds_key(p0.replace(split_tol=1e-3)) != bounds_key(p0.replace(split_tol=2e-3))


@pytest.mark.parametrize("bad", [0.0, -1e-3, float("nan"), float("inf"), True, "0.001"])
def test_bad_split_tol_is_refused(bad):
    with pytest.raises(InvalidInputError, match="split_tol must be a finite float > 0"):
        tiny_problem(split_tol=bad)


def test_split_tol_on_the_gp_route_is_refused():
    with pytest.raises(InvalidInputError, match="split_tol applies to error_bound = 'optimal' or 'ridge' only"):
        tiny_gp_problem(split_tol=1e-3)


def _write(tmp_path, extra: str, error_bound: str = "optimal"):
    from robust_imdp.casestudies.systems import write_problem_files

    path = write_problem_files("three_mode_linear", tmp_path, seed=0)
    text = path.read_text()
    assert "[learning]\n" in text
    text = text.replace("[learning]\n", f"[learning]\n{extra}\n", 1)
    if error_bound != "optimal":
        text = text.replace('error_bound = "optimal"', f'error_bound = "{error_bound}"')
    path.write_text(text)
    return path


def test_problem_file_split_tol(tmp_path):
    p = load_problem(_write(tmp_path, "split_tol = 0.0015"))
    assert isinstance(p, Problem) and p.split_tol == 0.0015 and "split_tol" not in p.gp_options
    assert load_problem(_write(tmp_path / "b", "")).split_tol is None
    with pytest.raises(ProblemFileError, match=r"learning\]?\.?split_tol must be > 0"):
        load_problem(_write(tmp_path / "c", "split_tol = 0"))
    with pytest.raises(ProblemFileError, match="split_tol must be a number"):
        load_problem(_write(tmp_path / "d", 'split_tol = "small"'))
