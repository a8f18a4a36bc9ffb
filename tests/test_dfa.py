"""Tests of the DFA type and of the LTLf -> minimal DFA translation.

Oracle: the direct finite-trace semantics ``robust_imdp.spec.ltlf.holds`` (dynamic programming over
the trace, no automaton), on every non-empty trace up to length 6 over 2 atoms, and on every
trace up to length 4 plus seeded random traces of length 5-6 over 3 atoms (8**6 traces per
formula would take too long). Minimality is checked by brute-force language comparison.
"""

import itertools
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robust_imdp.spec.dfa import DFA, ltlf_to_dfa, minimize
from robust_imdp.errors import DimensionError, InvalidInputError, InvalidModelError, UnknownAtomError
from robust_imdp.spec.ltlf import Not, holds, parse

from test_ltlf import formulas


def all_traces(atoms, max_len):
    letters = [frozenset(a for i, a in enumerate(atoms) if m >> i & 1) for m in range(2 ** len(atoms))]
    for n in range(1, max_len + 1):
        yield from (list(t) for t in itertools.product(letters, repeat=n))


def state_signatures(dfa, max_len):
    """(n_states, n_words) bool: acceptance from each state of every word of length <= max_len."""
    cols = [dfa.accepting.copy()]  # the empty word
    cur = np.arange(dfa.n_states)[:, None]
    for _ in range(max_len):
        cur = dfa.delta[cur].reshape(dfa.n_states, -1)  # extend every word by every letter
        cols.append(dfa.accepting[cur])
    return np.hstack([c.reshape(dfa.n_states, -1) for c in cols])


def assert_minimal(dfa):
    # all states reachable from the initial state
    seen, frontier = {dfa.initial}, [dfa.initial]
    while frontier:
        frontier = [int(t) for s in frontier for t in dfa.delta[s] if int(t) not in seen]
        seen.update(frontier)
    assert len(seen) == dfa.n_states
    # pairwise distinguishable: words of length <= n_states - 1 suffice (Moore), capped for speed
    # (a cap can only make this check fail spuriously, never pass wrongly)
    k = dfa.n_states - 1
    while k > 1 and dfa.n_letters**k > 40000:
        k -= 1
    sig = state_signatures(dfa, k)
    assert len(np.unique(sig, axis=0)) == dfa.n_states


@pytest.mark.parametrize(
    "text, size",
    [("G !obs & F des", 3), ("F des", 2), ("G !o & F d1 & F d2", 5), ("true", 1), ("false", 1)],
)
def test_reference_sizes(text, size):
    dfa = ltlf_to_dfa(text)
    assert dfa.n_states == size
    assert dfa.initial == 0
    assert_minimal(dfa)


def test_reach_avoid_structure():
    dfa = ltlf_to_dfa("G !obs & F des", atoms=("des", "obs"))
    # letters: 0 = {}, 1 = {des}, 2 = {obs}, 3 = {des, obs}
    assert dfa.delta.tolist() == [[0, 1, 2, 2], [1, 1, 2, 2], [2, 2, 2, 2]]
    assert dfa.accepting.tolist() == [False, True, False]
    assert dfa.sink_states().tolist() == [2]
    assert dfa.step(0, {"des"}) == 1 and dfa.step(0, set()) == 0 and dfa.step(1, 2) == 2
    assert dfa.accepts([set(), {"des"}]) and not dfa.accepts([{"obs"}, {"des"}])


@pytest.mark.slow
@settings(deadline=None, max_examples=40)
@given(formulas(("a", "b")))
def test_dfa_matches_semantics_two_atoms(f):
    dfa = ltlf_to_dfa(f, atoms=("a", "b"))
    for t in all_traces(("a", "b"), 6):  # 5460 traces
        assert dfa.accepts(t) == holds(f, t), (str(f), t)
    assert_minimal(dfa)


@pytest.mark.slow
@settings(deadline=None, max_examples=20)
@given(formulas(("a", "b", "c")), st.integers(0, 2**32 - 1))
def test_dfa_matches_semantics_three_atoms(f, seed):
    atoms = ("a", "b", "c")
    dfa = ltlf_to_dfa(f, atoms=atoms)
    for t in all_traces(atoms, 4):  # 4680 traces
        assert dfa.accepts(t) == holds(f, t), (str(f), t)
    rng = np.random.default_rng(seed)
    for _ in range(300):
        n = int(rng.integers(5, 7))
        t = [frozenset(a for a in atoms if rng.random() < 0.5) for _ in range(n)]
        assert dfa.accepts(t) == holds(f, t), (str(f), t)
    assert_minimal(dfa)


@settings(deadline=None, max_examples=25)
@given(formulas(("a", "b")))
def test_negation_complements_on_nonempty_traces(f):
    d, nd = ltlf_to_dfa(f, atoms=("a", "b")), ltlf_to_dfa(Not(f), atoms=("a", "b"))
    # complementing a complete DFA keeps its size, so minimal sizes of f and !f agree (the free
    # empty-trace bit maps one-to-one between the two): a check of minimality independent of Moore
    assert d.n_states == nd.n_states
    for t in all_traces(("a", "b"), 4):
        assert d.accepts(t) != nd.accepts(t)


def test_extra_atoms_are_dont_cares():
    small = ltlf_to_dfa("a U b")
    big = ltlf_to_dfa("a U b", atoms=("z", "b", "a"))
    assert big.atoms == ("z", "b", "a") and big.n_states == small.n_states
    for t in all_traces(("a", "b", "z"), 3):
        assert big.accepts(t) == small.accepts([s - {"z"} for s in t]) == holds("a U b", t)


def test_unknown_atoms_are_named_with_the_known_ones():
    with pytest.raises(UnknownAtomError, match=r"\['obs'\].*known atoms \['des', 'goal'\]"):
        ltlf_to_dfa("G !obs & F des", atoms=("des", "goal"))
    dfa = ltlf_to_dfa("F des")
    with pytest.raises(UnknownAtomError, match=r"unknown atoms \['obs'\]; the DFA's atoms are \['des'\]"):
        dfa.step(0, {"obs"})
    with pytest.raises(InvalidInputError, match="letter must be a set of atom names; got the str"):
        dfa.step(0, "des")
    with pytest.raises(InvalidInputError, match="letter must be an int in \\[0, 2\\)"):
        dfa.step(0, 2)


# --------------------------------------------------------------------------- explicit tables
def test_from_table_validation():
    ok = DFA.from_table(["p"], [[0, 1], [1, 1]], 0, [False, True])
    assert ok.n_states == 2 and ok.accepts([{"p"}])
    assert DFA.from_table(["p"], [[0, 1], [1, 1]], 0, [1]).accepting.tolist() == [False, True]
    with pytest.raises(DimensionError, match=r"delta must have 2\*\*len\(atoms\) = 2 columns.*got 3"):
        DFA.from_table(["p"], [[0, 1, 1], [1, 1, 1]], 0, [False, True])
    with pytest.raises(InvalidModelError, match=r"delta targets must lie in \[0, 2\); delta\[1, 0\] = 5"):
        DFA.from_table(["p"], [[0, 1], [5, 1]], 0, [False, True])
    with pytest.raises(InvalidModelError, match=r"initial must be an int in \[0, 2\); got 2"):
        DFA.from_table(["p"], [[0, 1], [1, 1]], 2, [False, True])
    with pytest.raises(DimensionError, match=r"accepting must be a \(2,\) bool array"):
        DFA.from_table(["p"], [[0, 1], [1, 1]], 0, [False, True, True])
    with pytest.raises(InvalidModelError, match=r"atoms must be distinct; \['p'\]"):
        DFA.from_table(["p", "p"], [[0, 0, 0, 0]], 0, [False])
    with pytest.raises(DimensionError, match="delta must be a 2-d"):
        DFA.from_table(["p"], [0, 1], 0, [False])
    with pytest.raises(InvalidModelError, match="accepting indices must lie in"):
        DFA.from_table(["p"], [[0, 1], [1, 1]], 0, [7])
    with pytest.raises(ValueError, match="read-only"):
        ok.delta[0, 0] = 1  # tables cannot be changed after validation


def test_minimize_merges_equivalent_states():
    # states 1 and 2 both accept everything: one state after minimisation; state 3 unreachable
    d = DFA.from_table(["p"], [[1, 2], [1, 1], [2, 2], [3, 0]], 0, [False, True, True, False])
    m = minimize(d)
    assert m.n_states == 2 and m.delta.tolist() == [[1, 1], [1, 1]]
    for t in all_traces(("p",), 5):
        assert m.accepts(t) == d.accepts(t)


def test_dict_json_and_dot_round_trip():
    dfa = ltlf_to_dfa("G !o & F d1 & F d2")
    back = DFA.from_dict(json.loads(json.dumps(dfa.to_dict())))
    assert back.atoms == dfa.atoms and back.initial == dfa.initial and back.formula == dfa.formula
    np.testing.assert_array_equal(back.delta, dfa.delta)
    np.testing.assert_array_equal(back.accepting, dfa.accepting)
    with pytest.raises(InvalidModelError, match=r"lacks the keys \['delta'\]"):
        DFA.from_dict({"atoms": [], "initial": 0, "accepting": []})
    dot = dfa.to_dot()
    assert dot.startswith("digraph") and "doublecircle" in dot and "__start -> 0" in dot


def test_parsed_and_ast_input_agree():
    f = parse("G (a -> X b) & F a")
    assert ltlf_to_dfa(f).delta.tolist() == ltlf_to_dfa(str(f)).delta.tolist()
