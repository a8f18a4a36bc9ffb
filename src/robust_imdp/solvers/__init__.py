"""Interval value iteration (robust and optimistic), strategies, LP cross-checks, products with a DFA."""

from robust_imdp._lazy import exports

__getattr__, __dir__ = exports(__name__, ["common", "kernels", "graph", "sweep", "ovi", "engine", "lp", "api",
                                           "product", "factored_kernels", "factored_order", "factored"])
