"""The layered value-iteration engine with sound lower and upper bounds: :func:`solve_layered`.

Contract
--------
``solve_layered(imdp, nxt, target, zero, *, ctrl, adv_max, horizon, precision, method)`` returns
a frozen :class:`~robust_imdp.solvers.common.ReachabilityResult` of (L, n) arrays whose
``lower``/``upper`` bracket the true value of every node (layer l, state q); a plain IMDP is one
layer (:func:`robust_imdp.solvers.api.solve_reachability`), an IMDP x DFA product one layer per
DFA state (:mod:`robust_imdp.solvers.product`).  ``method`` picks the unbounded algorithm from
:data:`METHODS`.

Soundness (why every printed bound is on the safe side)
-------------------------------------------------------
Let B be the Bellman operator of the (controller, adversary) pair: targets fixed to 1, avoid
states to 0, ``B(x)(s) = opt_a adv_{p in P(s,a)} p.x``.  B is monotone and the reachability
value V* is its *least* fixed point (for every combination max/min x max/min).

* **Lower**: ``l_0`` = indicator of the target <= V*; ``l_{k+1} = max(l_k, B_down(l_k))`` where
  ``B_down`` is B evaluated in floating point minus a proven bound of its rounding error
  (``ROW_ERR``, derivation below).  By monotonicity ``B_down(l) <= B(l) <= B(V*) = V*``.
  Unbounded iteration without floors updates in place (Gauss-Seidel): every partially
  updated vector is still a vector of lower bounds, so the same argument applies per node.
  (Upper bounds likewise with ``min``; k-step values use plain Jacobi sweeps.)
* **Graph pre-computation** (exact, integer/boolean): (a) the nodes with V* = 0 (no admissible
  way to put positive probability on the target; liberal in borderline cases, so it never
  zeroes a positive value) and (a') for a maximising controller or a fixed strategy the nodes
  with V* = 1 (almost-sure reachability, nested fixed point; conservative, so it never claims
  1 wrongly).  Both are fixed like avoid states / targets.
* **Upper**: (b) ``u_0 = 1`` elsewhere and ``u_{k+1} = min(u_k, B_up(u_k))``, sound since
  ``u >= V*`` implies ``B_up(u) >= B(u) >= B(V*) = V*``.  End components make (b) stall at a
  larger fixed point, so (d) the first iterations and every 4th one also apply
* **Lemma D (deflation)**.  Let C be any set of non-target nodes and u >= V*.  Call a row
  (s, a), s in C, *stay-able* if some admissible p has support inside C.  Define the row bound
  ``b(s, a)``: for a minimising adversary, -inf if the row is stay-able and ``B_a(u)(s)``
  otherwise; for a maximising adversary, -inf if no admissible p leaves C, otherwise (an
  upper bound of) the conditional exit average ``sup {p_out.u / p(out) : p(out) > 0}``.
  Let ``b(s)`` combine the rows as the controller does (max, min, or its fixed row) and
  ``e = max_{s in C} b(s)``.  Then ``V* <= max(e, 0)`` on C.
  *Proof.*  Put ``V' = min(V*, max(e, 0))`` on C and ``V' = V*`` elsewhere, so V' <= V* and
  ``B(V') <= B(V*) = V*``.  For s in C and a row a: a stay-able row under a minimising
  adversary gives ``B_a(V')(s) <= p_C.V' <= max_C V' <= max(e,0)``; a non-stay-able one
  ``<= B_a(V*)(s) <= B_a(u)(s) <= e``; under a maximising adversary every p gives
  ``p.V' <= p(C) max(e,0) + p_out.u <= p(C) max(e,0) + p(out) b(s,a) <= max(e,0)``.  Hence
  ``B(V') <= V'``, V' is a pre-fixed point, and by Knaster-Tarski V* = lfp <= V'.  QED.
  The lemma holds for *any* C; we apply it to the maximal end components of the stay-able
  rows (Haddad & Monmege 2014; Baier et al. CAV 2017; the game version is Kelmendi et al.
  CAV 2018), which is what makes the upper iterates converge in the usual cases.  When they
  do not within ``max_iterations``, the result says ``converged=False`` and a
  ``ConvergenceWarning`` is issued; the bracket is still sound.
* **Fixing the pre-computed nodes keeps the least fixed point.**  Let B' be B with the nodes of
  (a)/(a') fixed to 0/1.  V* is a fixed point of B'; for w = lfp(B') <= V*, B(w) = B'(w) = w on
  the other nodes, ``B(w) <= B(V*) = 0 = w`` on the value-0 nodes and ``B(w) <= 1 = w`` on the
  value-1 nodes, so w is a pre-fixed point of B and w >= V*: lfp(B') = V*.  Below, B means B'.
* **Lemma OVI (optimistic value iteration, Hartmanns & Kaminski CAV 2020).**  Any u with
  ``B(u) <= u`` satisfies ``u >= V*`` (Knaster-Tarski: the least fixed point is the least
  pre-fixed point).  We check it with ``B_up >= B``, so rounding can only make the check fail.
  The check is a Gauss-Seidel sweep ``u(s) <- B_up(u)(s)`` over the nodes in order; if no value
  increased, the final u_f is proven: with u^(s) the vector when s was processed, u_f <= u^(s)
  (values only decreased), hence ``B(u_f)(s) <= B(u^(s))(s) <= B_up(u^(s))(s) = u_f(s)``.
  Guesses: ``u = min(proven upper, lower + delta)`` once the lower iteration's estimated error
  is below delta, or the Aitken extrapolation of the lower iterates plus a margin (see
  :func:`ovi_component`); a refuted or undecided guess is discarded (the last proven vector is
  restored), so only proven vectors are ever reported.
* **OVI with end components** (Jacobi checks, :func:`_ovi_jacobi`).  Rounding makes ``B_up(u) <=
  u`` fail where a row can stay in a cycle of equal values, so a node s of an end component C
  may pass instead by ``cap_C <= u(s)``, with ``cap_C = max(0, e_C)`` Lemma D's bound computed
  from u (row values ``B_up(u)``, exit ratios of u).  If every node passes one way, u >= V*.
  *Proof.*  Let P be the nodes passing by the cap, ``w = cap_C`` on P (of C) and ``w = u``
  elsewhere, ``V' = min(V*, w) <= u``.  On C, ``V' <= cap_C`` everywhere: on P by definition,
  elsewhere in C because such a node failed the cap (``u < cap_C``).  At s in P every row gives
  at most cap_C: a stay-able row (minimising adversary) ``p.V' <= max_C V'``, a non-stay-able
  one ``B_a(V')(s) <= B_a(u)(s) <= e_C``, a maximising adversary ``p.V' <= p(C) cap_C + p_out.u
  <= cap_C``; elsewhere ``B(V')(s) <= B(u)(s) <= u(s) = w(s)``.  With ``B(V') <= B(V*) = V*``,
  V' is a pre-fixed point, so V* <= V' <= u.  QED.
* **Lower guesses** need a unique fixed point.  In a component C without end component (no set
  D in C where every node has a row with an admissible p supported in D; found liberally, see
  :func:`_end_components`) the restricted operator has one: for fixed points x, y let
  M = max(x - y) > 0 be attained on D; at s in D take x's row a and y's adversary choice p_y of
  that row (or symmetrically, depending on who maximises); then
  ``M = x(s) - y(s) <= p_y.(x - y) <= M`` forces p_y into D (the outside is common, difference
  0 < M), so D would be an end component.  Hence ``x <= B(x)`` implies x <= gfp = lfp = V*
  (Knaster-Tarski), checked by a Gauss-Seidel sweep ``x(s) <- B_down(x)(s)`` that decreased no
  value (the mirror image of the upper argument).
* **Topological order.**  Components C of the graph of possible successors are solved in
  reverse topological order; when C is solved, every successor outside C has its final
  bracket l <= V* <= u.  Lower sweeps on C read l outside: still below V* by monotonicity.
  For the upper end let ``B_C(x) = B(x on C, u outside)`` and ``B*_C(x) = B(x on C, V* outside)
  <= B_C(x)``.  V*_C is the least fixed point of B*_C (if y = lfp(B*_C) <= V*_C, the vector
  (y on C, V* outside) is a pre-fixed point of B, hence >= V*).  So ``B_C(u_C) <= u_C`` gives
  ``u_C >= lfp(B_C) >= lfp(B*_C) = V*_C``, and interval iteration on C (and Lemma D, which
  holds for any set C) is sound from a proven start as before.  Components without an end
  component have a unique fixed point (every strategy and adversary leave them), which is
  what makes the guesses succeed; components with one use the checks with Lemma D's caps
  above, falling back to interval iteration with Lemma D.

Strategy extraction: a minimising controller takes, at every node, a row of least value against
the proven upper vector (:func:`_minimising_strategy`: where ``B(u) <= u`` such a strategy's value is
at most u, and on the nodes proven 0 it keeps away from the target for ever).  A maximising one:
rows within ``_TIE_TOL`` of the best (w.r.t. the final lower values) are
optimal; among them a backward attractor picks rows that make progress toward the target, so a
maximising strategy is never trapped in an end component by a tie.  Ties are broken
lexicographically when the optimistic (max, max) solve is given (``tie_break``): among the
optimal rows through which a node joins the attractor, the one with the largest optimistic row
value ``max_p p.U`` (U the proven upper bound of the max-max value, the p_up_star vector of
synthesis) wins; a node the attractor never reaches -- its lower value is 0 for every row, e.g.
the nodes the graph pre-computation proved 0 -- takes the optimistic solve's own
(progress-making) row.  Choosing there by ``max_p p.U`` alone would not do: a row that stays in
a set of equal U values (a self-loop) ties with the best row, and the strategy could circle
forever.  Changing the rows of nodes whose value under the strategy is 0 cannot lower the
value of any other node: with ``y_k = B_pi^k(0)`` and ``x_k = B_pi'^k(0)``, pi' = pi off those
nodes Z, induction gives ``x_k >= y_k`` (``y_k = 0`` on Z, B monotone elsewhere), and the least
fixed points are the limits.  The strategy's bounds are always re-evaluated by the caller
(:func:`robust_imdp.synthesis.core.synthesize` checks they keep the optimal lower value).

More keys (:class:`EngineTies`).  ``tie_break`` may also be a sequence of keys, most significant
first, each the row values of a model with the same states and choices (the solved IMDP itself, or
another one: the nominal model of :mod:`robust_imdp.abstraction.nominal`) against a value vector of
its own, with a fallback strategy for the nodes the attractor never reaches.  The keys are merged
into one score by their lexicographic rank (:func:`_key_rank`; every key but the last is compared
on a grid of ``_KEY_TOL``), so the attractor and the fallback above are unchanged.  A minimising
controller with keys takes, among the rows of *exactly* least value against the proven upper vector
(so that ``B_pi(u) = B(u) <= u`` still holds and the value stays at most u), the one of least rank.
k steps: each key's model is iterated alongside the lower values (its k-step values under a
controller of the same direction), and the decision with t steps to go is, among the rows within
``_TIE_TOL`` of the best lower row value (exactly least for a minimising controller), the best by
the keys' rows against their (t - 1)-step values.  Keys only choose among rows that are optimal
for the value being solved; they never change a bound.

Where the pieces live: the kernels of the Bellman operator and of the per-component iteration
in :mod:`robust_imdp.solvers.kernels` (with the rounding-error bound ``ROW_ERR`` of one row), the
graph pre-computations and end components in :mod:`robust_imdp.solvers.graph`, the sweeps over
layers in :mod:`robust_imdp.solvers.sweep`, optimistic value iteration and interval iteration in
:mod:`robust_imdp.solvers.ovi`; this module runs them (:func:`solve_layered`) and extracts the
strategy.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, fields

import numpy as np

from robust_imdp.errors import ConvergenceWarning, DimensionError, InvalidInputError
from robust_imdp.solvers.common import Control, ReachabilityResult
from robust_imdp.solvers.graph import _end_components, almost_sure, graph_lanes, positive_attractor, progress_strategy
from robust_imdp.solvers.ovi import _interval_step, _ovi_jacobi, _topological
from robust_imdp.solvers.sweep import Sweeper


def solve_layered(imdp, nxt, target, zero, *, ctrl, adv_max, horizon=None, precision=1e-8,
                  max_iterations=100_000, strategy=None, method="vi", tie_break=None,
                  keep_steps=False, ends="both") -> ReachabilityResult:
    """Engine shared by :func:`~robust_imdp.solvers.api.solve_reachability`,
    :func:`~robust_imdp.solvers.api.evaluate_strategy` and the lazy product.

    Parameters
    ----------
    nxt : (L, n) int
        Layer of the successor q' when moving from layer l (``delta(s, L(q'))`` for the product).
    target, zero : (L, n) bool
        Nodes with value fixed to 1 / to 0 (``zero`` wins over ``target``).
    ctrl : Control (or its int)
        MAXIMISE, MINIMISE, or FIXED: the rows of ``strategy`` ((1 or k, L, n) choice indices).
    adv_max : bool
        The adversary maximises the value (else minimises).
    tie_break : result of the optimistic solve, or :class:`EngineTies`, optional
        A result: only for ``ctrl=MAXIMISE``, an object with ``upper`` (L, n) and ``strategy`` (L, n),
        the (max, max) solve of the same model (``ctrl=MAXIMISE, adv_max=True``).  Rows tied in the
        lower value are then chosen by their optimistic value (see "Strategy extraction" in the module
        docstring).  k-step: only its presence matters; the optimistic values of every step are
        recomputed alongside the lower ones (one more sweep per step).  An :class:`EngineTies`
        (``ctrl=MAXIMISE`` or ``MINIMISE``): the keys of "More keys" in the module docstring.
    method : a name of :data:`METHODS`
        The algorithm of the unbounded values (checked by the callers,
        :func:`robust_imdp.solvers.api.check_method`).

    Returns a ReachabilityResult with (L, n) arrays and a (L, n) or (k, L, n) strategy (a
    :class:`BoundedResult` with ``keep_steps`` or one end of a k-step bracket).
    """
    if horizon is not None:
        horizon = int(horizon)
        if horizon < 0:
            raise InvalidInputError(f"horizon must be a non-negative integer or None; got {horizon}")
    if not (np.isfinite(precision) and precision > 0):
        raise InvalidInputError(f"precision must be a positive number; got {precision!r}")
    ctrl = int(ctrl)  # the kernels take a plain int
    L, n = nxt.shape
    target = target & ~zero
    active = ~(target | zero)
    V0 = target.astype(np.float64)
    if strategy is not None:
        strategy = np.ascontiguousarray(strategy, dtype=np.int64)
    if tie_break is not None:
        tie_break = _check_tie_break(tie_break, imdp, L, n, ctrl, horizon)
    sw = Sweeper(imdp, nxt, active, ctrl, adv_max, strategy)
    if horizon is not None:
        if ends not in ("both", "lower", "upper"):
            raise InvalidInputError(f"ends must be 'both', 'lower' or 'upper'; got {ends!r}")
        out = {}
        res = _bounded(sw, V0, horizon, ctrl, strategy, tie_break, keep_steps, lower=ends != "upper",
                       upper=ends != "lower" or keep_steps, out=out)
        if not keep_steps and out["ends"] == "both":
            return res
        return BoundedResult(**{f.name: getattr(res, f.name) for f in fields(res)}, **out)
    return _unbounded(sw, imdp, nxt, target, zero, active, ctrl, adv_max, strategy, precision, max_iterations,
                      method, tie_break)


@dataclass(frozen=True, eq=False)
class EngineTies:
    """Keys of the lexicographic strategy choice of :func:`solve_layered`, most significant first
    (module docstring, "More keys"); :func:`robust_imdp.solvers.product.solve_product` builds it from its
    :class:`~robust_imdp.solvers.product.Ties`.

    Attributes
    ----------
    models : tuple of IMDP
        Per key, the model whose rows are valued: the same states and choices (``state_ptr``) as the
        solved IMDP.
    values : tuple of (L, n) float arrays, or of None with a horizon
        Per key, the vector its rows are valued against (k steps: iterated alongside from the target's
        indicator, so None).
    adv_max : tuple of bool
        Per key, whether its adversary maximises the row value.
    strategy : (L, n) int array or None
        The row of every node the attractor never reaches (-1 or None: none given); unbounded only.
    steps : tuple of (StepRows or None), optional
        k-step: per key, the row values of its iteration kept by an earlier solve (:class:`StepRows`);
        a key whose record does not match (:meth:`StepRows.serves`) or is None is iterated alongside.
    """

    models: tuple
    values: tuple
    adv_max: tuple
    strategy: np.ndarray | None = None
    steps: tuple = ()


#: The most numbers (k x layers x rows) a k-step solve keeps of its upper sweeps' row values
#: (``keep_steps``): 16 M float64, 128 MB; beyond it the keys of later solves are iterated again.
STEP_ROWS_MAX = 1 << 24


@dataclass(frozen=True, eq=False)
class StepRows:
    """The row values of the upper iteration of a k-step solve (``keep_steps``), for the tie keys of later
    solves of the same product: ``rows[t - 1]`` (layer-major, ``l * R + r``, -inf for rows of nodes not
    swept) is ``B_row(u_{t-1})``, rounded up, with ``u_0`` the target's indicator and ``u_t`` the solve's
    t-step upper values.  A key of another solve that values the rows of the same ``model`` under the same
    controller and adversary, on the same nodes (``nxt``, ``active``) from the same start ``V0``, iterates
    exactly these values -- the same sweep (same kernel arithmetic) of the same vectors -- so reading them
    gives the same bits as sweeping again (:func:`_bounded`; tests/test_step_reuse.py).

    Attributes
    ----------
    model : IMDP
        The swept model (compared by identity: an IMDP is immutable).
    nxt : (L, n) int array
    active : (L, n) bool array
    V0 : (L, n) float array
    ctrl : int
    adv_max : bool
    rows : (k, L * R) float array
    """

    model: object
    nxt: np.ndarray
    active: np.ndarray
    V0: np.ndarray
    ctrl: int
    adv_max: bool
    rows: np.ndarray

    def serves(self, model, nxt, active, V0, ctrl, adv_max, k) -> bool:
        """Whether the key sweep of ``model`` (``ctrl``, ``adv_max``) on these nodes from ``V0`` for ``k``
        steps is this record's: then its rows are bit for bit the ones the sweeps would compute."""
        return (self.model is model and self.ctrl == int(ctrl) and self.adv_max == bool(adv_max)
                and self.rows.shape[0] >= k and np.array_equal(self.nxt, nxt) and np.array_equal(self.active, active)
                and np.array_equal(self.V0, V0))


@dataclass(frozen=True)
class BoundedResult(ReachabilityResult):
    """A k-step :class:`~robust_imdp.solvers.common.ReachabilityResult` with the row values of its upper
    sweeps (``keep_steps``; ``steps`` is None where they were not kept: more than ``STEP_ROWS_MAX``
    numbers, or a fixed strategy) and the ``ends`` of the bracket that were iterated ("both", "lower",
    "upper"; the other end is its trivial bound)."""

    steps: StepRows | None = None
    ends: str = "both"


def _check_tie_break(tie_break, imdp, L, n, ctrl, horizon) -> EngineTies:
    """The checked keys: an optimistic result as the one key of the same model, or an :class:`EngineTies`."""
    if isinstance(tie_break, EngineTies):
        return _check_ties(tie_break, imdp, L, n, ctrl, horizon)
    if ctrl != Control.MAXIMISE:
        raise InvalidInputError(f"tie_break applies to a maximising controller only (ctrl=0); got ctrl={ctrl}")
    if not (hasattr(tie_break, "upper") and hasattr(tie_break, "strategy")):
        raise InvalidInputError("tie_break must be the result of the optimistic solve of the same model (with "
                                f"'upper' and 'strategy'); got {type(tie_break).__name__}")
    if horizon is not None:
        return EngineTies(models=(imdp,), values=(None,), adv_max=(True,),
                          steps=(getattr(tie_break, "steps", None),))
    up = np.asarray(tie_break.upper, dtype=np.float64)
    st = np.asarray(tie_break.strategy)
    if L == 1 and up.shape == (n,):  # a single-layer ReachabilityResult
        up = up[None, :]
    if up.shape != (L, n) or st.shape not in ((L, n), (n,) if L == 1 else (L, n)):
        raise DimensionError(f"tie_break must come from a solve of the same model: upper ({L}, {n}) and an "
                             f"({L}, {n}) stationary strategy; got upper {np.shape(tie_break.upper)}, "
                             f"strategy {st.shape}")
    return EngineTies(models=(imdp,), values=(np.ascontiguousarray(up),), adv_max=(True,),
                      strategy=np.ascontiguousarray(st.reshape(L, n), dtype=np.int64))


def _check_ties(ties: EngineTies, imdp, L, n, ctrl, horizon) -> EngineTies:
    """An :class:`EngineTies`, checked against the solved model (shapes, the keys' states and choices)."""
    if ctrl not in (Control.MAXIMISE, Control.MINIMISE):
        raise InvalidInputError(f"tie_break applies to a maximising or minimising controller (ctrl=0 or 1); got "
                                f"ctrl={ctrl}")
    k = len(ties.models)
    if k == 0 or len(ties.values) != k or len(ties.adv_max) != k:
        raise InvalidInputError(f"tie_break must give models, values and adv_max for each of at least one key; got "
                                f"{len(ties.models)}, {len(ties.values)} and {len(ties.adv_max)}")
    values = []
    for i, (m, v) in enumerate(zip(ties.models, ties.values)):
        if not hasattr(m, "state_ptr") or m.n_states != n or not np.array_equal(m.state_ptr, imdp.state_ptr):
            raise DimensionError(f"tie_break key {i}: its model must have the solved IMDP's {n} states and choices "
                                 f"(the same state_ptr); got {type(m).__name__} with "
                                 f"{getattr(m, 'n_states', '?')} states")
        if horizon is not None:
            values.append(None)
            continue
        v = np.asarray(v, dtype=np.float64)
        if v.shape != (L, n):
            raise DimensionError(f"tie_break key {i}: values must have shape ({L}, {n}); got {v.shape}")
        values.append(np.ascontiguousarray(v))
    st = ties.strategy
    if st is not None:
        st = np.asarray(st)
        if st.shape != (L, n) or not np.issubdtype(st.dtype, np.integer):
            raise DimensionError(f"tie_break strategy must be an ({L}, {n}) int array; got {st.dtype} {st.shape}")
        st = np.ascontiguousarray(st, dtype=np.int64)
    steps = tuple(ties.steps) if ties.steps else (None,) * k
    if len(steps) != k or not all(x is None or isinstance(x, StepRows) for x in steps):
        raise InvalidInputError(f"tie_break steps must give a StepRows or None for each of the {k} keys; got "
                                f"{ties.steps!r}")
    return EngineTies(models=tuple(ties.models), values=tuple(values), adv_max=tuple(bool(a) for a in ties.adv_max),
                      strategy=st, steps=steps if horizon is not None else (None,) * k)


def _key_rows(model, nxt, mask, values, adv_max, ctrl=Control.MAXIMISE):
    """Per row (index ``l*R + r``) of ``model`` its value against ``values`` (L, n) under the adversary
    ``adv_max``, rounded up; -inf for the rows of nodes outside ``mask``.  Only used to order tied rows."""
    sw = Sweeper(model, nxt, mask, ctrl, adv_max, None)
    _, _, rows = sw.sweep(values, +1, want_rows=True)
    return rows


def _key_rank(rows, maximise=True):
    """One score per row from the keys' row values ``rows`` (a list of (N,) arrays, most significant
    first): higher is better (the keys' larger values for a maximising controller, smaller ones for a
    minimising one); -inf where the first key is not finite (rows of nodes not evaluated).

    One key of a maximising controller is its own score (compared exactly, as before keys existed);
    otherwise the score is the rank of the row in the lexicographic order of the keys, every key but
    the last compared on a grid of ``_KEY_TOL`` (``floor(v / _KEY_TOL)``): values closer than that may
    tie, and then the next key decides.
    """
    if len(rows) == 1 and maximise:
        return rows[0]
    sign = 1.0 if maximise else -1.0
    fin = np.isfinite(rows[0])
    cols = []
    for i, r in enumerate(rows):
        r = np.asarray(r, dtype=np.float64)
        v = np.where(fin & np.isfinite(r), sign * r, -np.inf)
        cols.append(np.floor(v / _KEY_TOL) if i < len(rows) - 1 else v)
    order = np.lexsort(cols[::-1])  # np.lexsort sorts by its last key first
    srt = np.stack([c[order] for c in cols])
    new = np.ones(order.size, dtype=bool)
    new[1:] = np.any(srt[:, 1:] != srt[:, :-1], axis=0)
    rank = np.empty(order.size)
    rank[order] = np.cumsum(new)
    return np.where(fin, rank, -np.inf)


def _lex_choice(rows_lo, score, state_ptr, arg, maximise=True):
    """Per node, among its optimal rows by the lower row values ``rows_lo`` (L, R) -- within
    ``_TIE_TOL`` of the best for a maximising controller, exactly least for a minimising one -- the
    first one with the largest ``score`` (L, R); ``arg`` where no row was evaluated."""
    L = rows_lo.shape[0]
    nch = np.diff(state_ptr)
    has = nch > 0
    starts = state_ptr[:-1][has]
    out = arg.copy()
    fin = np.isfinite(rows_lo)
    if maximise:
        lo = np.where(fin, rows_lo, -1.0)
        best_lo = np.maximum.reduceat(lo, starts, axis=1)
        optimal = (lo >= np.repeat(best_lo, nch[has], axis=1) - _TIE_TOL) & fin
    else:
        lo = np.where(fin, rows_lo, np.inf)
        best_lo = np.minimum.reduceat(lo, starts, axis=1)
        optimal = (lo <= np.repeat(best_lo, nch[has], axis=1)) & fin
    sc = np.where(optimal, score, -np.inf)
    best = np.maximum.reduceat(sc, starts, axis=1)
    is_best = optimal & (sc >= np.repeat(best, nch[has], axis=1))
    pos = np.where(is_best, np.arange(rows_lo.shape[1])[None, :], rows_lo.shape[1])
    first = np.minimum.reduceat(pos, starts, axis=1)  # (L, number of states with rows)
    ok = np.isfinite(best)
    q_idx = np.flatnonzero(has)
    for l in range(L):
        sel = ok[l]
        out[l, q_idx[sel]] = first[l, sel] - starts[sel]
    return out


def _bounded(sw, V0, k, ctrl, strategy, tie_break=None, keep_steps=False, lower=True, upper=True, out=None):
    """k-step values by k exact Bellman steps, rounded down (lower) and up (upper).

    With ``tie_break`` (:class:`EngineTies`) the keys' k-step values are iterated alongside (the
    optimistic (max, max) values ``U_t`` for an optimistic result) and the decision with t steps to
    go is, among the rows within ``_TIE_TOL`` of the best lower row value (exactly least for a
    minimising controller), the best by the keys' rows ``B_row(U_{t-1})`` (no cycles to fear: the
    strategy is time-varying and every chosen row is optimal for the lower recursion).  A key whose
    rows an earlier solve kept (:class:`StepRows` that :meth:`~StepRows.serves` it) reads them instead:
    the same bits, one sweep per key and step fewer.  ``keep_steps``: keep this solve's upper rows.
    ``lower``/``upper`` False: that end is not iterated and stays its trivial sound bound (``ends`` of
    :func:`solve_layered`); without the lower end the strategy is the upper sweeps' rows, keys unread.
    ``out`` (a dict): receives the iterated ``ends`` and the kept ``steps`` (:class:`BoundedResult`).
    """
    lo = V0.copy()
    # the trivial bounds of the ends not iterated: values are in [0, 1], targets 1 and zero nodes 0 exactly
    up = V0.copy() if upper else np.where(sw.active, 1.0, V0)
    R = sw.m.n_choices
    keys, kept = [], []
    if tie_break is not None and lower:
        steps = tie_break.steps or (None,) * len(tie_break.models)
        for m, a, st in zip(tie_break.models, tie_break.adv_max, steps):
            if st is not None and st.serves(m, sw.nxt, sw.active, V0, ctrl, a, k):
                keys.append(None)
                kept.append(st.rows)
            else:
                keys.append(Sweeper(m, sw.nxt, sw.active, ctrl, a, None))
                kept.append(None)
    key_values = [None if ks is None else V0.copy() for ks in keys]
    record = None
    if keep_steps and ctrl != Control.FIXED and k * V0.shape[0] * R <= STEP_ROWS_MAX:
        record = np.empty((k, V0.shape[0] * R))
    strat = np.zeros((k,) + V0.shape, dtype=np.int64)
    for t in range(1, k + 1):
        # with t steps to go the decision is the one taken at time k - t
        sl = None if strategy is None else (k - t if strategy.shape[0] == k else 0)
        if lower:
            new_lo, arg, rows_lo = sw.sweep(lo, -1, strat_layer=sl, want_rows=bool(keys))
        if upper:
            up, arg_up, rows_up = sw.sweep(up, +1, strat_layer=sl, want_rows=record is not None)
            if record is not None:
                record[t - 1] = rows_up
            if not lower:
                arg = arg_up
        if keys:
            rows_k = []
            for i, ks in enumerate(keys):
                if ks is None:  # kept by an earlier solve: B_row(u_{t-1}) of the same sweeps
                    rows_k.append(kept[i][t - 1])
                    continue
                key_values[i], _, rows = ks.sweep(key_values[i], +1, want_rows=True)
                rows_k.append(rows)
            score = _key_rank(rows_k, ctrl == Control.MAXIMISE).reshape(-1, R)
            arg = _lex_choice(rows_lo.reshape(-1, R), score, sw.m.state_ptr, arg, ctrl == Control.MAXIMISE)
        if lower:
            lo = new_lo
        strat[k - t] = arg
    if ctrl == Control.FIXED:
        strat = np.broadcast_to(strategy, strat.shape).copy() if strategy.shape[0] == k else np.repeat(strategy, k, 0)
    if out is not None:  # what solve_layered adds to the result (a BoundedResult)
        out["ends"] = "both" if lower and upper else ("lower" if lower else "upper")
        if record is not None:
            record.setflags(write=False)
            out["steps"] = StepRows(model=sw.m, nxt=sw.nxt.copy(), active=np.array(sw.active, dtype=bool),
                                    V0=V0.copy(), ctrl=int(ctrl), adv_max=bool(sw.adv_max), rows=record)
    prec = float(np.max(up - lo)) if up.size else 0.0
    return ReachabilityResult(lower=lo, upper=up, strategy=strat, iterations=k, precision=prec, converged=True)


def _unbounded(sw, imdp, nxt, target, zero, active, ctrl, adv_max, strategy, precision, max_iterations, method,
               tie_break=None):
    """Unbounded values: graph pre-computation, the iteration of ``METHODS[method]``, strategy."""
    flat_strat = strategy[0].reshape(-1) if strategy is not None else np.zeros(1, dtype=np.int64)
    zero_all, fixed1, one, active2 = _fixed_nodes(imdp, nxt, target, zero, active, ctrl, adv_max, flat_strat)
    sw.active = active2
    sw.layers = [l for l in range(nxt.shape[0]) if active2[l].any()]
    lo = fixed1.astype(np.float64)
    up = np.where(zero_all, 0.0, 1.0)
    lo, up, it = METHODS[method](sw, imdp, nxt, lo, up, active2, ctrl, adv_max, flat_strat, precision,
                                 max_iterations)
    gap = float(np.max(up - lo)) if up.size else 0.0
    converged = gap <= precision
    if not converged:
        warnings.warn(f"value iteration stopped after {it} iterations with max(upper - lower) = {gap:.3g} > "
                      f"precision {precision:g}; the returned bounds are sound but loose", ConvergenceWarning,
                      stacklevel=3)
    if ctrl == Control.MINIMISE:
        strat = _minimising_strategy(sw, nxt, up, active, tie_break)
    else:
        strat = _extract_strategy(sw, imdp, nxt, lo, target, active, active2 | one, ctrl, adv_max, strategy,
                                  tie_break)
    return ReachabilityResult(lower=lo, upper=up, strategy=strat, iterations=it, precision=gap, converged=converged)


def _fixed_nodes(imdp, nxt, target, zero, active, ctrl, adv_max, flat_strat):
    """(a) and (a') of the module docstring: the nodes of value exactly 0 and exactly 1.

    Returns (value-0 nodes, value-1 nodes including the targets, the value-1 nodes found by the
    almost-sure pre-computation, the nodes left to iterate), each (L, n) bool."""
    L, n = nxt.shape
    # (a) graph pre-computation: nodes that reach the target with positive probability
    W = positive_attractor(imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.lower, imdp.upper, imdp.floor,
                           nxt, target.reshape(-1), zero.reshape(-1), ctrl, flat_strat, adv_max, graph_lanes())
    one = np.zeros(L * n, dtype=bool)
    if ctrl != Control.MINIMISE:
        # value exactly 1 (almost-sure reachability); not computed for a minimising controller
        one = almost_sure(imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.lower, imdp.upper, imdp.floor, nxt,
                          target.reshape(-1), W, ctrl, flat_strat, adv_max, graph_lanes())
    W = W.reshape(L, n)
    one = one.reshape(L, n) & ~target
    zero_all = zero | (active & ~W)  # value exactly 0: the target cannot be reached
    fixed1 = target | one  # value exactly 1: fixed like targets (lower = upper = 1 is sound)
    active2 = active & W & ~one
    return zero_all, fixed1, one, active2


def _value_iteration(sw, imdp, nxt, lo, up, active, ctrl, adv_max, flat_strat, precision, max_iterations):
    """``method="vi"``: components in reverse topological order with optimistic value iteration in
    each (models without floor rows), else optimistic value iteration with Jacobi sweeps on the
    whole model.  Returns (lo, up, iterations)."""
    topo = not imdp.has_floor
    comp, ncomp, comp_cnt, sccs = _end_components(imdp, nxt, active, ctrl, flat_strat, want_sccs=topo)
    if topo:
        it = _topological(imdp, nxt, lo, up, active, ctrl, adv_max, flat_strat, precision, max_iterations, sccs,
                          (comp, ncomp, comp_cnt))
        return lo, up, it
    # floor rows: optimistic value iteration with Jacobi sweeps on the whole model
    return _ovi_jacobi(sw, imdp, nxt, lo, up, active, ctrl, adv_max, flat_strat, precision, max_iterations,
                       (comp, ncomp, comp_cnt))


def _interval_iteration(sw, imdp, nxt, lo, up, active, ctrl, adv_max, flat_strat, precision, max_iterations):
    """``method="interval"``: interval iteration with deflation on the whole model (floor rows:
    their global order needs Jacobi sweeps).  Returns (lo, up, iterations)."""
    comp, ncomp, comp_cnt, _ = _end_components(imdp, nxt, active, ctrl, flat_strat, want_sccs=False)
    it = 0
    gap = float(np.max(up - lo)) if up.size else 0.0
    members = np.flatnonzero(active.reshape(-1)) if ncomp else None
    while gap > precision and it < max_iterations:
        it += 1
        lo, up, _ = _interval_step(sw, imdp, nxt, lo, up, it, (comp, ncomp, comp_cnt), members, adv_max, ctrl,
                                   flat_strat)
        gap = float(np.max(up - lo))
    return lo, up, it


#: The algorithms of the unbounded values, by ``method`` name: each takes (sweeper, imdp, nxt,
#: lo, up, active nodes, ctrl, adv_max, flat strategy, precision, max_iterations), improves the
#: sound bracket [lo, up] (L, n) of the active nodes and returns (lo, up, iterations).  A new
#: algorithm is one function of this shape and one entry here (docs: robust_imdp.solvers.api).
METHODS = {"vi": _value_iteration, "interval": _interval_iteration}


def _minimising_strategy(sw, nxt, up, active, tie_break=None):
    """A minimising controller's strategy: on every non-target node, a row of least value against the proven
    upper vector ``up`` (module docstring, "Strategy extraction"); with ``tie_break`` (:class:`EngineTies`), of
    the rows of exactly least value the one the keys rank best ("More keys").

    Why ``up`` and not the lower vector: where ``B(up) <= up`` (what the upper iteration keeps and the
    guesses are checked against), a strategy pi taking such rows has ``B_pi(up) = B(up) <= up``, so its value
    -- the least fixed point of ``B_pi`` -- is at most ``up`` (Knaster-Tarski): the strategy achieves the
    reported upper bound. On the nodes the graph pre-computation proved 0 (``up = 0``) a least row is one
    whose every possible successor has value 0, i.e. a row that keeps the path away from the target for
    ever; the first row there might not. The caller re-evaluates the strategy in any case.
    """
    sw.active = active
    sw.layers = [l for l in range(nxt.shape[0]) if active[l].any()]
    _, arg, rows = sw.sweep(up, +1, want_rows=tie_break is not None)
    if tie_break is None:
        return arg
    R = sw.m.n_choices
    score = _key_rank([_key_rows(m, nxt, active, v, a, Control.MINIMISE)
                       for m, v, a in zip(tie_break.models, tie_break.values, tie_break.adv_max)], maximise=False)
    return _lex_choice(rows.reshape(-1, R), score.reshape(-1, R), sw.m.state_ptr, arg, maximise=False)


def _extract_strategy(sw, imdp, nxt, lo, target, active, swept, ctrl, adv_max, strategy, tie_break):
    """The strategy: optimal rows w.r.t. the final lower values ``lo`` on the ``swept`` nodes
    (value-1 nodes included), ties broken toward progress to the *original* target (module
    docstring, "Strategy extraction")."""
    L, n = nxt.shape
    sw.active = swept
    sw.layers = [l for l in range(L) if sw.active[l].any()]
    _, arg, rows = sw.sweep(lo, -1, want_rows=(ctrl == Control.MAXIMISE))
    if ctrl == Control.FIXED:
        return strategy[0].copy()
    if ctrl != Control.MAXIMISE:
        return arg
    R = imdp.n_choices
    rv = rows.reshape(L, R)
    # best-row value of each node (computed with the same rounding) and a tie tolerance
    rowbest = np.maximum.reduceat(np.where(np.isfinite(rv), rv, -1.0), imdp.state_ptr[:-1], axis=1)
    optimal = rv >= np.repeat(rowbest, np.diff(imdp.state_ptr), axis=1) - _TIE_TOL
    # nodes the graph pre-computation proved 0 (not swept above): every row is optimal
    proven0 = active & ~sw.active
    optimal |= np.repeat(proven0, np.diff(imdp.state_ptr), axis=1)
    if tie_break is None:
        score = np.full(L * R, -np.inf)
    else:
        score = _key_rank([_key_rows(m, nxt, active, v, a)
                           for m, v, a in zip(tie_break.models, tie_break.values, tie_break.adv_max)])
    if tie_break is None or tie_break.strategy is None:
        tie_strat = np.full(L * n, -1, dtype=np.int64)
    else:
        tie_strat = tie_break.strategy.reshape(-1)
    strat = progress_strategy(imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.lower, imdp.upper, imdp.floor,
                              nxt, target.reshape(-1), optimal.reshape(-1), adv_max, arg.reshape(-1),
                              score, tie_strat, graph_lanes())
    return strat.reshape(L, n)


#: Rows whose (rounded) value is within this of the best row count as optimal (tied) for strategy
#: extraction.  Far below any precision a user asks for (>= 1e-10 in practice, 1e-8 by default),
#: so a tied row loses nothing the reported bracket could show; far above the rounding error of
#: one row (``ROW_ERR`` ~ 1e-14 for rows of a few dozen entries), so rows of equal value that
#: were rounded differently still tie.  Exact ties (the rows of a node whose lower value is 0)
#: need no tolerance at all.
_TIE_TOL = 1e-12

#: Grid on which every key but the last of an :class:`EngineTies` is compared (``floor(v / _KEY_TOL)``):
#: key values closer than this may tie and the next key decides.  The keys are values of other solves,
#: brackets of width up to their precision (1e-8 by default): differences below 1e-7 say little.
_KEY_TOL = 1e-7


__all__ = ["solve_layered", "METHODS", "EngineTies", "StepRows", "BoundedResult", "STEP_ROWS_MAX"]
