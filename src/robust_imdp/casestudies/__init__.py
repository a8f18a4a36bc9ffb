"""The paper's case studies (true systems, regions, problem files) and the assumption certificate."""

from robust_imdp._lazy import exports

__getattr__, __dir__ = exports(__name__, ["vehicle", "systems", "certificate"])
