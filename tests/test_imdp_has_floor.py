"""``IMDP.has_floor`` is computed once per model (``models/imdp.py``): the cached value is the definition's
(some row with an unlisted state has a positive floor) for random models, it survives neither as a pickled field
nor as a change to the model's fields, and pickling still sends exactly the model's arrays."""

from __future__ import annotations

import copy
import pickle

import numpy as np
import pytest

from robust_imdp.models.imdp import IMDP


def random_imdp(rng, n=6, floor_share=0.5):
    """Rows listing a random subset of states; each row's floor positive with probability ``floor_share``."""
    state_ptr = np.arange(0, 2 * n + 1, 2)  # two choices per state
    cols, lows, ups, ptr, floors = [], [], [], [0], []
    for _ in range(2 * n):
        c = np.sort(rng.choice(n, size=rng.integers(1, n + 1), replace=False))
        cols.append(c)
        lows.append(np.zeros(c.size))
        ups.append(np.ones(c.size))  # upper sums >= 1 whatever the floor
        ptr.append(ptr[-1] + c.size)
        floors.append(rng.uniform(0.01, 0.2) if rng.random() < floor_share else 0.0)
    return IMDP.from_csr(state_ptr, ptr, np.concatenate(cols), np.concatenate(lows), np.concatenate(ups),
                         floor=floors)


@pytest.mark.parametrize("share", [0.0, 0.2, 1.0])
def test_has_floor_is_the_definition_and_is_kept(share):
    rng = np.random.default_rng(11)
    for _ in range(20):
        m = random_imdp(rng, floor_share=share)
        expect = bool(np.any((m.floor > 0) & (m.n_unlisted > 0)))  # a floor counts on a row with unlisted states
        assert m.has_floor is expect and m.has_floor is expect  # computed, then read from the cache
        for c in (pickle.loads(pickle.dumps(m)), copy.copy(m), copy.deepcopy(m)):
            assert c.has_floor is expect


def test_a_floor_on_a_row_that_lists_every_state_does_not_count():
    # one state, one row listing it: no unlisted state, so the floor 0.5 can carry no mass
    m = IMDP.from_csr([0, 1], [0, 1], [0], [1.0], [1.0], floor=[0.5])
    assert not m.has_floor
    m2 = IMDP.from_csr([0, 1, 2], [0, 1, 2], [0, 1], [0.5, 1.0], [0.9, 1.0], floor=[0.5, 0.0])
    assert m2.has_floor  # row 0 lists state 0 only; state 1 unlisted with floor 0.5


def test_pickling_sends_the_fields_only_and_the_cache_cannot_be_set():
    m = random_imdp(np.random.default_rng(3))
    before = pickle.dumps(m)
    assert m.has_floor in (True, False)
    assert pickle.dumps(m) == before  # the cached value is not part of the pickled model
    assert "_has_floor" not in IMDP.__slots__  # __slots__ lists the model's fields (what __reduce__ sends)
    with pytest.raises(AttributeError, match="immutable"):
        m._has_floor = not m.has_floor
