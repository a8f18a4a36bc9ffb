"""Tests of the LTLf parser and of the direct finite-trace semantics ``holds``."""

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robust_imdp.errors import FormulaSyntaxError, InvalidInputError
from robust_imdp.spec.ltlf import (
    And,
    Atom,
    Bottom,
    Eventually,
    Globally,
    Iff,
    Implies,
    Next,
    Not,
    Or,
    Release,
    Top,
    Until,
    WeakNext,
    atoms_of,
    holds,
    parse,
    to_nnf,
)

a, b, c = Atom("a"), Atom("b"), Atom("c")


# --------------------------------------------------------------------------- parser
@pytest.mark.parametrize(
    "text, tree",
    [
        ("G !obs & F des", And(Globally(Not(Atom("obs"))), Eventually(Atom("des")))),
        ("a & b U c", And(a, Until(b, c))),  # U binds tighter than &
        ("a | b & c", Or(a, And(b, c))),  # & binds tighter than |
        ("a -> b -> c", Implies(a, Implies(b, c))),  # -> is right associative
        ("a <-> b -> c", Iff(a, Implies(b, c))),  # <-> is the loosest
        ("a U b R c", Until(a, Release(b, c))),  # U/R right associative, same level
        ("F a U b", Until(Eventually(a), b)),  # prefix operators bind tightest
        ("!X a", Not(Next(a))),
        ("WX (a | b)", WeakNext(Or(a, b))),
        ("a & b & c", And(And(a, b), c)),  # & left associative
        ("true | false", Or(Top(), Bottom())),
        ("G(F(a))", Globally(Eventually(a))),
        ("Obs_1 & obs_1", And(Atom("Obs_1"), Atom("obs_1"))),  # case kept
        ("Fdes", Atom("Fdes")),  # one identifier, not F des
        ("x & f", And(Atom("x"), Atom("f"))),  # lower-case x, f are atoms
    ],
)
def test_parse_precedence(text, tree):
    assert parse(text) == tree


@pytest.mark.parametrize(
    "text, pos, expected",
    [
        ("a &", 3, "expected an atom"),
        ("(a | b", 6, "expected '\\)'"),
        ("a $ b", 2, "unexpected character '\\$'"),
        ("a b", 2, "expected a binary operator"),
        ("G & a", 2, "expected an atom"),
        ("U a", 0, "expected an atom"),
        ("", 0, "found end of formula"),
        ("a)", 1, "found '\\)'"),
    ],
)
def test_parse_errors_show_caret(text, pos, expected):
    with pytest.raises(FormulaSyntaxError, match=expected) as info:
        parse(text)
    msg = str(info.value)
    assert f"position {pos}" in msg
    lines = msg.splitlines()
    # the formula is printed on one line and the caret right under the position (2-space indent)
    assert lines[-2] == "  " + text
    assert lines[-1] == "  " + " " * pos + "^"


def test_parse_rejects_non_string():
    with pytest.raises(FormulaSyntaxError, match="formula must be a str"):
        parse(3)


# --------------------------------------------------------------------------- semantics
E, A, B, AB = frozenset(), frozenset("a"), frozenset("b"), frozenset("ab")


@pytest.mark.parametrize(
    "text, trace, expected",
    [
        ("X a", [A], False),  # strong next is false at the last position
        ("WX a", [E], True),  # weak next is true at the last position
        ("X a", [E, A], True),
        ("WX a", [E, E], False),
        ("F a", [E, E, A], True),
        ("F a", [E, E], False),
        ("G a", [A, AB, A], True),
        ("G a", [A, B], False),
        ("a U b", [A, A, B], True),
        ("a U b", [A, A, A], False),  # strong until: b must occur
        ("a R b", [B, B, B], True),  # b held to the end: release holds
        ("a R b", [B, AB, E], True),
        ("a R b", [B, E], False),
        ("G !obs & F des", [set(), {"des"}], True),
        ("G !obs & F des", [{"obs"}, {"des"}], False),
        ("X X a", [E, E], False),
        ("G (a -> X b)", [A, B], True),
        ("G (a -> X b)", [B, A], False),  # a at the end has no next
        ("G (a -> WX b)", [B, A], True),
        ("a <-> b", [AB], True),
        ("a <-> b", [A], False),
    ],
)
def test_holds_hand_cases(text, trace, expected):
    assert holds(text, trace) is expected


def test_holds_rejects_empty_trace_and_bare_strings():
    with pytest.raises(InvalidInputError, match="trace must be non-empty"):
        holds("a", [])
    with pytest.raises(InvalidInputError, match=r"trace\[1\] must be a set"):
        holds("a", [{"a"}, "a"])


def test_atoms_of():
    assert atoms_of("G !obs & F (des | X d_2)") == {"obs", "des", "d_2"}
    assert atoms_of("true U false") == frozenset()


# --------------------------------------------------------------------------- random formulas
def formulas(names=("a", "b")):
    leaves = st.sampled_from([Atom(n) for n in names] + [Top(), Bottom()])
    unary = [Not, Next, WeakNext, Eventually, Globally]
    binary = [And, Or, Implies, Iff, Until, Release]

    def extend(children):
        return st.one_of(
            st.builds(lambda op, f: op(f), st.sampled_from(unary), children),
            st.builds(lambda op, f, g: op(f, g), st.sampled_from(binary), children, children),
        )

    return st.recursive(leaves, extend, max_leaves=6)


traces = st.lists(st.frozensets(st.sampled_from(["a", "b"])), min_size=1, max_size=6)


@settings(deadline=None, max_examples=60)
@given(formulas(), traces)
def test_str_round_trip_and_nnf_keep_meaning(f, trace):
    # printing then parsing gives the same tree; NNF keeps the meaning on every trace
    assert parse(str(f)) == f
    assert holds(to_nnf(f), trace) == holds(f, trace)
    # negation is exact on non-empty traces
    assert holds(Not(f), trace) != holds(f, trace)


@settings(deadline=None, max_examples=60)
@given(formulas(), formulas(), traces)
def test_holds_expansion_laws(f, g, trace):
    # f U g = g | (f & X(f U g)) and f R g = g & (f | WX(f R g)) (De Giacomo & Vardi 2013)
    assert holds(Until(f, g), trace) == holds(Or(g, And(f, Next(Until(f, g)))), trace)
    assert holds(Release(f, g), trace) == holds(And(g, Or(f, WeakNext(Release(f, g)))), trace)
    assert holds(Eventually(f), trace) == holds(Until(Top(), f), trace)
    assert holds(Globally(f), trace) == holds(Not(Eventually(Not(f))), trace)
