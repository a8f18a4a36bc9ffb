"""Certified ranges of f_u + g_u over cells: RKHS bounds (optimal, ridge, local weights), the GP route, per-component assumptions."""

from robust_imdp._lazy import exports

__getattr__, __dir__ = exports(__name__, ["rkhs", "rkhs_model", "rkhs_weights", "rkhs_check", "rkhs_local", "gp", "gp_model", "gp_error", "gp_cells", "assumptions", "methods", "fit", "calibrate"])
