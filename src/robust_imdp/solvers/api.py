"""Public API of the solvers: :func:`solve_reachability`, :func:`evaluate_strategy`,
:class:`ReachabilityResult`, and the registry of back-ends.

Contract
--------
``solve_reachability(imdp, target, *, avoid, adversary, objective, horizon, precision)`` and
``evaluate_strategy(imdp, target, strategy, ...)`` return a frozen :class:`ReachabilityResult`
whose ``lower``/``upper`` bracket the true value of every state.  Why the brackets are sound:
:mod:`robust_imdp.solvers.engine`.

Modules (bottom-up): ``common`` (enums, masks, the result type), ``kernels`` (numba kernels of
the Bellman operator and of optimistic value iteration per component), ``graph`` (graph
pre-computations, end components), ``sweep`` (layer sweeps), ``ovi`` (optimistic value
iteration, interval iteration), ``engine`` (:func:`~robust_imdp.solvers.engine.solve_layered`),
``lp`` (LP cross-checks), this module, ``product`` (IMDP x DFA).

How to add a back-end
---------------------
* A whole-model solver (like ``"lp"``): one new module ``solvers/<name>.py`` with a function of
  the keyword arguments of :data:`BACKENDS` returning a :class:`ReachabilityResult`, and one entry
  in :data:`BACKENDS` (import it inside the function if it is heavy, as ``_solve_lp`` does; a new
  module also gets its row in docs/ARCHITECTURE.md and its name in ``solvers/__init__.py``).
* An algorithm of the layered engine (then also usable by :func:`evaluate_strategy`, the
  product and synthesis): one function ``(sweeper, imdp, nxt, lo, up, active, ctrl, adv_max,
  flat_strategy, precision, max_iterations) -> (lo, up, iterations)`` in a new module, one entry
  in :data:`robust_imdp.solvers.engine.METHODS` and one in :data:`BACKENDS`
  (``_engine_backend("<name>")``).
"""

from __future__ import annotations

import numpy as np

from robust_imdp.errors import ConvergenceWarning, DimensionError, InvalidInputError
from robust_imdp.models.imdp import IMDP
from robust_imdp.solvers import engine
from robust_imdp.solvers.common import (Adversary, Control, Objective, ReachabilityResult, adversary_maximises,
                                        as_mask, check_strategy, control_of, enum_value, target_avoid)
from robust_imdp.solvers.engine import METHODS, _TIE_TOL, solve_layered

# Names of the solver modules re-exported here, read by tests, benchmarks and the warm-up.
from robust_imdp.solvers.graph import (_end_components, _response_family, almost_sure, positive_attractor,  # noqa: F401
                                       progress_strategy, response_end_components, self_loops, stay_exit_bounds,
                                       stayable_rows, strong_components)
from robust_imdp.solvers.kernels import (KIND_END_COMPONENT, KIND_OVI, KIND_SINGLE, PAR_BLOCK,  # noqa: F401
                                         PREFETCH_DISTANCE, ST_DEFLATED, ST_EXACT, ST_EXTRAP, ST_INTERVAL, ST_OPEN,
                                         ST_PLAIN, SWEEP_CHECK_LOWER, SWEEP_CHECK_UPPER, SWEEP_LOWER, SWEEP_UPPER,
                                         _check_guess, _exit_gap, bellman_layer, bellman_layer_parallel,
                                         component_levels, dd_prefix, fill_local_order, node_sweep, ovi_component,
                                         row_err, row_value, row_value_cached, solve_components)
from robust_imdp.solvers.ovi import OVI_PARAMS, _deflated_component, _ovi_jacobi, _topological  # noqa: F401
from robust_imdp.solvers.sweep import PAR_MIN_STATES, Sweeper  # noqa: F401

_Sweeper = Sweeper  # the old private name (tests, benchmarks)
_as_mask = as_mask
_enum = enum_value


def _engine_backend(method):
    """The back-end of ``solve_reachability(method=method)`` through the layered engine."""

    def solve(imdp, target, *, avoid, adversary, objective, horizon, precision, max_iterations, tie_break):
        adv_max = adversary_maximises(adversary, objective)
        ctrl = control_of(objective)
        t, z = _target_avoid(imdp, target, avoid)
        nxt = np.zeros((1, imdp.n_states), dtype=np.int64)
        res = solve_layered(imdp, nxt, t[None, :], z[None, :], ctrl=ctrl, adv_max=adv_max, horizon=horizon,
                            precision=precision, max_iterations=max_iterations, method=method, tie_break=tie_break)
        return _single_layer(res)

    return solve


def _solve_lp(imdp, target, *, avoid, adversary, objective, horizon, precision, max_iterations, tie_break):
    """``method="lp"``: :func:`robust_imdp.solvers.lp.solve_reachability_lp` (small models; unbounded
    only, ``horizon``, ``precision`` and ``max_iterations`` are not used), as a ReachabilityResult."""
    if tie_break is not None:
        raise InvalidInputError("tie_break is not available with method='lp'; use 'vi' or 'interval'")
    from robust_imdp.solvers import lp  # lazy: cvxpy is imported only there (lp is below api)

    r = lp.solve_reachability_lp(imdp, target, avoid=avoid, adversary=adversary, objective=objective)
    return ReachabilityResult(r.lower, r.upper, r.strategy, r.iterations, r.precision, r.converged)


#: The back-ends of :func:`solve_reachability`, by ``method`` name (in the order of its error
#: message); each takes ``(imdp, target, *, avoid, adversary, objective, horizon, precision,
#: max_iterations, tie_break)`` and returns a :class:`ReachabilityResult`.
BACKENDS = {"vi": _engine_backend("vi"), "interval": _engine_backend("interval"), "lp": _solve_lp}


def check_method(method, allowed=METHODS):
    """InvalidInputError unless ``method`` is in ``allowed`` (default: the layered engine's methods,
    the ones of :func:`evaluate_strategy` and the product); the message lists :data:`BACKENDS`."""
    if method not in allowed:
        names = [repr(m) for m in BACKENDS]
        raise InvalidInputError(f"method must be {', '.join(names[:-1])} or {names[-1]}; got {method!r}")


def solve_reachability(imdp: IMDP, target, *, avoid=None, adversary="pessimistic", objective="maximize",
                       horizon=None, precision=1e-8, max_iterations=100_000, method="vi", tie_break=None):
    """Sound bounds of the optimal probability to reach ``target`` while avoiding ``avoid``.

    Parameters
    ----------
    imdp : IMDP
    target, avoid : (n,) bool mask or 1-D int index array
        Target states count as reached (value 1); avoid states are absorbing failures (0).
    adversary : {"pessimistic", "optimistic"} or Adversary
    objective : {"maximize", "minimize"} or Objective
    horizon : int or None
        ``k`` gives k-step bounded reachability; None unbounded.
    precision : float
        Stop when ``max(upper - lower) <= precision`` (unbounded only).
    method : {"vi", "interval", "lp"}
        "vi" (default): strongly connected components in reverse topological order, each solved by
        optimistic value iteration with Gauss-Seidel sweeps and a proven upper vector (falls back to
        interval iteration; models with floor rows use "interval").  "interval": interval
        iteration (a lower and an upper sequence) on the whole model.  Both return proven
        brackets.  "lp" dispatches to :func:`robust_imdp.solvers.lp.solve_reachability_lp` (small models).
        The back-ends are the entries of :data:`BACKENDS`.
    tie_break : ReachabilityResult, optional
        ``objective="maximize"`` only, not with "lp": the ``adversary="optimistic"`` solve of the
        same problem.  Rows tied in the lower value are then chosen by their optimistic value
        (lexicographic choice, see "Strategy extraction" in :mod:`robust_imdp.solvers.engine`);
        without it ties go to the first choice.

    Returns
    -------
    ReachabilityResult
        ``lower``/``upper`` (n,) sound bracket, ``strategy`` (n,) or (k, n).

    Warns
    -----
    ConvergenceWarning
        When ``max_iterations`` is hit; the returned bracket is still sound.
    """
    check_method(method, BACKENDS)
    return BACKENDS[method](imdp, target, avoid=avoid, adversary=adversary, objective=objective, horizon=horizon,
                            precision=precision, max_iterations=max_iterations, tie_break=tie_break)


def evaluate_strategy(imdp: IMDP, target, strategy, *, avoid=None, adversary="pessimistic", horizon=None,
                      precision=1e-8, max_iterations=100_000, method="vi"):
    """Sound bounds of the reachability probability of a fixed strategy (an interval Markov chain).

    ``adversary="pessimistic"`` minimises the probability (the strategy's guaranteed value),
    ``"optimistic"`` maximises it.  ``strategy`` is (n,) or (k, n) (time-varying, with a horizon
    of k steps).  ``method`` as in :func:`solve_reachability` ("vi" or "interval").  Returns a
    :class:`ReachabilityResult` whose ``strategy`` is the input.
    """
    check_method(method)
    s = check_strategy(imdp, strategy)
    adv_max = enum_value(Adversary, adversary, "adversary") is Adversary.OPTIMISTIC
    if s.ndim == 2 and (horizon is None or s.shape[0] != int(horizon)):
        raise DimensionError(f"a time-varying strategy of shape {s.shape} needs horizon={s.shape[0]}; got {horizon}")
    t, z = _target_avoid(imdp, target, avoid)
    nxt = np.zeros((1, imdp.n_states), dtype=np.int64)
    strat = s[:, None, :] if s.ndim == 2 else s[None, None, :]
    res = solve_layered(imdp, nxt, t[None, :], z[None, :], ctrl=Control.FIXED, adv_max=adv_max, horizon=horizon,
                        precision=precision, max_iterations=max_iterations, strategy=strat, method=method)
    return _single_layer(res)


def _target_avoid(imdp, target, avoid):
    return target_avoid(imdp.n_states, target, avoid)


def _single_layer(res: ReachabilityResult) -> ReachabilityResult:
    strat = res.strategy[:, 0, :] if res.strategy.ndim == 3 else res.strategy[0]
    return ReachabilityResult(lower=res.lower[0], upper=res.upper[0], strategy=strat,
                              iterations=res.iterations, precision=res.precision, converged=res.converged)


_check_method = check_method

__all__ = ["Adversary", "Objective", "ReachabilityResult", "solve_reachability", "evaluate_strategy",
           "adversary_maximises", "check_strategy", "solve_layered"]
