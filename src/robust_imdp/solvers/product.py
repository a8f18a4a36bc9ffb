"""IMDP x DFA product, solved lazily.

Semantics (the *standard* one; the paper's printed definition reads the first label twice):
from product state (q, s) under choice u the system moves to (q', delta(s, L(q'))); the initial
product state of cell q is (q, delta(s0, L(q))).  Accepting DFA states are absorbing targets;
``avoid`` states (the outside-X state) are absorbing, never accepting, value 0 in every layer;
DFA states that cannot reach acceptance are sinks with value 0.  That is the reach reading of the
specification; under the safety reading (``semantics="safety"``) the avoid states and the sinks are
the bad nodes the controller keeps away from, accepting states are not absorbing, and the value is
one minus the minimal probability of reaching a bad node (:func:`solve_product`).

Lazy: values live in an (S, n) array (DFA state, base state).  Layer s reuses the base IMDP's
rows with successor values ``w_s[q'] = V[delta(s, L(q')), q']`` (a gather: per entry in the
default Gauss-Seidel engine, per layer and sweep in the Jacobi one), so no product row is
materialised, memory stays that of the base IMDP plus O(S n) values (and the solver's row
orders, S bytes per base entry), and a floor row stays a floor row: its unlisted base states
are exactly the unlisted product successors reachable from layer s.  The soundness argument of
:mod:`robust_imdp.solvers.engine` applies verbatim to the layered operator (it is the Bellman operator of
the materialised product); its strongly connected components may span layers and are solved
in reverse topological order.

A materialised product (:func:`materialize_product`) is provided for export (e.g. to Storm) and
for checking the lazy solver.  There a base floor row cannot stay a floor row: the unlisted
base state q' is one product state (delta(s, L(q')), q'), while every other product state of q'
must get upper 0, which a uniform floor cannot express.  The floor mass is therefore listed
explicitly ([0, floor] on each such successor): O(n) per floor row, for small models only;
rows without floor mass cost their listed entries.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robust_imdp._fp import complement_down, complement_up
from robust_imdp.errors import DimensionError, InvalidInputError, InvalidModelError
from robust_imdp.models.imdp import IMDP
from robust_imdp.solvers.api import check_method
from robust_imdp.solvers.common import Adversary, Control, as_mask, check_strategy, enum_value
from robust_imdp.solvers.engine import EngineTies, solve_layered


@dataclass(frozen=True)
class ProductResult:
    """Sound bounds on the lazy IMDP x DFA product.

    Attributes
    ----------
    lower, upper : (S, n) float arrays
        Bracket of the value of product state (DFA state s, base state q).
    strategy : (S, n) int array, or (k, S, n) with a horizon
        Choice index within base state q to use in DFA state s (at time t).
    initial_state : (n,) int array
        DFA state of q's initial product state, ``delta(dfa.initial, letters[q])``.
    initial_lower, initial_upper : (n,) float arrays
        ``lower``/``upper`` at the initial product state of every q.
    iterations : int
    precision : float
        Achieved ``max(upper - lower)``.
    converged : bool
    steps : engine.StepRows or None
        A k-step solve with ``keep_steps``: the row values of its upper sweeps, which a tie key of a later
        solve (:class:`TieKey` with this result) reads instead of iterating the same values again; None
        otherwise.
    ends : {"both", "lower", "upper"}
        The ends of the bracket that were iterated: "both", except for a k-step solve with ``need``, where the
        other end is its trivial sound bound.
    """

    lower: np.ndarray
    upper: np.ndarray
    strategy: np.ndarray
    initial_state: np.ndarray
    initial_lower: np.ndarray
    initial_upper: np.ndarray
    iterations: int
    precision: float
    converged: bool
    steps: object = None
    ends: str = "both"


@dataclass(frozen=True)
class MaterializedProduct:
    """An explicit product IMDP (product state ``s * n + q``).

    Attributes
    ----------
    imdp : IMDP
        ``S * n`` states; state ``index[s, q]`` has the choices of base state q.
    target, avoid : (S * n,) bool arrays
        Accepting product states (value 1) and value-0 states (avoid states, DFA sinks).
    index : (S, n) int array
        Product state id of (s, q).
    initial : (n,) int array
        Product state id of q's initial product state.
    """

    imdp: IMDP
    target: np.ndarray
    avoid: np.ndarray
    index: np.ndarray
    initial: np.ndarray


@dataclass(frozen=True, eq=False)
class TieKey:
    """One key of the lexicographic strategy choice (:class:`Ties`): the rows of ``model`` valued against
    the values of ``result``, a product solve of ``model`` (same letters, DFA, avoid states, reading and
    horizon) with ``adversary``.

    ``model`` has the same states and choices as the IMDP being solved: the IMDP itself (its optimistic
    solve: the best a controller can still hope for after the step) or another model of the same system,
    e.g. the nominal model of :mod:`robust_imdp.abstraction.nominal`. Unbounded: the rows are valued
    against ``result.upper`` (optimistic) or ``result.lower`` (pessimistic) of the reach value, and under
    the safety reading against the probability of a bad node, one minus them. k steps: the model's k-step
    values are iterated alongside, or read from ``result.steps`` where ``result`` kept the same iteration
    (``solve_product(model, ..., adversary=adversary, keep_steps=True)``: its upper values are the key's).
    """

    model: IMDP
    result: ProductResult
    adversary: str = "optimistic"


@dataclass(frozen=True, eq=False)
class Ties:
    """The keys of the lexicographic strategy choice of :func:`solve_product`, most significant first.

    Among the rows of best value (the value being solved: within the engine's tie tolerance for a
    maximising controller, exactly least for a minimising one) the keys decide in turn, each one's ties
    (values within ``robust_imdp.solvers.engine._KEY_TOL``) going to the next; a node the progress
    attractor never reaches (reach reading, unbounded: every row's value 0) takes the row of ``strategy``,
    by default the first key's strategy (module :mod:`robust_imdp.solvers.engine`, "More keys").

    Attributes
    ----------
    keys : tuple of TieKey
    strategy : (S, n) int array, optional
    """

    keys: tuple
    strategy: np.ndarray | None = None


def _engine_ties(ties, imdp, nxt, safety, horizon):
    """The engine's :class:`~robust_imdp.solvers.engine.EngineTies` of a :class:`Ties` (values in the engine's
    terms: the reach value, or under the safety reading the probability of reaching a bad node)."""
    if not isinstance(ties, Ties):
        return ties  # an optimistic ProductResult: the engine's own single key
    keys = tuple(ties.keys)
    if not keys or not all(isinstance(k, TieKey) for k in keys):
        raise InvalidInputError(f"tie_break.keys must be a non-empty sequence of TieKey; got {ties.keys!r}")
    S, n = nxt.shape
    models, values, adv_max, steps = [], [], [], []
    for i, k in enumerate(keys):
        if not isinstance(k.model, IMDP):
            raise InvalidInputError(f"tie_break key {i}: model must be an IMDP; got {type(k.model).__name__}")
        optimistic = enum_value(Adversary, k.adversary, "adversary") is Adversary.OPTIMISTIC
        models.append(k.model)
        # the adversary of the key's rows in the engine's terms (as evaluate_product_strategy reads it)
        adv_max.append(optimistic != safety)
        if horizon is not None:
            values.append(None)
            # the rows the key's solve kept, if it kept them (the engine checks they are this key's)
            steps.append(getattr(k.result, "steps", None))
            continue
        v = np.asarray(k.result.upper if optimistic else k.result.lower, dtype=np.float64)
        if v.shape != (S, n):
            raise DimensionError(f"tie_break key {i}: its result must be a solve of the same product, values "
                                 f"({S}, {n}); got {v.shape}")
        values.append(1.0 - v if safety else v)  # only ranks rows: no rounding direction needed
    st = ties.strategy
    if st is None and horizon is None:
        st = np.asarray(keys[0].result.strategy)
        st = st if st.shape == (S, n) else None
    return EngineTies(models=tuple(models), values=tuple(values), adv_max=tuple(adv_max),
                      strategy=None if st is None or horizon is not None else np.asarray(st),
                      steps=tuple(steps) if horizon is not None else ())


def _dfa_arrays(imdp: IMDP, letters, dfa, avoid):
    n = imdp.n_states
    for attr in ("n_states", "initial", "accepting", "delta"):
        if not hasattr(dfa, attr):
            raise InvalidModelError(f"dfa must have attribute {attr!r} (n_states, initial, accepting, delta); "
                                    f"got {type(dfa).__name__}")
    S = int(dfa.n_states)
    delta = np.asarray(dfa.delta)
    acc = np.asarray(dfa.accepting)
    if delta.ndim != 2 or delta.shape[0] != S or not np.issubdtype(delta.dtype, np.integer):
        raise InvalidModelError(f"dfa.delta must be an integer array of shape ({S}, 2**n_atoms); got "
                                f"{delta.dtype} {delta.shape}")
    if delta.size and (delta.min() < 0 or delta.max() >= S):
        raise InvalidModelError(f"dfa.delta must hold DFA states in [0, {S}); got values in "
                                f"[{int(delta.min())}, {int(delta.max())}]")
    if acc.shape != (S,):
        raise DimensionError(f"dfa.accepting must have shape ({S},); got {acc.shape}")
    if not 0 <= int(dfa.initial) < S:
        raise InvalidModelError(f"dfa.initial must be in [0, {S}); got {dfa.initial}")
    let = np.asarray(letters)
    if let.shape != (n,):
        raise DimensionError(f"letters must have shape ({n},) (one letter per base state); got {let.shape}")
    if let.size and not np.issubdtype(let.dtype, np.integer):
        raise InvalidInputError(f"letters must hold integer bit masks; got dtype {let.dtype}")
    bad = np.flatnonzero((let < 0) | (let >= delta.shape[1]))
    if bad.size:
        q = int(bad[0])
        raise InvalidInputError(f"letters[{q}] = {int(let[q])} is not a letter of the DFA's alphabet "
                                f"[0, {delta.shape[1]})")
    let = let.astype(np.int64)
    av = as_mask(avoid, n, "avoid", allow_none=True)
    acc = acc.astype(bool)
    # DFA states that cannot reach acceptance (backward reachability over all letters)
    good = acc.copy()
    while True:
        new = good | np.any(good[delta], axis=1)
        if np.array_equal(new, good):
            break
        good = new
    nxt = np.ascontiguousarray(delta[:, let], dtype=np.int64)  # (S, n): layer of successor q'
    zero = av[None, :] | ~good[:, None]
    target = acc[:, None] & ~zero
    initial_state = delta[int(dfa.initial), let].astype(np.int64)
    return nxt, target, zero, initial_state


def _result(res, initial_state, safety=False) -> ProductResult:
    ar = np.arange(initial_state.shape[0])
    lower, upper = res.lower, res.upper
    if safety:  # res brackets P(reach a bad node); satisfaction is its complement, rounded outward
        lower, upper = complement_down(res.upper), complement_up(res.lower)
    return ProductResult(lower=lower, upper=upper, strategy=res.strategy, initial_state=initial_state,
                         initial_lower=lower[initial_state, ar], initial_upper=upper[initial_state, ar],
                         iterations=res.iterations, precision=res.precision, converged=res.converged,
                         steps=getattr(res, "steps", None), ends=_SWAP[getattr(res, "ends", "both")] if safety
                         else getattr(res, "ends", "both"))


#: The satisfaction bracket's end of each end of the engine's under the safety reading (one minus it).
_SWAP = {"both": "both", "lower": "upper", "upper": "lower"}

#: What a k-step solve must compute by default (``need`` of :func:`solve_product`).
NEED_ALL = ("lower", "upper", "strategy")


def _engine_ends(need, safety, keep_steps, fixed=False) -> str:
    """The engine's ``ends`` (its terms: the reach value, or under the safety reading the probability of a bad
    node, whose ends are the satisfaction bracket's swapped) for what the caller ``need`` s of the result: the
    strategy comes from the engine's lower iteration, the kept rows from its upper one."""
    need = set(need)
    bad = need - set(NEED_ALL)
    if bad:
        raise InvalidInputError(f"need must be a subset of {NEED_ALL}; got {sorted(need)}")
    lo = ("lower" in need and not safety) or ("upper" in need and safety) or ("strategy" in need and not fixed)
    up = ("upper" in need and not safety) or ("lower" in need and safety) or keep_steps or not lo
    return "both" if lo and up else ("lower" if lo else "upper")


def _reading(semantics) -> bool:
    """True for the safety reading ("safety"), False for the reach reading ("reach")."""
    if semantics not in ("reach", "safety"):
        raise InvalidInputError(f"semantics must be 'reach' or 'safety'; got {semantics!r}")
    return semantics == "safety"


def _safety_nodes(target, zero):
    """The safety reading's (target, zero) of the engine: the bad nodes -- avoid states, DFA states from which
    acceptance is impossible: the reach reading's value-0 nodes -- become the target the controller keeps
    away from; accepting DFA states are no longer absorbing and nothing is fixed to 0."""
    return zero.copy(), np.zeros_like(zero)


def solve_product(imdp: IMDP, letters, dfa, *, avoid=None, adversary="pessimistic", horizon=None,
                  precision=1e-8, max_iterations=100_000, method="vi", tie_break=None,
                  semantics="reach", keep_steps=False, need=NEED_ALL) -> ProductResult:
    """Maximal probability of satisfying the specification, on the lazy product.

    ``semantics="reach"`` (the paper's reading): the probability of reaching an accepting DFA state.
    ``semantics="safety"``: the probability of never reaching a bad node -- an ``avoid`` state or a DFA
    state from which acceptance is impossible (a bad prefix) -- within the horizon (or ever), solved as
    one minus the *minimal* probability of reaching one: the controller minimises, the pessimistic
    adversary maximises it, and the bracket ``[lower, upper]`` of the reach value becomes
    ``[1 - upper, 1 - lower]`` rounded outward (README, "Two readings of a formula").

    Parameters
    ----------
    imdp : IMDP
    letters : (n,) int array
        Letter of every base state w.r.t. ``dfa.atoms`` (bit i set iff atoms[i] holds).
    dfa : object with ``n_states``, ``initial``, ``accepting`` (S,) bool, ``delta`` (S, 2**k) int
    avoid : (n,) bool mask or index array, optional
        Absorbing, never-accepting base states (value 0 in every DFA state).
    adversary : {"pessimistic", "optimistic"}
        Pessimistic: the intervals resolve against the controller (robust value).
    horizon : int or None
        k-step bounded satisfaction; the strategy is then (k, S, n).
    precision : float
    method : {"vi", "interval"}
        As in :func:`robust_imdp.solvers.api.solve_reachability` (the product's components across
        DFA layers are solved in reverse topological order by default).
    tie_break : ProductResult or Ties, optional
        The ``adversary="optimistic"`` solve of the same product (same horizon).  Rows tied in
        the lower value are then chosen by their optimistic value, and nodes where every row
        has lower value 0 take the optimistic strategy's row (lexicographic choice, see
        "Strategy extraction" in :mod:`robust_imdp.solvers.engine`); only with ``semantics="reach"``.
        :class:`Ties`: several keys in turn (e.g. the nominal model's value, then the optimistic
        value), under either reading.  Without it ties go to the first row.
    semantics : {"reach", "safety"}
        The reading of the specification (above).
    keep_steps : bool
        With a horizon: keep the row values of the upper iteration (``ProductResult.steps``, at most
        ``engine.STEP_ROWS_MAX`` numbers), so that a later solve with a :class:`TieKey` of this result (the
        same model and adversary) reads them instead of iterating them again; the values are the same.
    need : subset of ("lower", "upper", "strategy")
        With a horizon: what the caller reads of the result (default all). An end not needed (and not
        iterated for another need) is its trivial sound bound (0 or 1 off the fixed nodes: ``precision`` about
        1); a strategy not needed may be any (the upper iteration's rows). The needed parts are the same bits
        as with all. Unbounded: ignored.

    Returns
    -------
    ProductResult
        Bounds of the satisfaction probability, under either reading.
    """
    check_method(method)
    safety = _reading(semantics)
    nxt, target, zero, init = _dfa_arrays(imdp, letters, dfa, avoid)
    pessimistic = enum_value(Adversary, adversary, "adversary") is Adversary.PESSIMISTIC
    if safety:
        if tie_break is not None and not isinstance(tie_break, Ties):
            raise InvalidInputError("tie_break applies to the reach reading only (semantics='reach'), unless it is "
                                    f"a Ties; got {type(tie_break).__name__}")
        target, zero = _safety_nodes(target, zero)
        res = solve_layered(imdp, nxt, target, zero, ctrl=Control.MINIMISE, adv_max=pessimistic, horizon=horizon,
                            precision=precision, max_iterations=max_iterations, method=method,
                            tie_break=None if tie_break is None else _engine_ties(tie_break, imdp, nxt, True, horizon),
                            keep_steps=keep_steps and horizon is not None, ends=_engine_ends(need, True, keep_steps))
        return _result(res, init, safety=True)
    res = solve_layered(imdp, nxt, target, zero, ctrl=Control.MAXIMISE, adv_max=not pessimistic, horizon=horizon,
                        precision=precision, max_iterations=max_iterations, method=method,
                        tie_break=None if tie_break is None else _engine_ties(tie_break, imdp, nxt, False, horizon),
                        keep_steps=keep_steps and horizon is not None, ends=_engine_ends(need, False, keep_steps))
    return _result(res, init)


def evaluate_product_strategy(imdp: IMDP, letters, dfa, strategy, *, avoid=None, adversary="pessimistic",
                              horizon=None, precision=1e-8, max_iterations=100_000, method="vi",
                              semantics="reach", need=("lower", "upper")) -> ProductResult:
    """Bounds of the satisfaction probability of a fixed product strategy.

    ``strategy`` is (S, n) (stationary) or (k, S, n) with ``horizon=k``: the choice index within
    base state q used in DFA state s.  ``adversary="pessimistic"`` minimises the probability,
    ``"optimistic"`` maximises it.  ``method``, ``semantics`` and ``need`` (here a subset of
    ("lower", "upper")) as in :func:`solve_product`.
    """
    check_method(method)
    safety = _reading(semantics)
    nxt, target, zero, init = _dfa_arrays(imdp, letters, dfa, avoid)
    if safety:
        target, zero = _safety_nodes(target, zero)
    S, n = nxt.shape
    st = np.asarray(strategy)
    if st.ndim not in (2, 3) or st.shape[-2:] != (S, n):
        raise DimensionError(f"strategy must have shape ({S}, {n}) or (k, {S}, {n}); got {st.shape}")
    check_strategy(imdp, st.reshape(-1, n))
    if st.ndim == 3 and (horizon is None or st.shape[0] != int(horizon)):
        raise DimensionError(f"a time-varying strategy of shape {st.shape} needs horizon={st.shape[0]}; got {horizon}")
    strat = st.astype(np.int64) if st.ndim == 3 else st.astype(np.int64)[None]
    # the adversary against satisfaction minimises reaching the target under the reach reading, maximises
    # reaching it (the bad nodes) under the safety reading
    adv_max = (enum_value(Adversary, adversary, "adversary") is Adversary.OPTIMISTIC) != safety
    res = solve_layered(imdp, nxt, target, zero, ctrl=Control.FIXED, adv_max=adv_max, horizon=horizon,
                        precision=precision, max_iterations=max_iterations, strategy=strat, method=method,
                        ends=_engine_ends(need, safety, False, fixed=True))
    return _result(res, init, safety=safety)


def materialize_product(imdp: IMDP, letters, dfa, *, avoid=None, semantics="reach") -> MaterializedProduct:
    """The explicit product IMDP (S * n states); floor mass listed explicitly.

    ``semantics="safety"``: ``target`` marks the bad product states (avoid states, DFA states from which
    acceptance is impossible) and ``avoid`` is empty; the satisfaction probability is then one minus the
    probability of reaching ``target``, minimised by the controller (:func:`solve_product`).

    Product state ``s * n + q`` has the rows of q; the listed successor q' of a row becomes
    ``delta(s, L(q')) * n + q'``, and, for a floor row, every unlisted base state q' is listed
    with [0, floor] at ``delta(s, L(q')) * n + q'`` (see the module docstring).  Rows without
    floor mass keep their listed entries (sorted by successor), so a model without floors
    costs S x its own memory; each floor row costs O(n).
    """
    safety = _reading(semantics)
    nxt, target, zero, init = _dfa_arrays(imdp, letters, dfa, avoid)
    if safety:
        target, zero = _safety_nodes(target, zero)
    S, n = nxt.shape
    R = imdp.n_choices
    rl = np.diff(imdp.row_ptr)
    entry_row = np.repeat(np.arange(R), rl)
    rows_c, cols_c, lo_e, up_e = entry_row, imdp.col, imdp.lower, imdp.upper
    fl_rows = np.flatnonzero((imdp.floor > 0) & (imdp.n_unlisted > 0))
    if fl_rows.size:
        # unlisted states of the floor rows get [0, floor]: O(n) per floor row
        listed = np.zeros((fl_rows.size, n), dtype=bool)
        pos = np.full(R, -1, dtype=np.int64)
        pos[fl_rows] = np.arange(fl_rows.size)
        sel = pos[entry_row] >= 0
        listed[pos[entry_row[sel]], imdp.col[sel]] = True
        fr, fc = np.nonzero(~listed)
        rows_c = np.concatenate([rows_c, fl_rows[fr]])
        cols_c = np.concatenate([cols_c, fc])
        lo_e = np.concatenate([lo_e, np.zeros(fr.size)])
        up_e = np.concatenate([up_e, imdp.floor[fl_rows[fr]]])
    order = np.lexsort((cols_c, rows_c))  # rows in order, successors sorted inside each row
    rows_c, cols_c, lo_e, up_e = rows_c[order], cols_c[order], lo_e[order], up_e[order]
    per_row = np.bincount(rows_c, minlength=R)
    # product rows: layer-major, then the base rows in order
    col = (nxt[:, cols_c] * n + cols_c[None, :]).reshape(-1)
    row_ptr = np.zeros(S * R + 1, dtype=np.int64)
    np.cumsum(np.tile(per_row, S), out=row_ptr[1:])
    nch = np.diff(imdp.state_ptr)
    state_ptr = np.zeros(S * n + 1, dtype=np.int64)
    np.cumsum(np.tile(nch, S), out=state_ptr[1:])
    pm = IMDP.from_csr(state_ptr, row_ptr, col, np.tile(lo_e, S), np.tile(up_e, S),
                       actions=np.tile(imdp.actions, S))
    index = np.arange(S * n).reshape(S, n)
    return MaterializedProduct(imdp=pm, target=target.reshape(-1), avoid=zero.reshape(-1), index=index,
                               initial=index[init, np.arange(n)])


__all__ = ["ProductResult", "MaterializedProduct", "TieKey", "Ties", "solve_product", "evaluate_product_strategy",
           "materialize_product"]
