"""Which mode among equals: the keys of the lexicographic strategy choice of :func:`robust_imdp.synthesis.core.synthesize`.

The robust strategy maximises the guaranteed (lower) value; where several modes reach it -- all of them
where it is 0, which is most of the undecided cells of a natural problem -- the guarantee does not say
which mode to use. The choice is lexicographic (README, "What the controller does"):

1. the best robust lower value (the guarantee; never traded for anything below),
2. then the best value under the *nominal* model (:mod:`robust_imdp.abstraction.nominal`: the data-fitted
   or known dynamics at each cell's centre and the noise), solved for the best probability itself, with its
   own ties broken by the next key,
3. then the best optimistic value ``max_p p.U`` (U the max-max value, the vector of ``p_up_star``).

Without a nominal model the keys are (1) and (3), as before the nominal model existed. Under the safety
reading the controller minimises the probability of a bad prefix and the same keys apply mirrored: the
least upper bound of that probability (exactly least, so the strategy keeps the proven bound), then the
least nominal probability, then the least optimistic one. Where every mode's lower value is 0 (reach
reading, unbounded), a node takes the nominal solve's own mode, a progress-making choice of the nominal
model (the attractor of :mod:`robust_imdp.solvers.engine`), so the strategy does not circle where the
nominal values tie.

What the keys never change: the bounds. The synthesis evaluates the chosen strategy on the robust model
(``p_low``, ``p_up`` are its own), and checks that it keeps the optimal lower value at every cell.

Models. A joint :class:`~robust_imdp.models.imdp.IMDP` with a joint nominal model takes all keys at every
node. A factored model (``FactoredIMDP``, :mod:`robust_imdp.solvers.factored`) or a factored nominal model
takes the nominal solve's mode where the lower values are 0 for every mode (the nominal model's main effect)
and keeps the optimistic key elsewhere; under the safety reading a factored robust model keeps its own
choice (its solver takes no keys).
"""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np

from robust_imdp.errors import ConvergenceWarning, DimensionError, InvalidInputError
from robust_imdp.models.factored import FactoredIMDP
from robust_imdp.models.imdp import IMDP
from robust_imdp.solvers import product as _product

__all__ = ["check_nominal", "tie_break", "takes_nominal", "TIE_KEYS", "NOMINAL_PRECISION", "NOMINAL_MAX_ITERATIONS"]

#: The keys after the robust lower value, by whether a nominal model is given.
TIE_KEYS = {False: ("optimistic",), True: ("nominal", "optimistic")}
#: The nominal solve's precision and iteration cap (unbounded). Its values only rank modes: the lower ends,
#: which rise towards the nominal value from below at every sweep, are what the ranking reads, and a nominal
#: model is nearly deterministic, so its upper iterates can stall for long (a mode that nearly stays, e.g.
#: "stay" with a self-loop of 1 - 1e-9, is no end component to deflate). The cap bounds the cost; the
#: strategy extracted from the lower ends still makes progress (solvers.engine, "Strategy extraction").
NOMINAL_PRECISION = 1e-6
NOMINAL_MAX_ITERATIONS = 1000


def check_nominal(nominal, imdp):
    """``nominal`` checked against the robust model ``imdp``: the same states and modes (None passes)."""
    if nominal is None:
        return None
    if not isinstance(nominal, (IMDP, FactoredIMDP)):
        raise InvalidInputError(f"nominal must be an IMDP or a FactoredIMDP (abstraction.nominal); got "
                                f"{type(nominal).__name__}")
    if nominal.n_states != imdp.n_states:
        raise DimensionError(f"nominal must have the {imdp.n_states} states of imdp (cells, then the outside "
                             f"state); got {nominal.n_states}")
    if _n_modes(nominal) != _n_modes(imdp):
        raise DimensionError(f"nominal must have the {_n_modes(imdp)} modes of imdp; got {_n_modes(nominal)}")
    if isinstance(nominal, IMDP) and isinstance(imdp, IMDP) and not np.array_equal(nominal.state_ptr, imdp.state_ptr):
        bad = int(np.flatnonzero(np.diff(nominal.state_ptr) != np.diff(imdp.state_ptr))[0])
        raise DimensionError(f"nominal must have the choices of imdp in every state; state {bad} has "
                             f"{int(np.diff(nominal.state_ptr)[bad])} instead of {int(np.diff(imdp.state_ptr)[bad])}")
    return nominal


def _n_modes(model) -> int:
    return int(model.n_modes) if isinstance(model, FactoredIMDP) else int(np.diff(model.state_ptr).max())


def _solve(model, letters, dfa, *, adversary, tie_break, kw):
    """A maximising product solve of ``model`` (joint or factored), as ``synthesis.core`` calls them."""
    if isinstance(model, FactoredIMDP):
        from robust_imdp.solvers.factored import solve_factored_product

        kw = {k: v for k, v in kw.items() if k != "method"}
        return solve_factored_product(model, letters, dfa, adversary=adversary, tie_break=tie_break,
                                      control="maximize", **kw)
    if kw.get("horizon") is not None:
        # k steps: only the upper rows, which the robust solve's nominal key reads (solvers.product.TieKey): the
        # nominal strategy is not used with a horizon (tie_break), its bracket is a diagnostic only
        kw = dict(kw, keep_steps=True, need=())
    return _product.solve_product(model, letters, dfa, adversary=adversary, tie_break=tie_break, **kw)


def takes_nominal(imdp, *, horizon, semantics: str) -> bool:
    """Whether :func:`tie_break` (and so ``synthesize``) uses a nominal model of ``imdp`` at all.

    Not for a factored robust model with one mode (every strategy is that mode: ``synthesize`` solves it
    twice, without keys), with a horizon, or under the safety reading (its solver takes no keys, module
    docstring); a joint model takes the keys at every node. The pipeline builds no nominal model where this is
    False (it would only be thrown away: on car parking, factored, it was 46 of 49 s).

    Parameters
    ----------
    imdp : IMDP or FactoredIMDP
    horizon : int or None
    semantics : {"reach", "safety"}
        The resolved reading (``spec.api.resolve_semantics``).
    """
    if isinstance(imdp, FactoredIMDP):
        return imdp.n_modes > 1 and horizon is None and semantics != "safety"
    return True


def tie_break(imdp, nominal, letters, dfa, optimistic, kw):
    """The ``tie_break`` of the robust solve of ``imdp`` and the nominal solve behind it (module docstring).

    Parameters
    ----------
    imdp : IMDP or FactoredIMDP
        The robust model.
    nominal : IMDP or FactoredIMDP or None
        Its nominal model (:func:`check_nominal`).
    letters, dfa
        As in the product solves (letters of every base state).
    optimistic : ProductResult
        The optimistic (max, max) solve of ``imdp``.
    kw : dict
        The solves' keyword arguments (``avoid``, ``horizon``, ``precision``, ``method``, ``semantics``).

    Returns
    -------
    tie_break : ProductResult, Ties, an object with ``upper`` and ``strategy``, or None
        What the robust solve of ``imdp`` takes.
    nominal_result : ProductResult or None
        The nominal model's own (pessimistic) solve, None without a nominal model.
    """
    safety = kw["semantics"] == "safety"
    # without a nominal model, or where the robust solve would take none (takes_nominal: its solve would only be
    # thrown away, 47 of 50 s on BAS-4D, 10 steps): the optimistic key alone (none under the safety reading)
    if nominal is None or not takes_nominal(imdp, horizon=kw.get("horizon"), semantics=kw["semantics"]):
        return (None if safety else optimistic), None
    joint = isinstance(imdp, IMDP)
    unbounded = kw.get("horizon") is None
    opt_key = _product.TieKey(imdp, optimistic, "optimistic") if joint else None
    # the nominal model's best probability; its own ties go to the optimistic value of the robust model
    if isinstance(nominal, IMDP) and joint:
        nominal_ties = _product.Ties((opt_key,))
    else:
        nominal_ties = None if safety else optimistic
    nkw = dict(kw, precision=max(float(kw.get("precision", 1e-8)), NOMINAL_PRECISION),
               max_iterations=NOMINAL_MAX_ITERATIONS)
    with warnings.catch_warnings():  # the cap's ConvergenceWarning: the nominal values only rank modes
        warnings.simplefilter("ignore", ConvergenceWarning)
        nom = _solve(nominal, letters, dfa, adversary="pessimistic", tie_break=nominal_ties, kw=nkw)
    if isinstance(nominal, IMDP) and joint:
        keys = (_product.TieKey(nominal, nom, "pessimistic"), opt_key)
        return _product.Ties(keys, strategy=np.asarray(nom.strategy) if unbounded else None), nom
    # a factored model on either side: the nominal mode where every lower value is 0, the optimistic key elsewhere
    if joint:
        return _product.Ties((opt_key,), strategy=np.asarray(nom.strategy) if unbounded else None), nom
    return SimpleNamespace(upper=optimistic.upper, strategy=np.asarray(nom.strategy)), nom
