"""Tests of the IMDP type: construction, attributes, dense round trip, validation messages."""

import numpy as np
import pytest

from robust_imdp.errors import DimensionError, InvalidIntervalError, InvalidModelError
from robust_imdp.models.imdp import IMDP, ROW_SUM_TOL


def small():
    # state 0: two choices (row 0: to 0/1, row 1: to 2 with a floor); states 1, 2: self loops
    return dict(state_ptr=[0, 2, 3, 4], row_ptr=[0, 2, 3, 4, 5], col=[0, 1, 2, 1, 2],
                lower=[0.2, 0.3, 0.5, 1.0, 1.0], upper=[0.6, 0.8, 0.9, 1.0, 1.0],
                floor=[0.0, 0.3, 0.0, 0.0])


def test_attributes_and_defaults():
    m = IMDP.from_csr(**small())
    assert (m.n_states, m.n_choices, m.nnz) == (3, 4, 5)
    np.testing.assert_array_equal(m.actions, [0, 1, 0, 0])  # index of the row within its state
    np.testing.assert_array_equal(m.row_state, [0, 0, 1, 2])
    np.testing.assert_array_equal(m.n_unlisted, [1, 2, 2, 2])  # n - row length
    assert m.has_floor and list(m.choices_of(0)) == [0, 1]
    np.testing.assert_array_equal(m.n_choices_of(), [2, 1, 1])
    assert "n_states=3" in repr(m) and m.memory_bytes > 0
    kw = small()
    kw.pop("floor")
    kw["upper"] = [0.6, 0.8, 1.0, 1.0, 1.0]  # row 1 needs no floor any more
    np.testing.assert_array_equal(IMDP.from_csr(**kw).floor, np.zeros(4))
    with pytest.raises(InvalidModelError, match="state must be in"):
        m.choices_of(3)


def test_immutable_and_owns_its_arrays():
    kw = small()
    lower = np.array(kw["lower"])
    kw["lower"] = lower
    m = IMDP.from_csr(**kw)
    assert lower.flags.writeable  # the caller's array is not frozen nor aliased
    lower[0] = 0.9
    assert m.lower[0] == 0.2
    with pytest.raises(ValueError):
        m.lower[0] = 0.5
    with pytest.raises(AttributeError, match="immutable"):
        m.n_states = 4


def test_dense_round_trip_and_floor_expansion():
    m = IMDP.from_csr(**small())
    lo, up = m.to_dense()
    # row 1 lists state 2 with [0.5, 0.9]; states 0 and 1 are unlisted -> [0, floor = 0.3]
    np.testing.assert_array_equal(lo[1], [0.0, 0.0, 0.5])
    np.testing.assert_array_equal(up[1], [0.3, 0.3, 0.9])
    rng = np.random.default_rng(0)
    p = rng.dirichlet(np.ones(4), size=(4, 2))
    lo3, up3 = np.clip(p - 0.1, 0, 1), np.clip(p + 0.1, 0, 1)
    d = IMDP.from_dense(lo3, up3)
    l2, u2 = d.to_dense()
    np.testing.assert_array_equal(l2, lo3.reshape(8, 4))
    np.testing.assert_array_equal(u2, up3.reshape(8, 4))


@pytest.mark.parametrize("change, exc, match", [
    (dict(lower=[0.7, 0.3, 0.5, 1.0, 1.0]), InvalidIntervalError, r"row 0 \(state 0, action 0\), successor 0.*0 <= lower <= upper"),
    (dict(upper=[0.6, 1.2, 0.9, 1.0, 1.0]), InvalidIntervalError, "successor 1.*0 <= lower <= upper <= 1"),
    (dict(lower=[0.6, 0.5, 0.5, 1.0, 1.0], upper=[0.6, 0.8, 0.9, 1.0, 1.0]), InvalidIntervalError,
     r"row 0 .*sum of lower bounds 1\.1"),
    (dict(upper=[0.3, 0.5, 0.9, 1.0, 1.0]), InvalidIntervalError, r"row 0 .*sum of upper bounds 0\.8.*deficit 0\.2"),
    (dict(floor=[0.0, 0.01, 0.0, 0.0]), InvalidIntervalError, r"row 1 \(state 0, action 1\).*floor 0\.01 x 2 unlisted"),
    (dict(floor=[0.0, 1.5, 0.0, 0.0]), InvalidIntervalError, r"floor\[1\] = 1\.5"),
    (dict(col=[0, 0, 2, 1, 2]), InvalidModelError, "row 0 .* lists successor 0 twice"),
    (dict(col=[0, 1, 3, 1, 2]), InvalidModelError, r"col\[2\] = 3 .* not a state index in \[0, 3\)"),
    (dict(lower=[np.nan, 0.3, 0.5, 1.0, 1.0]), InvalidIntervalError, r"lower\[0\] = nan .* not finite"),
    (dict(state_ptr=[0, 2, 2, 4]), InvalidModelError, "at least one choice.*state 1 has 0"),
    (dict(row_ptr=[0, 2, 3, 4, 6]), InvalidModelError, r"row_ptr\[-1\] must equal nnz"),
    (dict(upper=[0.6, 0.8, 0.9, 1.0]), DimensionError, r"upper must have shape \(5,\)"),
    (dict(col=[[0, 1, 2, 1, 2]]), DimensionError, "col must be a 1-D integer array"),
    (dict(col=[0.5, 1, 2, 1, 2]), InvalidModelError, "col must hold integers"),
    (dict(actions=[0, 1, 0]), DimensionError, r"actions must have shape \(4,\)"),
])
def test_bad_input_names_row_and_amount(change, exc, match):
    kw = small()
    kw.update(change)
    with pytest.raises(exc, match=match):
        IMDP.from_csr(**kw)


def test_row_sum_tolerance_is_absolute_1e12_and_nothing_else():
    # 2 states: row with lower sum 1 + 0.5 tol is accepted, 1 + 10 tol rejected (not repaired)
    IMDP.from_csr(state_ptr=[0, 1, 2], row_ptr=[0, 2, 3], col=[0, 1, 1],
                  lower=[0.5, 0.5 + 0.5 * ROW_SUM_TOL, 1.0], upper=[1.0, 1.0, 1.0])
    with pytest.raises(InvalidIntervalError, match="sum of lower bounds"):
        IMDP.from_csr(state_ptr=[0, 1, 2], row_ptr=[0, 2, 3], col=[0, 1, 1],
                      lower=[0.5, 0.5 + 10 * ROW_SUM_TOL, 1.0], upper=[1.0, 1.0, 1.0])
    # the per-entry check has no tolerance: lower above upper by 1e-15 is an error
    with pytest.raises(InvalidIntervalError, match="0 <= lower <= upper"):
        IMDP.from_csr([0, 1], [0, 1], [0], [1.0], [1.0 - 1e-15])


def test_unsorted_columns_allowed_and_empty_floor_row():
    # columns in any order; a row listing nothing is fine when floor * n >= 1
    m = IMDP.from_csr([0, 2, 3], [0, 2, 2, 3], [1, 0, 1], [0.1, 0.2, 1.0], [0.9, 0.9, 1.0], floor=[0, 0.5, 0])
    assert m.n_unlisted[1] == 2


def test_vectorised_validation_on_100k_states():
    rng = np.random.default_rng(3)
    n, k = 100_000, 5
    col = np.sort(rng.integers(0, n, size=(n, k)), axis=1)
    col[:, 1:] += np.cumsum(np.diff(col, axis=1) == 0, axis=1)  # make rows duplicate-free
    col = np.minimum(col, n - 1)
    ok = np.all(np.diff(col, axis=1) > 0, axis=1)
    col[~ok] = np.arange(k)
    m = IMDP.from_csr(np.arange(n + 1), np.arange(0, n * k + 1, k), col.ravel(),
                      np.full(n * k, 0.1), np.full(n * k, 0.3))
    assert m.nnz == n * k
