"""Strategies, p_low / p_up / p_up_star and classes, deployable controllers, refinement, advice."""

from robust_imdp._lazy import exports

__getattr__, __dir__ = exports(__name__, ["core", "controller", "refine", "advice", "suggest", "margins", "ties"])
