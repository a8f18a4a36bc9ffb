"""Convex programs (cvxpy + Clarabel): LP cross-checks of the interval solver, SOCPs of the
RKHS bounds.

This is the only module of robust_imdp that imports cvxpy / clarabel, and it imports them
inside the functions, so ``import robust_imdp`` never pays for them.  The LPs are *checkers*
for small models: rows with a floor are densified (``IMDP.to_dense``, memory R x n), and the
LPs are solved by an interior-point method whose answers are accurate to about the solver
tolerances (1e-10 here), not proofs.  The SOCPs (:func:`rkhs_min_norm_socp`,
:func:`rkhs_vertex_socp`) only *propose* dual weights; ``robust_imdp.bounds.rkhs`` turns weights into
certified bounds, so an inaccurate solve costs tightness, never soundness.

Contents
--------
* :func:`inner_lp` -- the inner problem ``min/max p.v`` over one row's polytope
  ``{l <= p <= u, sum p = 1}``, as a plain LP.
* :func:`solve_reachability_lp` -- whole-problem LPs:

  - controller and nature optimise in the *same* direction (optimistic maximisation, or
    both minimising): one LP, by LP duality of the inner problem (see ``_game_lp``);
  - a fixed strategy (an interval Markov chain), either adversary: one LP;
  - controller and nature in *opposite* directions (pessimistic max-min): not a single LP
    in general; every deterministic memoryless strategy is evaluated by the fixed-strategy
    LP (brute force, only for tiny models) and the pointwise optimum is taken.  Memoryless
    deterministic strategies suffice for reachability in IMDPs with rectangular
    (row-wise independent) uncertainty, which is the model here.
* :func:`evaluate_strategy_lp` -- the fixed-strategy LP alone.

Duality used (for one row, dense bounds ``l, u`` over all n states, values ``x``)::

    max_p {p.x : l <= p <= u, 1.p = 1}  =  min_{lam, a>=0, b>=0} {lam + u.a - l.b : lam + a_j - b_j >= x_j}
    min_p {p.x : l <= p <= u, 1.p = 1}  =  max_{lam, a>=0, b>=0} {lam + l.b - u.a : lam + b_j - a_j <= x_j}

(weak duality: for feasible p, ``p.x <= sum_j p_j (lam + a_j - b_j) <= lam + u.a - l.b``;
strong duality holds because the primal is feasible and bounded).  So ``x_s >= max_p p.x``
is "there is a dual witness with ``lam + u.a - l.b <= x_s``", which is linear in
``(x, lam, a, b)``.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from robust_imdp.errors import ConvergenceError, DimensionError, InvalidInputError
from robust_imdp.solvers.common import Control, adversary_maximises, control_of, target_avoid

#: Clarabel tolerances used by every LP here (gap and feasibility).  Values of the whole
#: problems come out accurate to ~1e-9 on models of <= 30 states with these settings.
LP_TOL = 1e-10

#: Largest number of deterministic memoryless strategies enumerated by the brute force.
MAX_STRATEGIES = 4096


# ----------------------------------------------------------------------------- helpers
def _solve(problem, what: str):
    """Solve a cvxpy problem with Clarabel; raise ConvergenceError unless optimal."""
    import cvxpy as cp

    try:
        problem.solve(
            solver=cp.CLARABEL,
            tol_gap_abs=LP_TOL,
            tol_gap_rel=LP_TOL,
            tol_feas=LP_TOL,
            max_iter=500,
        )
    except cp.error.SolverError as exc:  # pragma: no cover - depends on the back-end
        raise ConvergenceError(f"CLARABEL failed on the {what} LP: {exc}") from exc
    if problem.status != cp.OPTIMAL:
        raise ConvergenceError(
            f"CLARABEL did not solve the {what} LP: status {problem.status!r} (expected 'optimal')"
        )
    return problem


def _normalise(value, name: str, allowed: tuple[str, ...]) -> str:
    """Accept the enum members of ``solvers.common`` or their lower-case strings (used by
    ``io.formats``; the solvers themselves use ``common.enum_value``)."""
    v = getattr(value, "value", value)
    v = v.lower() if isinstance(v, str) else getattr(value, "name", str(value)).lower()
    if v not in allowed:
        raise InvalidInputError(f"{name} must be one of {allowed}; got {value!r}")
    return v


def nature_maximises(adversary, objective) -> bool:
    """Direction of nature: True when nature maximises the reachability probability.

    ``"pessimistic"`` means nature plays against the controller's objective (it minimises
    the probability when the controller maximises it, and vice versa); ``"optimistic"``
    means nature cooperates.  This is Storm's ROBUST / COOPERATIVE; the same rule as
    :func:`robust_imdp.solvers.common.adversary_maximises`, which it is.
    """
    return adversary_maximises(adversary, objective)


def _target_avoid(n: int, target, avoid):
    """Masks of target and avoid; the target must be non-empty and disjoint from avoid."""
    return target_avoid(n, target, avoid, item="state")


def ordering_inner_dense(lo: np.ndarray, up: np.ndarray, v: np.ndarray, maximize: bool) -> np.ndarray:
    """Reference ordering solution of the inner problem for dense rows (tests and strategy ties).

    Every entry gets its lower bound; the remaining mass ``1 - sum(lo)`` goes to entries in
    decreasing (maximize) / increasing (minimize) order of ``v`` up to ``up - lo``.

    Parameters
    ----------
    lo, up : (R, n) float arrays
    v : (n,) float array
    maximize : bool

    Returns
    -------
    (R,) float array of optimal values ``p.v``.
    """
    order = np.argsort(-v if maximize else v, kind="stable")
    gap = (up - lo)[:, order]
    rem = 1.0 - lo.sum(axis=1, keepdims=True)
    before = np.cumsum(gap, axis=1) - gap
    alloc = np.clip(rem - before, 0.0, gap)
    return lo @ v + alloc @ v[order]


# ----------------------------------------------------------------------------- inner LP
def inner_lp(lower, upper, values, *, floor=0.0, n_unlisted=0, unlisted_values=None, maximize=True):
    """Optimise ``p.v`` over one row's interval polytope with cvxpy + Clarabel.

    The row lists k successors with intervals ``[lower, upper]`` and values ``values``; the
    ``n_unlisted`` other states each get the interval ``[0, floor]`` and values
    ``unlisted_values`` (densified here: this is a checker).

    Parameters
    ----------
    lower, upper, values : (k,) float arrays
    floor : float
    n_unlisted : int
    unlisted_values : (n_unlisted,) float array, required when ``n_unlisted > 0``
    maximize : bool

    Returns
    -------
    value : float
        ``p.v`` at the optimum (evaluated from the returned p).
    p : (k + n_unlisted,) float array
        An optimal distribution: listed entries first, then the unlisted ones.

    Raises
    ------
    DimensionError, InvalidInputError
        Mismatched lengths, missing ``unlisted_values``.
    ConvergenceError
        The solver did not report an optimal solution (e.g. an empty polytope).
    """
    import cvxpy as cp

    lo = np.asarray(lower, dtype=float).ravel()
    up = np.asarray(upper, dtype=float).ravel()
    v = np.asarray(values, dtype=float).ravel()
    if not (lo.shape == up.shape == v.shape):
        raise DimensionError(f"lower, upper and values must have one common shape (k,); got {lo.shape}, {up.shape}, {v.shape}")
    m = int(n_unlisted)
    if m < 0:
        raise InvalidInputError(f"n_unlisted must be >= 0; got {n_unlisted}")
    if m > 0:
        if unlisted_values is None:
            raise InvalidInputError(f"unlisted_values of shape ({m},) is required when n_unlisted = {m} > 0; got None")
        w = np.asarray(unlisted_values, dtype=float).ravel()
        if w.shape != (m,):
            raise DimensionError(f"unlisted_values must have shape ({m},) (n_unlisted); got {w.shape}")
        lo = np.concatenate([lo, np.zeros(m)])
        up = np.concatenate([up, np.full(m, float(floor))])
        v = np.concatenate([v, w])
    p = cp.Variable(v.shape[0])
    obj = (cp.Maximize if maximize else cp.Minimize)(v @ p)
    _solve(cp.Problem(obj, [p >= lo, p <= up, cp.sum(p) == 1]), "inner")
    pv = np.asarray(p.value, dtype=float)
    return float(pv @ v), pv


# ----------------------------------------------------------------------------- whole problems
def _prob0(lo, up, row_state, n, target, avoid, nature_max: bool, ctrl_max: bool) -> np.ndarray:
    """States whose value is 0, by the graph attractor of the positive-probability set.

    ``S_0 = target``; a state joins ``S`` when (controller max: some / min: every) row of it
    gives ``S`` positive mass under (nature max: some / min: every) distribution of the row:
    ``max_p p(S) = min(1, sum_S up) > 0`` resp. ``min_p p(S) = max(sum_S lo, 1 - sum_notS up) > 0``.
    Avoid states never join.  Returns the (n,) mask of states outside the final ``S``.
    """
    S = target & ~avoid
    while True:
        inS = S.astype(float)
        if nature_max:
            pos = (up @ inS) > 0
        else:
            pos = np.maximum(lo @ inS, 1.0 - up @ (1.0 - inS)) > 1e-15
        per_state_any = np.zeros(n, dtype=bool)
        per_state_all = np.ones(n, dtype=bool)
        np.logical_or.at(per_state_any, row_state, pos)
        np.logical_and.at(per_state_all, row_state, pos)
        new = S | ((per_state_any if ctrl_max else per_state_all) & ~avoid)
        if np.array_equal(new, S):
            return ~S
        S = new


def _game_lp(lo, up, row_state, n, target, zero, nature_max: bool):
    """One LP for the game where controller and nature optimise in the same direction.

    Both maximise: least fixed point of ``x_s = max_r max_p p.x`` = the minimiser of
    ``sum x`` over pre-fixed points ``x >= T(x)`` (Knaster-Tarski), with the inner max
    replaced by its dual witness (module docstring).  Both minimise: the greatest post-fixed
    point ``max sum x`` s.t. ``x <= T(x)``; it equals the least fixed point once the states
    of value 0 are fixed to 0 (``zero``, from :func:`_prob0`), as for minimal reachability
    in MDPs.  Returns (x (n,), row values (R,) from the duals, solver iterations).
    """
    import cvxpy as cp

    R = lo.shape[0]
    free = ~(target | zero)
    fixed = np.where(target, 1.0, 0.0)
    rows = np.flatnonzero(free[row_state])
    x = cp.Variable(n)
    cons = [x[~free] == fixed[~free]] if np.any(~free) else []
    cons += [x >= 0, x <= 1]
    if rows.size:
        k = rows.size
        lam = cp.Variable(k)
        a = cp.Variable((k, n), nonneg=True)
        b = cp.Variable((k, n), nonneg=True)
        L, U = lo[rows], up[rows]
        lam_col = cp.reshape(lam, (k, 1), order="C") @ np.ones((1, n))  # lam_r in every column
        x_row = np.ones((k, 1)) @ cp.reshape(x, (1, n), order="C")  # x_j in every row
        if nature_max:
            bound = lam + cp.sum(cp.multiply(U, a), axis=1) - cp.sum(cp.multiply(L, b), axis=1)
            cons += [lam_col + a - b >= x_row, x[row_state[rows]] >= bound]
        else:
            bound = lam + cp.sum(cp.multiply(L, b), axis=1) - cp.sum(cp.multiply(U, a), axis=1)
            cons += [lam_col + b - a <= x_row, x[row_state[rows]] <= bound]
    obj = cp.Minimize(cp.sum(x)) if nature_max else cp.Maximize(cp.sum(x))
    prob = _solve(cp.Problem(obj, cons), "reachability")
    xv = np.asarray(x.value, dtype=float)
    iters = int(getattr(prob.solver_stats, "num_iters", 0) or 0)
    return xv, iters


def _dense(imdp):
    lo, up = imdp.to_dense()
    return lo, up


def _greedy_p(lo: np.ndarray, up: np.ndarray, order: np.ndarray) -> np.ndarray:
    """(R, n) ordering distributions: lower bounds, then the remaining mass in ``order``."""
    gap = (up - lo)[:, order]
    rem = 1.0 - lo.sum(axis=1, keepdims=True)
    before = np.cumsum(gap, axis=1) - gap
    p = lo.copy()
    p[:, order] += np.clip(rem - before, 0.0, gap)
    return p


def _pick_strategy(lo, up, row_state, state_ptr, x, target, nature_max: bool, ctrl_max: bool) -> np.ndarray:
    """A memoryless strategy attaining ``x`` that is not trapped by end components.

    Optimal rows of a state are those whose inner value (reference ordering) is within
    1e-7 of the best.  States are assigned in backward layers from the target: a state takes
    an optimal row under which an optimal distribution of nature gives positive mass to the
    states already assigned.  When nature maximises, that distribution is the ordering one
    at ``x`` with ties (values equal to 1e-9) broken toward assigned states, so the pair
    (strategy, that distribution) is a Markov chain with fixed point ``x`` in which every
    assigned state reaches the target with positive probability -- hence its reachability
    value is ``x`` and the strategy attains ``x`` (the usual attractor argument for maximal
    reachability, e.g. Baier & Katoen, Principles of Model Checking, Lemma 10.102).  When
    nature minimises and the controller minimises too, any value-greedy row is optimal;
    the layers only make the choice deterministic.  States never assigned (value 0) take
    their first optimal row.
    """
    n = x.shape[0]
    q = ordering_inner_dense(lo, up, x, nature_max)
    best = np.full(n, -np.inf if ctrl_max else np.inf)
    (np.maximum if ctrl_max else np.minimum).at(best, row_state, q)
    optimal = np.abs(q - best[row_state]) <= 1e-7
    done = target.copy()
    choice = np.full(n, -1, dtype=np.int64)
    xr = np.round(x, 9)
    while True:
        inS = done.astype(float)
        if nature_max:
            order = np.lexsort((~done, -xr))  # value descending, assigned states first among ties
            pos = (_greedy_p(lo, up, order) @ inS) > 0
        else:
            pos = np.maximum(lo @ inS, 1.0 - up @ (1.0 - inS)) > 1e-15
        elig = optimal & pos & ~done[row_state] & (x[row_state] > 0)
        rows = np.flatnonzero(elig)
        if rows.size == 0:
            break
        states, first = np.unique(row_state[rows], return_index=True)
        choice[states] = rows[first]
        done[states] = True
    rest = np.flatnonzero(choice < 0)
    if rest.size:
        opt_rows = np.flatnonzero(optimal)
        st, first = np.unique(row_state[opt_rows], return_index=True)
        firstrow = np.full(n, -1, dtype=np.int64)
        firstrow[st] = opt_rows[first]
        choice[rest] = np.where(firstrow[rest] >= 0, firstrow[rest], state_ptr[rest])
    return choice - state_ptr[:-1]


@dataclass(frozen=True)
class LPReachability:
    """LP values of a reachability problem, bracketed by the solver accuracy (not a proof).

    The fields of :class:`robust_imdp.solvers.api.ReachabilityResult`, which ``solve_reachability(...,
    method="lp")`` turns this into: lp.py sits below solve.py and does not import it.

    Attributes
    ----------
    lower, upper : (n,) float arrays
        The LP value -/+ ``10 * LP_TOL * n``, clamped to [0, 1].
    strategy : (n,) int array
        Choice index within each state.
    iterations : int
        Interior-point iterations (summed over LPs).
    precision : float
        ``max(upper - lower)``.
    converged : bool
        Always True (an LP that is not solved raises ConvergenceError).
    """

    lower: np.ndarray
    upper: np.ndarray
    strategy: np.ndarray
    iterations: int
    precision: float
    converged: bool


def _result(x, strategy, iterations, target):
    # the LP value is accurate to about LP_TOL (interior point); the bracket is widened by
    # 10 * LP_TOL per state and clamped to [0, 1] -- safe because every reachability
    # probability lies in [0, 1].  This is a cross-check, not a proof.
    eps = 10 * LP_TOL * max(1, x.shape[0])
    x = np.where(target, 1.0, x)
    lower = np.clip(x - eps, 0.0, 1.0)
    upper = np.clip(x + eps, 0.0, 1.0)
    return LPReachability(
        lower=lower, upper=upper, strategy=np.asarray(strategy, dtype=np.int64), iterations=int(iterations),
        precision=float(np.max(upper - lower)) if x.size else 0.0, converged=True,
    )


def _check_strategy(imdp, strategy) -> np.ndarray:
    st = np.asarray(strategy)
    n = imdp.n_states
    if st.shape != (n,):
        raise DimensionError(f"strategy must have shape ({n},) (one choice per state); got {st.shape}")
    if st.size and not np.issubdtype(st.dtype, np.integer):
        raise InvalidInputError(f"strategy must hold integer choice indices; got dtype {st.dtype}")
    k = np.diff(imdp.state_ptr)
    bad = np.flatnonzero((st < 0) | (st >= k))
    if bad.size:
        s = int(bad[0])
        raise InvalidInputError(f"strategy[{s}] = {int(st[s])} is not a choice of state {s} (it has {int(k[s])} choices)")
    return st.astype(np.int64)


def evaluate_strategy_lp(imdp, target, strategy, *, avoid=None, adversary="pessimistic", objective="maximize"):
    """Value of the interval Markov chain induced by a memoryless strategy, by one LP.

    Parameters
    ----------
    imdp : IMDP (small: rows are densified, memory R x n)
    target, avoid : (n,) bool masks or index arrays
    strategy : (n,) int array of choice indices within each state
    adversary : "pessimistic" | "optimistic"
    objective : "maximize" | "minimize"
        Only used to orient ``adversary`` (see :func:`nature_maximises`).

    Returns
    -------
    LPReachability
    """
    n = imdp.n_states
    tgt, avd = _target_avoid(n, target, avoid)
    st = _check_strategy(imdp, strategy)
    nat = nature_maximises(adversary, objective)
    rows = imdp.state_ptr[:-1] + st
    lo, up = _dense(imdp)
    lo, up = lo[rows], up[rows]
    rs = np.arange(n)
    zero = _prob0(lo, up, rs, n, tgt, avd, nat, nat) & ~tgt
    x, it = _game_lp(lo, up, rs, n, tgt, zero | (avd & ~tgt), nat)
    return _result(x, st, it, tgt)


def solve_reachability_lp(imdp, target, *, avoid=None, adversary="pessimistic", objective="maximize",
                          horizon=None, max_strategies=MAX_STRATEGIES):
    """Reachability values of a small IMDP by linear programming (a cross-check).

    Parameters
    ----------
    imdp : IMDP
    target, avoid : (n,) bool masks or index arrays (non-empty target, disjoint from avoid)
    adversary : "pessimistic" | "optimistic"
    objective : "maximize" | "minimize"
    horizon : None
        Only unbounded reachability is available here.
    max_strategies : int
        Limit of the brute force used when controller and nature play against each other.

    Returns
    -------
    LPReachability
        ``lower``/``upper`` bracket the LP value by ``10 * LP_TOL * n`` (solver accuracy,
        not a proof); ``iterations`` are interior-point iterations (summed over LPs).

    Raises
    ------
    InvalidInputError
        A horizon was given, or the brute force would enumerate more than ``max_strategies``.
    ConvergenceError
        Clarabel did not report an optimal solution.
    """
    if horizon is not None:
        raise InvalidInputError(f"horizon must be None for solve_reachability_lp (unbounded reachability only); got {horizon!r}")
    n = imdp.n_states
    tgt, avd = _target_avoid(n, target, avoid)
    nat = nature_maximises(adversary, objective)
    ctrl = control_of(objective) is Control.MAXIMISE
    lo, up = _dense(imdp)
    if nat == ctrl:
        zero = _prob0(lo, up, imdp.row_state, n, tgt, avd, nat, ctrl) & ~tgt
        x, it = _game_lp(lo, up, imdp.row_state, n, tgt, zero | (avd & ~tgt), nat)
        strat = _pick_strategy(lo, up, imdp.row_state, imdp.state_ptr, x, tgt, nat, ctrl)
        return _result(x, strat, it, tgt)
    # opposite directions: brute force over deterministic memoryless strategies
    k = np.diff(imdp.state_ptr)
    count = int(np.prod(k.astype(float)))
    if count > max_strategies:
        raise InvalidInputError(
            f"imdp has {count} deterministic memoryless strategies, more than max_strategies = {max_strategies}; "
            "the pessimistic max-min (controller against nature) is solved here by brute force only for tiny models"
        )
    best_x, best_s, total_it = None, None, 0
    for combo in itertools.product(*(range(int(c)) for c in k)):
        res = evaluate_strategy_lp(imdp, tgt, np.array(combo, dtype=np.int64), avoid=avd,
                                   adversary=adversary, objective=objective)
        x = 0.5 * (res.lower + res.upper)
        total_it += res.iterations
        if best_x is None:
            best_x, best_s, best_sum = x.copy(), np.array(combo), x.sum()
            continue
        # pointwise optimum over strategies; keep the strategy with the best total as witness
        best_x = np.maximum(best_x, x) if ctrl else np.minimum(best_x, x)
        if (x.sum() > best_sum) if ctrl else (x.sum() < best_sum):
            best_s, best_sum = np.array(combo), x.sum()
    return _result(best_x, best_s, total_it, tgt)


__all__ = [
    "LP_TOL",
    "LPReachability",
    "MAX_STRATEGIES",
    "inner_lp",
    "solve_reachability_lp",
    "evaluate_strategy_lp",
    "nature_maximises",
    "ordering_inner_dense",
]


# ----------------------------------------------------------------------------- RKHS SOCPs
def _psd_factor(G: np.ndarray, rel_tol: float = 1e-13) -> np.ndarray:
    """``F`` with ``F.T @ F ~= G`` for a PSD Gram matrix (eigenvalues below ``rel_tol * max`` dropped)."""
    lam, V = np.linalg.eigh((G + G.T) / 2)
    keep = lam > rel_tol * max(lam.max(), 1e-300)
    return (V[:, keep] * np.sqrt(lam[keep])).T


def _solve_socp(problem, what: str) -> None:
    import cvxpy as cp

    try:
        problem.solve(solver=cp.CLARABEL)
    except cp.error.SolverError as exc:
        raise ConvergenceError(f"CLARABEL failed on the {what} SOCP: {exc}") from None
    if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
        raise ConvergenceError(f"CLARABEL did not solve the {what} SOCP: status {problem.status!r}")


def rkhs_min_norm_socp(K, y, bound) -> np.ndarray:
    """Dual weights of the smallest RKHS norm that explains the data within ``bound``.

    Program (primal, in the coordinates ``beta`` of the data span, ``K ~= M M^T``)::

        minimise  ||beta||_2   subject to   -bound <= M beta - y <= bound

    which is ``min { ||f||_H : |f(x_i) - y_i| <= bound }`` by the representer theorem. Its
    dual variables ``w = lambda_lower - lambda_upper`` give, for EVERY function with
    ``|f(x_i) - y_i| <= bound``, ``||f|| >= (w.y - bound ||w||_1) / sqrt(w.K w)`` (Cauchy-Schwarz
    on ``<f, Phi* w>``); ``rkhs.min_rkhs_norm`` evaluates that certificate with outward
    rounding, so the solver's accuracy only affects how large the certified minimum is.

    Parameters
    ----------
    K : (m, m) float array (kernel matrix)
    y : (m,) float array
    bound : float >= 0

    Returns
    -------
    w : (m,) float array
        The dual weights (zeros if the solver failed; the caller then falls back).
    value : float
        The solver's primal optimum (nan if it failed): the norm of a function in the
        eigen-truncated data span that meets the constraints to the solver's accuracy, an
        approximate *upper* bound of the minimum (used by the tests as the other side).
    """
    import cvxpy as cp

    K = np.asarray(K, float)
    y = np.asarray(y, float)
    M = _psd_factor(K).T  # (m, r): K ~= M M^T
    beta = cp.Variable(M.shape[1])
    upper = M @ beta - y <= bound
    lower = y - M @ beta <= bound
    prob = cp.Problem(cp.Minimize(cp.norm(beta)), [upper, lower])
    try:
        _solve_socp(prob, "minimum-norm")
    except ConvergenceError:
        return np.zeros_like(y), float("nan")
    return np.asarray(lower.dual_value - upper.dual_value, float), float(prob.value)


def rkhs_vertex_socp(K, y, b, s0, noise, rkhs_bound, side: int = 1):
    """The optimal certificate of one vertex functional (cross-check of ``rkhs._active_set``).

    Program::

        minimise over w in R^m   side * w.y + noise ||w||_1 + B || phi - Phi* w ||_H

    with ``||phi - Phi* w||^2 = s0 - 2 w.b + w.K w`` written as ``||F [w; 1]||`` for a factor
    ``F`` of the PSD Gram matrix ``[[K, -b], [-b^T, s0]]``. It is the conic dual of
    ``max { side <h, phi> : ||h|| <= B, |h(x_i) - y_i| <= noise }`` (Scharnhorst et al., IEEE TAC
    2022), so its optimum is the tightest bound of ``side <h, phi>`` given the data.

    Returns
    -------
    value : float
        The solver's optimum (not certified).
    w : (m,) float array
    """
    import cvxpy as cp

    K = np.asarray(K, float)
    m = K.shape[0]
    Gm = np.zeros((m + 1, m + 1))
    Gm[:m, :m] = K
    Gm[:m, m] = -np.asarray(b, float)
    Gm[m, :m] = -np.asarray(b, float)
    Gm[m, m] = float(s0)
    F = _psd_factor(Gm)
    w = cp.Variable(m)
    obj = side * (np.asarray(y, float) @ w) + noise * cp.norm1(w) + rkhs_bound * cp.norm(F @ cp.hstack([w, np.ones(1)]))
    prob = cp.Problem(cp.Minimize(obj))
    _solve_socp(prob, "vertex-bound")
    return float(prob.value), np.asarray(w.value, float)
