"""The margins on several cores (``pipeline.margins.PendingMargins``): whole factors in the side lane's helper, row
chunks wherever a core is free, the solves of chunked factors in this process; every factor's ``(p_low, p_up)``
the same bits as one after the other in one process (``_margin_task``), whoever ran which part, when the lane fails
and when a whole factor waits in the lane behind other side work."""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from robust_imdp.errors import DimensionError
from robust_imdp.pipeline import margins as margins_stage
from robust_imdp.pipeline import parallel
from robust_imdp.pipeline.parallel import SideLane

sys.path.insert(0, str(Path(__file__).parent))
from test_check_tasks import _problem  # noqa: E402  (the three-mode problem with 30 samples per mode)


@pytest.fixture(scope="module")
def factors(tmp_path_factory):
    """Every factor's ``_margin_task`` arguments of a solved 256-cell run, and their values one after the other."""
    from robust_imdp.pipeline.run import synthesize_from_data

    cache = tmp_path_factory.mktemp("cache")
    p = _problem(cell_size=np.array([0.25, 0.25]))
    r = synthesize_from_data(p, progress=False, workers=1, advice=False, margins=True, abstraction_cache=cache)
    scales = margins_stage.bound_scales()
    shape = (len(p.mode_names), r.partition.n_cells, 2)
    got = margins_stage._read_scaled(next(Path(cache).glob("scaled-*.npz")), scales, shape)
    args = margins_stage._factor_args(p, r.partition, r.synthesis, got[1], got[2], r.dfa)
    ref = [margins_stage._margin_task(*a) for a in args]
    return args, ref


def _bits(values):
    return [(np.asarray(lo).tobytes(), np.asarray(up).tobytes()) for lo, up in values]


def _pending(args, lane):
    return margins_stage.PendingMargins(margins_stage.bound_scales(), lane, lambda: args)


def test_whole_factors_and_row_chunks_in_both_processes_give_the_same_bits(factors, monkeypatch):
    args, ref = factors
    monkeypatch.setattr(margins_stage, "MIN_PIECE_CELLS", 16)  # 16 chunks of 16 cells per factor built in pieces
    with SideLane(1) as lane:
        pending = _pending(args, lane)
        got = [pending.value(j) for j in range(len(args))]
        pending.cancel()
        assert pending.futures and all(f.done() for f in pending.futures)  # the helper took part
    assert _bits(got) == _bits(ref)
    assert len(pending._piecewise) >= 1  # at least the last factor was built from row chunks here
    for pw in pending._piecewise.values():
        assert len(pw.starts) == 16 and pw.starts == list(range(0, 256, 16))


def test_beside_the_advice_the_helper_takes_chunks_then_whole_factors_then_the_last_factor_s_chunks(factors,
                                                                                                 monkeypatch):
    """This process busy elsewhere (the advice, whose own tasks queue in the lane): the helper takes the row chunks
    of the two largest factors (short tasks), then whole factors while two or more are not started, then the last
    factor's row chunks; this process then only solves the factors built from chunks."""
    args, ref = factors
    monkeypatch.setattr(margins_stage, "MIN_PIECE_CELLS", 64)
    with SideLane(1) as lane:
        pending = _pending(args, lane)
        deadline = time.perf_counter() + 120
        while time.perf_counter() < deadline:  # wait until no work is left for the helper
            with pending._cond:
                pws = pending._piecewise
                if (sorted(pws) == [0, 3, 4] and all(len(pw.pieces) == len(pw.starts) for pw in pws.values())
                        and sorted(pending.values) == [1, 2]):
                    break
            time.sleep(0.05)
        assert list(pending._piecewise) == [4, 3, 0]  # built from chunks, in this order, all rows from the helper
        assert sorted(pending.values) == [1, 2]  # whole factors, in the helper
        assert all(len(pw.starts) == 4 for pw in pending._piecewise.values())  # 256 cells in chunks of 64
        got = [pending.value(j) for j in range(len(args))]
    assert _bits(got) == _bits(ref)


def test_a_lane_that_is_gone_leaves_the_work_to_this_process(factors):
    args, ref = factors
    lane = SideLane(1)
    lane.close()
    pending = _pending(args, lane)
    got = [pending.value(j) for j in range(len(args))]
    assert _bits(got) == _bits(ref)
    assert not pending._sent and len(pending._piecewise) == len(args)  # every factor built here


def test_a_whole_factor_waiting_behind_other_side_work_is_taken_back(factors):
    args, ref = factors
    with SideLane(1) as lane:
        busy = lane.submit(time.sleep, 60)  # e.g. the figures: the margins' first task waits in the lane
        pending = _pending(args, lane)
        got = [pending.value(j) for j in range(len(args))]
        assert not busy.done()
        assert pending.futures and all(f.cancelled() for f in pending.futures)  # taken back, never run there
    assert _bits(got) == _bits(ref)


def test_a_factor_that_fails_raises_here(factors):
    args, _ = factors
    import dataclasses

    bad = [a[:-1] + (dataclasses.replace(a[-1], strategy=np.zeros((1, 3), dtype=np.int64)),) for a in args]
    with SideLane(1) as lane:
        pending = _pending(bad, lane)
        with pytest.raises(DimensionError, match="strategy"):
            pending.value(0)
        pending.cancel()
        assert lane.submit(math.factorial, 4).result(timeout=60) == 24  # the helper is still there


def test_boxes_not_at_hand_leave_the_stage_to_bound_them(factors):
    with SideLane(1) as lane:
        pending = margins_stage.PendingMargins(margins_stage.bound_scales(), lane, lambda: None)
        assert not pending.wait_ready()
        assert not pending.futures


@pytest.mark.parametrize("advice", [True, False])
def test_a_run_with_the_margins_packed_gives_the_one_core_margins(monkeypatch, tmp_path, advice):
    """A whole run from the cache of the boxes at larger B (read beside the advice; without an advice the margins
    start at once) on two cores: the one-core b_margin and counts, bit for bit."""
    from robust_imdp.pipeline.run import synthesize_from_data

    p = _problem(cell_size=np.array([0.25, 0.25]))
    one = synthesize_from_data(p, progress=False, workers=1, advice=advice, margins=True, abstraction_cache=tmp_path)
    monkeypatch.setattr(parallel, "SIDE_MIN_CELL_MODES", 0)
    monkeypatch.setattr(parallel, "local_cores", lambda: 2)
    monkeypatch.setattr(margins_stage, "MIN_PIECE_CELLS", 32)
    started = []
    start = margins_stage.start_margins
    monkeypatch.setattr(margins_stage, "start_margins", lambda *a: started.append(start(*a)) or started[-1])
    two = synthesize_from_data(p, progress=False, advice=advice, margins=True, abstraction_cache=tmp_path)
    assert started and started[0] is not None and started[0].from_cache  # the boxes came from the cache
    assert np.asarray(two.b_margin).tobytes() == np.asarray(one.b_margin).tobytes()
    keep = ("scales", "kept_yes", "kept_no", "solved")
    assert {k: two.margins[k] for k in keep} == {k: one.margins[k] for k in keep}
