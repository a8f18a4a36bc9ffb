"""Robust strategy synthesis on the abstraction: IMDP + cell labels + DFA -> SynthesisResult.

Implements the paper's Sec. 5 ("Strategy Synthesis") on the product of :mod:`robust_imdp.solvers.product`
(standard label semantics: the initial product state of cell ``q`` is ``(q, delta(s0, L(q)))``):

* the robust strategy ``pi = argmax_pi min_adversary P(reach accept)``          (eq. strategy-near-optimal)
* ``p_low(q) = min_adversary P(... | pi)``                                        (eq. plow)
* ``p_up(q)  = max_adversary P(... | pi)``                                        (eq. pup)
* ``p_up_star(q) = max_pi max_adversary P(...)``                                  (eq. prob-upper-bound)
* ``error = p_up_star - p_low`` (Thm. 2) and the classes ``Q_yes`` (``p_low >= threshold``),
  ``Q_no`` (``p_up < threshold``), ``Q_?`` (otherwise).

Soundness. Every solver call returns a sound bracket ``[lower, upper]`` of the value it
approximates. We report

* ``p_low``  = the LOWER end of the bracket of pi's value against the minimising adversary,
* ``p_up``   = ``min(U1, U2)`` with ``U1`` the UPPER end of the bracket of pi's value against the
  maximising adversary and ``U2 = p_up_star``; both are upper bounds of that value because
  ``max_adv P(pi) <= max_pi max_adv P`` -- so the minimum is one too,
* ``p_up_star`` = the UPPER end of the bracket of the optimistic (max, max) value.

Hence ``p_low <= p_up <= p_up_star`` holds exactly: ``p_up <= p_up_star`` by the minimum, and
``p_low <= true value <= p_up`` because both are sound bounds of ordered true values (checked; a
violation raises :class:`~robust_imdp.errors.SoundnessError`). The classes can therefore never
be both "yes" and "no". ``p_low`` is computed by *evaluating* the returned strategy (not read off
the max-min iteration, whose lower bracket belongs to the optimal value, not to ``pi``).

Which action among equals. Where several actions reach the best lower value (all of them where
the lower value is 0) the choice is lexicographic: best lower value, then -- with a ``nominal``
model (:mod:`robust_imdp.abstraction.nominal`: the fitted or known dynamics at a few points of
each cell and the noise) -- the best value under the nominal model, then the best optimistic value
``max_p p.U`` with U the upper bound of the max-max value (the vector whose initial states give
``p_up_star``): it is the best any controller can still hope for after the step. The nominal
value is what separates "into the obstacle" from "round it" when no action has a guaranteed
positive value; the optimistic value alone is 1 for several actions there (the adversary of the
optimistic solve may always steer round). Where the lower value is 0 for every action the
nominal solve's own action is used, else the optimistic solve's (each makes progress towards
acceptance in its model; a choice by values alone can circle, see :mod:`robust_imdp.solvers.engine`).
Under the safety reading the same keys choose among the actions of exactly least upper bound of the
bad-prefix probability (:mod:`robust_imdp.synthesis.ties`). The tie tolerance is
``robust_imdp.solvers.engine._TIE_TOL`` (1e-12, absolute). The strategy is then evaluated as
any other, and it is checked that its ``p_low`` keeps the optimal robust lower value at every
cell (``_keeps_optimal_lower``); if it did not, the first-choice strategy would be used.
``no_strategy_can`` (``p_up_star < threshold``) marks the Q_no cells where no controller can meet
the threshold; the other Q_no cells are "no" under the returned controller only.

Two readings (README, "Two readings of a formula"; :func:`robust_imdp.spec.dfa.classify`). Under the
*reach* reading (the paper's) a path satisfies the formula when some prefix -- within the horizon, if
one is set -- is accepted: accepting product states are absorbing targets, as above. Under the
*safety* reading a path satisfies it when no prefix is a bad prefix (the DFA never enters a state
from which acceptance is impossible) and the path never leaves X. It is solved as one minus a
reachability value with the objective and the adversaries swapped: the bad nodes (DFA sinks, the
outside state) are the target, the controller *minimises* the probability of reaching them and the
pessimistic adversary maximises it, so

* ``pi = argmin_pi max_adv P(reach bad)`` (the minimising controller of
  :func:`robust_imdp.solvers.engine.solve_layered`),
* ``p_low = 1 - U`` with U the UPPER end of the bracket of ``max_adv P(reach bad | pi)``,
* ``p_up = min(1 - L, p_up_star)`` with L the LOWER end of the bracket of ``min_adv P(reach bad | pi)``,
* ``p_up_star = 1 - L*`` with L* the LOWER end of the bracket of ``min_pi min_adv P(reach bad)``,

each complement rounded outward (``_fp.complement_down`` / ``complement_up``;
:mod:`robust_imdp.solvers.product` returns the satisfaction brackets). The argument for
``p_low <= p_up <= p_up_star`` above carries over word for word.

k steps (joint models). Each solve iterates only the ends of its bracket that are read (``need`` of
:func:`robust_imdp.solvers.product.solve_product`): the optimistic solve its upper end (``p_up_star``), the robust
solve its lower end and strategy, the nominal solve only the upper values its key reads, the optimistic
evaluation its upper end (``p_up``); the pessimistic evaluation both (``p_low``, and its width is the tolerance of
``_keeps_optimal_lower``). Under the safety reading the engine's ends are the satisfaction bracket's swapped,
so some solves need both. An end not iterated is its trivial sound bound (0 or 1), and its run says so
(``SolverRun.ends``, ``max_gap`` nan); the ends that are read are the same bits as with every end iterated.
The keys' k-step values are the optimistic and the nominal solves' upper values: those solves keep the row
values of every step (``keep_steps``) and the keys read them instead of iterating them again. On car parking
(``benchmarks/finite_horizon.py``) this is 3 full sweeps per step instead of 9.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any, Sequence

import numpy as np

from robust_imdp import _fp
from robust_imdp.solvers import product as _product
from robust_imdp.synthesis.controller import Controller, remap_letters  # below synthesis: numpy only
from robust_imdp.synthesis import ties as _ties
from robust_imdp.spec.api import check_reading, is_dfa, resolve_semantics
from robust_imdp.errors import ConvergenceWarning, DimensionError, InvalidInputError, SoundnessError
from robust_imdp.models.factored import FactoredIMDP
from robust_imdp.models.imdp import IMDP

__all__ = ["SolverRun", "SynthesisResult", "synthesize", "robust_lower", "remap_letters"]

CLASS_YES, CLASS_NO, CLASS_MAYBE = "yes", "no", "maybe"

#: One ulp towards +inf: the outward rounding of upper bounds computed by a subtraction.
_round_up = _fp.up


# --------------------------------------------------------------------------- results
@dataclass(frozen=True)
class SolverRun:
    """Diagnostics of one product solve.

    Attributes
    ----------
    name : str
        ``"robust"`` (max-min, gives the strategy), ``"optimistic"`` (max-max, gives p_up_star),
        ``"evaluate_pessimistic"`` / ``"evaluate_optimistic"`` (the strategy against both adversaries),
        ``"nominal"`` (the nominal model's solve that ranks actions of equal robust value).
    iterations : int
    converged : bool
    max_gap : float
        Largest width ``upper - lower`` of the value bracket at the cells' initial states; nan where only one
        end was iterated.
    ends : {"both", "lower", "upper"}
        The ends of the solve's bracket that were iterated: with a horizon (joint models) a solve computes only
        the ends that are read of it (module docstring, "k steps").
    """

    name: str
    iterations: int
    converged: bool
    max_gap: float
    ends: str = "both"


@dataclass(frozen=True, eq=False)
class SynthesisResult:
    """Robust strategy and satisfaction bounds for every cell (read fields by name).

    Attributes
    ----------
    strategy : (n_cells, S) int array, or (k, n_cells, S) for a k-step horizon
        Mode index to apply in cell ``q`` when the DFA is in state ``s`` (``strategy[t, q, s]`` at
        time ``t``). Entries for accepting or sink DFA states are never used.
    p_low : (n_cells,) float
        LOWER end of the sound bracket of ``min_adv P(spec | pi)`` from the cell's initial product
        state: a guaranteed lower bound of the satisfaction probability under ``pi``.
    p_up : (n_cells,) float
        An UPPER bound of ``max_adv P(spec | pi)`` (the smaller of the UPPER end of its bracket and
        ``p_up_star``).
    p_up_star : (n_cells,) float
        UPPER end of the sound bracket of ``max_pi max_adv P(spec)``.
    error : (n_cells,) float
        ``p_up_star - p_low`` rounded up: bounds the distance to the optimal switching strategy.
    classes : (n_cells,) str array of "yes" / "no" / "maybe"
    initial_dfa_state : (n_cells,) int
        ``delta(s0, L(q))``.
    labels : (n_cells,) int
        Cell letters w.r.t. ``dfa.atoms``.
    dfa : DFA
    threshold : float
    horizon : int or None
    n_modes : int
    runs : tuple of SolverRun
    precision : float
    strategy_choice : str
        ``"lexicographic"``: among actions of (tied) best lower value, the best optimistic value
        (module docstring); ``"first"``: the first such action, used only when the
        lexicographic strategy would have a smaller ``p_low`` somewhere (never seen; kept as a
        safeguard); ``"least"`` (safety reading): at every node an action of least value against
        the proven upper bound of the probability of a bad prefix.
    semantics : {"reach", "safety"}
        The reading the bounds are of (module docstring, "Two readings").
    tie_keys : tuple of str
        The keys that chose among actions of equal robust value, in order: ``("nominal", "optimistic")``
        with a nominal model, else ``("optimistic",)`` (module docstring, "Which action among equals").
    """

    strategy: np.ndarray
    p_low: np.ndarray
    p_up: np.ndarray
    p_up_star: np.ndarray
    error: np.ndarray
    classes: np.ndarray
    initial_dfa_state: np.ndarray
    labels: np.ndarray
    dfa: Any  # a DFA (duck type, docs/ARCHITECTURE.md)
    threshold: float
    horizon: int | None
    n_modes: int
    runs: tuple
    precision: float
    strategy_choice: str = "lexicographic"
    semantics: str = "reach"
    tie_keys: tuple = ("optimistic",)

    @property
    def n_cells(self) -> int:
        """Number of cells."""
        return int(self.p_low.shape[0])

    @property
    def no_strategy_can(self) -> np.ndarray:
        """(n_cells,) bool: ``p_up_star < threshold``, no strategy at all can meet the threshold
        (p_up_star bounds every strategy's value from above, eq. prob-upper-bound); a refinement
        of Q_no, whose other cells are "no" only under the returned controller."""
        return np.asarray(self.p_up_star) < self.threshold

    def class_counts(self) -> dict:
        """``{"yes": n, "no": n, "maybe": n}``."""
        return {c: int(np.count_nonzero(self.classes == c)) for c in (CLASS_YES, CLASS_NO, CLASS_MAYBE)}

    def controller(self, partition: Any, mode_names: Sequence[str] | None = None, inputs: Any = None):
        """The refined switching controller (paper eq. mapping-strategy) on ``partition``.

        Parameters
        ----------
        partition : geometry.Partition
            The partition whose cells are this result's IMDP states (same cell order and labels).
        mode_names : sequence of str, optional
            Names returned by :meth:`Controller.act` instead of mode indices.
        inputs : models.inputs.InputGrid or (n_modes, m) array, optional
            The modes' input vectors, returned by :meth:`Controller.act_input`.
        """
        return Controller.from_result(self, partition, mode_names=mode_names, inputs=inputs)


# --------------------------------------------------------------------------- helpers
def _check_labels(labels: Any, atoms: Sequence[str]) -> np.ndarray:
    lab = np.asarray(labels)
    if lab.ndim != 1:
        raise DimensionError(f"labels must be a 1-D (n_cells,) int array; got shape {lab.shape}")
    if lab.size and not np.issubdtype(lab.dtype, np.integer):
        raise InvalidInputError(f"labels must hold integer letters; got dtype {lab.dtype}")
    lab = lab.astype(np.int64)
    bad = np.flatnonzero((lab < 0) | (lab >= 2 ** len(atoms)))
    if bad.size:
        raise InvalidInputError(
            f"labels must be letters in [0, 2**{len(atoms)}) over atoms {list(atoms)}; "
            f"labels[{int(bad[0])}] = {int(lab[bad[0]])}"
        )
    return lab


def _check_threshold(threshold: Any) -> float:
    if isinstance(threshold, bool) or not isinstance(threshold, Real) or not 0.0 <= float(threshold) <= 1.0:
        raise InvalidInputError(f"threshold must be a probability in [0, 1]; got {threshold!r}")
    return float(threshold)


def _check_horizon(horizon: Any) -> int | None:
    if horizon is None:
        return None
    if isinstance(horizon, bool) or not isinstance(horizon, Integral) or horizon < 1:
        raise InvalidInputError(f"horizon must be None (unbounded) or an int >= 1; got {horizon!r}")
    return int(horizon)


def _keeps_optimal_lower(ev_low: Any, robust: Any, n_cells: int, precision: float) -> bool:
    """Whether the evaluated strategy keeps the optimal robust lower value at every cell.

    Its lower bracket end ``ev_low.initial_lower`` must reach the optimum's ``robust.initial_lower``
    within the width of its own bracket plus ``precision``: if the strategy is optimal, both
    brackets contain the same value, so ``ev_low.lower >= V - gap >= robust.lower - gap``; the
    extra ``precision`` absorbs the tie tolerance of the strategy extraction (1e-12 per step).
    """
    got = np.asarray(ev_low.initial_lower, dtype=np.float64)[:n_cells]
    best = np.asarray(robust.initial_lower, dtype=np.float64)[:n_cells]
    return bool(np.all(got >= best - (float(ev_low.precision) + float(precision))))


def _run(name: str, res: Any, n_cells: int) -> SolverRun:
    ends = getattr(res, "ends", "both")
    if ends != "both":  # the other end is its trivial bound: no width to report
        return SolverRun(name, int(res.iterations), bool(res.converged), float("nan"), ends)
    gap = np.asarray(res.initial_upper)[:n_cells] - np.asarray(res.initial_lower)[:n_cells]
    return SolverRun(name, int(res.iterations), bool(res.converged), float(gap.max(initial=0.0)))


# --------------------------------------------------------------------------- synthesis
def synthesize(
    imdp: IMDP,
    labels: Any,
    atoms: Sequence[str],
    dfa: Any,
    *,
    threshold: float,
    horizon: int | None = None,
    outside_state: int | None = None,
    precision: float = 1e-8,
    method: str = "vi",
    semantics: str = "auto",
    nominal: Any = None,
) -> SynthesisResult:
    """Robust strategy, bounds ``p_low <= p_up <= p_up_star`` and classes for every cell.

    Parameters
    ----------
    imdp : IMDP or FactoredIMDP
        Abstraction: states ``0 .. n_cells-1`` are cells, then (optionally) the outside-X state;
        the choice index within a state is the mode index. A factored model (docs/factored.md, "In
        synthesis") is solved by :func:`robust_imdp.solvers.factored.solve_factored_product` in every
        solve (same product, readings, horizons and lexicographic choice; its bracket is of the factored
        operator's value, which is below the product set's for the adversary against the controller), and
        always has the outside state ``n_cells``.
    labels : (n_cells,) int array
        Letter of each cell w.r.t. ``atoms`` (e.g. ``partition.labels``).
    atoms : sequence of str
        Atom order of ``labels`` (e.g. ``partition.atoms``); must contain ``dfa.atoms``.
    dfa : DFA
        Automaton of the specification: any object of the DFA duck type (docs/ARCHITECTURE.md;
        :func:`robust_imdp.spec.api.to_dfa` makes one from an LTLf formula).
    threshold : float in [0, 1]
        Probability threshold of the classification.
    horizon : int >= 1, optional
        Number of steps for a k-step (bounded) objective; ``None`` for unbounded.
    outside_state : int, optional
        Index of the absorbing outside-X state, which must be ``n_cells`` (then
        ``imdp.n_states == n_cells + 1``); it is never accepting. ``None`` when the IMDP has
        no outside state (``imdp.n_states == n_cells``).
    precision : float
        Target width of the value brackets of the unbounded solves.
    method : str
        Algorithm of the product solves (a name of :data:`robust_imdp.solvers.engine.METHODS`); a factored
        model has one (value iteration with the factored operator) and ignores it.
    semantics : {"auto", "reach", "safety"}
        The reading of the specification (module docstring, "Two readings"): "reach", a path satisfies
        it when some prefix is accepted; "safety", when no prefix is a bad prefix and the path stays in X;
        "auto" (default), the reading :func:`robust_imdp.spec.dfa.classify` gives the DFA (safety for a
        safety formula such as ``G safe``, reach otherwise).
    nominal : IMDP or FactoredIMDP, optional
        A nominal model of the same states and modes (:func:`robust_imdp.abstraction.nominal.nominal_abstraction`):
        among actions of equal robust value, the one of best value under it is chosen (module docstring,
        "Which action among equals"). It changes the strategy only, never how its bounds are computed.

    Returns
    -------
    SynthesisResult

    Raises
    ------
    InvalidInputError, DimensionError, UnknownAtomError
        Bad threshold/horizon, wrong label length, unknown atoms.
    VacuousSpecificationError
        Under the reading in use the cells' own labels decide the specification
        (:func:`robust_imdp.spec.dfa.check_reading`).
    SoundnessError
        If the solver's brackets contradict ``p_low <= p_up`` (a bug, never repaired).
    """
    threshold, horizon, atoms, lab, avoid = _check_inputs(imdp, labels, atoms, dfa, threshold, horizon,
                                                          outside_state)
    n_cells = int(lab.shape[0])
    cell_letters = remap_letters(lab, atoms, dfa.atoms)
    reading, kind = resolve_semantics(dfa, semantics)
    check_reading(dfa, cell_letters, reading, kind)
    # the outside state's letter is never read: it is absorbing, never accepting (avoid; a bad node under
    # the safety reading)
    letters = np.concatenate([cell_letters, np.zeros(imdp.n_states - n_cells, dtype=np.int64)])

    kw = dict(avoid=avoid, horizon=horizon, precision=precision, method=method, semantics=reading)
    nominal = _ties.check_nominal(nominal, imdp)
    optimistic, robust, ev_low, ev_up, pi, choice, extra_runs = _solve(imdp, letters, dfa, n_cells, precision, kw,
                                                                       nominal)
    p_low, p_up, p_up_star, error, classes = _bounds(optimistic, ev_low, ev_up, n_cells, threshold)

    if horizon is None:
        strategy = pi[:, :n_cells].T  # (S, n) -> (n_cells, S)
    else:
        strategy = np.transpose(pi[:, :, :n_cells], (0, 2, 1))  # (k, S, n) -> (k, n_cells, S)
    strategy = np.ascontiguousarray(strategy, dtype=np.int64)
    init = np.asarray(robust.initial_state, dtype=np.int64)[:n_cells].copy()
    arrays = [strategy, p_low, p_up, p_up_star, error, classes, init, cell_letters]
    for a in arrays:
        a.setflags(write=False)
    runs = (
        _run("robust", robust, n_cells),
        _run("optimistic", optimistic, n_cells),
        _run("evaluate_pessimistic", ev_low, n_cells),
        _run("evaluate_optimistic", ev_up, n_cells),
    ) + extra_runs
    return SynthesisResult(
        strategy=strategy, p_low=p_low, p_up=p_up, p_up_star=p_up_star, error=error,
        classes=classes, initial_dfa_state=init, labels=cell_letters, dfa=dfa,
        threshold=threshold, horizon=horizon, n_modes=_n_modes(imdp),
        runs=runs, precision=float(precision), strategy_choice=choice, semantics=reading,
        tie_keys=_ties.TIE_KEYS[nominal is not None],
    )


def robust_lower(imdp, labels: Any, atoms: Sequence[str], dfa: Any, *, horizon: int | None = None,
                 outside_state: int | None = None, precision: float = 1e-8, semantics: str = "auto") -> np.ndarray:
    """Per cell the robust solve's proven lower value: the satisfaction probability the best strategy is
    guaranteed (to ``precision``), which is what Q_yes reads (``p_low >= threshold``), from the one solve of
    :func:`synthesize` that computes it: no optimistic solve, no tie keys (they choose among modes of equal lower
    value), no evaluations of the strategy (``synthesize``'s ``p_low`` is the evaluation of its tie-broken
    strategy, which keeps this value to the brackets' widths). For estimates that read only Q_yes (the advice's
    re-solves); the arguments are :func:`synthesize`'s.

    Returns
    -------
    (n_cells,) float array, read-only
    """
    _, horizon, atoms, lab, avoid = _check_inputs(imdp, labels, atoms, dfa, 0.5, horizon, outside_state)
    n_cells = int(lab.shape[0])
    cell_letters = remap_letters(lab, atoms, dfa.atoms)
    reading, kind = resolve_semantics(dfa, semantics)
    check_reading(dfa, cell_letters, reading, kind)
    letters = np.concatenate([cell_letters, np.zeros(imdp.n_states - n_cells, dtype=np.int64)])
    solve_product, _ = _solvers(imdp)
    # k steps, joint: the lower end only (``need``; the upper one is then its trivial bound, not read here)
    need = {"need": ("lower",)} if not isinstance(imdp, FactoredIMDP) and horizon is not None else {}
    robust = solve_product(imdp, letters, dfa, adversary="pessimistic", avoid=avoid, horizon=horizon,
                           precision=precision, method="vi", semantics=reading, **need)
    out = np.array(np.asarray(robust.initial_lower)[:n_cells], dtype=np.float64)
    out.setflags(write=False)
    return out


def _check_inputs(imdp, labels, atoms, dfa, threshold, horizon, outside_state):
    """The checked inputs of :func:`synthesize`: (threshold, horizon, atoms tuple, labels as int64,
    avoid = the outside state or None)."""
    if not isinstance(imdp, (IMDP, FactoredIMDP)):
        raise InvalidInputError(f"imdp must be an IMDP or a FactoredIMDP; got {type(imdp).__name__}")
    if not is_dfa(dfa):
        raise InvalidInputError(f"dfa must be a DFA; got {type(dfa).__name__}")
    threshold = _check_threshold(threshold)
    horizon = _check_horizon(horizon)
    if isinstance(atoms, str):
        raise InvalidInputError(f"atoms must be a sequence of atom names; got the str {atoms!r}")
    atoms = tuple(atoms)
    lab = _check_labels(labels, atoms)
    n_cells = int(lab.shape[0])
    if outside_state is None:
        if imdp.n_states != n_cells:
            raise DimensionError(
                f"labels must have one entry per IMDP state ({imdp.n_states}) when outside_state is "
                f"None; got {n_cells} (pass outside_state=n_cells if the last state is outside X)"
            )
        avoid = None
    else:
        if outside_state != n_cells or imdp.n_states != n_cells + 1:
            raise DimensionError(
                f"outside_state must be n_cells = len(labels) = {n_cells} with imdp.n_states = "
                f"n_cells + 1; got outside_state={outside_state!r}, imdp.n_states={imdp.n_states}"
            )
        avoid = np.array([n_cells], dtype=np.int64)
    return threshold, horizon, atoms, lab, avoid


def _n_modes(model) -> int:
    return int(model.n_modes) if isinstance(model, FactoredIMDP) else int(model.n_choices_of().max())


def _solvers(model):
    """``(solve_product, evaluate_product_strategy)`` for the model's kind: the joint solvers of
    :mod:`robust_imdp.solvers.product`, or :func:`~robust_imdp.solvers.factored.solve_factored_product` with the
    same arguments and results (``control="maximize"``: the reported value is the satisfaction probability, and
    "pessimistic" minimises it under both readings, as the joint solvers read it; ``method`` does not apply)."""
    if not isinstance(model, FactoredIMDP):
        return _product.solve_product, _product.evaluate_product_strategy
    from robust_imdp.solvers.factored import solve_factored_product

    def solve(m, letters, dfa, *, adversary, tie_break=None, method=None, **kw):
        return solve_factored_product(m, letters, dfa, adversary=adversary, tie_break=tie_break, control="maximize",
                                      **kw)

    def evaluate(m, letters, dfa, strategy, *, adversary, method=None, **kw):
        return solve_factored_product(m, letters, dfa, adversary=adversary, strategy=strategy, control="maximize",
                                      **kw)

    return solve, evaluate


def _solve(imdp, letters, dfa, n_cells, precision, kw, nominal=None):
    """The product solves of :func:`synthesize`: (optimistic, robust, ev_low, ev_up, strategy,
    strategy_choice, extra runs)."""
    solve_product, evaluate_product_strategy = _solvers(imdp)
    safety = kw["semantics"] == "safety"
    # k steps, joint: each solve computes only what is read of it (``need``, module docstring "k steps"), and the
    # optimistic solve keeps its upper rows, which the keys of the nominal and the robust solves read instead of
    # iterating the same values again (solvers.product.TieKey; the same bits)
    sub = not isinstance(imdp, FactoredIMDP) and kw.get("horizon") is not None
    keys_read = not safety or nominal is not None
    need = (lambda *parts: {"need": parts}) if sub else (lambda *parts: {})
    keep = {"keep_steps": keys_read} if sub else {}
    optimistic = solve_product(imdp, letters, dfa, adversary="optimistic", **kw, **keep, **need("upper"))
    if isinstance(imdp, FactoredIMDP) and imdp.n_modes == 1:
        # one mode: every strategy is that mode, so the robust solve is its pessimistic evaluation and the
        # optimistic solve its optimistic one (the same operator applied to the same vectors): two solves, not four
        robust = solve_product(imdp, letters, dfa, adversary="pessimistic", **kw)
        return optimistic, robust, robust, optimistic, np.asarray(robust.strategy), \
            ("least" if safety else "lexicographic"), ()
    # Lexicographic choice: best lower value, then the nominal model's value, then the best optimistic value
    # (module docstring; synthesis.ties). Safety: the minimising controller's least rows against the proven upper
    # bound (solvers.engine._minimising_strategy), then the same keys.
    ties, nom = _ties.tie_break(imdp, nominal, letters, dfa, optimistic, kw)
    robust = solve_product(imdp, letters, dfa, adversary="pessimistic", tie_break=ties, **kw,
                           **need("lower", "strategy"))
    pi = np.asarray(robust.strategy)
    ev_low = evaluate_product_strategy(imdp, letters, dfa, pi, adversary="pessimistic", **kw)
    choice = "least" if safety else "lexicographic"
    extra_runs = () if nom is None else (_run("nominal", nom, n_cells),)
    if safety:
        if not _keeps_optimal_lower(ev_low, robust, n_cells, precision):
            # its bounds are still sound (they are its own evaluation), only below the best ones
            gap = np.asarray(robust.initial_lower)[:n_cells] - np.asarray(ev_low.initial_lower)[:n_cells]
            warnings.warn(f"the safety strategy's guaranteed value is below the optimal robust lower value by up "
                          f"to {float(gap.max()):.3g} (more than the brackets' widths); its p_low is sound but not "
                          "optimal", ConvergenceWarning, stacklevel=3)
    elif not _keeps_optimal_lower(ev_low, robust, n_cells, precision):
        # the tie-broken strategy lost lower value somewhere (it must not): use the first-choice
        # extraction instead if that one does better anywhere
        first = solve_product(imdp, letters, dfa, adversary="pessimistic", **kw)
        ev_first = evaluate_product_strategy(imdp, letters, dfa, first.strategy, adversary="pessimistic", **kw)
        extra_runs += (_run("robust_first_choice", first, n_cells),
                       _run("evaluate_first_choice", ev_first, n_cells))
        tol = ev_low.precision + ev_first.precision + precision
        if np.any(np.asarray(ev_first.initial_lower)[:n_cells] > np.asarray(ev_low.initial_lower)[:n_cells] + tol):
            robust, ev_low, pi, choice = first, ev_first, np.asarray(first.strategy), "first"
    ev_up = evaluate_product_strategy(imdp, letters, dfa, pi, adversary="optimistic", **kw, **need("upper"))
    return optimistic, robust, ev_low, ev_up, pi, choice, extra_runs


def _bounds(optimistic, ev_low, ev_up, n_cells, threshold):
    """(p_low, p_up, p_up_star, error, classes) of the cells from the solves (module docstring)."""
    p_low = np.array(ev_low.initial_lower, dtype=np.float64)[:n_cells]
    p_up_star = np.array(optimistic.initial_upper, dtype=np.float64)[:n_cells]
    # Both are upper bounds of max_adv P(pi): its own bracket's upper end, and p_up_star since
    # max_adv P(pi) <= max_pi max_adv P. Their minimum is an upper bound too, and <= p_up_star.
    p_up = np.minimum(np.array(ev_up.initial_upper, dtype=np.float64)[:n_cells], p_up_star)
    bad = np.flatnonzero(~(p_low <= p_up))
    if bad.size:
        q = int(bad[0])
        raise SoundnessError(
            f"cell {q}: p_low = {float(p_low[q])!r} > p_up = {float(p_up[q])!r}; the solver brackets are not sound"
        )
    # error bounds |P(pi_x) - p_opt| <= p_up_star - p_low (Thm. 2); round the difference up.
    # The clamp to 1 is safe: both are probabilities, so the true difference is at most 1.
    error = np.minimum(_round_up(p_up_star - p_low), 1.0)
    classes = np.where(p_low >= threshold, CLASS_YES, np.where(p_up < threshold, CLASS_NO, CLASS_MAYBE))
    return p_low, p_up, p_up_star, error, classes
