"""The assumption per mode and component, and the known parts' share of the bound stage.

Assumption 1 of the paper bounds each component of each mode's unknown part on its own:
``||g_u^(i)|| <= B_{u,i}``. ``rkhs_bound``, ``lengthscale`` and ``misspecification`` therefore each
take

* a number (every mode and component),
* a list with one entry per component (every mode), or
* a table per mode, ``{east = [0.2, 0.1], west = 0.3}``, whose values are either of the above.

``lengthscale`` is a vector over the input dimensions already: a list of numbers keeps that
meaning (one ARD lengthscale per input dimension, for every component). Per component it is a list
of ``n`` entries of which at least one is a list, each entry a number (every input dimension) or a
list of ``n`` numbers: ``[[4, 1, 1], [4, 1, 1], 1.0]``.

A component with ``rkhs_bound = 0`` (or ``known = true``) is **known**: it is not learned, its
image over a cell is the known part's certified range widened by its misspecification tau, and the
assumption check is that every residual lies within the noise bound plus tau (plus the residual's
rounding bound, for a nonlinear known part).

:func:`resolve` turns the user's values into arrays (:class:`Settings`); :func:`bound_mode_chunk`
is the bound stage's unit of work for a mode whose components differ (it runs
``rkhs.bound_chunk`` once per group of components that share a setting); :func:`check_modes` is
the assumption check per mode and component.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from robust_imdp.errors import AssumptionError, DimensionError, InvalidInputError

__all__ = ["Settings", "resolve", "bound_mode_chunk", "known_component_ranges", "check_modes", "add_ranges"]


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)


def _entries(value, name: str, mode_names: Sequence[str]) -> list:
    """The value of every mode, in mode order (a table per mode, or one value for all)."""
    if isinstance(value, dict):
        unknown = [k for k in value if str(k) not in mode_names]
        if unknown:
            raise InvalidInputError(f"{name} names modes {unknown} that are not defined; the modes are "
                                    f"{list(mode_names)}")
        missing = [m for m in mode_names if m not in {str(k) for k in value}]
        if missing:
            raise InvalidInputError(f"{name} is a table per mode and must give every mode; missing {missing} "
                                    f"(got {value!r})")
        table = {str(k): v for k, v in value.items()}
        return [(f"{name}.{m}" if _plain(m) else f'{name}."{m}"', table[m]) for m in mode_names]
    return [(name, value)] * len(mode_names)


def _plain(m: str) -> bool:
    return m.replace("_", "").replace("-", "").isalnum()


def _per_component(value, name: str, n: int, *, lo: float, strict: bool) -> np.ndarray:
    """A number or a list of n numbers, each >= lo (> lo when strict) and finite: (n,)."""
    if _is_number(value):
        arr = np.full(n, float(value))
    else:
        if isinstance(value, np.ndarray):
            value = value.tolist()
        if not isinstance(value, (list, tuple)) or len(value) != n or not all(_is_number(v) for v in value):
            got = f"{len(value)} entries: {value!r}" if isinstance(value, (list, tuple)) else repr(value)
            raise DimensionError(f"{name} must be a number or a list of {n} numbers (one per component); got {got}")
        arr = np.asarray(value, dtype=float)
    bad = ~np.isfinite(arr) | ((arr <= lo) if strict else (arr < lo))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        rel = ">" if strict else ">="
        raise InvalidInputError(f"{name} must be finite and {rel} {lo:g} for every component; got {value!r} "
                                f"(component {i + 1}: {arr[i]!r})")
    return arr


def _lengthscales(value, name: str, n: int, d: int) -> np.ndarray:
    """(n, d): a number, a list of d numbers (per input dimension) or a list per component."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if _is_number(value) or (isinstance(value, (list, tuple)) and all(_is_number(v) for v in value)):
        per_dim = _per_dimension(value, name, d)
        return np.broadcast_to(per_dim, (n, d)).copy()
    if not isinstance(value, (list, tuple)) or len(value) != n:
        got = f"{len(value)} entries: {value!r}" if isinstance(value, (list, tuple)) else repr(value)
        raise DimensionError(f"{name} must be a number, a list of {d} numbers (one per input dimension) or a list "
                             f"of {n} entries (one per component, each a number or {d} numbers); got {got}")
    return np.stack([_per_dimension(v, f"{name}[{i + 1}]", d) for i, v in enumerate(value)])


def _per_dimension(value, name: str, d: int) -> np.ndarray:
    if _is_number(value):
        arr = np.full(d, float(value))
    elif isinstance(value, (list, tuple)) and len(value) in (1, d) and all(_is_number(v) for v in value):
        arr = np.broadcast_to(np.asarray(value, dtype=float), (d,)).copy()
    else:
        got = f"{len(value)} entries: {value!r}" if isinstance(value, (list, tuple)) else repr(value)
        raise DimensionError(f"{name} must be a number or a list of {d} numbers (one per input dimension); got {got}")
    if not np.all(np.isfinite(arr) & (arr > 0)):
        raise InvalidInputError(f"{name} must be finite and > 0 in every input dimension; got {value!r}")
    return arr


def _is_scalar_setting(value) -> bool:
    return _is_number(value)


@dataclass(frozen=True, eq=False)
class Settings:
    """The assumption of every mode and component, as arrays.

    Attributes
    ----------
    rkhs_bound : (n_modes, n) float array
        B per mode and component; 0 marks a known component.
    lengthscale : (n_modes, n, d) float array
    misspecification : (n_modes, n) float array
    uniform : bool
        One positive B, one lengthscale vector and one tau for every mode and component, each
        given as one value (the pipeline's one-setting path, unchanged by this module).
    """

    rkhs_bound: np.ndarray
    lengthscale: np.ndarray
    misspecification: np.ndarray
    uniform: bool

    @property
    def known(self) -> np.ndarray:
        """(n_modes, n) bool: the components that are not learned."""
        return self.rkhs_bound == 0

    def groups(self, u: int) -> list:
        """Components of mode ``u`` sharing one setting: ``(indices, B, lengthscale (d,), tau)`` in order of
        first appearance; known components (B = 0) form groups of their own."""
        out: dict = {}
        for i in range(self.rkhs_bound.shape[1]):
            key = (float(self.rkhs_bound[u, i]), tuple(self.lengthscale[u, i].tolist()),
                   float(self.misspecification[u, i]))
            out.setdefault(key, []).append(i)
        return [(np.asarray(idx, dtype=np.int64), k[0], np.asarray(k[1]), k[2]) for k, idx in out.items()]

    def key(self):
        """What the cache keys fingerprint: the arrays (or nothing more when uniform)."""
        return [self.rkhs_bound, self.lengthscale, self.misspecification]

    def to_rows(self, mode_names) -> list:
        """One JSON-able row per mode and component (diagnostics)."""
        M, n = self.rkhs_bound.shape
        return [{"mode": mode_names[u], "component": i + 1, "rkhs_bound": float(self.rkhs_bound[u, i]),
                 "lengthscale": self.lengthscale[u, i].tolist(),
                 "misspecification": float(self.misspecification[u, i]), "known": bool(self.rkhs_bound[u, i] == 0)}
                for u in range(M) for i in range(n)]


def resolve(rkhs_bound, lengthscale, misspecification, mode_names: Sequence[str], n: int, *,
            prefix: str = "", known=None) -> Settings:
    """The user's values (number, list per component, table per mode) as :class:`Settings`.

    Parameters
    ----------
    rkhs_bound, misspecification : number, list of n numbers, or dict mode -> either
        B >= 0 (0: a known component), tau >= 0.
    lengthscale : number, list of n numbers (per input dimension), list of n per-component entries,
        or dict mode -> any of these; None means 1.0
    mode_names : the modes in order
    n : the state dimension (components = input dimensions)
    prefix : put before the names in messages (``"[learning]."`` for a problem file)
    known : list of n bools or dict mode -> list, optional
        Components declared known (their B is set to 0).

    Raises
    ------
    InvalidInputError, DimensionError
        Naming ``[learning].rkhs_bound`` (etc.), the mode, the expected form and what was given.
    """
    names = [str(m) for m in mode_names]
    M = len(names)
    B = np.stack([_per_component(v, where, n, lo=0.0, strict=False)
                  for where, v in _entries(rkhs_bound, f"{prefix}rkhs_bound", names)])
    tau = np.stack([_per_component(v, where, n, lo=0.0, strict=False)
                    for where, v in _entries(misspecification, f"{prefix}misspecification", names)])
    ls_value = 1.0 if lengthscale is None else lengthscale
    L = np.stack([_lengthscales(v, where, n, n) for where, v in _entries(ls_value, f"{prefix}lengthscale", names)])
    if known is not None:
        for u, (where, v) in enumerate(_entries(known, f"{prefix}known", names)):
            if isinstance(v, np.ndarray):
                v = v.tolist()
            if not isinstance(v, (list, tuple)) or len(v) != n or not all(isinstance(k, (bool, np.bool_)) for k in v):
                got = f"{len(v)} entries: {v!r}" if isinstance(v, (list, tuple)) else repr(v)
                raise DimensionError(f"{where} must be a list of {n} true/false values (one per component); got {got}")
            B[u, np.asarray(v, dtype=bool)] = 0.0
    ls_list = lengthscale.tolist() if isinstance(lengthscale, np.ndarray) else lengthscale
    one_lengthscale = lengthscale is None or _is_number(ls_list) or (
        isinstance(ls_list, (list, tuple)) and all(_is_number(v) for v in ls_list))
    uniform = (known is None or not np.any(B == 0)) and _is_scalar_setting(rkhs_bound) \
        and _is_scalar_setting(misspecification) and float(rkhs_bound) > 0 and one_lengthscale
    assert B.shape == (M, n) and L.shape == (M, n, n)
    return Settings(B, L, tau, bool(uniform))


# ============================================================================ interval sums
def add_ranges(lo_a, hi_a, lo_b, hi_b):
    """``[lo_a + lo_b, hi_a + hi_b]`` rounded outward (one ulp beyond the round-to-nearest sum).

    The sum of two ranges holds the sum of the two functions (Minkowski sum of intervals); the
    floating-point sum is within half an ulp of the exact one, so one ulp outward contains it.
    """
    return (np.nextafter(np.asarray(lo_a, float) + np.asarray(lo_b, float), -np.inf),
            np.nextafter(np.asarray(hi_a, float) + np.asarray(hi_b, float), np.inf))


def known_component_ranges(A, b, cells_lower, cells_upper, tau) -> tuple:
    """Image of known components: the affine part's certified range over each cell, widened by tau.

    Parameters
    ----------
    A : (k_out, d) float array, b : (k_out,) float array
        The rows of the components (zeros for a nonlinear known part, whose range is added later).
    cells_lower, cells_upper : (k, d) float arrays
    tau : float >= 0

    Returns
    -------
    lower, upper : (k, k_out) float arrays
    """
    from robust_imdp.models.system import AffineMap

    A = np.asarray(A, float)
    d = A.shape[1]
    # a square map with the rows of the components (the other rows 0): AffineMap.image_bounds
    k_out = A.shape[0]
    out_lo = np.empty((np.shape(cells_lower)[0], k_out))
    out_hi = np.empty_like(out_lo)
    for j in range(k_out):
        Af, bf = np.zeros((d, d)), np.zeros(d)  # fresh per row: AffineMap makes its arrays read-only
        Af[0], bf[0] = A[j], float(np.asarray(b, float)[j])
        r = AffineMap(Af, bf).image_bounds(cells_lower, cells_upper)
        out_lo[:, j], out_hi[:, j] = r.lower[:, 0], r.upper[:, 0]
    t = np.full_like(out_lo, float(tau))
    # |g| <= tau on X for a known component (its h is 0): range + [-tau, tau], rounded outward
    return add_ranges(out_lo, out_hi, -t, t)


# ============================================================================ the bound stage
def bound_mode_chunk(X, Y, A, b, cells_lower, cells_upper, local, mode: dict, *, threads=1, **settings) -> dict:
    """``rkhs.bound_chunk`` for one mode whose components differ in their assumption or noise allowance.

    Parameters
    ----------
    X, Y, A, b, cells_lower, cells_upper, settings
        As ``rkhs.bound_chunk``; ``settings`` holds the problem-wide values.
    local : None or (points, ridge lambda)
        The mode's local weights (``pipeline._local_settings``).
    mode : dict
        ``noise_bound`` (n,): the data-noise allowance of this mode (noise bound plus the residuals'
        rounding bound); optionally ``groups`` (from :meth:`Settings.groups`) and ``local_lambda``
        (one per group, for ridge with local weights).

    Returns
    -------
    dict like ``rkhs.bound_chunk``'s; a known component has ``eps = 0`` and ``support = 0``. With
    ``settings["scales"]`` (every learned component's B times each scale) a known component's scaled
    boxes are its own boxes: B = 0 stays 0.
    """
    from robust_imdp.bounds.rkhs import bound_chunk

    Y = np.asarray(Y, float).reshape(np.shape(X)[0], -1)
    n = Y.shape[1]
    k = np.shape(cells_lower)[0]
    nb = np.broadcast_to(np.asarray(mode["noise_bound"], float), (n,))
    th = settings.get("iid_theta")
    th = None if th is None else np.broadcast_to(np.asarray(th, float), (n,))

    def run(idx, extra, lam):
        s = dict(settings, noise_bound=nb[idx], iid_theta=None if th is None else th[idx], **extra)
        if local is not None:
            s["local_points"], s["local_lambda"] = local[0], (local[1] if lam is None else lam)
        return bound_chunk(X, Y[:, idx], np.asarray(A, float)[idx], np.asarray(b, float)[idx], cells_lower,
                           cells_upper, threads=threads, **s)

    groups = mode.get("groups")
    if groups is None:  # one setting for every component: only the noise allowance differs
        return run(np.arange(n), {}, None)
    out = {key: np.empty((k, n)) for key in ("lower", "upper", "eps")}
    out["support"] = np.zeros((k, n), dtype=np.int64)
    out["n_unconverged"] = 0
    scales = settings.get("scales")
    if scales is not None:
        out["scaled_lower"] = np.empty((len(scales), k, n))
        out["scaled_upper"] = np.empty((len(scales), k, n))
    lams = mode.get("local_lambda") or [None] * len(groups)
    for (idx, B, L, tau), lam in zip(groups, lams):
        if B == 0:
            lo, hi = known_component_ranges(np.asarray(A, float)[idx], np.asarray(b, float)[idx], cells_lower,
                                            cells_upper, tau)
            out["lower"][:, idx], out["upper"][:, idx], out["eps"][:, idx] = lo, hi, 0.0
            if scales is not None:  # a known component is known at every scale of B
                out["scaled_lower"][:, :, idx], out["scaled_upper"][:, :, idx] = lo[None], hi[None]
            continue
        r = run(idx, {"rkhs_bound": float(B), "lengthscale": np.asarray(L, float), "misspecification": float(tau)},
                lam)
        for key in ("lower", "upper", "eps", "support"):
            out[key][:, idx] = r[key]
        if scales is not None:
            out["scaled_lower"][:, :, idx], out["scaled_upper"][:, :, idx] = r["scaled_lower"], r["scaled_upper"]
        out["n_unconverged"] += int(r["n_unconverged"])
    return out


# ============================================================================ the assumption check
def check_modes(data, settings: Settings, noise_bound, *, mode_names, sample_index=None, max_points: int = 300,
                solver: bool = True, refuse: bool = True, norms=None) -> tuple:
    """The assumption check per mode and component (``rkhs.check_assumption`` for each setting).

    Parameters
    ----------
    data : sequence (n_modes) of (X (m_u, d), Y (m_u, n)) pairs (residuals)
    settings : Settings
    noise_bound : (n_modes, n) float array
        The data-noise allowance of each mode and component (noise bound plus rounding bound).
    mode_names, sample_index
        For messages (``sample_index[u]``: the data rows of mode u's samples).
    norms : callable, optional
        Runs the per-component jobs (``rkhs_check.check_assumption``'s ``norms``; default in this process).

    Returns
    -------
    tuple of rkhs.NormCheck (a known component has minimum 0 when its residuals pass)

    Raises
    ------
    AssumptionError
        Naming ``[learning].rkhs_bound``, the mode, the component and the sample (or the data-implied
        minimum), for the worst refuted component.
    """
    from robust_imdp.bounds.rkhs_check import NormCheck, refutation_reason, serial_norms

    nb = np.asarray(noise_bound, float)
    jobs, where = [], []
    for u, (X, Y) in enumerate(data):
        Y = np.asarray(Y, float).reshape(np.shape(X)[0], -1)
        for i in range(Y.shape[1]):
            B, tau = float(settings.rkhs_bound[u, i]), float(settings.misspecification[u, i])
            jobs.append((X, Y[:, i], settings.lengthscale[u, i], float(nb[u, i]), tau, max_points, solver and B > 0))
            where.append((u, i, Y, B, tau))
    checks, bad = [], []
    for (u, i, Y, B, tau), r in zip(where, (norms or serial_norms)(jobs)):
        s = r["sample"]
        row = int(sample_index[u][s]) if sample_index is not None else int(s)
        c = NormCheck(u, i, r["minimum"], r["n_points"], row, r["single_minimum"], float(Y[s, i]))
        checks.append(c)
        if c.minimum > B:
            bad.append((c, B, tau, float(nb[u, i])))
    if refuse and bad:
        c, B, tau, nbi = max(bad, key=lambda t: t[0].minimum - t[1])
        name = mode_names[c.mode]
        if B == 0:
            raise AssumptionError(
                f"[learning] declares component {c.output + 1} of mode {name!r} known (rkhs_bound = 0 or known = true), "
                f"but sample {c.sample} has residual {c.residual:.6g} there, beyond the noise bound + "
                f"misspecification = {nbi + tau:.6g}: the known part does not explain the data; give the component "
                "an rkhs_bound > 0, a misspecification allowance, or check the known part and the data"
                + (f" ({len(bad)} components are refuted)" if len(bad) > 1 else ""))
        why = refutation_reason(c, B, nbi, tau)
        raise AssumptionError(
            f"[learning].rkhs_bound = {B:g} for mode {name!r}, component {c.output + 1} is refuted by the data: it needs an "
            f"RKHS norm of at least {c.minimum:.4g} (lengthscale {settings.lengthscale[c.mode, c.output].tolist()}); "
            f"{why}. Choose rkhs_bound >= {c.minimum:.4g} for it (with a margin), a different lengthscale, a "
            "misspecification allowance, or check the data"
            + (f" ({len(bad)} of {len(checks)} components are refuted)" if len(bad) > 1 else ""))
    return tuple(checks)


# ============================================================================ the data-fitted function
class ComponentFits:
    """``bounds.fit.FittedModes`` per mode and lengthscale, read as one (a diagnostic, not a bound).

    ``parts`` : list of (mode, component indices, FittedModes of that one mode); the ranges of each
    component come from the fit with its own lengthscale and ridge parameter.
    """

    def __init__(self, parts, n_modes: int, n: int):
        self.parts, self.n_modes, self.n = parts, n_modes, n

    def _gather(self, per_part):
        lo = hi = None
        for (u, idx, _), (l, h) in zip(self.parts, per_part):
            if lo is None:
                lo = np.empty((self.n_modes,) + l.shape[1:-1] + (self.n,))
                hi = np.empty_like(lo)
            lo[u][..., idx], hi[u][..., idx] = l[0][..., idx], h[0][..., idx]
        return lo, hi

    def grid_ranges(self, breakpoints):
        """As ``FittedModes.grid_ranges``: ``(n_modes, n_cells, n)`` twice."""
        return self._gather([fm.grid_ranges(breakpoints) for _, _, fm in self.parts])

    def cell_ranges(self, lower, upper):
        """As ``FittedModes.cell_ranges``: ``(n_modes, k, n)`` twice."""
        return self._gather([fm.cell_ranges(lower, upper) for _, _, fm in self.parts])

    def __call__(self, x):
        vals = [fm(x) for _, _, fm in self.parts]
        return self._gather([(v, v) for v in vals])[0]


def fit_components(data, maps, settings: Settings, sigma) -> ComponentFits:
    """Kernel-ridge fits (``bounds.fit.fit_modes``) with each mode's and component's lengthscale and
    ``lambda = (sigma / B)^2`` (kept >= 1e-6); a known component (B = 0) is fitted with ``lambda = 1e12``,
    so its fit is its known part."""
    from robust_imdp.bounds.fit import fit_modes

    sigma = np.broadcast_to(np.asarray(sigma, float), (settings.rkhs_bound.shape[1],))
    parts = []
    for u in range(len(data)):
        B = settings.rkhs_bound[u]
        with np.errstate(divide="ignore"):
            lam = np.where(B > 0, np.maximum(sigma / np.where(B > 0, B, 1.0), 1e-3) ** 2, 1e12)
        by_l: dict = {}
        for i in range(B.size):
            by_l.setdefault(tuple(settings.lengthscale[u, i].tolist()), []).append(i)
        for L, idx in by_l.items():
            parts.append((u, np.asarray(idx), fit_modes([data[u]], [maps[u]], np.asarray(L), lam)))
    return ComponentFits(parts, len(data), settings.rkhs_bound.shape[1])
