"""LTLf: linear temporal logic on finite traces (De Giacomo & Vardi, IJCAI 2013).

Syntax accepted by :func:`parse`
--------------------------------
=====================  ===============================================
``true``, ``false``    constants
``a``, ``Obs``, ``d_1``  atoms: ``[A-Za-z_][A-Za-z0-9_]*``, case kept
``!f``                 negation
``f & g``, ``f | g``   conjunction, disjunction
``f -> g``, ``f <-> g``  implication, equivalence
``X f``, ``WX f``      strong next, weak next
``F f``, ``G f``       eventually, globally
``f U g``, ``f R g``   until, release
``( f )``              grouping
=====================  ===============================================

The words ``true``, ``false``, ``X``, ``WX``, ``F``, ``G``, ``U`` and ``R`` are reserved and
cannot be atoms (``x``, ``f``, ``Goal`` are ordinary atoms). Operators made of letters must be
separated from their operand by a space or a parenthesis: ``F des`` or ``F(des)``, not ``Fdes``
(which is the atom ``Fdes``) nor ``GF a`` (write ``G F a``).

Precedence, from the loosest to the tightest binding:

1. ``<->``           (left associative)
2. ``->``            (right associative: ``a -> b -> c`` is ``a -> (b -> c)``)
3. ``|``             (left associative)
4. ``&``             (left associative)
5. ``U``, ``R``      (right associative, same level: ``a U b R c`` is ``a U (b R c)``)
6. ``!``, ``X``, ``WX``, ``F``, ``G``   (prefix)

So ``G !obs & F des`` is ``(G (!obs)) & (F des)``, ``a & b U c`` is ``a & (b U c)`` and
``F a U b`` is ``(F a) U b``, as in Spot.

Semantics
---------
A trace is a *non-empty* finite sequence of sets of atoms (De Giacomo & Vardi 2013 interpret
LTLf over traces with at least one position; the empty trace is rejected by :func:`holds`).
At position ``i`` of a trace of length ``n``:

* ``X f`` holds iff ``i + 1 < n`` and ``f`` holds at ``i + 1`` (false at the last position),
* ``WX f`` holds iff ``i + 1 == n`` or ``f`` holds at ``i + 1`` (true at the last position),
* ``f U g`` holds iff some ``j`` in ``[i, n)`` has ``g`` at ``j`` and ``f`` at every ``k`` in
  ``[i, j)``; ``f R g`` is ``!(!f U !g)``; ``F f`` is ``true U f``; ``G f`` is ``!F !f``.

Atoms not mentioned in a trace position are false there.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import ClassVar, Iterable, Sequence, Union

import numpy as np

from robust_imdp.errors import FormulaSyntaxError, InvalidInputError

__all__ = [
    "Formula",
    "Top",
    "Bottom",
    "Atom",
    "Not",
    "And",
    "Or",
    "Implies",
    "Iff",
    "Next",
    "WeakNext",
    "Until",
    "Release",
    "Eventually",
    "Globally",
    "parse",
    "holds",
    "atoms_of",
    "to_nnf",
]


# --------------------------------------------------------------------------- AST
class _Node:
    """Mixin giving every AST node a readable, re-parsable ``str``."""

    def __str__(self) -> str:  # pragma: no cover - overridden
        raise NotImplementedError


@dataclass(frozen=True)
class _Unary(_Node):
    """A node with one operand, written ``symbol operand`` (``symbol`` per subclass)."""

    operand: "Formula"
    symbol: ClassVar[str] = ""

    def __str__(self) -> str:
        return f"{self.symbol}{_wrap(self.operand)}"


@dataclass(frozen=True)
class _Binary(_Node):
    """A node with two operands, written ``(left symbol right)`` (``symbol`` per subclass)."""

    left: "Formula"
    right: "Formula"
    symbol: ClassVar[str] = ""

    def __str__(self) -> str:
        return f"({self.left} {self.symbol} {self.right})"


@dataclass(frozen=True)
class Top(_Node):
    """The constant ``true``."""

    def __str__(self) -> str:
        return "true"


@dataclass(frozen=True)
class Bottom(_Node):
    """The constant ``false``."""

    def __str__(self) -> str:
        return "false"


@dataclass(frozen=True)
class Atom(_Node):
    """An atomic proposition ``name``."""

    name: str

    def __str__(self) -> str:
        return self.name


@dataclass(frozen=True)
class Not(_Unary):
    """Negation ``!operand``."""

    symbol: ClassVar[str] = "!"


@dataclass(frozen=True)
class Next(_Unary):
    """Strong next ``X operand`` (false at the last position)."""

    symbol: ClassVar[str] = "X "


@dataclass(frozen=True)
class WeakNext(_Unary):
    """Weak next ``WX operand`` (true at the last position)."""

    symbol: ClassVar[str] = "WX "


@dataclass(frozen=True)
class Eventually(_Unary):
    """``F operand`` = ``true U operand``."""

    symbol: ClassVar[str] = "F "


@dataclass(frozen=True)
class Globally(_Unary):
    """``G operand`` = ``!F !operand``."""

    symbol: ClassVar[str] = "G "


@dataclass(frozen=True)
class And(_Binary):
    """Conjunction ``left & right``."""

    symbol: ClassVar[str] = "&"


@dataclass(frozen=True)
class Or(_Binary):
    """Disjunction ``left | right``."""

    symbol: ClassVar[str] = "|"


@dataclass(frozen=True)
class Implies(_Binary):
    """Implication ``left -> right``."""

    symbol: ClassVar[str] = "->"


@dataclass(frozen=True)
class Iff(_Binary):
    """Equivalence ``left <-> right``."""

    symbol: ClassVar[str] = "<->"


@dataclass(frozen=True)
class Until(_Binary):
    """``left U right``: ``right`` eventually holds and ``left`` holds until then."""

    symbol: ClassVar[str] = "U"


@dataclass(frozen=True)
class Release(_Binary):
    """``left R right`` = ``!(!left U !right)``."""

    symbol: ClassVar[str] = "R"


Formula = Union[
    Top, Bottom, Atom, Not, And, Or, Implies, Iff, Next, WeakNext, Until, Release, Eventually, Globally
]

_UNARY = {"!": Not, "X": Next, "WX": WeakNext, "F": Eventually, "G": Globally}
_BINARY_TEMPORAL = {"U": Until, "R": Release}
_KEYWORDS = {"true", "false", "X", "WX", "F", "G", "U", "R"}


def _wrap(f: Formula) -> str:
    """Parenthesise compound operands of prefix operators (binary nodes print their own)."""
    return str(f)


# --------------------------------------------------------------------------- parser
_TOKEN_RE = re.compile(
    r"\s*(?:(?P<ident>[A-Za-z_][A-Za-z0-9_]*)|(?P<op><->|->|[!&|()]))"
)


@dataclass(frozen=True)
class _Token:
    kind: str  # "ident", "op" or "end"
    text: str
    pos: int


def _syntax_error(text: str, pos: int, expected: str, found: str) -> FormulaSyntaxError:
    caret = " " * pos + "^"
    return FormulaSyntaxError(
        f"cannot parse formula at position {pos}: expected {expected}, found {found}\n"
        f"  {text}\n  {caret}"
    )


def _tokenize(text: str) -> list[_Token]:
    tokens: list[_Token] = []
    pos = 0
    while True:
        while pos < len(text) and text[pos].isspace():
            pos += 1
        if pos >= len(text):
            tokens.append(_Token("end", "", pos))
            return tokens
        m = _TOKEN_RE.match(text, pos)
        if m is None or m.end() == pos:
            raise _syntax_error(
                text, pos, "an atom, a constant, an operator or a parenthesis",
                f"unexpected character {text[pos]!r}",
            )
        kind = "ident" if m.group("ident") is not None else "op"
        tok = m.group(kind)
        tokens.append(_Token(kind, tok, m.start(kind)))
        pos = m.end()


class _Parser:
    """Recursive-descent parser following the precedence table of the module docstring."""

    def __init__(self, text: str):
        self.text = text
        self.tokens = _tokenize(text)
        self.i = 0

    @property
    def tok(self) -> _Token:
        return self.tokens[self.i]

    def _describe(self, tok: _Token) -> str:
        return "end of formula" if tok.kind == "end" else repr(tok.text)

    def _expect(self, text: str, expected: str) -> None:
        if self.tok.text != text or self.tok.kind == "end":
            raise _syntax_error(self.text, self.tok.pos, expected, self._describe(self.tok))
        self.i += 1

    def parse(self) -> Formula:
        f = self.iff()
        if self.tok.kind != "end":
            raise _syntax_error(
                self.text, self.tok.pos,
                "a binary operator (<->, ->, |, &, U, R) or the end of the formula",
                self._describe(self.tok),
            )
        return f

    def iff(self) -> Formula:
        f = self.implies()
        while self.tok.kind == "op" and self.tok.text == "<->":
            self.i += 1
            f = Iff(f, self.implies())
        return f

    def implies(self) -> Formula:
        f = self.disj()
        if self.tok.kind == "op" and self.tok.text == "->":
            self.i += 1
            return Implies(f, self.implies())
        return f

    def disj(self) -> Formula:
        f = self.conj()
        while self.tok.kind == "op" and self.tok.text == "|":
            self.i += 1
            f = Or(f, self.conj())
        return f

    def conj(self) -> Formula:
        f = self.temporal()
        while self.tok.kind == "op" and self.tok.text == "&":
            self.i += 1
            f = And(f, self.temporal())
        return f

    def temporal(self) -> Formula:
        f = self.unary()
        if self.tok.kind == "ident" and self.tok.text in _BINARY_TEMPORAL:
            cls = _BINARY_TEMPORAL[self.tok.text]
            self.i += 1
            return cls(f, self.temporal())
        return f

    def unary(self) -> Formula:
        tok = self.tok
        if tok.text in _UNARY and tok.kind in ("op", "ident"):
            self.i += 1
            return _UNARY[tok.text](self.unary())
        if tok.kind == "op" and tok.text == "(":
            self.i += 1
            f = self.iff()
            self._expect(")", "')' closing the parenthesis")
            return f
        if tok.kind == "ident" and tok.text not in _KEYWORDS:
            self.i += 1
            return Atom(tok.text)
        if tok.kind == "ident" and tok.text == "true":
            self.i += 1
            return Top()
        if tok.kind == "ident" and tok.text == "false":
            self.i += 1
            return Bottom()
        raise _syntax_error(
            self.text, tok.pos,
            "an atom, 'true', 'false', '(' or a prefix operator (!, X, WX, F, G)",
            self._describe(tok),
        )


def parse(text: str) -> Formula:
    """Parse an LTLf formula (grammar and precedence in the module docstring).

    Parameters
    ----------
    text : str
        The formula, e.g. ``"G !obs & F des"``.

    Returns
    -------
    Formula
        The abstract syntax tree (frozen, hashable dataclasses).

    Raises
    ------
    FormulaSyntaxError
        With the position, what was expected, and the formula with a caret under the position.
    """
    if not isinstance(text, str):
        raise FormulaSyntaxError(f"formula must be a str; got {type(text).__name__}")
    return _Parser(text).parse()


def _as_formula(formula: Formula | str) -> Formula:
    return parse(formula) if isinstance(formula, str) else formula


# --------------------------------------------------------------------------- queries
def atoms_of(formula: Formula | str) -> frozenset[str]:
    """Return the set of atom names occurring in ``formula`` (a string is parsed first)."""
    f = _as_formula(formula)
    out: set[str] = set()
    stack = [f]
    while stack:
        g = stack.pop()
        if isinstance(g, Atom):
            out.add(g.name)
        elif isinstance(g, (Not, Next, WeakNext, Eventually, Globally)):
            stack.append(g.operand)
        elif isinstance(g, (And, Or, Implies, Iff, Until, Release)):
            stack.extend((g.left, g.right))
    return frozenset(out)


def holds(formula: Formula | str, trace: Sequence[Iterable[str]]) -> bool:
    """Decide ``trace |= formula`` by the finite-trace semantics (De Giacomo & Vardi 2013).

    Direct dynamic programming from the last position backwards over the syntax tree: every
    subformula gets a boolean vector over the positions, computed from the definitions in the
    module docstring (independent of the automaton construction in :mod:`robust_imdp.spec.dfa`).

    Parameters
    ----------
    formula : Formula or str
    trace : sequence of iterables of str, length n >= 1
        ``trace[i]`` is the set of atoms true at position ``i``.

    Returns
    -------
    bool

    Raises
    ------
    InvalidInputError
        If ``trace`` is empty (LTLf traces have at least one position) or a position is a bare
        ``str`` (write ``{"a"}``, not ``"a"``).
    """
    f = _as_formula(formula)
    letters = []
    for i, pos in enumerate(trace):
        if isinstance(pos, str):
            raise InvalidInputError(
                f"trace[{i}] must be a set of atom names; got the str {pos!r} (write {{{pos!r}}})"
            )
        letters.append(frozenset(pos))
    if not letters:
        raise InvalidInputError(
            "trace must be non-empty (LTLf traces have at least one position); got an empty trace"
        )
    return bool(_eval(f, letters, {})[0])


def _eval(f: Formula, letters: list[frozenset], memo: dict) -> np.ndarray:
    """Boolean vector ``v[i] = (trace, i |= f)`` for every position ``i``."""
    key = f
    if key in memo:
        return memo[key]
    n = len(letters)
    if isinstance(f, Top):
        v = np.ones(n, dtype=bool)
    elif isinstance(f, Bottom):
        v = np.zeros(n, dtype=bool)
    elif isinstance(f, Atom):
        v = np.array([f.name in s for s in letters], dtype=bool)
    elif isinstance(f, Not):
        v = ~_eval(f.operand, letters, memo)
    elif isinstance(f, And):
        v = _eval(f.left, letters, memo) & _eval(f.right, letters, memo)
    elif isinstance(f, Or):
        v = _eval(f.left, letters, memo) | _eval(f.right, letters, memo)
    elif isinstance(f, Implies):
        v = ~_eval(f.left, letters, memo) | _eval(f.right, letters, memo)
    elif isinstance(f, Iff):
        v = _eval(f.left, letters, memo) == _eval(f.right, letters, memo)
    elif isinstance(f, (Next, WeakNext)):
        a = _eval(f.operand, letters, memo)
        v = np.empty(n, dtype=bool)
        v[:-1] = a[1:]
        v[-1] = isinstance(f, WeakNext)  # X false / WX true at the last position
    elif isinstance(f, (Until, Eventually)):
        left = _eval(f.left, letters, memo) if isinstance(f, Until) else np.ones(n, dtype=bool)
        right = _eval(f.right if isinstance(f, Until) else f.operand, letters, memo)
        v = np.empty(n, dtype=bool)
        nxt = False  # value at position n: nothing holds beyond the end
        for i in range(n - 1, -1, -1):
            nxt = bool(right[i] or (left[i] and nxt))
            v[i] = nxt
    elif isinstance(f, (Release, Globally)):
        left = _eval(f.left, letters, memo) if isinstance(f, Release) else np.zeros(n, dtype=bool)
        right = _eval(f.right if isinstance(f, Release) else f.operand, letters, memo)
        v = np.empty(n, dtype=bool)
        nxt = True  # f R g holds vacuously beyond the end
        for i in range(n - 1, -1, -1):
            nxt = bool(right[i] and (left[i] or nxt))
            v[i] = nxt
    else:
        raise InvalidInputError(f"formula must be an LTLf AST node or str; got {type(f).__name__}")
    memo[key] = v
    return v


# --------------------------------------------------------------------------- normal form
def to_nnf(formula: Formula | str) -> Formula:
    """Negation normal form: ``Not`` only on atoms; no ``Implies``/``Iff``; same LTLf meaning.

    Uses the finite-trace dualities ``!X f = WX !f``, ``!(f U g) = !f R !g``, ``!F f = G !f``
    (De Giacomo & Vardi 2013, Sec. 2).
    """
    return _nnf(_as_formula(formula), False)


def _nnf(f: Formula, neg: bool) -> Formula:
    if isinstance(f, Top):
        return Bottom() if neg else f
    if isinstance(f, Bottom):
        return Top() if neg else f
    if isinstance(f, Atom):
        return Not(f) if neg else f
    if isinstance(f, Not):
        return _nnf(f.operand, not neg)
    if isinstance(f, And):
        cls = Or if neg else And
        return cls(_nnf(f.left, neg), _nnf(f.right, neg))
    if isinstance(f, Or):
        cls = And if neg else Or
        return cls(_nnf(f.left, neg), _nnf(f.right, neg))
    if isinstance(f, Implies):
        return _nnf(Or(Not(f.left), f.right), neg)
    if isinstance(f, Iff):
        return _nnf(Or(And(f.left, f.right), And(Not(f.left), Not(f.right))), neg)
    if isinstance(f, Next):
        return (WeakNext if neg else Next)(_nnf(f.operand, neg))
    if isinstance(f, WeakNext):
        return (Next if neg else WeakNext)(_nnf(f.operand, neg))
    if isinstance(f, Eventually):
        return (Globally if neg else Eventually)(_nnf(f.operand, neg))
    if isinstance(f, Globally):
        return (Eventually if neg else Globally)(_nnf(f.operand, neg))
    if isinstance(f, Until):
        return (Release if neg else Until)(_nnf(f.left, neg), _nnf(f.right, neg))
    if isinstance(f, Release):
        return (Until if neg else Release)(_nnf(f.left, neg), _nnf(f.right, neg))
    raise InvalidInputError(f"formula must be an LTLf AST node or str; got {type(f).__name__}")
