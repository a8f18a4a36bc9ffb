"""The input of the abstraction: certified image boxes per (mode, cell) and, on the GP route, the error law.

:class:`CellBounds` holds a box containing ``{f_u(x) + mu_u(x) : x in cell}`` for every mode and
cell, and optionally ``std_upper`` (an upper bound of the GP posterior std over each cell). The
abstraction itself needs only the boxes when the dynamics are known or the learning error was
already folded into them; ``std_upper`` and the duck-typed ``error_models`` are the GP route's
(Thm 1 with a GP error probability, ``guarantee="paper"``).

:func:`confidence_cell_bounds` is the GP route's converter for ``guarantee="confidence"``: it
folds the GP error into the boxes at one data-confidence level and returns plain boxes
(``std_upper=None``). It lives here, next to the type it produces, until the GP route has a
module of its own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robust_imdp._fp import down, up
from robust_imdp.errors import DimensionError, InvalidInputError

__all__ = ["CellBounds", "CellErrors", "confidence_cell_bounds"]


@dataclass(frozen=True, eq=False)
class CellBounds:
    """Certified per-cell bounds, the input of :func:`abstract`.

    Parameters
    ----------
    image_lower, image_upper : (n_modes, n_cells, d) float arrays
        A box containing ``{f_u(x) + mu_u(x) : x in cell}`` for each mode and cell.
    std_upper : (n_modes, n_cells, d) float array or None
        Upper bound of the posterior std over each cell; ``None`` means known dynamics
        (``g = 0``: eps = 0 and error probability 1).
    """

    image_lower: np.ndarray
    image_upper: np.ndarray
    std_upper: np.ndarray | None = None

    def __post_init__(self):
        lo = np.array(self.image_lower, dtype=float)
        hi = np.array(self.image_upper, dtype=float)
        if lo.ndim != 3:
            raise DimensionError(f"image_lower must have shape (n_modes, n_cells, d); got {lo.shape}")
        if hi.shape != lo.shape:
            raise DimensionError(f"image_upper must have shape {lo.shape} like image_lower; got {hi.shape}")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise InvalidInputError("image_lower and image_upper must be finite")
        bad = np.argwhere(lo > hi)
        if bad.size:
            u, q, i = (int(v) for v in bad[0])
            raise InvalidInputError(
                f"image_lower must be <= image_upper; got [{lo[u, q, i]}, {hi[u, q, i]}] at mode {u}, cell {q}, dim {i}"
            )
        std = None
        if self.std_upper is not None:
            std = np.array(self.std_upper, dtype=float)
            if std.shape != lo.shape:
                raise DimensionError(f"std_upper must have shape {lo.shape} like image_lower; got {std.shape}")
            if not np.all(np.isfinite(std)) or np.any(std < 0):
                raise InvalidInputError("std_upper must be finite and >= 0")
            std.setflags(write=False)
        lo.setflags(write=False)
        hi.setflags(write=False)
        object.__setattr__(self, "image_lower", lo)
        object.__setattr__(self, "image_upper", hi)
        object.__setattr__(self, "std_upper", std)

    @property
    def n_modes(self) -> int:
        return self.image_lower.shape[0]

    @property
    def n_cells(self) -> int:
        return self.image_lower.shape[1]

    @property
    def dim(self) -> int:
        return self.image_lower.shape[2]


class CellErrors:
    """What Thm 1 needs of the learning route, per mode u, dimension i and cell: the error law.

    The abstraction asks two things of the error ``g_i - mu_i`` over a cell (and nothing about GPs):

    * ``mode(u).eps_for_prob(i, level)``: (n_cells,) radii eps with
      ``P[sup_cell |g_i - mu_i| <= eps] >= level`` (may be inf or negative: unusable);
    * ``mode(u).prob_within(i, eps, rows)``: a lower bound of ``P[sup_cell |g_i - mu_i| <= eps]`` for
      the cells ``rows`` (broadcast with ``eps``), non-decreasing in eps, checked to lie in [0, 1].

    The GP route builds it from ``std_upper`` (an upper bound of the posterior std per cell) and its
    error models (``eps_for_prob(p, std_upper)``, ``prob_within(eps, std_upper)``, e.g.
    ``bounds.gp.RKHSErrorBound``): :meth:`from_gp`. Known dynamics (or the error folded into the
    boxes, :func:`confidence_cell_bounds`) need none (``None``).
    """

    def __init__(self, std_upper: np.ndarray, models):
        self.std_upper, self.models = std_upper, models

    @classmethod
    def from_gp(cls, cell_bounds: "CellBounds", error_models) -> "CellErrors | None":
        """The error law of ``cell_bounds.std_upper`` under ``error_models`` (None for known dynamics)."""
        if error_models is None:
            return None
        return cls(cell_bounds.std_upper, _check_models(error_models, cell_bounds.n_modes, cell_bounds.dim))

    def mode(self, u: int) -> "_ModeErrors":
        return _ModeErrors(self.std_upper[u], self.models[u])


class _ModeErrors:
    """:class:`CellErrors` of one mode: ``std`` (n_cells, d) and the d error models."""

    def __init__(self, std, models):
        self.std, self.models = std, models

    def eps_for_prob(self, i, level):
        return self.models[i].eps_for_prob(level, self.std[:, i])

    def prob_within(self, i, eps, rows):
        s = self.std[rows, i]
        pr = np.asarray(self.models[i].prob_within(eps, s), dtype=float)
        if pr.shape != np.broadcast(eps, s).shape or not np.all((pr >= 0) & (pr <= 1)):
            raise InvalidInputError(
                f"error_models[.][{i}].prob_within must return probabilities in [0, 1] of shape "
                f"{np.broadcast(eps, s).shape}; got shape {pr.shape}"
            )
        return pr


def _check_models(error_models, n_modes, d):
    if error_models is None:
        return None
    try:
        models = [list(m) for m in error_models]
    except TypeError:
        raise InvalidInputError(
            f"error_models must be a sequence of {n_modes} sequences of {d} error models; got {type(error_models).__name__}"
        ) from None
    if len(models) != n_modes or any(len(m) != d for m in models):
        raise DimensionError(
            f"error_models must have shape ({n_modes} modes, {d} dims); got {[len(m) for m in models]}"
        )
    for u, row in enumerate(models):
        for i, m in enumerate(row):
            if not (callable(getattr(m, "prob_within", None)) and callable(getattr(m, "eps_for_prob", None))):
                raise InvalidInputError(
                    f"error_models[{u}][{i}] must have prob_within(eps, std_upper) and eps_for_prob(p, std_upper); "
                    f"got {type(m).__name__}"
                )
    return models


def confidence_cell_bounds(cell_bounds: CellBounds, error_models, confidence: float = 0.99) -> CellBounds:
    """Fold the GP error into the image boxes at one data-confidence level (the sound default).

    Why. Thm 1 mixes two different probabilities: ``P[sup_q |g - mu| <= eps]`` is a probability
    over the *training data* (g is a fixed unknown function), while ``T(q'|x)`` is a probability
    over the process noise. For a fixed system and a fixed data set the printed product
    ``P_g * P_v * 1[...]`` is therefore not a bound of ``T(q'|x)``: when the realised error is
    large, the true ``T`` can be below the printed lower bound (``tests/test_soundness_audit.py``
    shows 0.575 printed against 0.436 true). The statement that does hold is a confidence
    statement: by Lemma 1 (Chowdhury & Gopalan 2017, Thm 2) applied with ``delta_ui`` to the GP of
    mode u and output i, and a union bound over all ``n_modes * d`` GPs, with probability at least
    ``confidence = 1 - sum delta_ui`` over the data,

        for every mode u, output i and x in X:  |g_ui(x) - mu_ui(x)| <= beta_ui(delta_ui) sigma_ui(x).

    On that event the true successor mean ``f_u(x) + g_u(x)`` of every x in cell q lies in the
    image box expanded by ``eps_uqi = beta_ui(delta_ui) * std_upper[u, q, i]``, so the
    known-dynamics abstraction of the expanded boxes (eps = 0, error probability 1) contains
    the true transition probabilities of *every* row simultaneously, and every p_low/p_up
    computed from it holds with that confidence. No independence between GPs is needed.

    Parameters
    ----------
    cell_bounds : CellBounds
        Image boxes of ``f_u + mu_u`` and std bounds (``std_upper`` must not be None).
    error_models : sequence (n_modes) of sequences (d) of error models
        Each with ``eps_for_prob(p, std_upper)`` returning ``beta(1 - p) * std_upper`` rounded up.
    confidence : float in (0, 1)
        Probability over the data with which the resulting abstraction is sound.

    Returns
    -------
    CellBounds
        Expanded image boxes (rounded outward) with ``std_upper=None``.
    """
    confidence = float(confidence)
    if not 0.0 < confidence < 1.0:
        raise InvalidInputError(f"confidence must lie in (0, 1); got {confidence}")
    if cell_bounds.std_upper is None:
        raise InvalidInputError("cell_bounds.std_upper is None (known dynamics): there is no GP error to fold in")
    M, _, d = cell_bounds.image_lower.shape
    models = _check_models(error_models, M, d)
    # Union bound over the M*d GPs: each gets an equal share of 1 - confidence. 1 - confidence
    # is rounded down (smaller delta -> larger beta -> larger eps: the safe side).
    delta_each = down(down(1.0 - confidence) / (M * d))
    # p one ulp above fl(1 - delta_each): then 1 - p (exact by Sterbenz) <= delta_each, so the
    # per-GP failure probability used by eps_for_prob never exceeds its union-bound share.
    p_each = up(1.0 - delta_each)
    eps = np.empty_like(cell_bounds.std_upper)
    for u in range(M):
        for i in range(d):
            eps[u, :, i] = models[u][i].eps_for_prob(p_each, cell_bounds.std_upper[u, :, i])
    # Expansion by eps, rounded outward (one correctly rounded subtraction/addition each).
    lo = down(cell_bounds.image_lower - eps)
    hi = up(cell_bounds.image_upper + eps)
    return CellBounds(lo, hi, None)
