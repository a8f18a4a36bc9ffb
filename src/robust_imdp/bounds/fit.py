"""The data-fitted function: the known part plus a kernel-ridge fit of the residuals, per mode.

A diagnostic, not a bound: it measures how far the certified image boxes reach beyond the range of a
function that explains the data (``excess_radius``), for the bound diagnostics (eps), the advice
(``synthesis.advice``) and the per-component fits (``bounds.assumptions.fit_components``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robust_imdp._kernels import se_gram
from robust_imdp.errors import DimensionError, InvalidInputError

__all__ = ["FittedModes", "fit_modes", "excess_radius", "evenly_spaced", "FIT_POINTS"]

#: Data points per mode used by the fit (an evenly spaced subset of the mode's samples beyond it).
FIT_POINTS = 500
#: Entries of the separable kernel contraction's product tensor held at once (32 MB).
_BLOCK = 1 << 22


@dataclass(frozen=True, eq=False)
class FittedModes:
    """Known part plus a kernel-ridge fit of the residuals, per mode (a diagnostic, not a bound).

    Attributes
    ----------
    points : tuple (n_modes) of (m_u, d) float arrays
        Fitted data points of each mode.
    alpha : tuple (n_modes) of (m_u, n) float arrays
        Ridge weights: ``g_hat_u(x)_i = sum_j alpha[u][j, i] k(x, points[u][j])``.
    A : (n_modes, n, d) float array, b : (n_modes, n) float array
        Known affine parts.
    inv_l2 : (d,) float array
        ``1 / lengthscale^2`` of the SE kernel ``k(x, z) = exp(-sum_a (x_a - z_a)^2 inv_l2_a / 2)``.
    known : tuple (n_modes) of None or callables ``(k, d) -> (k, n)``, optional
        Nonlinear known parts (their mode's ``A``, ``b`` are 0): added to the values.
    """

    points: tuple
    alpha: tuple
    A: np.ndarray
    b: np.ndarray
    inv_l2: np.ndarray
    known: tuple = ()

    @property
    def n_modes(self) -> int:
        return len(self.points)

    def __call__(self, x) -> np.ndarray:
        """``f_u(x) + g_hat_u(x)`` at points ``x (k, d)``: ``(n_modes, k, n)``."""
        x = np.asarray(x, float)
        out = np.empty((self.n_modes, x.shape[0], self.A.shape[1]))
        for s0 in range(0, x.shape[0], 4096):
            xs = x[s0:s0 + 4096]
            for u in range(self.n_modes):
                z = np.sum((xs[:, None, :] - self.points[u][None, :, :]) ** 2 * self.inv_l2, axis=2)
                out[u, s0:s0 + 4096] = np.exp(-0.5 * z) @ self.alpha[u] + xs @ self.A[u].T + self.b[u]
                if self.known and self.known[u] is not None:
                    out[u, s0:s0 + 4096] += self.known[u](xs)
        return out

    def lattice(self, axes) -> np.ndarray:
        """``f_u + g_hat_u`` on the tensor grid ``axes[0] x ... x axes[d-1]``: ``(n_modes, n, k_0, ..., k_{d-1})``.

        The SE kernel factors over the axes, ``k(z, x) = prod_a k_a(z_a, x_a)``, so the sum over
        the data is a chain of products of per-axis kernel matrices (the last one a matrix
        product), computed in blocks of the first axis.
        """
        axes = [np.asarray(a, float) for a in axes]
        d = len(axes)
        shape = tuple(a.size for a in axes)
        n = self.A.shape[1]
        out = np.empty((self.n_modes, n) + shape)
        inner = int(np.prod(shape[1:-1])) if d > 2 else 1
        for u in range(self.n_modes):
            P, al = self.points[u], self.alpha[u]
            # rows of the first axis per block: the product tensor has n * step * inner * m entries
            step = max(1, _BLOCK // (n * inner * P.shape[0]))
            F = [np.exp(-0.5 * (a[:, None] - P[None, :, j]) ** 2 * self.inv_l2[j]) for j, a in enumerate(axes)]
            for s0 in range(0, shape[0], step):
                T = al.T[:, None, :] * F[0][None, s0:s0 + step, :]  # (n, b, m)
                for j in range(1, d - 1):
                    T = (T[..., None, :] * F[j]).reshape(n, -1, P.shape[0])
                T = T @ F[-1].T if d > 1 else T.sum(axis=-1)  # (n, b * prod k_1..k_{d-2}, k_{d-1})
                out[u, :, s0:s0 + step] = T.reshape((n, -1) + shape[1:])
            lin = np.broadcast_to(self.b[u].reshape((n,) + (1,) * d), (n,) + shape).copy()
            for j, a in enumerate(axes):
                lin += self.A[u][:, j].reshape((n,) + (1,) * d) * a.reshape((1,) * (j + 1) + (-1,) + (1,) * (d - 1 - j))
            out[u] += lin
            if self.known and self.known[u] is not None:  # a nonlinear known part, at every lattice point
                pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, d)
                out[u] += np.moveaxis(self.known[u](pts).reshape(shape + (n,)), -1, 0)
        return out

    def grid_ranges(self, breakpoints):
        """Range of ``f_u + g_hat_u`` over every cell of a rectilinear grid, from its 3^d lattice points.

        The points of a cell are its vertices, edge and face midpoints and centre (the grid of its
        breakpoints with midpoints inserted), so the range is the same function of the cell for
        every component and every cell.

        Returns
        -------
        lower, upper : (n_modes, n_cells, n) float arrays, cells in C order of the grid.
        """
        axes = []
        for bp in breakpoints:
            bp = np.asarray(bp, float)
            ax = np.empty(2 * bp.size - 1)
            ax[0::2], ax[1::2] = bp, 0.5 * (bp[:-1] + bp[1:])
            axes.append(ax)
        V = self.lattice(axes)
        lo, hi = V, V
        for j in range(len(axes)):
            ax = 2 + j

            def take(a, s):  # lattice points s, s + 2, ... along this axis: the cells' 3 points are s = 0, 1, 2
                return a[(slice(None),) * ax + (slice(s, a.shape[ax] - 2 + s, 2),)]

            lo = np.minimum(np.minimum(take(lo, 0), take(lo, 1)), take(lo, 2))
            hi = np.maximum(np.maximum(take(hi, 0), take(hi, 1)), take(hi, 2))
        M, n = lo.shape[:2]
        return (np.moveaxis(lo.reshape(M, n, -1), 1, 2), np.moveaxis(hi.reshape(M, n, -1), 1, 2))

    def cell_ranges(self, lower, upper):
        """The same range as :meth:`grid_ranges` for arbitrary cells ``(k, d)``: ``(n_modes, k, n)`` twice."""
        lower, upper = np.asarray(lower, float), np.asarray(upper, float)
        k, d = lower.shape
        offs = np.stack(np.meshgrid(*[np.array([0.0, 0.5, 1.0])] * d, indexing="ij"), axis=-1).reshape(-1, d)
        pts = (lower[:, None, :] + offs[None] * (upper - lower)[:, None, :]).reshape(-1, d)
        v = self(pts).reshape(self.n_modes, k, offs.shape[0], -1)
        return v.min(axis=2), v.max(axis=2)


def evenly_spaced(m: int, k: int) -> np.ndarray:
    """Indices of an evenly spaced subset of about ``k`` of ``m`` samples (first and last included)."""
    return np.unique(np.linspace(0, m - 1, int(k)).round().astype(int))


def fit_modes(data, maps, lengthscale, regulariser, *, max_points: int = FIT_POINTS) -> FittedModes:
    """Kernel-ridge fit of every mode's residuals with the SE kernel of the assumption.

    Parameters
    ----------
    data : sequence (n_modes) of (x (m_u, d), residuals (m_u, n)) pairs
    maps : sequence (n_modes) of objects with ``A (n, d)`` and ``b (n,)`` (the known parts), or
        callables ``(k, d) -> (k, n)`` (nonlinear known parts, ``known.KnownDynamics``)
    lengthscale : float or (d,) float array
    regulariser : float or (n,) float array, > 0
        Ridge parameter per component: ``alpha = (K + lambda I)^-1 y`` (the GP posterior mean with
        prior variance B^2 and noise variance sigma^2 has ``lambda = sigma^2 / B^2``).
    max_points : int
        Beyond this many samples a mode is fitted on an evenly spaced subset of them.
    """
    if len(data) != len(maps) or not data:
        raise DimensionError(f"data and maps must have one entry per mode; got {len(data)} and {len(maps)}")
    d = np.asarray(data[0][0]).shape[1]
    ls = np.broadcast_to(np.asarray(lengthscale, float), (d,))
    if not np.all(np.isfinite(ls) & (ls > 0)):
        raise InvalidInputError(f"lengthscale must be positive and finite; got {ls.tolist()}")
    inv_l2 = 1.0 / (ls * ls)
    points, alphas = [], []
    for x, y in data:
        x = np.asarray(x, float)
        y = np.asarray(y, float).reshape(x.shape[0], -1)
        lam = np.broadcast_to(np.asarray(regulariser, float), (y.shape[1],))
        if not np.all(np.isfinite(lam) & (lam > 0)):
            raise InvalidInputError(f"regulariser must be positive and finite; got {lam.tolist()}")
        if x.shape[0] > max_points:
            keep = evenly_spaced(x.shape[0], max_points)
            x, y = x[keep], y[keep]
        K = se_gram(x, x, inv_l2)
        al = np.empty_like(y)
        for i in range(y.shape[1]):
            al[:, i] = np.linalg.solve(K + lam[i] * np.eye(x.shape[0]), y[:, i])
        points.append(x)
        alphas.append(al)
    affine = [hasattr(m, "A") and hasattr(m, "b") for m in maps]
    n = alphas[0].shape[1]
    A = np.stack([np.asarray(m.A, float) if a else np.zeros((n, d)) for m, a in zip(maps, affine)])
    b = np.stack([np.asarray(m.b, float).reshape(-1) if a else np.zeros(n) for m, a in zip(maps, affine)])
    known = () if all(affine) else tuple(None if a else m for m, a in zip(maps, affine))
    return FittedModes(tuple(points), tuple(alphas), A, b, inv_l2, known)


def _excess_sides(lower, upper, fit_lower, fit_upper):
    """How far the box reaches beyond the fitted range on each side (>= 0)."""
    return np.maximum(fit_lower - lower, 0.0), np.maximum(upper - fit_upper, 0.0)


def excess_radius(lower, upper, fit_lower, fit_upper) -> np.ndarray:
    """Half of (box width - fitted range), at least 0: ``(n_modes, n_cells, n)``.

    0 means the box is as narrow as the fitted function's own spread over the cell (only a
    finer grid narrows it); a value near the cell's half-width means the uncertainty about ``g``
    alone spreads the image over neighbouring cells (more data narrows it).
    """
    return np.maximum(0.5 * ((upper - lower) - (fit_upper - fit_lower)), 0.0)
