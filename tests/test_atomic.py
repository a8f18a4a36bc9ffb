"""``robust_imdp._atomic.fetch_add``: the shared counter from which the bound kernels' lanes take their work units.

Every unit must be taken exactly once whatever the lanes and the threads (a lost or doubled update would drop a
block of cells or compute it twice), and the counter must be the old value plus the increments.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

from robust_imdp._atomic import fetch_add


@numba.njit(parallel=True)
def _take_all(n_units, lanes, work):  # pragma: no cover - compiled
    """Units taken from one counter by ``lanes`` prange lanes: how often each was taken and by which lane."""
    counter = np.zeros(1, dtype=np.int64)
    hits = np.zeros(n_units, dtype=np.int64)
    lane = np.full(n_units, -1, dtype=np.int64)
    for t in numba.prange(lanes):
        while True:
            j = fetch_add(counter, 0, 1)
            if j >= n_units:
                break
            hits[j] += 1
            lane[j] = t
            s = 0.0
            for i in range(work[j]):  # uneven units, so the lanes interleave
                s += np.sqrt(i + 1.0)
            if s < 0.0:
                hits[j] += 1000
    return hits, lane, counter  # the array: a read of counter[0] here could be moved before the loop (_atomic)


@pytest.mark.parametrize("lanes", [1, 2, 3, 8])
def test_every_unit_taken_exactly_once(lanes):
    rng = np.random.default_rng(0)  # seeded uneven costs
    n_units = 2_000
    work = rng.integers(0, 20_000, n_units)
    hits, lane, counter = _take_all(n_units, lanes, work)
    final = int(counter[0])
    np.testing.assert_array_equal(hits, np.ones(n_units, dtype=np.int64))
    assert lane.min() >= 0 and lane.max() < lanes
    # every lane that found the counter below n_units added one more increment when it saw the end
    assert n_units < final <= n_units + lanes


def test_returns_the_old_value_and_adds():
    @numba.njit
    def seq(c):  # pragma: no cover - compiled
        a = fetch_add(c, 1, 5)
        b = fetch_add(c, 1, -2)
        return a, b

    c = np.array([7, 10], dtype=np.int64)
    assert seq(c) == (10, 15)
    np.testing.assert_array_equal(c, [7, 13])


def test_rejects_a_non_int64_counter():
    @numba.njit
    def bad(c):  # pragma: no cover - compiled
        return fetch_add(c, 0, 1)

    with pytest.raises(numba.core.errors.TypingError):
        bad(np.zeros(2))
