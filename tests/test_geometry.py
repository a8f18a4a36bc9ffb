"""Tests of robust_imdp.models.geometry: boxes, regions, region-respecting partitions, locate."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robust_imdp.errors import DimensionError, InvalidInputError, OutsideDomainError
from robust_imdp.models.geometry import Box, Partition, Region


# ----------------------------------------------------------------------------- Box / Region
def test_box_validation_messages():
    with pytest.raises(InvalidInputError, match="lower < upper"):
        Box([0.0, 1.0], [1.0, 1.0])  # empty in dim 1
    with pytest.raises(InvalidInputError, match="lower = 2.0 >= upper = 1.0 in dimension 1 "):
        Box([2.0], [1.0])  # inverted (dimensions are numbered from 1 in messages)
    with pytest.raises(DimensionError, match="same length"):
        Box([0.0, 0.0], [1.0])
    with pytest.raises(InvalidInputError, match="finite"):
        Box([0.0], [np.inf])


def test_box_intersection_needs_every_axis():
    a = Box([0, 0], [1, 1])
    assert a.intersects(Box([1, 1], [2, 2]))  # closed: touching corner counts
    assert not a.intersects(Box([0.5, 1.5], [0.7, 2.0]))  # overlaps on axis 0 only
    assert a.contains_box(Box([0.2, 0.2], [1, 1]))
    np.testing.assert_array_equal(a.contains([[0.5, 0.5], [1.0, 1.0], [1.1, 0.0]]), [True, True, False])


def test_region_needs_boxes_and_name():
    with pytest.raises(InvalidInputError, match="at least one Box"):
        Region("a", ())
    with pytest.raises(InvalidInputError, match="name"):
        Region("", (Box([0], [1]),))
    with pytest.raises(DimensionError, match="one dimension"):
        Region("a", (Box([0], [1]), Box([0, 0], [1, 1])))


# ----------------------------------------------------------------------------- Partition
def test_uniform_grid_and_c_order():
    P = Partition(Box([-2, -1], [2, 1]), [1.0, 0.5])
    assert P.shape == (4, 4) and P.n_cells == 16 and P.outside_state == 16
    np.testing.assert_array_equal(P.breakpoints[0], [-2, -1, 0, 1, 2])
    # cell index = ravel_multi_index (C order): cell 5 is (1, 1) -> [-1, 0] x [-0.5, 0]
    np.testing.assert_array_equal(P.cells_lower[5], [-1, -0.5])
    np.testing.assert_array_equal(P.cells_upper[5], [0, 0])


def test_cell_size_not_dividing_says_how_to_fix():
    with pytest.raises(InvalidInputError, match=r"cell_size in dimension 1 is 0.3, which does not divide .* 0.333333 \(3 cells\)"):
        Partition(Box([0.0], [1.0]), 0.3)
    with pytest.raises(DimensionError, match="cell_size"):
        Partition(Box([0, 0], [1, 1]), [0.5, 0.5, 0.5])
    with pytest.raises(InvalidInputError, match="> 0"):
        Partition(Box([0.0], [1.0]), -0.5)


def test_region_outside_x_is_an_error():
    with pytest.raises(OutsideDomainError, match="region 'far'"):
        Partition(Box([0, 0], [1, 1]), 0.5, [Region("far", (Box([0.5, 0.5], [1.5, 1.0]),))])


def test_misaligned_regions_split_cells_and_label_exactly():
    goal = Region("goal", (Box([0.3, 0.1], [0.65, 0.5]),))
    obst = Region("obst", (Box([-1.0, -1.0], [-0.5, -0.5]), Box([0.5, 0.75], [1.0, 1.0])))
    P = Partition(Box([-1, -1], [1, 1]), 0.5, {"goal": goal, "obst": obst})
    assert P.atoms == ("goal", "obst")
    # off-grid boundaries 0.3, 0.65 (dim 0) and 0.1, 0.75 (dim 1) become breakpoints
    np.testing.assert_allclose(P.breakpoints[0], [-1, -0.5, 0, 0.3, 0.5, 0.65, 1])
    np.testing.assert_allclose(P.breakpoints[1], [-1, -0.5, 0, 0.1, 0.5, 0.75, 1])
    # every cell is inside a region or meets it only on its boundary: check with cell centres
    # and corners (the label of a cell == membership of its interior points)
    rng = np.random.default_rng(0)
    for r_i, region in enumerate(P.regions):
        labelled = (P.labels >> r_i) & 1 == 1
        t = rng.uniform(0.01, 0.99, (P.n_cells, 2))
        interior = P.cells_lower + t * (P.cells_upper - P.cells_lower)
        np.testing.assert_array_equal(region.contains(interior), labelled)
    # union of the labelled goal cells has the area of the goal box (0.35 * 0.4)
    g = (P.labels & 1) == 1
    area = np.prod(P.cells_upper[g] - P.cells_lower[g], axis=1).sum()
    assert area == pytest.approx(0.35 * 0.4, rel=1e-12)
    sets = P.label_sets()
    assert sets[int(np.flatnonzero(g)[0])] == frozenset({"goal"})


def test_region_boundary_near_tick_keeps_region_value():
    # 0.1 * 3 = 0.30000000000000004: the region's exact value replaces the tick (no sliver)
    P = Partition(Box([0.0], [1.0]), 0.1, [Region("a", (Box([0.3], [0.7]),))])
    assert P.shape == (10,)
    assert 0.3 in P.breakpoints[0].tolist() and 0.7 in P.breakpoints[0].tolist()
    np.testing.assert_array_equal(np.flatnonzero(P.labels), [3, 4, 5, 6])


def test_locate_convention_and_outside():
    P = Partition(Box([0, 0], [1, 1]), 0.5)
    x = np.array([[0.25, 0.25], [0.5, 0.5], [1.0, 1.0], [0.0, 1.0], [1.0001, 0.5], [-1e-12, 0.2]])
    # half-open [b_k, b_{k+1}) except the last interval, closed at the upper end of X
    np.testing.assert_array_equal(P.locate(x), [0, 3, 3, 1, -1, -1])
    with pytest.raises(DimensionError, match="x must have shape"):
        P.locate([[0.1, 0.2, 0.3]])


@settings(deadline=None, max_examples=25)
@given(st.integers(0, 2**31 - 1))
def test_locate_agrees_with_cell_boxes(seed):
    rng = np.random.default_rng(seed)
    P = Partition(Box([-1, 0], [1, 2]), [0.25, 0.5], [Region("r", (Box([-0.37, 0.2], [0.11, 1.3]),))])
    x = rng.uniform([-1.2, -0.2], [1.2, 2.2], (200, 2))
    idx = P.locate(x)
    inside = P.contains(x)
    np.testing.assert_array_equal(idx >= 0, inside)
    xi = x[inside]
    assert np.all(P.cells_lower[idx[inside]] <= xi) and np.all(xi <= P.cells_upper[idx[inside]])


def test_dict_round_trip_is_json():
    P = Partition(Box([-2, -2], [2, 2]), 0.5, [Region("a", (Box([-0.3, 0.1], [0.5, 1.0]),))])
    Q = Partition.from_dict(json.loads(json.dumps(P.to_dict())))
    for bp, bq in zip(P.breakpoints, Q.breakpoints):
        np.testing.assert_array_equal(bp, bq)
    np.testing.assert_array_equal(P.labels, Q.labels)
    assert Q.atoms == ("a",)


def test_duplicate_region_names_rejected():
    r = Region("a", (Box([0], [0.5]),))
    with pytest.raises(InvalidInputError, match="unique"):
        Partition(Box([0], [1]), 0.5, [r, r])
    with pytest.raises(InvalidInputError, match="key must equal the name"):
        Partition(Box([0], [1]), 0.5, {"b": r})


def test_partition_is_immutable():
    P = Partition(Box([0], [1]), 0.5)
    with pytest.raises(AttributeError, match="immutable"):
        P.n_cells = 3
    with pytest.raises(ValueError):
        P.labels[0] = 1  # read-only array
