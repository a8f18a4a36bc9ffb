"""The whole run: Problem, Result, synthesize_from_data, caches, schedulers."""

from robust_imdp._lazy import exports

__getattr__, __dir__ = exports(__name__, ["run", "problem", "result", "runtime", "cache", "preflight", "bound_stage",
                                          "bound_rkhs", "bound_gp", "parallel", "margins", "advice_stage",
                                          "nominal_stage"])
