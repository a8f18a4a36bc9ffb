"""Tests of robust synthesis on hand-built IMDPs.

``bruteforce_solve`` below is an independent, deliberately naive product solver (dense
intervals, Python loops, ordering-based inner problem, plain value iteration): an oracle for
the numbers of ``robust_imdp.solvers.product`` on small random models, next to hand-derived cases.
"""

import importlib
from types import SimpleNamespace

import numpy as np
import pytest

from robust_imdp.spec.dfa import ltlf_to_dfa
from robust_imdp.errors import DimensionError, InvalidInputError, SoundnessError, UnknownAtomError
from robust_imdp.models.imdp import IMDP
from robust_imdp.synthesis.core import SynthesisResult, remap_letters, synthesize

from soundness_checks import check_synthesis


# --------------------------------------------------------------------------- brute-force oracle
def _inner(w, lo, up, maximize):
    """Ordering solution of min/max p.w over {lo <= p <= up, sum p = 1} (Givan et al. 2000)."""
    order = np.argsort(-w if maximize else w, kind="stable")
    p, rem = lo.copy(), 1.0 - lo.sum()
    for j in order:
        add = min(up[j] - lo[j], rem)
        p[j] += add
        rem -= add
    return float(p @ w)


def bruteforce_solve(imdp, letters, dfa, *, avoid=None, adversary="pessimistic", horizon=None,
                     precision=1e-8, strategy=None):
    """Value iteration on the product: (s, q) -u-> (delta(s, L(q')), q'); avoid states value 0."""
    lo, up = imdp.to_dense()
    n, S = imdp.n_states, dfa.n_states
    letters = np.asarray(letters)
    nxt = dfa.delta[:, letters]  # (S, n): DFA state after entering q'
    maximize = str(getattr(adversary, "value", adversary)).lower() == "optimistic"
    avoid_mask = np.zeros(n, bool)
    if avoid is not None:
        avoid_mask[np.asarray(avoid)] = True
    base = np.zeros((S, n))
    base[dfa.accepting] = 1.0
    base[:, avoid_mask] = 0.0  # the outside state is never accepting

    def bellman(V, fixed):
        newV, choice = base.copy(), np.zeros((S, n), dtype=np.int64)
        for s in np.flatnonzero(~dfa.accepting):
            w = V[nxt[s], np.arange(n)]
            for q in np.flatnonzero(~avoid_mask):
                rows = range(imdp.state_ptr[q], imdp.state_ptr[q + 1])
                vals = [_inner(w, lo[r], up[r], maximize) for r in rows]
                c = int(np.argmax(vals)) if fixed is None else int(fixed[s, q])
                newV[s, q], choice[s, q] = vals[c], c
        return newV, choice

    V, it = base.copy(), 0
    if horizon is None:
        while True:
            newV, choice = bellman(V, strategy)
            it += 1
            if np.max(np.abs(newV - V)) < precision * 1e-3:
                break
            V = newV
        V, strat = newV, choice
    else:
        strat = np.zeros((horizon, S, n), dtype=np.int64)
        for t in range(horizon):
            V, strat[horizon - 1 - t] = bellman(V, None if strategy is None else strategy[horizon - 1 - t])
            it += 1
    init = dfa.delta[dfa.initial, letters]
    iv = V[init, np.arange(n)]
    return SimpleNamespace(lower=V, upper=V, strategy=strat, initial_state=init, initial_lower=iv,
                           initial_upper=iv, iterations=it, precision=precision, converged=True)


def bruteforce_evaluate(imdp, letters, dfa, strategy, **kw):
    return bruteforce_solve(imdp, letters, dfa, strategy=np.asarray(strategy), **kw)


@pytest.fixture
def product_module():
    return importlib.import_module("robust_imdp.solvers.product")


# --------------------------------------------------------------------------- hand-built model
def reach_avoid_imdp():
    """Cells 0 (free), 1 (obs), 2 (des) and the outside state 3; two modes.

    cell 0, mode 0: -> des [0.5, 0.7], -> obs [0.3, 0.5]
    cell 0, mode 1: -> self [0.2, 0.4], -> des [0.4, 0.6], -> outside [0, 0.2]
    cells 1, 2 and the outside state loop on themselves under both modes.
    """
    n, a = 4, 2
    lo, up = np.zeros((n, a, n)), np.zeros((n, a, n))
    lo[0, 0, 2], up[0, 0, 2], lo[0, 0, 1], up[0, 0, 1] = 0.5, 0.7, 0.3, 0.5
    lo[0, 1, 0], up[0, 1, 0], lo[0, 1, 2], up[0, 1, 2], up[0, 1, 3] = 0.2, 0.4, 0.4, 0.6, 0.2
    for q in (1, 2, 3):
        lo[q, :, q] = up[q, :, q] = 1.0
    return IMDP.from_dense(lo, up)


ATOMS = ("obs", "des")  # partition order differs from the DFA's sorted ("des", "obs")
LABELS = np.array([0, 1, 2])  # cell 1: obs (bit 0), cell 2: des (bit 1)
SPEC = "G !obs & F des"


def test_hand_built_unbounded():
    dfa = ltlf_to_dfa(SPEC)
    res = synthesize(reach_avoid_imdp(), LABELS, ATOMS, dfa, threshold=0.9, outside_state=3)
    # cell 0, mode 1 against the minimising adversary: 0.2 to outside, 0.4 back, 0.4 to des:
    # v = 0.4 v + 0.4 -> 2/3 > 0.5 (mode 0's worst case); maximising adversary: v = 0.4 v + 0.6 = 1.
    # cell 1 starts in the DFA sink (first label obs), cell 2 in the accepting state (first label des).
    np.testing.assert_allclose(res.p_low, [2 / 3, 0, 1], atol=1e-6)  # tolerance: precision 1e-8 + VI
    np.testing.assert_allclose(res.p_up, [1, 0, 1], atol=1e-6)
    np.testing.assert_allclose(res.p_up_star, [1, 0, 1], atol=1e-6)
    assert res.classes.tolist() == ["maybe", "no", "yes"]
    assert res.initial_dfa_state.tolist() == [0, 2, 1]
    assert res.labels.tolist() == [0, 2, 1]  # remapped to ("des", "obs")
    assert res.strategy.shape == (3, dfa.n_states) and res.strategy[0, 0] == 1
    assert res.horizon is None and res.threshold == 0.9 and res.n_modes == 2
    assert np.all(res.error >= res.p_up_star - res.p_low)
    assert res.class_counts() == {"yes": 1, "no": 1, "maybe": 1}


def test_hand_built_k_step_strategy_depends_on_time():
    dfa = ltlf_to_dfa(SPEC)
    imdp = reach_avoid_imdp()
    r1 = synthesize(imdp, LABELS, ATOMS, dfa, threshold=0.55, horizon=1, outside_state=3)
    # one step: mode 0 reaches des with [0.5, 0.7], mode 1 with [0.4, 0.6]
    np.testing.assert_allclose(r1.p_low, [0.5, 0, 1], atol=1e-9)
    np.testing.assert_allclose(r1.p_up, [0.7, 0, 1], atol=1e-9)
    np.testing.assert_allclose(r1.p_up_star, [0.7, 0, 1], atol=1e-9)
    assert r1.classes.tolist() == ["maybe", "no", "yes"]
    r2 = synthesize(imdp, LABELS, ATOMS, dfa, threshold=0.55, horizon=2, outside_state=3)
    # two steps: mode 1 first (0.4 des + 0.4 back x 0.5 = 0.6), then mode 0
    np.testing.assert_allclose(r2.p_low, [0.6, 0, 1], atol=1e-9)
    assert r2.strategy.shape == (2, 3, dfa.n_states)
    assert r2.strategy[0, 0, 0] == 1 and r2.strategy[1, 0, 0] == 0
    assert r2.classes.tolist() == ["yes", "no", "yes"]


def random_imdp(rng, n, a, width):
    """Random intervals of half-width ``width`` around a random distribution over the cells,
    plus a leak [0, width] to the absorbing outside state ``n - 1``."""
    p = rng.dirichlet(np.ones(n - 1) * 0.5, size=(n - 1, a))
    p[p < 0.05] = 0.0
    p /= p.sum(axis=2, keepdims=True)
    lo, up = np.zeros((n, a, n)), np.zeros((n, a, n))
    lo[:-1, :, :-1] = np.clip(p - width, 0, 1) * (p > 0)
    up[:-1, :, :-1] = np.clip(p + width, 0, 1) * (p > 0)
    up[:-1, :, -1] = width
    lo[-1, :, -1] = up[-1, :, -1] = 1.0
    return IMDP.from_dense(lo, up)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("horizon", [None, 3])
def test_random_bounds_ordered_and_equal_to_evaluation(seed, horizon, product_module):
    rng = np.random.default_rng(seed)
    n_cells = 6
    imdp = random_imdp(rng, n_cells + 1, 2, width=0.1)
    atoms = ("o", "d1", "d2")
    labels = rng.choice([0, 1, 2, 4, 6], size=n_cells)
    dfa = ltlf_to_dfa("G !o & F d1 & F d2")
    thr = 0.3
    res = synthesize(imdp, labels, atoms, dfa, threshold=thr, horizon=horizon, outside_state=n_cells)
    # ordering holds exactly (no tolerance): by construction, see synthesis module docstring
    assert np.all(res.p_low <= res.p_up) and np.all(res.p_up <= res.p_up_star)
    assert np.all((0 <= res.p_low) & (res.p_up_star <= 1))
    np.testing.assert_array_equal(res.error >= res.p_up_star - res.p_low, True)
    # p_low is the evaluation of the returned strategy against the minimising adversary
    letters = np.append(res.labels, 0)
    pi = res.strategy.T if horizon is None else np.transpose(res.strategy, (0, 2, 1))
    pi = np.concatenate([pi, np.zeros(pi.shape[:-1] + (1,), dtype=np.int64)], axis=-1)
    ev = product_module.evaluate_product_strategy(
        imdp, letters, dfa, pi, avoid=np.array([n_cells]), adversary="pessimistic", horizon=horizon)
    np.testing.assert_array_equal(res.p_low, np.asarray(ev.initial_lower)[:n_cells])
    # the brute-force oracle agrees within the solvers' precision (1e-8 target; 1e-6 allows VI slack)
    bf = bruteforce_evaluate(imdp, letters, dfa, pi, avoid=[n_cells], adversary="pessimistic", horizon=horizon)
    np.testing.assert_allclose(res.p_low, bf.initial_lower[:n_cells], atol=1e-6)
    bf_up = bruteforce_solve(imdp, letters, dfa, avoid=[n_cells], adversary="optimistic", horizon=horizon)
    np.testing.assert_allclose(res.p_up_star, bf_up.initial_upper[:n_cells], atol=1e-6)
    # p_up bounds pi's value against the maximising adversary (sensitivity of this check:
    # test_sensitivity.py, test_synthesis_check_sees_a_shrink)
    bf_opt = bruteforce_evaluate(imdp, letters, dfa, pi, avoid=[n_cells], adversary="optimistic", horizon=horizon)
    assert check_synthesis(res.p_low, res.p_up, res.p_up_star, bf.initial_lower[:n_cells],
                           bf_opt.initial_lower[:n_cells], bf_up.initial_upper[:n_cells], 1e-6) == \
        {"p_low": 0, "p_up": 0, "p_up_star": 0}
    # classification follows the definition
    assert np.array_equal(res.classes == "yes", res.p_low >= thr)
    assert np.array_equal(res.classes == "no", res.p_up < thr)
    # the strategy only uses existing modes
    assert res.strategy.min() >= 0 and res.strategy.max() < 2


def test_p_up_is_capped_by_p_up_star(monkeypatch, product_module):
    """If the evaluation's upper end is looser than p_up_star, p_up takes the smaller sound bound."""
    real_eval = product_module.evaluate_product_strategy

    def loose_eval(*args, **kw):
        r = real_eval(*args, **kw)
        if kw.get("adversary") == "optimistic":
            return SimpleNamespace(**{**vars(r), "initial_upper": np.ones_like(r.initial_upper)})
        return r

    monkeypatch.setattr(product_module, "evaluate_product_strategy", loose_eval, raising=False)
    res = synthesize(reach_avoid_imdp(), LABELS, ATOMS, ltlf_to_dfa(SPEC), threshold=0.5, outside_state=3)
    np.testing.assert_array_equal(res.p_up, res.p_up_star)  # 1 capped to p_up_star (cell 1: 0)
    assert res.p_up[1] == 0


def test_inconsistent_brackets_raise_soundness_error(monkeypatch, product_module):
    real_eval = product_module.evaluate_product_strategy

    def bad_eval(*args, **kw):
        r = real_eval(*args, **kw)
        if kw.get("adversary") == "pessimistic":
            return SimpleNamespace(**{**vars(r), "initial_lower": np.ones_like(r.initial_lower)})
        return r

    monkeypatch.setattr(product_module, "evaluate_product_strategy", bad_eval, raising=False)
    with pytest.raises(SoundnessError, match=r"cell \d: p_low = 1.0 > p_up = 0"):
        synthesize(reach_avoid_imdp(), LABELS, ATOMS, ltlf_to_dfa(SPEC), threshold=0.5, outside_state=3)


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("thr", [-0.1, 1.5, float("nan"), True, "0.5"])
def test_threshold_outside_unit_interval(thr):
    with pytest.raises(InvalidInputError, match="threshold must be a probability in \\[0, 1\\]"):
        synthesize(reach_avoid_imdp(), LABELS, ATOMS, ltlf_to_dfa(SPEC), threshold=thr, outside_state=3)


def test_unknown_atoms_named_with_known_labels():
    with pytest.raises(UnknownAtomError, match=r"\['goal'\] that no region defines; known labels are \['obs', 'des'\]"):
        synthesize(reach_avoid_imdp(), LABELS, ATOMS, ltlf_to_dfa("F goal"), threshold=0.5, outside_state=3)


def test_wrong_label_lengths_and_outside_state():
    dfa = ltlf_to_dfa(SPEC)
    with pytest.raises(DimensionError, match=r"outside_state must be n_cells = len\(labels\) = 2"):
        synthesize(reach_avoid_imdp(), LABELS[:2], ATOMS, dfa, threshold=0.5, outside_state=3)
    with pytest.raises(DimensionError, match=r"labels must have one entry per IMDP state \(4\)"):
        synthesize(reach_avoid_imdp(), LABELS, ATOMS, dfa, threshold=0.5)
    with pytest.raises(DimensionError, match="labels must be a 1-D"):
        synthesize(reach_avoid_imdp(), LABELS[None], ATOMS, dfa, threshold=0.5, outside_state=3)
    with pytest.raises(InvalidInputError, match=r"labels\[2\] = 4"):
        synthesize(reach_avoid_imdp(), [0, 1, 4], ATOMS, dfa, threshold=0.5, outside_state=3)
    with pytest.raises(InvalidInputError, match="horizon must be None"):
        synthesize(reach_avoid_imdp(), LABELS, ATOMS, dfa, threshold=0.5, outside_state=3, horizon=0)


def test_remap_letters():
    # bit i over ("a", "b", "c") -> bit j over ("c", "a")
    out = remap_letters([0b001, 0b100, 0b111, 0b010], ("a", "b", "c"), ("c", "a"))
    assert out.tolist() == [0b10, 0b01, 0b11, 0b00]


def test_result_is_frozen():
    res = synthesize(reach_avoid_imdp(), LABELS, ATOMS, ltlf_to_dfa(SPEC), threshold=0.5, outside_state=3)
    assert isinstance(res, SynthesisResult)
    with pytest.raises(AttributeError):
        res.threshold = 0.1
    with pytest.raises(ValueError, match="read-only"):
        res.p_low[0] = 0.0
