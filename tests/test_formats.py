"""DRN / PRISM explicit import-export: round trips, floors, and line-numbered errors."""

from __future__ import annotations

import numpy as np
import pytest

from robust_imdp.errors import InvalidInputError, InvalidIntervalError, InvalidModelError
from robust_imdp.io.formats import (
    densified_rows,
    load_drn,
    load_prism_explicit,
    read_drn,
    read_prism_explicit,
    write_drn,
    write_prism_explicit,
)
from robust_imdp.models.imdp import IMDP

FIELDS = ("state_ptr", "row_ptr", "col", "lower", "upper", "floor", "actions")


def random_csr(rng, n, max_actions=3, k=3, floor=False):
    """Random IMDP with a varying number of choices per state, unsorted columns, odd floats."""
    n_act = rng.integers(1, max_actions + 1, size=n)
    state_ptr = np.concatenate([[0], np.cumsum(n_act)])
    R = int(state_ptr[-1])
    cols, lo, up, row_ptr = [], [], [], [0]
    for _ in range(R):
        kk = int(rng.integers(1, k + 1))
        succ = rng.choice(n, size=kk, replace=False)  # not sorted: must survive the round trip
        p = rng.dirichlet(np.ones(kk))
        w = rng.uniform(0, 0.1, size=kk) / 3.0  # values like 0.0123456789012345 test repr round trip
        lo += list(np.clip(p - w, 0, 1))
        up += list(np.clip(p + w, 0, 1))
        cols += list(succ)
        row_ptr.append(len(cols))
    fl = np.where(rng.uniform(size=R) < 0.5, 1e-3 / 3, 0.0) if floor else None
    actions = np.arange(R) - np.repeat(state_ptr[:-1], n_act) + 10  # non-default labels
    return IMDP.from_csr(state_ptr, row_ptr, cols, lo, up, floor=fl, actions=actions)


def assert_same(a, b):
    for f in FIELDS:
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)


# ----------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_drn_round_trip_identical(tmp_path, seed):
    m = random_csr(np.random.default_rng(seed), 7)
    tgt = np.zeros(7, bool)
    tgt[[2, 5]] = True
    write_drn(m, tmp_path / "m.drn", target=tgt, labels={"goal": [1]}, initial=3)
    f = load_drn(tmp_path / "m.drn")
    assert_same(m, f.imdp)
    np.testing.assert_array_equal(f.labels["target"], tgt)
    np.testing.assert_array_equal(np.flatnonzero(f.labels["init"]), [3])
    np.testing.assert_array_equal(np.flatnonzero(f.labels["goal"]), [1])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_prism_round_trip_identical(tmp_path, seed):
    m = random_csr(np.random.default_rng(seed), 6)
    tgt = np.zeros(6, bool)
    tgt[4] = True
    paths = write_prism_explicit(m, tmp_path / "m", target=tgt)
    assert sorted(p.rsplit(".", 1)[1] for p in paths) == ["lab", "props", "sta", "tra"]
    f = load_prism_explicit(tmp_path / "m")
    assert_same(m, f.imdp)
    np.testing.assert_array_equal(f.labels["target"], tgt)
    assert read_prism_explicit(tmp_path / "m").n_states == 6


def test_floor_rows_are_densified(tmp_path):
    m = random_csr(np.random.default_rng(4), 5, floor=True)
    assert m.has_floor
    write_drn(m, tmp_path / "f.drn")
    back = read_drn(tmp_path / "f.drn")
    assert not back.has_floor
    lo1, up1 = m.to_dense()
    lo2, up2 = back.to_dense()
    np.testing.assert_array_equal(lo1, lo2)  # same intervals for every (row, state)
    np.testing.assert_array_equal(up1, up2)
    write_prism_explicit(m, tmp_path / "f")
    lo3, up3 = read_prism_explicit(tmp_path / "f").to_dense()
    np.testing.assert_array_equal(up1, up3)
    # rows without floor keep exactly their listed entries
    row_ptr, col, _, _ = densified_rows(m)
    plain = np.flatnonzero(m.floor == 0)
    np.testing.assert_array_equal(np.diff(row_ptr)[plain], np.diff(m.row_ptr)[plain])


def test_size_limit_refuses_dense_floor_export(tmp_path):
    m = random_csr(np.random.default_rng(4), 5, floor=True)
    with pytest.raises(InvalidInputError, match="max_entries = 3"):
        write_drn(m, tmp_path / "x.drn", max_entries=3)
    with pytest.raises(InvalidInputError, match="max_entries"):
        write_prism_explicit(m, tmp_path / "x", max_entries=3)


def test_dtmc_and_plain_values(tmp_path):
    p = tmp_path / "d.drn"
    p.write_text("@type: DTMC\n@parameters\n\n@reward_models\n\n@nr_states\n2\n@nr_choices\n2\n@model\n"
                 "state 0 init\n\t0 : 0.25\n\t1 : [0.5, 0.75]\nstate 1 target\n\t1 : 1\n")
    m = read_drn(p)
    np.testing.assert_array_equal(m.lower, [0.25, 0.5, 1.0])
    np.testing.assert_array_equal(m.upper, [0.25, 0.75, 1.0])


# ----------------------------------------------------------------------------- malformed files
GOOD = ("@type: MDP\n@parameters\n\n@reward_models\n\n@nr_states\n2\n@nr_choices\n2\n@model\n"
        "state 0 init\n\taction 0\n\t\t0 : [0.2, 0.5]\n\t\t1 : [0.5, 0.8]\nstate 1\n\taction 0\n\t\t1 : [1, 1]\n")


@pytest.mark.parametrize("bad,pattern", [
    (GOOD.replace("[0.2, 0.5]", "[0.2; 0.5]"), r"line 13: expected a probability interval"),
    (GOOD.replace("state 1\n", "state 2\n"), r"line 15: states must appear in order"),
    (GOOD.replace("\t\t0 : [0.2", "\t\tzero : [0.2"), r"line 13: expected '<successor> : \[lower, upper\]'"),
    (GOOD.replace("action 0\n\t\t0", "action go\n\t\t0"), r"line 12: expected 'action <integer>'"),
    (GOOD.replace("@nr_states\n2", "@nr_states\n3"), r"line 7: @nr_states says 3 but the model has 2"),
    (GOOD.replace("@type: MDP", "@type: CTMC"), r"line 1: @type must be MDP or DTMC"),
    (GOOD.replace("@model\n", ""), r"line 10: expected a header line starting with '@' before '@model'"),
    (GOOD.split("@model")[0], r"no '@model' section"),
    (GOOD.replace("@reward_models\n\n", "@reward_models\ncost\n"), r"line 5: @reward_models are not supported"),
])
def test_malformed_drn_names_the_line(tmp_path, bad, pattern):
    p = tmp_path / "bad.drn"
    p.write_text(bad)
    with pytest.raises(InvalidModelError, match=pattern):
        read_drn(p)


def test_semantic_errors_come_from_the_imdp_validation(tmp_path):
    p = tmp_path / "bad.drn"
    p.write_text(GOOD.replace("[0.2, 0.5]", "[0.6, 0.5]"))
    with pytest.raises(InvalidIntervalError, match=r"row 0 \(state 0, action 0\)"):
        read_drn(p)


@pytest.mark.parametrize("bad,pattern", [
    ("2 2 3\n0 0 0 [0.2,0.5]\n0 0 1 [0.5,0.8]\n1 0 1 1\n", None),  # good (plain number allowed)
    ("2 2 3\n0 0 0 [0.2,0.5]\n0 0 1 (0.5,0.8)\n1 0 1 1\n", r"line 3: expected a probability interval"),
    ("2 2 3\n1 0 1 1\n0 0 0 [0.2,0.5]\n0 0 1 [0.5,0.8]\n", r"line 2: transitions must be sorted by source"),
    ("2 2 3\n0 1 0 [0.2,0.5]\n0 1 1 [0.5,0.8]\n1 0 1 1\n", r"line 2: choices of source 0 must be numbered"),
    ("2 2 4\n0 0 0 [0.2,0.5]\n0 0 1 [0.5,0.8]\n1 0 1 1\n", r"line 1: header says 4 transitions"),
    ("two states\n", r"line 1: expected 'n_states n_choices n_transitions'"),
    ("2 2 3\n0 0 0 [0.2,0.5] extra words\n0 0 1 [0.5,0.8]\n1 0 1 1\n", r"line 2: expected 'source choice target"),
])
def test_malformed_prism_names_the_line(tmp_path, bad, pattern):
    (tmp_path / "m.tra").write_text(bad)
    if pattern is None:
        assert read_prism_explicit(tmp_path / "m").n_choices == 2
        return
    with pytest.raises(InvalidModelError, match=pattern):
        read_prism_explicit(tmp_path / "m")


def test_malformed_prism_labels(tmp_path):
    m = random_csr(np.random.default_rng(0), 3)
    write_prism_explicit(m, tmp_path / "m")
    (tmp_path / "m.lab").write_text('0="init" 1="target"\n0: 0\n1: 5\n')
    with pytest.raises(InvalidModelError, match=r"m.lab, line 3: label index 5 is not declared"):
        load_prism_explicit(tmp_path / "m")


def test_bad_labels_rejected(tmp_path):
    m = random_csr(np.random.default_rng(0), 3)
    with pytest.raises(InvalidInputError, match="identifiers"):
        write_drn(m, tmp_path / "x.drn", labels={"my goal": [0]})
    with pytest.raises(InvalidInputError, match="label 'target'"):
        write_drn(m, tmp_path / "x.drn", target=[9])
    with pytest.raises(InvalidInputError, match="initial"):
        write_drn(m, tmp_path / "x.drn", initial=5)
