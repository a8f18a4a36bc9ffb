"""k-step synthesis: the tie keys read the per-step row values an earlier solve kept (solvers.engine.StepRows).

A k-step synthesis iterates the optimistic values U_t in its optimistic solve and again in the keys of the nominal
and the robust solves, and the nominal values in the nominal solve and again in the robust solve's key. With
``keep_steps`` the optimistic and the nominal solves keep the row values of their upper sweeps and the keys read
them. These tests pin that what is read is bit for bit what the key's own sweeps compute (every step, both
readings), that the synthesis gives the same bits with and without the reuse (and does fewer sweeps), that a
record serves only the sweeps it was made by, and -- the teeth -- that a perturbed record does change the strategy,
so the comparisons above would catch a wrong reuse.
"""

import numpy as np
import pytest

from robust_imdp.solvers import engine, product
from robust_imdp.solvers import sweep as sweep_module
from robust_imdp.solvers.common import Control
from robust_imdp.solvers.sweep import Sweeper
from robust_imdp.spec.dfa import ltlf_to_dfa
from robust_imdp._fp import complement_down
from robust_imdp.errors import InvalidInputError
from robust_imdp.synthesis.core import remap_letters, synthesize

from test_nominal_ties import ATOMS, LABELS, NORTH, EAST, S, obstacle_models
from test_synthesis import random_imdp


def _random_case(seed, semantics):
    """A random robust model, an unrelated random nominal model, labels and the DFA (test_nominal_ties' worst
    case for the keys)."""
    rng = np.random.default_rng(seed)
    n_cells = 8
    imdp = random_imdp(rng, n_cells + 1, 3, width=0.15)
    nominal = random_imdp(rng, n_cells + 1, 3, width=0.0)
    labels = rng.choice([0, 0, 1, 2, 4, 6], size=n_cells)
    dfa = ltlf_to_dfa("G !o & F d1 & F d2" if semantics == "reach" else "G !o")
    return imdp, nominal, labels, ("o", "d1", "d2"), dfa, n_cells


def _letters(labels, atoms, dfa):
    """The product's letters: the cells' labels over the DFA's atoms, then the outside state's (never read)."""
    return np.append(remap_letters(labels, atoms, dfa.atoms), 0)


def _engine_arrays(imdp, letters, dfa, avoid, semantics):
    """(nxt, V0, active) of the engine for the product (as solve_layered builds them)."""
    nxt, target, zero, _ = product._dfa_arrays(imdp, letters, dfa, avoid)
    if semantics == "safety":
        target, zero = product._safety_nodes(target, zero)
    target = target & ~zero
    return nxt, target.astype(np.float64), ~(target | zero)


@pytest.mark.parametrize("semantics", ["reach", "safety"])
@pytest.mark.parametrize("adversary", ["optimistic", "pessimistic"])
def test_kept_rows_are_the_key_sweeps_rows_at_every_step(semantics, adversary):
    """The rows a solve keeps are, at every step t, the rows of a key sweep of the same model and adversary
    against the key's own (t-1)-step values, bit for bit; and its last upper values are the key's k-step values."""
    imdp, _, labels, atoms, dfa, n_cells = _random_case(3, semantics)
    letters = _letters(labels, atoms, dfa)
    avoid = np.array([n_cells])
    k = 5
    res = product.solve_product(imdp, letters, dfa, avoid=avoid, adversary=adversary, horizon=k, semantics=semantics,
                                keep_steps=True)
    steps = res.steps
    assert isinstance(steps, engine.StepRows) and steps.rows.shape == (k, dfa.n_states * imdp.n_choices)
    nxt, V0, active = _engine_arrays(imdp, letters, dfa, avoid, semantics)
    safety = semantics == "safety"
    ctrl = Control.MINIMISE if safety else Control.MAXIMISE
    adv_max = (adversary == "optimistic") != safety  # the key's adversary in the engine's terms (product._engine_ties)
    assert steps.serves(imdp, nxt, active, V0, ctrl, adv_max, k)
    key = Sweeper(imdp, nxt, active, ctrl, adv_max, None)
    v = V0.copy()
    for t in range(1, k + 1):
        v, _, rows = key.sweep(v, +1, want_rows=True)
        np.testing.assert_array_equal(steps.rows[t - 1], rows)  # the same bits, -inf on rows not swept
        assert np.isfinite(rows).any()
    # the key's k-step values are the solve's upper ones (under safety complemented into its lower end)
    np.testing.assert_array_equal(res.lower if safety else res.upper, complement_down(v) if safety else v)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("semantics, with_nominal", [("reach", True), ("reach", False), ("safety", True)])
def test_synthesis_with_reuse_equals_recomputation(seed, semantics, with_nominal, monkeypatch):
    """The keys' rows of every decision, p_low, p_up, p_up_star, error and the strategy are the same bits whether
    the keys read the kept rows or sweep again (STEP_ROWS_MAX = 0: nothing kept), and the reuse saves 3 full sweeps per step with a nominal
    model (its key of the optimistic values, the robust solve's two keys), 1 without (the robust solve's key; the
    safety reading takes no keys without a nominal model)."""
    imdp, nominal, labels, atoms, dfa, n_cells = _random_case(seed, semantics)
    k = 4
    kw = dict(threshold=0.3, horizon=k, outside_state=n_cells, semantics=semantics,
              nominal=nominal if with_nominal else None)
    counts = {True: [0], False: [0]}
    orig = sweep_module.Sweeper.sweep

    def counted(self, V, direction, *a, **kk):
        if self.strategy is None:
            counts[current[0]][0] += len(self.layers)
        return orig(self, V, direction, *a, **kk)

    # the keys' rows every decision reads, in order: the reused ones must be the recomputed ones, bit for bit
    seen = {True: [], False: []}
    orig_rank = engine._key_rank

    def recorded(rows, maximise=True):
        seen[current[0]].append([np.array(r, copy=True) for r in rows])
        return orig_rank(rows, maximise)

    current = [True]
    monkeypatch.setattr(sweep_module.Sweeper, "sweep", counted)
    monkeypatch.setattr(engine, "_key_rank", recorded)
    try:
        reused = synthesize(imdp, labels, atoms, dfa, **kw)
    except Exception as exc:  # a reading the labels decide alone (VacuousSpecificationError): nothing to choose
        pytest.skip(str(exc))
    current[0] = False
    monkeypatch.setattr(engine, "STEP_ROWS_MAX", 0)
    again = synthesize(imdp, labels, atoms, dfa, **kw)
    assert len(seen[True]) == len(seen[False]) >= k
    for mine, theirs in zip(seen[True], seen[False]):
        assert len(mine) == len(theirs)
        for a, b in zip(mine, theirs):
            np.testing.assert_array_equal(a, b)
    for name in ("p_low", "p_up", "p_up_star", "error", "strategy"):
        np.testing.assert_array_equal(getattr(reused, name), getattr(again, name), err_msg=name)
    assert [(r.name, r.iterations, r.ends) for r in reused.runs] == [(r.name, r.iterations, r.ends)
                                                                     for r in again.runs]
    np.testing.assert_array_equal([r.max_gap for r in reused.runs], [r.max_gap for r in again.runs])
    layers = counts[False][0] - counts[True][0]
    saved_per_layer_step = 2 if with_nominal else 1
    assert layers > 0 and layers % (saved_per_layer_step * k) == 0, (counts, with_nominal)


def test_a_record_serves_only_the_sweeps_it_was_made_by():
    """Another model (even with equal arrays), adversary, controller, node set, start or a longer horizon: the
    record does not serve, and the key is iterated (the same result as without the record)."""
    imdp, nominal, labels, atoms, dfa, n_cells = _random_case(1, "reach")
    letters = _letters(labels, atoms, dfa)
    avoid = np.array([n_cells])
    res = product.solve_product(imdp, letters, dfa, avoid=avoid, adversary="optimistic", horizon=3, keep_steps=True)
    st = res.steps
    nxt, V0, active = _engine_arrays(imdp, letters, dfa, avoid, "reach")
    ok = (imdp, nxt, active, V0, Control.MAXIMISE, True, 3)
    assert st.serves(*ok) and st.serves(imdp, nxt, active, V0, Control.MAXIMISE, True, 2)
    twin = type(imdp).from_csr(imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.lower, imdp.upper, imdp.floor)
    fewer = active.copy()
    fewer[np.argwhere(active)[0][0], np.argwhere(active)[0][1]] = False
    bad = [(twin,) + ok[1:], (nominal,) + ok[1:], ok[:5] + (False,) + ok[6:], ok[:4] + (Control.MINIMISE,) + ok[5:],
           ok[:2] + (fewer,) + ok[3:], ok[:3] + (1.0 - V0,) + ok[4:], ok[:6] + (4,)]
    for args in bad:
        assert not st.serves(*args)
    # a longer solve than the record: recomputed, and the same as without any record
    with_rec = product.solve_product(imdp, letters, dfa, avoid=avoid, horizon=5, tie_break=res)
    plain = product.solve_product(imdp, letters, dfa, avoid=avoid, horizon=5,
                                  tie_break=product.solve_product(imdp, letters, dfa, avoid=avoid,
                                                                  adversary="optimistic", horizon=5))
    np.testing.assert_array_equal(with_rec.strategy, plain.strategy)


def test_nothing_kept_beyond_the_cap_or_for_a_fixed_strategy(monkeypatch):
    imdp, _, labels, atoms, dfa, n_cells = _random_case(2, "reach")
    letters = _letters(labels, atoms, dfa)
    pk = dict(avoid=np.array([n_cells]), horizon=3)
    assert product.solve_product(imdp, letters, dfa, **pk).steps is None  # not asked
    res = product.solve_product(imdp, letters, dfa, keep_steps=True, **pk)
    assert res.steps is not None and not res.steps.rows.flags.writeable
    ev = product.evaluate_product_strategy(imdp, letters, dfa, res.strategy, **pk)
    assert ev.steps is None
    monkeypatch.setattr(engine, "STEP_ROWS_MAX", 3 * dfa.n_states * imdp.n_choices - 1)
    assert product.solve_product(imdp, letters, dfa, keep_steps=True, **pk).steps is None


@pytest.mark.parametrize("semantics", ["reach"])
def test_a_perturbed_record_changes_the_strategy(semantics):
    """The teeth: where the robust lower values tie at 0 the nominal key decides (north, round the obstacle); fed
    a record of the nominal solve whose rows are perturbed (negated: the ranking reversed) the robust solve goes
    east. So the bit-for-bit comparisons above would see a wrong record."""
    robust, nominal, _ = obstacle_models()
    dfa = ltlf_to_dfa("G !obstacle & F goal")
    letters = np.append(LABELS, 0)
    pk = dict(avoid=np.array([4]), horizon=3)
    opt = product.solve_product(robust, letters, dfa, adversary="optimistic", keep_steps=True, **pk)
    opt_key = product.TieKey(robust, opt, "optimistic")
    nom = product.solve_product(nominal, letters, dfa, tie_break=product.Ties((opt_key,)), keep_steps=True, **pk)
    s0 = int(opt.initial_state[S])

    def first_move(nom_result):
        ties = product.Ties((product.TieKey(nominal, nom_result, "pessimistic"), opt_key))
        return int(product.solve_product(robust, letters, dfa, tie_break=ties, **pk).strategy[0, s0, S])

    assert first_move(nom) == NORTH
    rows = -np.asarray(nom.steps.rows)
    bad = engine.StepRows(model=nom.steps.model, nxt=nom.steps.nxt, active=nom.steps.active, V0=nom.steps.V0,
                          ctrl=nom.steps.ctrl, adv_max=nom.steps.adv_max, rows=rows)
    from dataclasses import replace
    assert first_move(replace(nom, steps=bad)) == EAST


# --------------------------------------------------------------------------- k steps: only the ends that are read
def _full_and_part(imdp, letters, dfa, pk, need, **kw):
    return (product.solve_product(imdp, letters, dfa, **pk, **kw),
            product.solve_product(imdp, letters, dfa, **pk, **kw, need=need))


@pytest.mark.parametrize("semantics", ["reach", "safety"])
@pytest.mark.parametrize("adversary", ["optimistic", "pessimistic"])
def test_a_solve_of_some_ends_gives_their_bits_and_trivial_sound_others(semantics, adversary):
    """With ``need`` a k-step solve gives the needed ends (and the strategy, when needed) bit for bit as the full
    solve, and the others as their trivial bounds, which bracket the full solve's (0 <= lower, upper <= 1, the
    fixed nodes exact)."""
    imdp, _, labels, atoms, dfa, n_cells = _random_case(5, semantics)
    letters = _letters(labels, atoms, dfa)
    pk = dict(avoid=np.array([n_cells]), horizon=4, semantics=semantics, adversary=adversary)
    for need in [("lower",), ("upper",), ("lower", "strategy"), ("upper", "strategy"), ()]:
        full, part = _full_and_part(imdp, letters, dfa, pk, need)
        assert full.ends == "both"
        for end in ("lower", "upper"):
            if end in need:
                np.testing.assert_array_equal(getattr(part, end), getattr(full, end))
        if "strategy" in need:
            np.testing.assert_array_equal(part.strategy, full.strategy)
        assert np.all(part.lower <= full.lower) and np.all(part.upper >= full.upper)
        assert np.all(part.lower >= 0.0) and np.all(part.upper <= 1.0)
        assert part.ends in ("both", "lower", "upper")
        if part.ends == "both":
            assert part.precision == full.precision
        for end in ("lower", "upper"):
            if end not in need and part.ends != "both" and part.ends != end:
                # a trivial end: the fixed nodes' values (0 or 1) and 0 / 1 elsewhere
                assert set(np.unique(getattr(part, end))) <= {0.0, 1.0}
    # evaluations of a fixed strategy likewise
    st = product.solve_product(imdp, letters, dfa, **{**pk, "adversary": "pessimistic"}).strategy
    for need in [("lower",), ("upper",)]:
        full = product.evaluate_product_strategy(imdp, letters, dfa, st, **pk)
        part = product.evaluate_product_strategy(imdp, letters, dfa, st, **pk, need=need)
        np.testing.assert_array_equal(getattr(part, need[0]), getattr(full, need[0]))
        assert part.ends == need[0] and np.all(part.lower <= full.lower) and np.all(part.upper >= full.upper)


def test_need_names_its_parts():
    imdp, _, labels, atoms, dfa, n_cells = _random_case(0, "reach")
    with pytest.raises(InvalidInputError, match="need"):
        product.solve_product(imdp, _letters(labels, atoms, dfa), dfa, avoid=np.array([n_cells]), horizon=2,
                              need=("lower", "values"))


@pytest.mark.parametrize("semantics", ["reach", "safety"])
def test_synthesis_runs_say_which_ends_they_iterated(semantics):
    """k steps: the robust solve iterates its lower end (and under safety, where its strategy comes from the
    engine's other end, both), the evaluation against the pessimistic adversary both (its width is the safeguard's
    tolerance); a one-ended run reports max_gap nan, a two-ended one its width. Unbounded: every run both."""
    imdp, nominal, labels, atoms, dfa, n_cells = _random_case(1, semantics)
    for horizon in (3, None):
        res = synthesize(imdp, labels, atoms, dfa, threshold=0.3, horizon=horizon, outside_state=n_cells,
                         semantics=semantics, nominal=nominal)
        runs = {r.name: r for r in res.runs}
        if horizon is None:
            assert all(r.ends == "both" and np.isfinite(r.max_gap) for r in res.runs)
            continue
        assert runs["evaluate_pessimistic"].ends == "both"
        assert runs["robust"].ends == ("lower" if semantics == "reach" else "both")
        assert runs["evaluate_optimistic"].ends == "upper" and runs["nominal"].ends != "both"
        for r in res.runs:
            assert np.isnan(r.max_gap) == (r.ends != "both")
