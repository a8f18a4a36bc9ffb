"""Deterministic finite automata over the alphabet 2^atoms, and LTLf -> minimal DFA.

Letters are ``int`` bit masks: bit ``i`` of a letter is set iff ``atoms[i]`` holds
(``docs/ARCHITECTURE.md``). A :class:`DFA` is complete: ``delta`` has one target for every
(state, letter) pair.

Construction of :func:`ltlf_to_dfa` (our own code, no external tool)
--------------------------------------------------------------------
1. The formula is put in negation normal form (:func:`robust_imdp.spec.ltlf.to_nnf`).
2. A DFA state is a formula in a canonical disjunctive normal form: a set of clauses, each a set
   of *elementary* subformulas (literals, ``X``, ``WX``, ``U``, ``R``, ``F``, ``G``), with
   subsumed clauses removed. Every elementary formula that can occur is a subformula of the
   NNF formula or one of the two helpers ``F true`` ("the rest of the trace is non-empty") and
   ``G false`` ("the rest is empty"), so there are finitely many states.
3. Reading a letter ``a`` *progresses* the state (Bacchus & Kabanza 1998, adapted to finite
   traces): ``prog(f, a)`` is a formula with ``a.w |= f  <=>  w |= prog(f, a)`` for every
   possibly empty remainder ``w``. On the empty remainder, literals, ``X``, ``U`` and ``F`` are
   false and ``WX``, ``R`` and ``G`` are true (the end-of-trace convention), and

   * ``prog(X f) = f & F true``        (strong next: there must be a next position),
   * ``prog(WX f) = f | G false``      (weak next: or the trace ends here),
   * ``prog(f U g) = prog(g) | (prog(f) & (f U g))``,
   * ``prog(f R g) = prog(g) & (prog(f) | (f R g))``,
   * ``prog(F f) = prog(f) | F f``, ``prog(G f) = prog(f) & G f``.

4. A state accepts iff its formula holds on the empty remainder, so a non-empty trace is
   accepted iff it satisfies the formula (induction on the trace with the equivalence in 3).
5. Moore partition refinement merges equivalent states; states are renumbered in breadth-first
   order from the initial state (state 0), so the result is canonical.

The empty trace is not an LTLf trace; whether the initial state accepts is therefore free. We
build both choices, minimise both and keep the smaller automaton (ties: the end-of-trace
convention of step 3), so the result is a minimal DFA for the formula's non-empty language.
"""

from __future__ import annotations

import json
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from robust_imdp.errors import (DimensionError, InvalidInputError, InvalidModelError, SpecificationWarning,
                                 UnknownAtomError, VacuousSpecificationError)
from robust_imdp.spec.ltlf import (
    And,
    Atom,
    Bottom,
    Eventually,
    Formula,
    Globally,
    Next,
    Not,
    Or,
    Release,
    Top,
    Until,
    WeakNext,
    atoms_of,
    parse,
    to_nnf,
)

__all__ = ["DFA", "ltlf_to_dfa", "minimize", "SpecKind", "classify", "resolve_semantics", "check_reading",
           "SEMANTICS", "READINGS"]

#: Largest alphabet (number of atoms) accepted: the transition table has 2**n_atoms columns.
MAX_ATOMS = 16


# --------------------------------------------------------------------------- DFA type
@dataclass(frozen=True, eq=False)
class DFA:
    """A complete deterministic finite automaton over letters ``0 .. 2**len(atoms) - 1``.

    Build with :meth:`from_table` (validated) or :func:`ltlf_to_dfa`.

    Attributes
    ----------
    atoms : tuple of str
        Atom names; bit ``i`` of a letter is ``atoms[i]``.
    delta : (n_states, 2**len(atoms)) int64 array, read-only
        ``delta[s, letter]`` is the successor of state ``s``.
    initial : int
    accepting : (n_states,) bool array, read-only
    formula : str or None
        The LTLf formula the automaton was built from, if any (information only).
    """

    atoms: tuple
    delta: np.ndarray
    initial: int
    accepting: np.ndarray
    formula: str | None = field(default=None)

    def __post_init__(self) -> None:
        _validate(self.atoms, self.delta, self.initial, self.accepting)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_table(
        cls,
        atoms: Sequence[str],
        delta: Any,
        initial: int,
        accepting: Any,
        *,
        formula: str | None = None,
    ) -> "DFA":
        """Build a DFA from an explicit table, validating every part.

        Parameters
        ----------
        atoms : sequence of str
            Distinct atom names; the alphabet is ``2**len(atoms)`` letters.
        delta : (n_states, 2**len(atoms)) int array-like
            Successor of each state under each letter; targets in ``[0, n_states)``.
        initial : int
            Initial state in ``[0, n_states)``.
        accepting : (n_states,) bool array-like, or a collection of accepting state indices
            A bool array of length ``n_states`` is taken as a mask; an int sequence as indices.

        Raises
        ------
        InvalidModelError, DimensionError
            Naming the wrong part (alphabet size, out-of-range target, ...).
        """
        if isinstance(atoms, str):
            raise InvalidModelError(f"atoms must be a sequence of atom names; got the str {atoms!r}")
        atoms_t = tuple(atoms)
        d = np.asarray(delta)
        if d.ndim != 2:
            raise DimensionError(
                f"delta must be a 2-d (n_states, 2**len(atoms)) table; got shape {d.shape}"
            )
        if d.size and not np.issubdtype(d.dtype, np.integer):
            raise InvalidModelError(f"delta must hold integer state indices; got dtype {d.dtype}")
        d = d.astype(np.int64)
        acc = np.array(accepting)  # a copy: validation freezes it
        if acc.dtype != bool:
            idx = acc.astype(np.int64).ravel() if acc.size else np.zeros(0, dtype=np.int64)
            if acc.size and not np.issubdtype(acc.dtype, np.integer):
                raise InvalidModelError(
                    f"accepting must be a bool mask or integer state indices; got dtype {acc.dtype}"
                )
            if idx.size and (idx.min() < 0 or idx.max() >= d.shape[0]):
                raise InvalidModelError(
                    f"accepting indices must lie in [0, {d.shape[0]}); got {idx.tolist()}"
                )
            acc = np.zeros(d.shape[0], dtype=bool)
            acc[idx] = True
        if isinstance(initial, (bool, np.bool_)) or not isinstance(initial, (int, np.integer)):
            raise InvalidModelError(f"initial must be an int state index; got {initial!r}")
        return cls(atoms_t, d, int(initial), acc, formula)

    # ------------------------------------------------------------------ basic queries
    @property
    def n_states(self) -> int:
        """Number of states."""
        return int(self.delta.shape[0])

    @property
    def n_letters(self) -> int:
        """Alphabet size ``2**len(atoms)``."""
        return int(self.delta.shape[1])

    def letter_of(self, atoms: Iterable[str] | int) -> int:
        """Letter (bit mask) of a set of atom names; an int letter is range-checked and returned.

        Raises
        ------
        UnknownAtomError
            If a name is not in :attr:`atoms` (the message lists the known atoms).
        """
        if isinstance(atoms, (int, np.integer)) and not isinstance(atoms, (bool, np.bool_)):
            if not 0 <= int(atoms) < self.n_letters:
                raise InvalidInputError(
                    f"letter must be an int in [0, {self.n_letters}); got {int(atoms)}"
                )
            return int(atoms)
        if isinstance(atoms, str):
            raise InvalidInputError(
                f"letter must be a set of atom names; got the str {atoms!r} (write {{{atoms!r}}})"
            )
        names = set(atoms)
        unknown = sorted(names.difference(self.atoms))
        if unknown:
            raise UnknownAtomError(
                f"letter names unknown atoms {unknown}; the DFA's atoms are {list(self.atoms)}"
            )
        return sum(1 << i for i, a in enumerate(self.atoms) if a in names)

    def step(self, state: int, letter: Iterable[str] | int) -> int:
        """Successor of ``state`` reading ``letter`` (a set of atom names or an int bit mask)."""
        if not 0 <= int(state) < self.n_states:
            raise InvalidInputError(f"state must be in [0, {self.n_states}); got {state}")
        return int(self.delta[int(state), self.letter_of(letter)])

    def run(self, trace: Iterable[Iterable[str] | int]) -> int:
        """State reached from :attr:`initial` after reading ``trace``."""
        s = self.initial
        for letter in trace:
            s = int(self.delta[s, self.letter_of(letter)])
        return s

    def accepts(self, trace: Iterable[Iterable[str] | int]) -> bool:
        """Whether the run on ``trace`` ends in an accepting state.

        For a DFA built from a formula the empty trace's answer is a convention (LTLf traces are
        non-empty; see the module docstring).
        """
        return bool(self.accepting[self.run(trace)])

    def sink_states(self) -> np.ndarray:
        """Non-accepting states from which no accepting state is reachable, sorted ``(k,)`` int."""
        return np.flatnonzero(~_coreachable(self.delta, self.accepting))

    # ------------------------------------------------------------------ export
    def to_dict(self) -> dict:
        """Plain JSON-serialisable dictionary (inverse: :meth:`from_dict`)."""
        return {
            "format": "robust_imdp.DFA",
            "version": 1,
            "atoms": list(self.atoms),
            "initial": self.initial,
            "accepting": [int(s) for s in np.flatnonzero(self.accepting)],
            "delta": self.delta.tolist(),
            "formula": self.formula,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "DFA":
        """Rebuild a DFA from :meth:`to_dict` output (validated like :meth:`from_table`)."""
        missing = [k for k in ("atoms", "initial", "accepting", "delta") if k not in data]
        if missing:
            raise InvalidModelError(f"DFA dictionary lacks the keys {missing}; got keys {sorted(data)}")
        n_atoms = len(data["atoms"])
        delta = np.asarray(data["delta"], dtype=np.int64).reshape(-1, 2**n_atoms)
        return cls.from_table(
            data["atoms"], delta, data["initial"],
            np.asarray(data["accepting"], dtype=np.int64), formula=data.get("formula"),
        )

    def to_json(self) -> str:
        """JSON text of :meth:`to_dict`."""
        return json.dumps(self.to_dict())

    def to_dot(self) -> str:
        """Graphviz text; parallel edges are merged and labelled by their letters' atom sets."""
        lines = ["digraph DFA {", "  rankdir=LR;", '  __start [shape=point, label=""];']
        for s in range(self.n_states):
            shape = "doublecircle" if self.accepting[s] else "circle"
            lines.append(f'  {s} [shape={shape}, label="{s}"];')
        lines.append(f"  __start -> {self.initial};")
        for s in range(self.n_states):
            for t in np.unique(self.delta[s]):
                letters = np.flatnonzero(self.delta[s] == t)
                if len(letters) == self.n_letters:
                    label = "*"
                else:
                    label = ", ".join(self._letter_text(int(a)) for a in letters)
                lines.append(f'  {s} -> {int(t)} [label="{label}"];')
        lines.append("}")
        return "\n".join(lines)

    def _letter_text(self, letter: int) -> str:
        names = [a for i, a in enumerate(self.atoms) if letter >> i & 1]
        return "{" + ",".join(names) + "}"

    def __repr__(self) -> str:
        return (
            f"DFA(atoms={self.atoms}, n_states={self.n_states}, initial={self.initial}, "
            f"accepting={np.flatnonzero(self.accepting).tolist()}, formula={self.formula!r})"
        )


def _check_atoms(atoms: Any) -> None:
    if not isinstance(atoms, tuple) or not all(isinstance(a, str) for a in atoms):
        raise InvalidModelError(f"atoms must be a tuple of str; got {atoms!r}")
    if len(set(atoms)) != len(atoms):
        dup = sorted({a for a in atoms if atoms.count(a) > 1})
        raise InvalidModelError(f"atoms must be distinct; {dup} appear more than once in {list(atoms)}")
    if len(atoms) > MAX_ATOMS:
        raise InvalidModelError(f"atoms must number at most {MAX_ATOMS}; got {len(atoms)}")


def _validate(atoms: Any, delta: Any, initial: Any, accepting: Any) -> None:
    _check_atoms(atoms)
    if not isinstance(delta, np.ndarray) or delta.ndim != 2 or not np.issubdtype(delta.dtype, np.integer):
        raise InvalidModelError("delta must be a 2-d integer numpy array; use DFA.from_table")
    n_states, n_letters = delta.shape
    if n_states < 1:
        raise InvalidModelError(f"delta must have at least one state (row); got shape {delta.shape}")
    if n_letters != 2 ** len(atoms):
        raise DimensionError(
            f"delta must have 2**len(atoms) = {2 ** len(atoms)} columns (one per letter over "
            f"{list(atoms)}); got {n_letters}"
        )
    bad = (delta < 0) | (delta >= n_states)
    if bad.any():
        s, a = np.argwhere(bad)[0]
        raise InvalidModelError(
            f"delta targets must lie in [0, {n_states}); delta[{s}, {a}] = {delta[s, a]}"
        )
    if not isinstance(initial, int) or isinstance(initial, bool) or not 0 <= initial < n_states:
        raise InvalidModelError(f"initial must be an int in [0, {n_states}); got {initial!r}")
    if not isinstance(accepting, np.ndarray) or accepting.dtype != bool or accepting.shape != (n_states,):
        shape = getattr(accepting, "shape", None)
        raise DimensionError(f"accepting must be a ({n_states},) bool array; got {shape}")
    delta.setflags(write=False)
    accepting.setflags(write=False)


def _coreachable(delta: np.ndarray, accepting: np.ndarray) -> np.ndarray:
    """Mask of states from which an accepting state is reachable (backward fixed point)."""
    good = accepting.copy()
    while True:
        new = good | good[delta].any(axis=1)
        if (new == good).all():
            return good
        good = new


# --------------------------------------------------------------------------- minimisation
def minimize(dfa: DFA) -> DFA:
    """Minimal equivalent DFA: drop unreachable states, merge equivalent ones (Moore refinement).

    States of the result are numbered in breadth-first order from the initial state (which is
    state 0), letters in increasing order, so equal languages give identical tables.
    """
    delta, acc = _minimize_table(dfa.delta, dfa.initial, dfa.accepting)
    return DFA(dfa.atoms, delta, 0, acc, dfa.formula)


def _minimize_table(delta: np.ndarray, initial: int, accepting: np.ndarray):
    # 1. reachable part
    reach = np.zeros(delta.shape[0], dtype=bool)
    reach[initial] = True
    frontier = np.array([initial])
    while frontier.size:
        nxt = np.unique(delta[frontier])
        nxt = nxt[~reach[nxt]]
        reach[nxt] = True
        frontier = nxt
    # 2. Moore refinement: block(s) <- (block(s), block(delta(s, a)) for every letter a)
    block = accepting.astype(np.int64)
    n_blocks = len(np.unique(block[reach]))
    while True:
        sig = np.column_stack([block, block[delta]])
        sig[~reach] = -1
        _, new_block = np.unique(sig, axis=0, return_inverse=True)
        new_block = new_block.ravel()
        n_new = len(np.unique(new_block[reach]))
        block = new_block
        if n_new == n_blocks:
            break
        n_blocks = n_new
    # 3. canonical numbering: breadth-first from the initial block
    order = {int(block[initial]): 0}
    rep = {0: initial}
    queue = deque([initial])
    while queue:
        s = queue.popleft()
        for t in delta[s]:
            b = int(block[t])
            if b not in order:
                order[b] = len(order)
                rep[order[b]] = int(t)
                queue.append(int(t))
    n = len(order)
    reps = np.array([rep[i] for i in range(n)])
    relabel = np.full(block.max() + 1, -1, dtype=np.int64)
    for b, i in order.items():
        relabel[b] = i
    new_delta = relabel[block[delta[reps]]]
    return new_delta.astype(np.int64), accepting[reps].copy()


# --------------------------------------------------------------------------- LTLf -> DFA
# A DNF is a frozenset of clauses; a clause is a frozenset of elementary NNF formulas.
_TRUE = frozenset([frozenset()])
_FALSE: frozenset = frozenset()
_NONEMPTY = Eventually(Top())  # holds on w iff w is non-empty
_EMPTY = Globally(Bottom())  # holds on w iff w is empty


def _absorb(clauses: Iterable[frozenset]) -> frozenset:
    """Remove clauses that are supersets of another clause (c | (c & d) = c)."""
    cs = sorted(set(clauses), key=len)
    kept: list[frozenset] = []
    for c in cs:
        if not any(k <= c for k in kept):
            kept.append(c)
    return frozenset(kept)


def _dnf_or(a: frozenset, b: frozenset) -> frozenset:
    return _absorb(a | b)


def _dnf_and(a: frozenset, b: frozenset) -> frozenset:
    return _absorb(x | y for x in a for y in b)


def _dnf(f: Formula) -> frozenset:
    """DNF of an NNF formula, treating temporal operators and literals as elementary."""
    if isinstance(f, Top):
        return _TRUE
    if isinstance(f, Bottom):
        return _FALSE
    if isinstance(f, And):
        return _dnf_and(_dnf(f.left), _dnf(f.right))
    if isinstance(f, Or):
        return _dnf_or(_dnf(f.left), _dnf(f.right))
    return frozenset([frozenset([f])])


def _accepts_empty(e: Formula) -> bool:
    """End-of-trace convention for elementary formulas (module docstring, step 3)."""
    return isinstance(e, (WeakNext, Release, Globally))


class _Progressor:
    """Memoised progression of elementary formulas over letters (frozensets of true atoms)."""

    def __init__(self) -> None:
        self.memo: dict = {}

    def formula(self, f: Formula, letter: frozenset) -> frozenset:
        if isinstance(f, Top):
            return _TRUE
        if isinstance(f, Bottom):
            return _FALSE
        if isinstance(f, And):
            return _dnf_and(self.formula(f.left, letter), self.formula(f.right, letter))
        if isinstance(f, Or):
            return _dnf_or(self.formula(f.left, letter), self.formula(f.right, letter))
        key = (f, letter)
        if key not in self.memo:
            self.memo[key] = self._elementary(f, letter)
        return self.memo[key]

    def _elementary(self, f: Formula, letter: frozenset) -> frozenset:
        if isinstance(f, Atom):
            return _TRUE if f.name in letter else _FALSE
        if isinstance(f, Not):  # NNF: operand is an Atom
            return _FALSE if f.operand.name in letter else _TRUE
        if isinstance(f, Next):  # a.w |= X f  iff  w non-empty and w |= f
            return _dnf_and(_dnf(f.operand), frozenset([frozenset([_NONEMPTY])]))
        if isinstance(f, WeakNext):  # a.w |= WX f  iff  w empty or w |= f
            return _dnf_or(_dnf(f.operand), frozenset([frozenset([_EMPTY])]))
        if isinstance(f, Until):  # f U g = g | (f & X(f U g)); "X" is implied by f U g itself
            return _dnf_or(
                self.formula(f.right, letter),
                _dnf_and(self.formula(f.left, letter), frozenset([frozenset([f])])),
            )
        if isinstance(f, Release):  # f R g = g & (f | WX(f R g)); f R g holds on the empty w
            return _dnf_and(
                self.formula(f.right, letter),
                _dnf_or(self.formula(f.left, letter), frozenset([frozenset([f])])),
            )
        if isinstance(f, Eventually):
            return _dnf_or(self.formula(f.operand, letter), frozenset([frozenset([f])]))
        if isinstance(f, Globally):
            return _dnf_and(self.formula(f.operand, letter), frozenset([frozenset([f])]))
        raise InvalidInputError(f"unexpected node {type(f).__name__} in NNF")  # pragma: no cover

    def state(self, state: frozenset, letter: frozenset) -> frozenset:
        out = _FALSE
        for clause in state:
            c = _TRUE
            for e in clause:
                c = _dnf_and(c, self.formula(e, letter))
                if not c:
                    break
            out = _dnf_or(out, c)
        return out


def _resolve_atoms(formula: Formula, atoms: Sequence[str] | None) -> tuple:
    used = atoms_of(formula)
    if atoms is None:
        return tuple(sorted(used))
    if isinstance(atoms, str):
        raise InvalidInputError(f"atoms must be a sequence of atom names; got the str {atoms!r}")
    atoms_t = tuple(atoms)
    unknown = sorted(used.difference(atoms_t))
    if unknown:
        raise UnknownAtomError(
            f"formula uses atoms {unknown} that are not among the known atoms {list(atoms_t)}"
        )
    return atoms_t


def ltlf_to_dfa(formula: Formula | str, atoms: Sequence[str] | None = None) -> DFA:
    """Minimal complete DFA accepting exactly the non-empty traces that satisfy ``formula``.

    Parameters
    ----------
    formula : str or Formula
        LTLf formula (syntax in :mod:`robust_imdp.spec.ltlf`).
    atoms : sequence of str, optional
        Alphabet order (bit ``i`` = ``atoms[i]``). Must contain every atom of the formula; extra
        atoms are don't-cares. Default: the formula's atoms, sorted.

    Returns
    -------
    DFA
        Minimal, initial state 0, states in breadth-first order. Reference sizes:
        ``G !obs & F des`` 3, ``F des`` 2, ``G !o & F d1 & F d2`` 5.

    Raises
    ------
    FormulaSyntaxError
        If a string formula does not parse.
    UnknownAtomError
        If the formula uses an atom missing from ``atoms`` (named, with the known atoms listed).
    """
    text = formula if isinstance(formula, str) else str(formula)
    f = parse(formula) if isinstance(formula, str) else formula
    atoms_t = _resolve_atoms(f, atoms)
    _check_atoms(atoms_t)
    letters = [frozenset(a for i, a in enumerate(atoms_t) if m >> i & 1) for m in range(2 ** len(atoms_t))]

    prog = _Progressor()
    init = _dnf(to_nnf(f))
    index = {init: 0}
    states = [init]
    rows: list[list[int]] = []
    i = 0
    while i < len(states):  # breadth-first exploration of the progression states
        row = []
        for letter in letters:
            t = prog.state(states[i], letter)
            if t not in index:
                index[t] = len(states)
                states.append(t)
            row.append(index[t])
        rows.append(row)
        i += 1
    delta = np.array(rows, dtype=np.int64)
    accepting = np.array(
        [any(all(_accepts_empty(e) for e in clause) for clause in s) for s in states], dtype=bool
    )

    # The empty trace is not an LTLf trace: a fresh initial state with the same outgoing
    # transitions may accept or not. Minimise both and keep the smaller (tie: the convention).
    best = None
    for acc0 in (bool(accepting[0]), not accepting[0]):
        d2 = np.vstack([delta, delta[0:1]])
        a2 = np.append(accepting, acc0)
        md, ma = _minimize_table(d2, len(states), a2)
        if best is None or md.shape[0] < best[0].shape[0]:
            best = (md, ma)
    return DFA(atoms_t, best[0], 0, best[1], text)


# --------------------------------------------------------------------------- readings of a specification
#: The values of ``[spec].semantics`` (``Problem.semantics``): "auto" picks a reading from the DFA (:func:`classify`).
SEMANTICS = ("auto", "reach", "safety")
#: The two readings of a specification over the paths of the system (README, "Two readings of a formula").
READINGS = ("reach", "safety")


@dataclass(frozen=True)
class SpecKind:
    """What a specification's DFA says about prefixes, and the reading ``semantics = "auto"`` takes.

    The two readings of a formula over a path ``x_0 x_1 ...`` (of ``horizon + 1`` states, or infinite):

    * **reach** (the paper's): the path satisfies the formula when some prefix is accepted by the DFA;
    * **safety**: the path satisfies it when no prefix is a *bad prefix*, i.e. the DFA's run never enters a
      state from which acceptance is impossible (:attr:`DFA.sink_states`) and the path never leaves X.

    Attributes
    ----------
    co_safety : bool
        Every extension of an accepted trace is accepted: the accepting states reachable from the initial
        state by a non-empty trace only lead to accepting states. Then "some prefix is accepted" is the
        formula's own meaning (``F goal``, ``a U b``, ``F a & F b``).
    safety : bool
        Every violation shows in a finite bad prefix: with every strong next ``X`` outside an eventuality
        (``F f``, the right of ``f U g``) read as a weak next ``WX`` (they agree on infinite paths), every state reachable by a non-empty trace from which
        acceptance is still possible is accepting, i.e. every prefix of an accepted trace is accepted
        (``G safe``, ``G (a -> X b)``, ``safe R ok``). Then "no bad prefix" is the formula's own meaning,
        with a requirement of a strong next still pending at the last step of a horizon counted as met.
    reading : {"reach", "safety"}
        The reading ``semantics = "auto"`` takes: "reach" when ``co_safety``; else "safety" when ``safety``;
        else "reach", the paper's reading of a formula that is neither (``G !obs & F goal``: reach goal
        while avoiding obs until then; what happens after the goal is not constrained).
    reason : str
        Why, in one sentence (printed with the reading).
    """

    co_safety: bool
    safety: bool
    reading: str
    reason: str


def _reachable_after_letter(dfa) -> np.ndarray:
    """(S,) bool: states reachable from the initial state by a non-empty trace."""
    delta = np.asarray(dfa.delta)
    reach = np.zeros(delta.shape[0], dtype=bool)
    frontier = np.unique(delta[int(dfa.initial)])
    reach[frontier] = True
    while frontier.size:
        nxt = np.unique(delta[frontier])
        nxt = nxt[~reach[nxt]]
        reach[nxt] = True
        frontier = nxt
    return reach


def _universal(delta: np.ndarray, accepting: np.ndarray) -> np.ndarray:
    """(S,) bool: states from which every reachable state is accepting (every extension is accepted)."""
    return ~_coreachable(delta, ~np.asarray(accepting, dtype=bool))


def _closed(dfa) -> bool:
    """Whether every state reachable by a non-empty trace from which acceptance is possible is accepting."""
    delta, acc = np.asarray(dfa.delta), np.asarray(dfa.accepting, dtype=bool)
    live = _reachable_after_letter(dfa) & _coreachable(delta, acc)
    return bool(np.all(acc[live]))


def _weak_next_dfa(dfa):
    """The DFA of the formula with its strong nexts read as weak ones outside eventualities (in negation normal
    form, where both occur only positively, so the language can only grow), or None for a DFA without a
    parsable formula."""
    text = getattr(dfa, "formula", None)
    if not isinstance(text, str):
        return None
    try:
        f = to_nnf(parse(text))
    except InvalidInputError:
        return None

    def weak(g):
        # an eventuality's operand (F f, the right of f U g) keeps its strong nexts: WX is true at the end of
        # a finite trace, so weakening there would discharge the eventuality (F (a | X b) would become valid)
        if isinstance(g, Next):
            return WeakNext(weak(g.operand))
        if isinstance(g, (WeakNext, Globally)):
            return type(g)(weak(g.operand))
        if isinstance(g, Until):
            return Until(weak(g.left), g.right)
        if isinstance(g, (And, Or, Release)):
            return type(g)(weak(g.left), weak(g.right))
        return g  # Top, Bottom, Atom, Not(Atom), F f

    return ltlf_to_dfa(weak(f), tuple(dfa.atoms))


def classify(dfa) -> SpecKind:
    """Co-safety, safety, or neither: the DFA-based classification of a specification (:class:`SpecKind`).

    Parameters
    ----------
    dfa : DFA (duck type)
        With ``formula`` (a DFA of :func:`ltlf_to_dfa`), the safety test reads the formula with ``X`` as
        ``WX`` outside eventualities (:attr:`SpecKind.safety`); a DFA without a formula is tested as it is.

    Returns
    -------
    SpecKind

    Examples
    --------
    >>> [classify(ltlf_to_dfa(f)).reading for f in ("F goal", "G safe", "G (a -> X b)", "G !obs & F goal")]
    ['reach', 'safety', 'safety', 'reach']
    """
    delta, acc = np.asarray(dfa.delta), np.asarray(dfa.accepting, dtype=bool)
    reach = _reachable_after_letter(dfa)
    co_safety = bool(np.all(acc[np.unique(delta[reach & acc])])) if np.any(reach & acc) else True
    weak = _weak_next_dfa(dfa)
    safety = _closed(weak if weak is not None else dfa)
    name = repr(dfa.formula) if isinstance(getattr(dfa, "formula", None), str) else "the specification"
    if co_safety:
        reason = (f"{name} is co-safety: every extension of an accepted prefix is accepted, so reaching an "
                  "accepting prefix decides it")
        reading = "reach"
    elif safety:
        reason = (f"{name} is safety: every violation shows in a finite bad prefix, after which no extension "
                  "is accepted")
        reading = "safety"
    else:
        reason = (f"{name} is neither safety nor co-safety; the reach reading takes the first accepted prefix "
                  "(e.g. G !obs & F goal: reach goal, avoiding obs until then)")
        reading = "reach"
    return SpecKind(co_safety=co_safety, safety=safety, reading=reading, reason=reason)


def resolve_semantics(dfa, semantics: str = "auto") -> tuple:
    """``(reading, kind)``: the reading ``semantics`` asks for ("auto": :attr:`SpecKind.reading`) and the
    DFA's :class:`SpecKind`.

    Raises
    ------
    InvalidInputError
        ``semantics`` is not one of :data:`SEMANTICS`.
    """
    if semantics not in SEMANTICS:
        raise InvalidInputError(f"semantics must be one of {', '.join(map(repr, SEMANTICS))}; got {semantics!r}")
    kind = classify(dfa)
    return (kind.reading if semantics == "auto" else semantics), kind


def check_reading(dfa, letters, reading: str, kind: SpecKind | None = None) -> None:
    """Refuse a specification that the cells decide by their labels alone under ``reading``; warn where the
    reading drops part of it.

    Parameters
    ----------
    dfa : DFA (duck type)
    letters : (n_cells,) int array
        Every cell's letter over ``dfa.atoms``.
    reading : {"reach", "safety"}
    kind : SpecKind, optional
        :func:`classify`'s answer (computed when omitted).

    Raises
    ------
    VacuousSpecificationError
        * reach: every cell's one-state trace is accepted or a bad prefix, and some accepted one has
          an extension that is not: the result would be ``p_low = 1`` from the label alone, whatever
          the dynamics (``G safe`` read as reach);
        * safety: no trace from any cell can reach a bad prefix: only leaving X could violate the
          formula (``F goal`` read as safety).

    Warns
    -----
    SpecificationWarning
        * reach on a safety formula that some cells satisfy by their own label;
        * safety on a formula that is not safety (its "eventually" parts are dropped).
    """
    import warnings

    kind = classify(dfa) if kind is None else kind
    delta, acc = np.asarray(dfa.delta), np.asarray(dfa.accepting, dtype=bool)
    first = delta[int(dfa.initial), np.asarray(letters, dtype=np.int64)]
    dead = ~_coreachable(delta, acc)
    name = repr(dfa.formula) if isinstance(getattr(dfa, "formula", None), str) else "the specification"
    if reading == "reach":
        decided = acc[first] | dead[first]
        early = acc[first] & ~_universal(delta, acc)[first]  # accepted now, but a later step could violate it
        if first.size and np.all(decided) and np.any(early):
            raise VacuousSpecificationError(
                f"under the reach reading (some prefix accepted) {name} is satisfied by the one-state trace of "
                f"{int(np.count_nonzero(acc[first]))} of {first.size} cells and violated by that of the others: "
                "every cell would get p_low in {0, 1} from its own label, whatever the dynamics. "
                + ("It is a safety formula: write [spec].semantics = \"safety\" (or \"auto\") to require that no "
                   "prefix within the horizon (or ever, without one) is a bad prefix" if kind.safety else
                   "Write a formula that needs the future, e.g. F goal or G !obs & F goal, or "
                   "[spec].semantics = \"safety\""))
        if kind.safety and not kind.co_safety and np.any(early):
            warnings.warn(
                f"{name} is a safety formula read as reach ([spec].semantics = \"reach\"): "
                f"{int(np.count_nonzero(early))} of {first.size} cells satisfy it by their own label (p_low = 1 "
                "whatever happens next); [spec].semantics = \"safety\" requires no bad prefix instead",
                SpecificationWarning, stacklevel=3)
        return
    if reading != "safety":
        raise InvalidInputError(f"reading must be 'reach' or 'safety'; got {reading!r}")
    can_fail = _coreachable(delta, dead) & ~dead  # live states from which a bad prefix can follow
    if first.size and not np.any(dead[first] | can_fail[first]):
        raise VacuousSpecificationError(
            f"under the safety reading (no bad prefix) {name} cannot be violated from any cell: it has no bad "
            "prefix, so only leaving X would count, and every probability would be that of staying in X. "
            + ("It is co-safety: write [spec].semantics = \"reach\" (or \"auto\"), where a path satisfies it "
               "when some prefix is accepted" if kind.co_safety else
               "Write [spec].semantics = \"reach\", or a safety formula such as G safe"))
    if not kind.safety:
        warnings.warn(
            f"{name} is not a safety formula but is read as safety ([spec].semantics = \"safety\"): a path counts "
            "as satisfying it while no bad prefix occurs, so its eventualities (F, U, X) need not be met; "
            "[spec].semantics = \"reach\" requires an accepted prefix instead", SpecificationWarning, stacklevel=3)
