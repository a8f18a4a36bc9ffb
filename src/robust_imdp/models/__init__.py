"""Data types of the problem: the interval MDP (joint and factored), the state space's geometry, the system's known parts (and input grids) and data, the noise."""

from robust_imdp._lazy import exports

__getattr__, __dir__ = exports(__name__, ["imdp", "factored", "geometry", "system", "noise", "known", "inputs", "intervals", "expressions"])
