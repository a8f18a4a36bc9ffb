"""Assumption margins: how far each guarantee of a run survives a larger RKHS norm bound (docs/margins.md).

Every class of a run holds under the assumption ``||h_u^(i)|| <= B_{u,i}``. For a factor ``beta >= 1`` the
assumption with every B replaced by ``beta B`` is weaker (it admits more functions), and the bound stage
has already certified the image boxes under it with the same certificate weights (eq. W holds for any
weights; ``bounds/rkhs_model.scaled_ranges``). Given the interval MDP built from those boxes, this module
evaluates **the run's own controller** on it (the strategy is fixed; only the adversary's ambiguity set
grows) and reads off, per cell, the largest factor of :data:`MARGIN_SCALES` at which the cell keeps its
class:

* a Q_yes cell keeps ``p_low(beta) >= threshold``: the deployed controller still guarantees the threshold
  if the true norms were up to ``beta B``;
* a Q_no cell keeps ``p_up(beta) < threshold`` (``p_up`` as the run defines it: the controller's upper
  bound capped by ``p_up_star``, both at ``beta B``);
* a Q_? cell gets NaN (nothing to keep).

Monotonicity (why the scan stops early). For ``beta' > beta`` every image box at ``beta' B`` contains the
one at ``beta B`` (``scaled_ranges`` only adds non-negative terms), so every transition interval of the
abstraction is at least as wide (the noise mass in a target is minimised and maximised over a larger box)
and the IMDP at ``beta'`` admits every transition law of the one at ``beta``. For the fixed strategy the
pessimistic value is a minimum over these laws, hence ``p_low(beta') <= p_low(beta)``, and the optimistic
values (``p_up``, ``p_up_star``) a maximum, hence ``p_up(beta') >= p_up(beta)``. A cell that loses its class
at ``beta`` cannot regain it at ``beta'``; the scan over the factors in increasing order stops when no cell
keeps its class. A margin is only claimed where the class held at every factor up to it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from robust_imdp.errors import DimensionError, InvalidInputError

__all__ = ["MARGIN_SCALES", "Margins", "assumption_margins", "strategy_bounds", "margins_line"]

#: The factors of B the margins are read on: 1 (the run) and five larger ones.
MARGIN_SCALES = (1.0, 1.25, 1.5, 2.0, 3.0, 4.0)


@dataclass(frozen=True, eq=False)
class Margins:
    """Per cell, the largest factor of B at which it keeps its class.

    Attributes
    ----------
    scales : tuple of float
        The factors, increasing, ``scales[0] == 1`` (the run).
    b_margin : (n_cells,) float array
        Largest ``scales[j]`` such that the cell keeps its class at every factor up to it; NaN for Q_? cells.
    kept_yes, kept_no : tuple of int
        Per factor, the Q_yes (Q_no) cells that keep their class there (exact also for factors not solved:
        after the scan stopped no cell keeps its class).
    solved : tuple of float
        The factors above 1 whose abstraction was built and solved.
    seconds : float
    """

    scales: tuple
    b_margin: np.ndarray
    kept_yes: tuple
    kept_no: tuple
    solved: tuple
    seconds: float

    def to_dict(self) -> dict:
        """The JSON-able summary (``result.json``'s ``diagnostics.margins``; the array is ``b_margin``)."""
        return {"scales": list(self.scales), "kept_yes": list(self.kept_yes), "kept_no": list(self.kept_no),
                "solved": list(self.solved), "seconds": float(self.seconds)}


def assumption_margins(classes, evaluate: Callable, threshold: float, scales=MARGIN_SCALES) -> Margins:
    """The margins of every cell from the bounds of the run's controller at each factor (see the module docstring).

    Parameters
    ----------
    classes : (n_cells,) array of "yes" / "no" / "maybe"
        The run's classes (factor 1).
    evaluate : callable(scale) -> (p_low (n_cells,), p_up (n_cells,))
        The run's controller's bounds on the abstraction at ``scale * B`` (:func:`strategy_bounds`).
    threshold : float
    scales : increasing sequence of float, first 1.0

    Returns
    -------
    Margins
    """
    t0 = time.perf_counter()
    scales = tuple(float(s) for s in scales)
    if not scales or scales[0] != 1.0 or any(b <= a for a, b in zip(scales, scales[1:])):
        raise InvalidInputError(f"scales must increase from 1.0; got {scales!r}")
    classes = np.asarray(classes).astype(str)
    if classes.ndim != 1:
        raise DimensionError(f"classes must be a (n_cells,) array; got shape {classes.shape}")
    yes, no = classes == "yes", classes == "no"
    margin = np.where(yes | no, 1.0, np.nan)
    kept_yes, kept_no, solved = [int(yes.sum())], [int(no.sum())], []
    for s in scales[1:]:
        if not (yes.any() or no.any()):  # monotone: nothing regains its class at a larger factor
            kept_yes.append(0)
            kept_no.append(0)
            continue
        p_low, p_up = (np.asarray(v, float) for v in evaluate(s))
        if p_low.shape != classes.shape or p_up.shape != classes.shape:
            raise DimensionError(f"evaluate({s}) must give p_low and p_up of shape {classes.shape}; got "
                                 f"{p_low.shape} and {p_up.shape}")
        solved.append(s)
        yes &= p_low >= threshold  # Q_yes: p_low >= threshold (synthesis.core), at every factor so far
        no &= p_up < threshold  # Q_no: p_up < threshold
        margin[yes | no] = s
        kept_yes.append(int(yes.sum()))
        kept_no.append(int(no.sum()))
    return Margins(scales, margin, tuple(kept_yes), tuple(kept_no), tuple(solved), time.perf_counter() - t0)


def strategy_bounds(imdp, labels, atoms, dfa, synthesis, *, outside_state=None):
    """``(p_low, p_up)`` of the controller of ``synthesis`` on another abstraction ``imdp`` of the same cells.

    The strategy is fixed (``synthesis.strategy``; the outside state, absorbing, takes mode 0) and evaluated
    by the solvers ``synthesis.core`` uses, with its precision, horizon and reading: ``p_low`` is the lower
    end of the pessimistic bracket, ``p_up`` the upper end of the optimistic one capped by the upper end of
    the optimistic synthesis (``p_up_star``), exactly as ``synthesis.core`` reads them. On the run's own
    abstraction this gives the run's ``p_low`` and ``p_up``.

    Parameters
    ----------
    imdp : IMDP or FactoredIMDP
        States ``0 .. n_cells-1`` the cells (then the outside state, if any); choices the modes. A factored
        model is evaluated by the factored solver, as ``synthesis.core`` solves it.
    labels : (n_cells,) int array
        The cells' letters over ``atoms`` (``partition.labels``).
    atoms : sequence of str
    dfa : DFA
    synthesis : synthesis.core.SynthesisResult
    outside_state : int, optional

    Returns
    -------
    p_low, p_up : (n_cells,) float arrays
    """
    from robust_imdp.synthesis.controller import remap_letters
    from robust_imdp.synthesis.core import _solvers

    solve_product, evaluate_product_strategy = _solvers(imdp)

    labels = np.asarray(labels, dtype=np.int64)
    n_cells = int(labels.shape[0])
    strat = np.asarray(synthesis.strategy, dtype=np.int64)
    if strat.shape[-2] != n_cells:
        raise DimensionError(f"synthesis.strategy must hold {n_cells} cells like labels; got shape {strat.shape}")
    letters = np.concatenate([remap_letters(labels, tuple(atoms), dfa.atoms),
                              np.zeros(imdp.n_states - n_cells, dtype=np.int64)])
    avoid = None if outside_state is None else np.array([int(outside_state)], dtype=np.int64)
    # the product strategy (S, n_states) or (k, S, n_states); the outside state is absorbing: any mode
    pi = np.zeros(strat.shape[:-2] + (strat.shape[-1], imdp.n_states), dtype=np.int64)
    pi[..., :n_cells] = np.swapaxes(strat, -1, -2)
    kw = dict(avoid=avoid, horizon=synthesis.horizon, precision=float(synthesis.precision))
    reading = getattr(synthesis, "semantics", "reach")
    if reading != "reach":  # only then: the solvers' default reading is reach
        kw["semantics"] = reading
    low = evaluate_product_strategy(imdp, letters, dfa, pi, adversary="pessimistic", **kw)
    up = evaluate_product_strategy(imdp, letters, dfa, pi, adversary="optimistic", **kw)
    star = solve_product(imdp, letters, dfa, adversary="optimistic", **kw)
    p_low = np.array(low.initial_lower, dtype=np.float64)[:n_cells]
    p_up = np.minimum(np.array(up.initial_upper, dtype=np.float64)[:n_cells],
                      np.array(star.initial_upper, dtype=np.float64)[:n_cells])
    return p_low, p_up


def margins_line(doc: dict) -> str:
    """One line of the summary: how many Q_yes (and Q_no) cells keep their class at each factor of B."""
    if not doc:
        return ""
    if "skipped" in doc:
        return f"assumption margins: not computed ({doc['skipped']})"
    scales, yes, no = doc["scales"], doc["kept_yes"], doc["kept_no"]

    def fmt(s):
        return f"{s:g} B"

    head = ""
    if yes[0]:
        j = scales.index(2.0) if 2.0 in scales else len(scales) - 1
        rest = ", ".join(f"{fmt(s)}: {k}" for s, k in zip(scales[1:], yes[1:]) if s != scales[j])
        head = f"{yes[j]} of {yes[0]} Q_yes cells stay Q_yes at {fmt(scales[j])} ({rest})"
    tail = f"{no[-1]} of {no[0]} Q_no cells stay Q_no at {fmt(scales[-1])}" if no[0] else ""
    body = "; ".join(t for t in (head, tail) if t) or "no Q_yes or Q_no cells"
    return f"assumption margins (the run's controller with every B scaled): {body}"
