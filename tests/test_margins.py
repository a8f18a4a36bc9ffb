"""Assumption margins of a run (``synthesis/margins.py``, ``pipeline/margins.py``; docs/margins.md).

* the scan: per cell the largest factor of B at which its class is kept at every factor up to it, NaN for
  Q_?, early stop, hand-made bounds;
* at beta = 1 the run's controller evaluated on the run's own abstraction gives the run's p_low and p_up
  bit for bit, so the margins' classes at 1 are the run's;
* monotone in beta on a pipeline run (every factor solved, no early stop): the boxes are nested, the
  Q_yes and Q_no sets shrink, p_low falls and p_up rises (to the solver's precision), and ``b_margin``
  agrees with the classes solved at every factor;
* the files (result.json with null for Q_?, result.npz, the schema, the summary), the cache (the boxes at
  larger B reused, or bounded again once), ``margins=False``, the exact transitions, refined results, the
  GP route and known dynamics (skipped with a reason), the figure and the command line switch.
"""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from robust_imdp.errors import DimensionError, InvalidInputError
from robust_imdp.synthesis.margins import MARGIN_SCALES, assumption_margins, margins_line, strategy_bounds

from test_pipeline import tiny_gp_problem, tiny_problem


# ----------------------------------------------------------------------------- the scan, by hand
def test_margins_by_hand_keep_the_largest_factor_held_throughout_and_stop_early():
    classes = np.array(["yes", "yes", "yes", "no", "no", "maybe"])
    # per factor (1.25, 1.5, 2, 3, 4): p_low of the yes cells, p_up of the no cells (threshold 0.9)
    p_low = {1.25: [0.95, 0.95, 0.80, 0.0, 0.0, 0.5], 1.5: [0.95, 0.89, 0.95, 0.0, 0.0, 0.5],
             2.0: [0.91, 0.80, 0.95, 0.0, 0.0, 0.5]}
    p_up = {1.25: [1.0, 1.0, 1.0, 0.5, 0.85, 0.95], 1.5: [1.0, 1.0, 1.0, 0.95, 0.89, 0.95],
            2.0: [1.0, 1.0, 1.0, 0.5, 0.95, 0.95]}
    p_low[3.0], p_up[3.0] = [0.5] * 6, [1.0] * 6
    p_low[4.0] = p_up[4.0] = None  # nothing is kept at 3: the scan must not ask
    calls = []

    def evaluate(s):
        calls.append(s)
        return np.array(p_low[s]), np.array(p_up[s])

    m = assumption_margins(classes, evaluate, 0.9)
    # cell 0 keeps yes up to 2 (0.91 >= 0.9); cell 1 loses it at 1.5; cell 2 at 1.25 although p_low is back
    # at 0.95 later (a margin needs the class at every factor up to it); cell 3 loses no at 1.5 and does not
    # regain it at 2; cell 4 keeps no up to 1.5 (0.89 < 0.9); the Q_? cell has none
    np.testing.assert_array_equal(m.b_margin[:5], [2.0, 1.25, 1.0, 1.25, 1.5])
    assert np.isnan(m.b_margin[5])
    assert calls == [1.25, 1.5, 2.0, 3.0] and m.solved == (1.25, 1.5, 2.0, 3.0)
    assert m.kept_yes == (3, 2, 1, 1, 0, 0) and m.kept_no == (2, 2, 1, 0, 0, 0)
    doc = m.to_dict()
    assert doc["scales"] == list(MARGIN_SCALES) and json.dumps(doc)
    line = margins_line(doc)
    assert "1 of 3 Q_yes cells stay Q_yes at 2 B" in line and "0 of 2 Q_no cells stay Q_no at 4 B" in line


def test_bad_scales_and_shapes_are_refused():
    classes = np.array(["yes", "no"])
    with pytest.raises(InvalidInputError, match="scales must increase from 1.0"):
        assumption_margins(classes, lambda s: None, 0.9, scales=(1.25, 2.0))
    with pytest.raises(InvalidInputError, match="scales must increase from 1.0"):
        assumption_margins(classes, lambda s: None, 0.9, scales=(1.0, 2.0, 2.0))
    with pytest.raises(DimensionError, match=r"evaluate\(1.25\) must give p_low and p_up of shape \(2,\)"):
        assumption_margins(classes, lambda s: (np.zeros(3), np.zeros(2)), 0.9)


# ----------------------------------------------------------------------------- a pipeline run
@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from robust_imdp.pipeline.run import synthesize_from_data

    cache = tmp_path_factory.mktemp("cache")
    res = synthesize_from_data(tiny_problem(), progress=False, abstraction_cache=cache, advice=False)
    return res, cache


def _scaled_entry(res, cache):
    from robust_imdp.pipeline.cache import _load_npz, bounds_key

    return _load_npz(cache / f"scaled-{bounds_key(res.problem)}.npz")


def _bounds(res, cache):
    from robust_imdp.pipeline.cache import _load_bounds, bounds_key

    return _load_bounds(cache / f"bounds-{bounds_key(res.problem)}.npz")[0]


def test_margin_at_beta_1_is_the_runs_classes(run):
    res, _ = run
    p_low, p_up = strategy_bounds(res.abstraction.imdp, res.partition.labels, res.partition.atoms, res.dfa,
                                  res.synthesis, outside_state=res.partition.outside_state)
    np.testing.assert_array_equal(p_low, res.synthesis.p_low)  # the same solves: the same bits
    np.testing.assert_array_equal(p_up, res.synthesis.p_up)
    cls = res.class_names
    decided = cls != "maybe"
    assert np.all(res.b_margin[decided] >= 1.0) and np.all(np.isnan(res.b_margin[~decided]))
    assert set(np.unique(res.b_margin[decided])) <= set(MARGIN_SCALES)
    doc = res.margins
    assert doc["kept_yes"][0] == res.counts["yes"] and doc["kept_no"][0] == res.counts["no"]
    assert doc["kept_yes"][1] < doc["kept_yes"][0] or doc["kept_yes"][-1] < doc["kept_yes"][0]  # not all kept
    assert "margins" in res.timings and "assumption margins" in res.summary()
    assert "margins" not in res.diagnostics  # formula-dependent: Result.margins (result.json: diagnostics.margins)


def test_margins_are_monotone_in_beta(run):
    # Every factor solved (no early stop), from the boxes the bound stage saved: nested boxes (exactly), nested
    # classes, p_low non-increasing and p_up non-decreasing up to the solver's precision (each is one end of a
    # bracket of width <= precision around the exact, monotone value), and b_margin = the largest factor with
    # the class kept at every factor up to it.
    from robust_imdp.abstraction.cell_bounds import CellBounds
    from robust_imdp.abstraction.rows import abstract

    res, cache = run
    z = _scaled_entry(res, cache)
    base = _bounds(res, cache)
    lo = np.concatenate([np.asarray(base.image_lower)[None], z["lower"]])
    hi = np.concatenate([np.asarray(base.image_upper)[None], z["upper"]])
    np.testing.assert_array_equal(z["scales"], MARGIN_SCALES[1:])
    assert np.all(np.diff(lo, axis=0) <= 0) and np.all(np.diff(hi, axis=0) >= 0)
    P, prec = res.partition, res.synthesis.precision
    lows, ups = [], []
    for j in range(len(MARGIN_SCALES)):
        ab = abstract(P, CellBounds(lo[j], hi[j], None), res.problem.noise, **res.problem.abstraction_options())
        pl, pu = strategy_bounds(ab.imdp, P.labels, P.atoms, res.dfa, res.synthesis, outside_state=P.outside_state)
        lows.append(pl)
        ups.append(pu)
    lows, ups = np.array(lows), np.array(ups)
    assert np.all(np.diff(lows, axis=0) <= 2 * prec) and np.all(np.diff(ups, axis=0) >= -2 * prec)
    thr = res.threshold
    yes, no = lows >= thr, ups < thr
    assert np.all(yes[1:] <= yes[:-1]) and np.all(no[1:] <= no[:-1])  # nested
    np.testing.assert_array_equal(yes[0], res.class_names == "yes")
    np.testing.assert_array_equal(no[0], res.class_names == "no")
    kept = np.where(res.class_names == "yes", np.cumprod(yes, axis=0), np.cumprod(no, axis=0)).astype(bool)
    expect = np.array([MARGIN_SCALES[int(np.flatnonzero(kept[:, q])[-1])] if kept[0, q] else np.nan
                       for q in range(P.n_cells)])
    np.testing.assert_array_equal(res.b_margin, expect)
    assert yes[0].sum() > yes[-1].sum()  # the larger B costs something here (the test is not vacuous)


def test_result_files_carry_b_margin(run, tmp_path):
    from robust_imdp.io.files import load_result, save_result
    from test_result_schema import SCHEMA, validate_schema

    res, _ = run
    save_result(res, tmp_path)
    doc = json.loads((tmp_path / "result.json").read_text())
    assert validate_schema(doc, SCHEMA) == []
    maybe = res.class_names == "maybe"
    assert all(v is None for v, m in zip(doc["b_margin"], maybe) if m)
    np.testing.assert_array_equal([v for v, m in zip(doc["b_margin"], maybe) if not m], res.b_margin[~maybe])
    with np.load(tmp_path / "result.npz") as z:
        np.testing.assert_array_equal(z["b_margin"], res.b_margin)  # NaN where Q_? (assert_array_equal: NaN == NaN)
    back = load_result(tmp_path)
    np.testing.assert_array_equal(back.b_margin, res.b_margin)
    assert doc["diagnostics"]["margins"] == json.loads(json.dumps(res.margins)) == back.margins
    assert margins_line(back.margins) in back.summary() and margins_line(res.margins) in res.summary()
    # a file without margins reads as None and validates
    del doc["b_margin"]
    assert validate_schema(doc, SCHEMA) == []
    (tmp_path / "result.json").write_text(json.dumps(doc))
    assert load_result(tmp_path).b_margin is None
    bad = dict(doc, b_margin=[1.75] * len(maybe))  # not a factor of the grid
    assert validate_schema(bad, SCHEMA)


def test_margins_off_and_the_cache(run, tmp_path):
    from robust_imdp.pipeline.cache import bounds_key
    from robust_imdp.pipeline.run import synthesize_from_data

    res, cache = run
    problem = tiny_problem()
    # margins off: nothing computed, nothing said
    off = synthesize_from_data(problem, progress=False, abstraction_cache=cache, advice=False, margins=False)
    assert off.b_margin is None and off.margins == {} and "margins" not in off.timings
    assert "assumption margins" not in off.summary()
    np.testing.assert_array_equal(off.synthesis.p_low, res.synthesis.p_low)
    # the abstraction and the boxes at larger B reused from the cache: the same margins
    again = synthesize_from_data(problem, progress=False, abstraction_cache=cache, advice=False)
    assert again.from_cache and "bound" not in again.timings
    np.testing.assert_array_equal(again.b_margin, res.b_margin)
    # a cache written without margins: the bound stage runs once more with them, then its boxes are reused
    fresh = tmp_path / "cache"
    synthesize_from_data(problem, progress=False, abstraction_cache=fresh, advice=False, margins=False)
    assert not (fresh / f"scaled-{bounds_key(problem)}.npz").exists()
    late = synthesize_from_data(problem, progress=False, abstraction_cache=fresh, advice=False)
    assert "bound" in late.timings and (fresh / f"scaled-{bounds_key(problem)}.npz").exists()
    np.testing.assert_array_equal(late.b_margin, res.b_margin)
    with pytest.raises(InvalidInputError, match="margins must be True or False"):
        synthesize_from_data(problem, progress=False, margins="yes")


def test_margins_with_the_exact_transitions(tmp_path):
    # the margins' abstractions go through the run's abstraction function: the exact rows here
    from robust_imdp.pipeline.run import synthesize_from_data

    res = synthesize_from_data(tiny_problem(transitions="exact"), progress=False, abstraction_cache=tmp_path,
                               advice=False)
    assert res.abstraction.transitions == "exact"
    p_low, _ = strategy_bounds(res.abstraction.imdp, res.partition.labels, res.partition.atoms, res.dfa,
                               res.synthesis, outside_state=res.partition.outside_state)
    np.testing.assert_array_equal(p_low, res.synthesis.p_low)
    decided = res.class_names != "maybe"
    assert np.all(res.b_margin[decided] >= 1.0) and np.all(np.isnan(res.b_margin[~decided]))
    assert res.margins["solved"]


def test_margins_of_a_refined_result(tmp_path):
    # refined cells get the boxes the refinement's bounder certified for them at every factor (no fallback
    # to the grid cell when this run bounded them), and the margins are the run's classes at 1
    from robust_imdp.models.geometry import BoxPartition
    from robust_imdp.pipeline.run import synthesize_from_data

    problem = tiny_problem(refine={"max_cells": 120, "max_rounds": 2, "growth": 0.5})
    res = synthesize_from_data(problem, progress=False, abstraction_cache=tmp_path, advice=False)
    P = res.partition
    assert isinstance(P, BoxPartition) and P.depth.max() >= 1 and res.b_margin.shape == (P.n_cells,)
    doc = res.margins
    assert "refined_from_grid_cell" not in doc and doc["kept_yes"][0] == res.counts["yes"]
    decided = res.class_names != "maybe"
    assert np.all(res.b_margin[decided] >= 1.0) and np.all(np.isnan(res.b_margin[~decided]))
    # the refined abstraction reused from the cache: the refined cells fall back to their grid cell's boxes
    # (sound, looser: never a larger margin)
    again = synthesize_from_data(problem, progress=False, abstraction_cache=tmp_path, advice=False)
    assert again.margins["refined_from_grid_cell"] == int(np.sum(P.depth > 0))
    assert np.all(np.nan_to_num(again.b_margin) <= np.nan_to_num(res.b_margin))


def test_margins_are_skipped_with_a_reason_on_the_gp_route_and_for_known_dynamics():
    from robust_imdp.pipeline.margins import run_margins, skip_reason

    gp = tiny_gp_problem()
    why = skip_reason(gp)
    assert "chowdhury" in why and "'optimal' or 'ridge'" in why
    assert run_margins(gp, None, None, None, None, None, _quiet(), None, None, abstract=None,
                       learn_and_bound=None) == (None, {"skipped": why})
    assert skip_reason(tiny_problem()) is None
    assert "known dynamics" in skip_reason(SimpleNamespace(known=True))  # Problem.known: every component known
    assert margins_line({"skipped": why}) == f"assumption margins: not computed ({why})"


def _quiet():
    from robust_imdp.pipeline.runtime import _Log

    return _Log(False)


# ----------------------------------------------------------------------------- figure and command line
def test_margin_map(run, tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    from robust_imdp.plotting import plot_margins, save_figures

    res, _ = run
    ax = plot_margins(res)
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert len(labels) == len(MARGIN_SCALES) + 2
    n_at_4 = int(np.sum((res.class_names == "yes") & (res.b_margin == 4.0)))
    assert f"Q_yes up to 4 B: {n_at_4}" in labels
    written = save_figures(res, tmp_path)
    assert tmp_path / "b_margin.png" in written
    from robust_imdp.io.files import load_result, save_result

    save_result(res, tmp_path / "r")
    doc = json.loads((tmp_path / "r" / "result.json").read_text())
    del doc["b_margin"]
    with pytest.raises(InvalidInputError, match="no assumption margins"):
        plot_margins(doc)
    assert "b_margin.png" not in {p.name for p in save_figures(doc, tmp_path / "none")}
    assert load_result(tmp_path / "r").b_margin is not None


def test_command_line_switch():
    from robust_imdp.cli import RESULT_OUTPUTS, _parser

    p = _parser()
    assert p.parse_args(["run", "p.toml", "--out", "o"]).margins == "on"
    assert p.parse_args(["run", "p.toml", "--out", "o", "--margins", "off"]).margins == "off"
    assert "b_margin.png" in RESULT_OUTPUTS


def test_margins_of_a_k_step_result(tmp_path):
    # a time-varying controller (k, n_cells, S): evaluated with its horizon, the run's p_low and p_up at beta = 1
    from robust_imdp.pipeline.run import synthesize_from_data

    res = synthesize_from_data(tiny_problem(horizon=6), progress=False, abstraction_cache=tmp_path, advice=False)
    assert np.asarray(res.synthesis.strategy).ndim == 3
    p_low, p_up = strategy_bounds(res.abstraction.imdp, res.partition.labels, res.partition.atoms, res.dfa,
                                  res.synthesis, outside_state=res.partition.outside_state)
    np.testing.assert_array_equal(p_low, res.synthesis.p_low)
    np.testing.assert_array_equal(p_up, res.synthesis.p_up)
    decided = res.class_names != "maybe"
    assert np.all(res.b_margin[decided] >= 1.0) and res.margins["kept_yes"][0] == res.counts["yes"]
