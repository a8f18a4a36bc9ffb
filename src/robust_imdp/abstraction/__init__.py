"""Cell bounds to an interval MDP (the paper's Thm 1, corrected, with an outside-X state; or the exact per-axis integrals)."""

from robust_imdp._lazy import exports

__getattr__, __dir__ = exports(__name__, ["cell_bounds", "probabilities", "periodic", "targets", "marginals", "factored",
                                          "exact_rows", "rows", "nominal"])
