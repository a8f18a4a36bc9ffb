"""Specifications: LTLf formulas and their minimal DFAs."""

from robust_imdp._lazy import exports

__getattr__, __dir__ = exports(__name__, ["ltlf", "dfa", "api"])
