"""The result of a run: :class:`Result` (partition, abstraction, synthesis, classes, diagnostics, its shortcuts)
and the one-line summary of the bound diagnostics.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from robust_imdp.pipeline.problem import CLASS_NAMES, Problem


class ClassCounts(dict):
    """Cells per class, ``{"yes": .., "no": .., "maybe": ..}``: what ``result.counts`` gives.

    ``counts`` is a property (read ``result.counts["yes"]``, like ``result.n_cells``). Earlier
    versions had a method ``counts()``; calling the dict returns the dict itself, so that code keeps
    working (``result.counts()["yes"]``).
    """

    def __call__(self) -> "ClassCounts":
        return self

    @classmethod
    def of(cls, classes) -> "ClassCounts":
        """The counts of a ``(n_cells,)`` array of ``"yes"`` / ``"no"`` / ``"maybe"``."""
        classes = np.asarray(classes)
        return cls({c: int(np.sum(classes == c)) for c in CLASS_NAMES})


def summary_text(*, formula: str, threshold: float, horizon, classes, p_low, error, p_up_star, diagnostics: dict,
                 advice: dict, timings: dict, source: str, semantics: str | None = None) -> str:
    """The lines of a result's summary (``Result.summary``, ``io.result_file.ResultFile.summary``).

    Class counts, Q_no split by whether any controller could meet the threshold (``p_up_star <
    threshold``), mean p_low and error, where the abstraction came from (``source``), the bound
    diagnostics, the advice and the stage times. ``semantics``: the reading of the formula, named on its line.
    """
    c = ClassCounts.of(classes)
    n = int(np.size(classes))
    no = np.asarray(classes) == "no"
    cannot = int(np.count_nonzero(no & (np.asarray(p_up_star) < threshold)))
    lines = [
        f"formula {formula!r}, threshold {threshold:g}" + (f", horizon {horizon}" if horizon is not None else "")
        + ("" if semantics is None else f" ({semantics} reading)"),
        f"cells: {n}  Q_yes {c['yes']}  Q_no {c['no']}  Q_? {c['maybe']}",
        f"Q_no: {cannot} where no controller can meet the threshold (p_up_star < {threshold:g}), "
        f"{int(np.count_nonzero(no)) - cannot} under this controller only",
        f"mean p_low {np.mean(p_low):.4f}  mean error {np.mean(error):.4f}  ({source})",
    ]
    why = diagnostics_line(diagnostics)
    if why:
        lines.append(why)
    if (diagnostics or {}).get("margins"):
        from robust_imdp.synthesis.margins import margins_line

        lines.append(margins_line(diagnostics["margins"]))
    if advice:
        from robust_imdp.synthesis.advice import advice_line

        lines.append(advice_line(advice))
    lines.append("stage times: " + ", ".join(f"{k} {v:.2f} s" for k, v in timings.items()))
    return "\n".join(lines)


@dataclass(frozen=True, eq=False)
class Result:
    """Output of :func:`synthesize_from_data`.

    Attributes
    ----------
    problem : Problem
    partition : geometry.Partition
    abstraction : abstraction.Abstraction
    dfa : dfa.DFA
    synthesis : synthesis.SynthesisResult
        ``strategy (n_cells, S)``, ``p_low``, ``p_up``, ``p_up_star``, ``error``, ``classes``.
    class_names : (n_cells,) str array
        ``"yes"`` / ``"no"`` / ``"maybe"`` per cell.
    timings : dict str -> float
        Seconds per stage (``specify``, ``partition``, ``learn``, ``bound``, ``abstract``,
        ``synthesize``, ``total``; ``load_abstraction`` when the cache was used).
    parameters : dict
        The settings that produced the result (JSON-able).
    from_cache : bool
        Whether the abstraction was reused.
    advice : dict
        Which lever (finer grid, more data, sub-boxes, larger local pools) would move most of X into Q_yes,
        estimated after the solve (``advice.Advice.to_dict()``; empty with ``advice=False`` and after
        :func:`resynthesize`).
    diagnostics : dict
        Why cells are undecided (JSON-able): the stated confidence, the error radius ``eps``
        per mode and output (median, max, against the cell half-width), the mean number of
        successors per IMDP row and the assumption check (data-implied minimum RKHS norms).
    b_margin : (n_cells,) float array or None
        Assumption margins (docs/margins.md): per cell the largest factor beta of (1, 1.25, 1.5, 2, 3, 4)
        such that the run's controller keeps the cell's class (Q_yes, Q_no) with every B replaced by
        beta B; NaN for Q_? cells. None when not computed (``margins=False``, known dynamics, the GP route,
        :func:`resynthesize`).
    margins : dict
        The margins' counts per factor of B (``synthesis.margins.Margins.to_dict()``: ``scales``, ``kept_yes``,
        ``kept_no``, ``solved``, ``seconds``, ``statement``) or ``{"skipped": reason}``; ``result.json``'s
        ``diagnostics.margins``. Empty when not asked for. Kept apart from ``diagnostics`` (which holds what the
        data and the abstraction say, reused with a cached abstraction): the margins depend on the formula.
    """

    problem: Problem
    partition: Any
    abstraction: Any
    dfa: Any
    synthesis: Any
    class_names: np.ndarray
    timings: dict
    parameters: dict
    from_cache: bool = False
    diagnostics: dict = field(default_factory=dict)
    advice: dict = field(default_factory=dict)
    b_margin: np.ndarray | None = None
    margins: dict = field(default_factory=dict)

    # Convenience views used by io.result_to_dict and plotting.
    def suggest_samples(self, n: int) -> list:
        """Where to collect data next: ``n`` (state, mode) sample requests, best first
        (:func:`robust_imdp.synthesis.suggest.suggest_samples`)."""
        from robust_imdp.synthesis.suggest import suggest_samples

        return suggest_samples(self, n)

    @property
    def mode_names(self) -> tuple:
        return tuple(self.problem.mode_names)

    @property
    def space_lower(self) -> np.ndarray:
        return np.asarray(self.problem.space_lower, float)

    @property
    def space_upper(self) -> np.ndarray:
        return np.asarray(self.problem.space_upper, float)

    @property
    def formula(self) -> str:
        return self.problem.formula

    @property
    def semantics(self) -> str:
        """The reading the bounds are of: "reach" (some prefix accepted) or "safety" (no bad prefix, staying in X)."""
        return getattr(self.synthesis, "semantics", "reach")

    @property
    def threshold(self) -> float:
        return float(self.problem.threshold)

    @property
    def horizon(self):
        return self.problem.horizon

    # Shortcuts to the synthesis and partition arrays (per cell, in the cells' index order).
    @property
    def p_low(self) -> np.ndarray:
        """(n_cells,) guaranteed lower bound of P(formula) under the strategy (``synthesis.p_low``)."""
        return self.synthesis.p_low

    @property
    def p_up(self) -> np.ndarray:
        """(n_cells,) upper bound of P(formula) under the strategy (``synthesis.p_up``)."""
        return self.synthesis.p_up

    @property
    def p_up_star(self) -> np.ndarray:
        """(n_cells,) upper bound of P(formula) over all strategies (``synthesis.p_up_star``)."""
        return self.synthesis.p_up_star

    @property
    def error(self) -> np.ndarray:
        """(n_cells,) ``p_up_star - p_low`` rounded up (``synthesis.error``)."""
        return self.synthesis.error

    @property
    def strategy(self) -> np.ndarray:
        """(n_cells, S) mode indices into ``mode_names`` ((k, n_cells, S) for a k-step horizon)."""
        return self.synthesis.strategy

    @property
    def classes(self) -> np.ndarray:
        """(n_cells,) ``"yes"`` / ``"no"`` / ``"maybe"`` (the same array as ``class_names``)."""
        return self.class_names

    @property
    def n_cells(self) -> int:
        return int(self.partition.n_cells)

    @property
    def cells_lower(self) -> np.ndarray:
        """(n_cells, n) lower corners of the cells (``partition.cells_lower``)."""
        return self.partition.cells_lower

    @property
    def cells_upper(self) -> np.ndarray:
        """(n_cells, n) upper corners of the cells (``partition.cells_upper``)."""
        return self.partition.cells_upper

    @property
    def dim_names(self):
        """The dimension names (``[space].names``), or None."""
        return getattr(self.problem, "dim_names", None)

    def __repr__(self) -> str:  # a few lines: the dataclass default prints every array (tens of KB)
        c = self.counts
        return (f"Result({len(self.class_names)} cells: Q_yes {c['yes']}, Q_no {c['no']}, Q_? {c['maybe']}; "
                f"formula {self.formula!r}, threshold {self.threshold:g}\n"
                f"  mean p_low {float(np.mean(self.synthesis.p_low)):.4f}, mean error "
                f"{float(np.mean(self.synthesis.error)):.4f}; modes {list(self.mode_names)}; abstraction "
                f"{'reused from cache' if self.from_cache else 'built'}\n"
                f"  arrays: p_low, p_up, p_up_star, error, classes, strategy; summary() for the details)")

    @property
    def counts(self) -> ClassCounts:
        """Number of cells per class: ``{"yes": .., "no": .., "maybe": ..}`` (a :class:`ClassCounts`;
        ``counts()``, the method form of earlier versions, still works)."""
        return ClassCounts.of(self.class_names)

    def controller(self):
        """The refined switching controller (``controller.Controller``; :meth:`~Controller.act_input` gives the
        input vector of a problem with an input grid)."""
        return self.synthesis.controller(self.partition, self.mode_names, inputs=getattr(self.problem, "inputs", None))

    @property
    def no_strategy_can(self) -> np.ndarray:
        """(n_cells,) bool: ``p_up_star < threshold``: no controller at all meets the threshold."""
        return np.asarray(self.synthesis.p_up_star) < self.threshold

    @property
    def _summary_diagnostics(self) -> dict:
        """``diagnostics`` with the margins, as ``result.json`` writes them (the summary reads both from there)."""
        return {**self.diagnostics, **({"margins": self.margins} if self.margins else {})}

    def summary(self) -> str:
        """Class counts (Q_no split by whether any controller could do better), mean error and
        stage times as text."""
        return summary_text(formula=self.formula, threshold=self.threshold, horizon=self.horizon,
                            classes=self.class_names, p_low=self.synthesis.p_low, error=self.synthesis.error,
                            p_up_star=self.synthesis.p_up_star, diagnostics=self._summary_diagnostics, advice=self.advice,
                            timings=self.timings, semantics=self.semantics,
                            source=f"abstraction {'reused from cache' if self.from_cache else 'built'}")


def diagnostics_line(diag: dict) -> str:
    """One line saying why cells may be undecided (error radius, successors, assumption margin); for known
    dynamics, that they are known."""
    if diag and diag.get("dynamics") == "known":
        text = "known dynamics: no data, no learning, no assumption check; the bounds hold with probability 1"
        if "successors_per_row" in diag:
            text += f"; {diag['successors_per_row']:.1f} successors per row"
        return text
    if not diag or "eps" not in diag:
        return ""
    med = max(r["median"] for r in diag["eps"])
    mx = max(r["max"] for r in diag["eps"])
    half = min(diag["cell_half_width"])
    text = (f"error radius eps: median {med:.3g}, max {mx:.3g} (cell half-width {half:.3g})")
    if "successors_per_row" in diag:
        text += f"; {diag['successors_per_row']:.1f} successors per row"
    mins = [r["minimum"] for r in diag["assumption"]["min_norm"]]
    if mins:
        text += f"; data need ||g|| >= {max(mins):.3g} of B = {diag['assumption']['rkhs_bound']:g}"
    conf = diag.get("confidence")
    if conf is not None:
        text += "; holds with probability 1" if conf >= 1.0 else f"; holds with confidence {conf:g} over the data"
    return text
