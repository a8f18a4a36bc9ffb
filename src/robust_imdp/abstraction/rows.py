r"""Per-cell image and error bounds -> IMDP: the paper's Thm 1 with corrected complements.

Setting (paper, Process (1)): ``x' = f_u(x) + g_u(x) + v`` with ``g_u`` learned as
``mu_u`` by one GP per output dimension and ``v`` additive noise with independent
components. For a cell ``q``, mode ``u`` and target ``q'``:

* ``Im(q)`` is a box containing ``{f_u(x) + mu_u(x) : x in q}`` (``CellBounds.image_*``);
* ``E_g = {sup_{x in q} |g_i(x) - mu_i(x)| <= eps_i  for all i}``, with
  ``P(E_g) >= P_g``: ``P_g = prod_i p_i`` (``p_i = error_models[u][i].prob_within(eps_i,
  std_upper[u, q, i])``, independent components as in the paper) or the union bound
  ``P_g = max(0, 1 - sum_i (1 - p_i))`` (``combine="union"``, no independence needed);
* ``E_v = {|v_i| <= eta_i for all i}``, ``P(E_v) >= P_v = prod_i P[|v_i| <= eta_i]`` (or the
  union bound); ``v`` is independent of ``E_g`` (fresh noise).

Derivation (law of total probability over ``E_g`` and ``E_v``). On ``E_g ∩ E_v`` every
successor of every ``x in q`` lies in the closed box ``Im(q) ⊕ [-(eps+eta), eps+eta]``.
Hence for every ``x in q``::

    T(q'|x) <= P(E_g) [ P(E_v) 1[Im ⊕ (eps+eta) ∩ q' != ∅] + (1 - P(E_v)) ] + (1 - P(E_g))
            = 1 - P(E_g) P(E_v) (1 - 1[...])                              (Thm 1, eq. upper-bound)
    T(q'|x) >= P(E_g) P(E_v) 1[Im ⊕ (eps+eta) ⊆ q']                        (Thm 1, eq. lower-bound)

Both right-hand sides are monotone in ``P(E_g)`` and ``P(E_v)`` in the safe direction, so
the lower bounds ``P_g``, ``P_v`` may replace them. **Deviation from the printed paper**
(corrected complements): the paper weights the "bad" branches with ``prod_i P[|v_i| > eta_i]`` and
``prod_i (1 - p_i)``, the probability that *all* components fail; the complement of
``E_v`` (resp. ``E_g``) is that *some* component fails, ``1 - prod_i P[|v_i| <= eta_i]``.
For ``d >= 2`` the printed upper bound is too small whenever ``P_v < 1`` (e.g. Gaussian
noise); ``tests/test_abstraction.py`` shows a Monte-Carlo counterexample.

The authors' code also (a) drops the noise factor from the upper bound (sound only if
``P_v = 1``) and (b) measures image-to-target separation with a max over all axes,
overlapping ones included. Neither is done here: two closed boxes intersect iff they
overlap on EVERY axis, i.e. they are disjoint iff some axis ``j`` has a strictly positive
gap ``gap_j > eps_j + eta_j``.

Outside state (corollary): ``lower(q,u,out) = 1 - [upper bound of T(X|x)] =
P_g P_v 1[Im ⊕ (eps+eta) ∩ X = ∅]`` and ``upper(q,u,out) = 1 - P_g P_v 1[Im ⊕ (eps+eta) ⊆ X]``.

Cells and boundaries: cells are closed boxes sharing faces; since ``v`` has a density and
is independent of ``x``, ``P[x' ∈ ∂q'] = 0``, so closed/half-open cell conventions give the
same probabilities and the closed tests above are exact for :meth:`Partition.locate`'s cells.

Modules: the input type and the confidence-mode converter are in ``abstraction.cell_bounds``,
the eps/eta candidates and the combined probabilities in ``abstraction.probabilities``, the listed
targets of each row (grid or box partition) in ``abstraction.targets``; this module builds the rows.

Choosing eps and eta. The theorem holds for every ``eps, eta > 0`` and each bound may use
its own values:

* ``eps_rule="paper"``: eta = the given ``eta`` (default: noise bound, else 0.99 quantile);
  for the target containing ``Im(q)``, the largest eps with ``Im ⊕ (eps+eta) ⊆ q'``
  (``eps_i = m_i - eta_i``, margins ``m``); otherwise ``eps = eps_for_prob(0.99)``.
* ``eps_rule="optimized"`` (default): per (cell, mode, target) and per dimension, the best
  split of the available margin/gap ``t_i`` into ``eps_i + eta_i < t_i``: eps over a
  geometric grid of probability levels (``EPS_LEVELS``, via ``eps_for_prob``, probabilities
  recomputed with ``prob_within``) and the paper's candidate, eta = the whole rest of the
  margin (or the fixed ``eta`` when given). For the product combination this maximises
  ``P_g P_v`` dimension by dimension (the constraint and the objective separate); an axis
  that is not constrained uses the largest candidates. The paper's choices are among the
  candidates, so the optimised bounds are never looser (for ``combine="product"``).

Sparse output: each row lists the targets whose closed box meets ``Im ⊕ e_f`` for a per-row
"floor" pair ``(eps_f, eta_f)`` plus the outside state; every other target is separated
from ``Im ⊕ e_f`` along some axis, so ``1 - P_g(eps_f) P_v(eta_f)`` is a valid upper bound for
all of them: the row's ``floor``. The floor pair takes, per dimension, the smallest level
``>= 0.99`` with ``p_i P[|v_i| <= eta_i] >= 1 - floor_tol/d`` (else the best level).

Periodic dimensions (``partition.periodic``, see docs/periodic.md): a target cell is the union of its
translates by whole periods, so gaps and margins along a periodic axis are those on the circle
(``abstraction.periodic``), and the outside state is reached only through the non-periodic axes:
in the corollary a periodic axis contributes the factors ``p = P_v = 1`` and never separates.

Rounding: all computed bounds go through :mod:`robust_imdp._fp` (error bound + ``np.nextafter``):
probabilities of good events down, upper bounds up; margins/gaps down, expansions up.

Exact transitions (``transitions="exact"``, docs/abstraction.md): instead of Thm 1's containment
events, every entry's bounds are the exact minimum and maximum over the image box of the noise's
mass in the target (per axis, ``abstraction.marginals``; joint rows, ``abstraction.exact_rows``).
:func:`abstract_rows` dispatches to them and returns the same :class:`AbstractionRows` (Thm 1's
per-row eps/eta records are NaN and ``containing_cell`` -1 there), so chunking, refinement, the
cache and every consumer of :class:`Abstraction` work unchanged.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from robust_imdp._fp import U, down, up
from robust_imdp.abstraction.cell_bounds import CellBounds, CellErrors, confidence_cell_bounds
from robust_imdp.abstraction.exact_rows import exact_rows
from robust_imdp.abstraction.periodic import circle_margin
from robust_imdp.abstraction.probabilities import EPS_LEVELS, _combine_down, _complement_up, _Mode, _separated_best
from robust_imdp.abstraction.targets import targets_of
from robust_imdp.errors import DimensionError, InvalidInputError, SoundnessError
from robust_imdp.models.geometry import BoxPartition, Partition, partition_from_dict
from robust_imdp.models.imdp import IMDP
from robust_imdp.models.noise import NoiseModel

__all__ = ["CellBounds", "Abstraction", "AbstractionRows", "abstract", "abstract_rows", "assemble_abstraction",
           "select_rows", "join_rows",
           "confidence_cell_bounds", "EPS_LEVELS", "TRANSITIONS"]

#: How transition bounds are computed: Thm 1's containment events, or the exact per-axis integrals.
TRANSITIONS = ("thm1", "exact")


@dataclass(frozen=True, eq=False)
class Abstraction:
    """Result of :func:`abstract`.

    Attributes
    ----------
    imdp : IMDP
        States: cells ``0..n_cells-1`` then the outside state ``n_cells``; choice = mode.
    partition : Partition
    eps_rule, combine : str
    eta : (d,) float array or None
        The fixed eta (given, or the paper rule's default); None when optimised freely.
    floor_tol : float
    floor_eps, floor_eta : (n_modes, n_cells, d) float arrays
        The per-row pair defining the listed targets and the floor.
    lower_eps, lower_eta : (n_modes, n_cells, d) float arrays
        The pair behind the lower bound to the cell containing the image (NaN if none).
    containing_cell : (n_modes, n_cells) int array
        The cell containing ``Im(q)`` with positive margins (-1 if none).
    nnz_per_row : (n_choices,) int array
        Listed entries per IMDP row (including the outside state).
    transitions : {"thm1", "exact"}
        How the bounds were computed (module docstring); with "exact" the Thm 1 records above are
        NaN / -1 and ``floor_tol`` is not used.
    """

    imdp: IMDP
    partition: Partition
    eps_rule: str
    combine: str
    eta: np.ndarray | None
    floor_tol: float
    floor_eps: np.ndarray
    floor_eta: np.ndarray
    lower_eps: np.ndarray
    lower_eta: np.ndarray
    containing_cell: np.ndarray
    nnz_per_row: np.ndarray = field(repr=False)
    transitions: str = "thm1"

    @property
    def n_modes(self) -> int:
        return self.floor_eps.shape[0]

    def save(self, path) -> None:
        """Write an ``.npz`` file (no pickle): IMDP arrays, partition JSON and parameters."""
        m = self.imdp
        meta = {"partition": self.partition.to_dict(), "eps_rule": self.eps_rule, "combine": self.combine,
                "floor_tol": self.floor_tol}
        if self.transitions != "thm1":  # files of Thm 1 abstractions stay as they were
            meta["transitions"] = self.transitions
        arrays = dict(state_ptr=m.state_ptr, row_ptr=m.row_ptr, col=m.col, lower=m.lower, upper=m.upper,
                      floor=m.floor, actions=m.actions, floor_eps=self.floor_eps, floor_eta=self.floor_eta,
                      lower_eps=self.lower_eps, lower_eta=self.lower_eta, containing_cell=self.containing_cell,
                      nnz_per_row=self.nnz_per_row, meta=np.array(json.dumps(meta)))
        if self.eta is not None:
            arrays["eta"] = self.eta
        np.savez_compressed(Path(path), **arrays)

    @classmethod
    def load(cls, path) -> "Abstraction":
        """Read a file written by :meth:`save` (the IMDP is validated again)."""
        with np.load(Path(path), allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            imdp = IMDP.from_csr(z["state_ptr"], z["row_ptr"], z["col"], z["lower"], z["upper"],
                                 floor=z["floor"], actions=z["actions"])
            return cls(imdp=imdp, partition=partition_from_dict(meta["partition"]), eps_rule=meta["eps_rule"],
                       combine=meta["combine"], eta=np.array(z["eta"]) if "eta" in z else None,
                       floor_tol=float(meta["floor_tol"]), floor_eps=np.array(z["floor_eps"]),
                       floor_eta=np.array(z["floor_eta"]), lower_eps=np.array(z["lower_eps"]),
                       lower_eta=np.array(z["lower_eta"]), containing_cell=np.array(z["containing_cell"]),
                       nnz_per_row=np.array(z["nnz_per_row"]), transitions=meta.get("transitions", "thm1"))


def abstract(partition: Partition, cell_bounds: CellBounds, noise: NoiseModel, error_models=None, *,
             eta=None, eps_rule: str = "optimized", combine: str = "product", floor_tol: float = 1e-6,
             block_size: int = 4096, transitions: str = "thm1") -> Abstraction:
    """Build the IMDP abstraction (Thm 1 with corrected complements, corollary for outside X).

    Parameters
    ----------
    partition : Partition
        The cells (``n_cells``, dimension d).
    cell_bounds : CellBounds
        ``(n_modes, n_cells, d)`` image boxes and std bounds.
    noise : NoiseModel
        Additive noise with independent components, dimension d.
    error_models : sequence (n_modes) of sequences (d) of error models, or None
        Duck-typed: ``prob_within(eps, std_upper)`` (a lower bound of
        ``P[sup_cell |g_i - mu_i| <= eps]``, vectorised, non-decreasing in eps) and
        ``eps_for_prob(p, std_upper)``. Must be None iff ``cell_bounds.std_upper`` is None.
    eta : float or (d,) float array, optional
        Fixed noise radius (> 0). Default: the paper rule uses ``noise.default_eta()``,
        the optimised rule chooses eta freely per pair.
    eps_rule : {"optimized", "paper"}
    combine : {"product", "union"}
        How per-dimension probabilities are combined (independence vs union bound).
    floor_tol : float in (0, 1)
        Per-row floor target: the floor pair is the smallest level >= 0.99 whose per-dimension
        good-event probability is >= 1 - floor_tol/d, so the floor is about floor_tol (plus the
        GP part). Smaller values list more targets (nnz grows slowly, ~log) and tighten the
        unbounded-horizon results (benchmarks/results/abstraction.md: 1e-4 -> 1e-6 turned 44 of
        762 "maybe" cells of the 32x32 example into "yes" for +5 % non-zeros).
    block_size : int
        Cells processed at once (memory/speed trade-off only).
    transitions : {"thm1", "exact"}
        Thm 1's bounds, or the exact per-axis integrals (module docstring; docs/abstraction.md):
        never looser per entry, and the only ones with non-zero lower bounds when the noise is
        wider than a cell. ``eta`` and ``eps_rule`` are Thm 1's and unused by "exact"; there every
        row's floor is at least ``floor_tol / 20`` and entries below it are not listed.

    Returns
    -------
    Abstraction

    Raises
    ------
    DimensionError, InvalidInputError
        Bad shapes or parameters.
    SoundnessError
        A row violates ``sum(lower) <= 1 <= sum(upper) + floor * n_unlisted`` after rounding.
    """
    return assemble_abstraction(partition, [abstract_rows(
        partition, cell_bounds, noise, error_models, eta=eta, eps_rule=eps_rule, combine=combine,
        floor_tol=floor_tol, block_size=block_size, transitions=transitions, _chunk=False)])


@dataclass(frozen=True, eq=False)
class AbstractionRows:
    """The IMDP rows of a chunk of cells (all modes), in cell order: the unit of :func:`assemble_abstraction`.

    Rows are ``q * M + u`` for the chunk's local cell index q; columns are global cell indices
    (``n_cells`` is the outside state).
    """

    row_len: np.ndarray
    col: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    floor: np.ndarray
    lower_eps: np.ndarray
    lower_eta: np.ndarray
    containing: np.ndarray
    floor_eps: np.ndarray
    floor_eta: np.ndarray
    n_modes: int
    eps_rule: str
    combine: str
    eta: np.ndarray | None
    floor_tol: float
    transitions: str = "thm1"


def abstract_rows(partition: Partition, cell_bounds: CellBounds, noise: NoiseModel, error_models=None, *,
                  eta=None, eps_rule: str = "optimized", combine: str = "product", floor_tol: float = 1e-6,
                  block_size: int = 4096, transitions: str = "thm1", _chunk: bool = True) -> AbstractionRows:
    """The rows of :func:`abstract` for the cells whose image boxes ``cell_bounds`` holds (a chunk).

    A pure function of its arguments: each row depends only on its own cell's image box (and the
    partition), so computing the rows chunk by chunk and concatenating them in cell order
    (:func:`assemble_abstraction`) gives exactly :func:`abstract`'s IMDP. Parameters as in
    :func:`abstract`, except that ``cell_bounds`` may hold any number of cells.

    Steps: check the arguments; per mode, the candidate (eps, p) pairs and noise context
    (:class:`~robust_imdp.abstraction.probabilities._Mode`); pass 1 lists every row's targets and
    its floor; pass 2 computes the bounds block by block (:func:`_block_rows`).
    ``transitions="exact"``: the rows of :func:`~robust_imdp.abstraction.exact_rows.exact_rows` instead.
    """
    if transitions not in TRANSITIONS:
        raise InvalidInputError(f"transitions must be one of {', '.join(TRANSITIONS)}; got {transitions!r}")
    if transitions == "exact":
        return _exact_abstraction_rows(partition, cell_bounds, noise, error_models, eps_rule, combine, floor_tol,
                                       _chunk)
    errors, eta_fixed = _check_arguments(partition, cell_bounds, noise, error_models, eta, eps_rule, combine,
                                         floor_tol, _chunk)
    modes = [_Mode(u, cell_bounds, errors, noise, eta_fixed, eps_rule, floor_tol, combine)
             for u in range(cell_bounds.n_modes)]
    targets = targets_of(partition)
    listings, n_listed, floors = _list_targets(targets, cell_bounds, modes, combine)
    out = _RowArrays.allocate(n_listed, cell_bounds.dim)
    for u, md in enumerate(modes):
        for start in range(0, cell_bounds.n_cells, block_size):
            rows = np.arange(start, min(start + block_size, cell_bounds.n_cells))
            entries = targets.entries(listings[u], md, rows, cell_bounds.image_lower[u, rows],
                                      cell_bounds.image_upper[u, rows], n_listed[u, rows])
            _block_rows(out, u, md, rows, cell_bounds, entries, partition, combine)
    return AbstractionRows(
        row_len=out.row_len, col=out.col, lower=out.lower, upper=out.upper, floor=floors.T.ravel(),
        lower_eps=out.lower_eps, lower_eta=out.lower_eta, containing=out.containing,
        floor_eps=np.stack([md.floor_eps for md in modes]), floor_eta=np.stack([md.floor_eta for md in modes]),
        n_modes=cell_bounds.n_modes, eps_rule=eps_rule, combine=combine,
        eta=None if eta_fixed is None else np.array(eta_fixed), floor_tol=float(floor_tol))


def _exact_abstraction_rows(partition, cell_bounds, noise, error_models, eps_rule, combine, floor_tol, chunk):
    """:func:`abstract_rows` with ``transitions="exact"``: the exact rows, Thm 1's records NaN / -1."""
    _check_arguments(partition, cell_bounds, noise, error_models, None, eps_rule, combine, floor_tol, chunk)
    # floor_tol / 20: the floor below which listed entries are dropped (docs/abstraction.md, "Never looser")
    ex = exact_rows(partition, cell_bounds, noise, error_models, combine=combine, floor_level=floor_tol / 20)
    M, N, d = cell_bounds.image_lower.shape
    nan = np.full((M, N, d), np.nan)
    return AbstractionRows(
        row_len=ex.row_len, col=ex.col, lower=ex.lower, upper=ex.upper, floor=ex.floor, lower_eps=nan,
        lower_eta=nan.copy(), containing=np.full((M, N), -1, dtype=np.int64), floor_eps=nan.copy(),
        floor_eta=nan.copy(), n_modes=M, eps_rule=eps_rule, combine=combine, eta=None, floor_tol=float(floor_tol),
        transitions="exact")


def _check_arguments(partition, cell_bounds, noise, error_models, eta, eps_rule, combine, floor_tol, chunk):
    """Validate :func:`abstract_rows`' arguments; returns ``(errors, eta_fixed)`` (either may be None).

    ``errors`` is the :class:`~robust_imdp.abstraction.cell_bounds.CellErrors` of the GP route
    (``std_upper`` with ``error_models``), the only place the abstraction meets it."""
    if not isinstance(partition, (Partition, BoxPartition)):
        raise InvalidInputError(f"partition must be a Partition or a BoxPartition; got {type(partition).__name__}")
    if not isinstance(cell_bounds, CellBounds):
        raise InvalidInputError(f"cell_bounds must be a CellBounds; got {type(cell_bounds).__name__}")
    if not isinstance(noise, NoiseModel):
        raise InvalidInputError(f"noise must be a NoiseModel; got {type(noise).__name__}")
    if eps_rule not in ("optimized", "paper"):
        raise InvalidInputError(f"eps_rule must be 'optimized' or 'paper'; got {eps_rule!r}")
    if combine not in ("product", "union"):
        raise InvalidInputError(f"combine must be 'product' or 'union'; got {combine!r}")
    if not (0 < floor_tol < 1):
        raise InvalidInputError(f"floor_tol must lie in (0, 1); got {floor_tol!r}")
    N, d = cell_bounds.n_cells, cell_bounds.dim
    if (N != partition.n_cells and not chunk) or d != partition.dim:
        raise DimensionError(
            f"cell_bounds must have shape (n_modes, {partition.n_cells}, {partition.dim}) for this partition; "
            f"got {cell_bounds.image_lower.shape}"
        )
    if noise.dim != d:
        raise DimensionError(f"noise must have dimension {d}; got {noise.dim}")
    if (error_models is None) != (cell_bounds.std_upper is None):
        raise InvalidInputError(
            "error_models must be given exactly when cell_bounds.std_upper is given "
            f"(std_upper is {'None' if cell_bounds.std_upper is None else 'an array'}, "
            f"error_models is {'None' if error_models is None else 'given'})"
        )
    errors = CellErrors.from_gp(cell_bounds, error_models)
    eta_fixed = None
    if eta is not None:
        eta_fixed = np.asarray(eta, dtype=float)
        if eta_fixed.ndim == 0:
            eta_fixed = np.full(d, float(eta_fixed))
        if eta_fixed.shape != (d,):
            raise DimensionError(f"eta must be a float or have shape ({d},); got shape {eta_fixed.shape}")
        if not np.all(np.isfinite(eta_fixed)) or np.any(eta_fixed <= 0):
            raise InvalidInputError(f"eta must be finite and > 0 in every dimension; got {eta_fixed.tolist()}")
    elif eps_rule == "paper":
        eta_fixed = noise.default_eta()
    return errors, eta_fixed


def _list_targets(targets, cell_bounds, modes, combine):
    """Pass 1: per mode, the targets each row lists and its floor.

    A row lists every cell meeting the closed box ``[a - e_f, b + e_f] ⊇ Im ⊕ e_f`` (``e_f`` the
    row's floor pair ``eps_f + eta_f`` rounded up); every other cell is separated from it along
    some axis, so the floor ``1 - P_g(eps_f) P_v(eta_f)`` bounds them all.
    Returns ``(listings, n_listed (M, N), floors (M, N))``.
    """
    M, N = cell_bounds.n_modes, cell_bounds.n_cells
    listings = []
    n_listed = np.empty((M, N), dtype=np.int64)
    floors = np.empty((M, N))
    for u, md in enumerate(modes):
        a, b = cell_bounds.image_lower[u], cell_bounds.image_upper[u]
        ef = up(md.floor_eps + md.floor_eta)
        n_listed[u], listing = targets.list(down(a - ef), up(b + ef))  # closed box ⊇ Im ⊕ e_f
        listings.append(listing)
        floors[u] = _complement_up(_combine_down(md.floor_p, md.floor_pv, combine))
    return listings, n_listed, floors


@dataclass(frozen=True, eq=False)
class _RowArrays:
    """The state-major CSR arrays being filled (row ``q * M + u``; each row's last entry: the outside state)."""

    row_len: np.ndarray
    row_ptr: np.ndarray
    col: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    lower_eps: np.ndarray
    lower_eta: np.ndarray
    containing: np.ndarray

    @classmethod
    def allocate(cls, n_listed, d):
        M, N = n_listed.shape
        row_len = (n_listed + 1).T.ravel()  # rows q*M + u (the outside state's rows: assemble_abstraction)
        row_ptr = np.zeros(row_len.size + 1, dtype=np.int64)
        np.cumsum(row_len, out=row_ptr[1:])
        nnz = int(row_ptr[-1])
        return cls(row_len=row_len, row_ptr=row_ptr, col=np.empty(nnz, dtype=np.int64), lower=np.zeros(nnz),
                   upper=np.empty(nnz), lower_eps=np.full((M, N, d), np.nan), lower_eta=np.full((M, N, d), np.nan),
                   containing=np.full((M, N), -1, dtype=np.int64))


def _block_rows(out: _RowArrays, u, md, rows, cell_bounds, entries, partition, combine):
    """Pass 2 for the rows ``rows`` of mode ``u``: Thm 1's bounds of every listed entry and the outside state."""
    M = cell_bounds.n_modes
    a = cell_bounds.image_lower[u, rows]
    b = cell_bounds.image_upper[u, rows]
    er, cols = entries.row, entries.cell
    low_c, cont = _containing(out, u, md, rows, a, b, entries, partition, combine)
    up_out, low_out = _outside_bounds(md, rows, a, b, partition.space, combine, getattr(partition, "periodic", None))
    # -- listed cells: the separation bound of every entry (Thm 1, eq. upper-bound)
    G = np.zeros(er.size)
    P0, PV0 = md.top(rows)
    for j in range(a.shape[1]):
        P, PV = P0[er], PV0[er]
        P[:, j], PV[:, j] = entries.gap_p[j], entries.gap_pv[j]
        G = np.maximum(G, _combine_down(P, PV, combine))
    low = np.where(cols == cont[er], low_c[er], 0.0)
    # -- scatter into the state-major CSR (row = q * M + u), outside state last
    eoff = np.zeros(rows.size + 1, dtype=np.int64)
    np.cumsum(np.bincount(er, minlength=rows.size), out=eoff[1:])
    grow = rows * M + u
    dest = out.row_ptr[grow][er] + np.arange(er.size) - eoff[er]
    out.col[dest] = cols
    out.upper[dest] = _complement_up(G)
    out.lower[dest] = low
    dout = out.row_ptr[grow + 1] - 1
    out.col[dout] = partition.n_cells  # the outside state (global index)
    out.upper[dout] = up_out
    out.lower[dout] = low_out


def _containing(out: _RowArrays, u, md, rows, a, b, entries, partition, combine):
    """The cell containing ``Im(q)`` with positive margins and its lower bound (Thm 1, eq. lower-bound).

    Among a row's listed entries, the one with margins ``min(a_j - lo_j(q'), hi_j(q') - b_j) > 0``
    (rounded down) on every axis; at most one, since cells have disjoint interiors. Records the
    pair (eps, eta) behind the bound and the cell (-1 if none or if the bound is 0) in ``out``.
    Returns ``(low_c, cont)``, (B,) each.
    """
    er, cols = entries.row, entries.cell
    tlo, thi = partition.cells_lower, partition.cells_upper
    B, d = a.shape
    m = np.empty((er.size, d))
    periodic = getattr(partition, "periodic", None)
    circle = [j for j in range(d) if periodic is not None and periodic[j]]
    for j in range(d):
        if j not in circle:
            m[:, j] = down(np.minimum(a[er, j] - tlo[cols, j], thi[cols, j] - b[er, j]))
    # a periodic axis' margin (inside one translate of the cell) only where every other margin is
    # positive: elsewhere the entry is no containing cell whatever it is (set to 0, not > 0)
    cand = np.flatnonzero(np.all(m[:, [j for j in range(d) if j not in circle]] > 0, axis=1))
    for j in circle:
        m[:, j] = 0.0
        m[cand, j] = circle_margin(tlo[cols[cand], j], thi[cols[cand], j], a[er[cand], j], b[er[cand], j],
                                   float(partition.space.lower[j]), float(partition.space.upper[j]))
    hit = np.flatnonzero(np.all(m > 0, axis=1))  # at most one entry per row
    rin = er[hit]
    Pc, PVc = np.zeros((hit.size, d)), np.zeros((hit.size, d))
    for j in range(d):
        p_, pv_, e_, h_ = md.split(m[hit, j], rows[rin], j, paper_candidate=True)
        Pc[:, j], PVc[:, j] = p_, pv_
        out.lower_eps[u, rows[rin], j], out.lower_eta[u, rows[rin], j] = e_, h_
    low_in = _combine_down(Pc, PVc, combine) if hit.size else np.zeros(0)
    low_c = np.zeros(B)
    cont = np.full(B, -1, dtype=np.int64)
    low_c[rin] = low_in
    cont[rin] = np.where(low_in > 0, cols[hit], -1)
    out.containing[u, rows] = cont
    out.lower_eps[u, rows[cont < 0]] = np.nan
    out.lower_eta[u, rows[cont < 0]] = np.nan
    return low_c, cont


def _outside_bounds(md, rows, a, b, space, combine, periodic=None):
    """Bounds of the transition to the outside state (the corollary of Thm 1): ``(upper, lower)``, (B,) each.

    ``upper = 1 - P_g P_v 1[Im ⊕ e ⊆ X]`` (margins to X's faces) and ``lower = P_g P_v 1[Im ⊕ e ∩ X = ∅]``
    (the best axis separating the image from X, every other axis at its top candidates). A periodic
    axis is never left: the event needs no good event there (factors 1) and it separates nothing.
    """
    Xlo, Xhi = space.lower, space.upper
    B, d = a.shape
    PX, PVX = np.zeros((B, d)), np.zeros((B, d))
    g_out = np.zeros(B)
    for j in range(d):
        if periodic is not None and periodic[j]:
            PX[:, j], PVX[:, j] = 1.0, 1.0
            continue
        mX = down(np.minimum(a[:, j] - Xlo[j], Xhi[j] - b[:, j]))
        PX[:, j], PVX[:, j], _, _ = md.split(mX, rows, j, paper_candidate=True)
        gX = down(np.maximum(Xlo[j] - b[:, j], a[:, j] - Xhi[j]))
        sp, spv, _, _ = md.split(gX, rows, j, paper_candidate=False)
        g_out = np.maximum(g_out, _separated_best(md, sp, spv, rows, j))
    return _complement_up(_combine_down(PX, PVX, combine)), g_out


def select_rows(rows: AbstractionRows, cells) -> AbstractionRows:
    """The rows of ``cells`` (local indices into ``rows``' cells), in that order: a chunk of its own.

    With :func:`join_rows` this lets a refinement keep the rows of the cells it did not touch
    (a row depends only on its cell's image box and on the target cells it lists).
    """
    cells = np.asarray(cells, dtype=np.int64)
    M = rows.n_modes
    ptr = np.zeros(rows.row_len.size + 1, dtype=np.int64)
    np.cumsum(rows.row_len, out=ptr[1:])
    r = (cells[:, None] * M + np.arange(M)[None, :]).ravel()
    lens = rows.row_len[r]
    starts = np.repeat(ptr[r], lens)
    o = np.zeros(r.size + 1, dtype=np.int64)
    np.cumsum(lens, out=o[1:])
    idx = starts + np.arange(int(o[-1])) - np.repeat(o[:-1], lens)
    return AbstractionRows(
        row_len=lens, col=rows.col[idx], lower=rows.lower[idx], upper=rows.upper[idx], floor=rows.floor[r],
        lower_eps=rows.lower_eps[:, cells], lower_eta=rows.lower_eta[:, cells], containing=rows.containing[:, cells],
        floor_eps=rows.floor_eps[:, cells], floor_eta=rows.floor_eta[:, cells], n_modes=M, eps_rule=rows.eps_rule,
        combine=rows.combine, eta=rows.eta, floor_tol=rows.floor_tol, transitions=rows.transitions)


def join_rows(chunks) -> AbstractionRows:
    """Concatenate chunks of rows (in the order given) into one :class:`AbstractionRows`."""
    chunks = list(chunks)
    f = chunks[0]

    def cat(name, axis=0):
        return np.concatenate([getattr(c, name) for c in chunks], axis=axis)

    return AbstractionRows(
        row_len=cat("row_len"), col=cat("col"), lower=cat("lower"), upper=cat("upper"), floor=cat("floor"),
        lower_eps=cat("lower_eps", 1), lower_eta=cat("lower_eta", 1), containing=cat("containing", 1),
        floor_eps=cat("floor_eps", 1), floor_eta=cat("floor_eta", 1), n_modes=f.n_modes, eps_rule=f.eps_rule,
        combine=f.combine, eta=f.eta, floor_tol=f.floor_tol, transitions=_same_transitions(chunks))


def _same_transitions(chunks) -> str:
    """The chunks' common ``transitions`` (rows of both kinds in one IMDP would be a caller's bug)."""
    kinds = {getattr(c, "transitions", "thm1") for c in chunks}
    if len(kinds) != 1:
        raise InvalidInputError(f"chunks must all have the same transitions; got {sorted(kinds)}")
    return kinds.pop()


def assemble_abstraction(partition: Partition, chunks) -> Abstraction:
    """Concatenate :func:`abstract_rows` results (in cell order, covering every cell once) into the IMDP.

    Adds the absorbing outside state and checks every row (``sum(lower) <= 1 <= sum(upper) +
    floor x unlisted``).
    """
    chunks = list(chunks)
    if not chunks:
        raise InvalidInputError("chunks must hold at least one AbstractionRows; got none")
    M = chunks[0].n_modes
    N = partition.n_cells
    n_rows = sum(c.row_len.size for c in chunks)
    if n_rows != N * M or any(c.n_modes != M for c in chunks):
        raise DimensionError(f"chunks must cover the {N} cells x {M} modes of the partition once; got {n_rows} rows")
    row_len = np.concatenate([c.row_len for c in chunks] + [np.ones(M, dtype=np.int64)])
    row_ptr = np.zeros(row_len.size + 1, dtype=np.int64)
    np.cumsum(row_len, out=row_ptr[1:])
    col = np.concatenate([c.col for c in chunks] + [np.full(M, N, dtype=np.int64)])
    lower = np.concatenate([c.lower for c in chunks] + [np.ones(M)])
    upper = np.concatenate([c.upper for c in chunks] + [np.ones(M)])
    # outside-state rows: absorbing self-loops [1, 1], floor 0
    floor = np.concatenate([c.floor for c in chunks] + [np.zeros(M)])
    _check_rows(row_ptr, lower, upper, floor, N + 1, M)
    state_ptr = np.arange(0, (N + 1) * M + 1, M, dtype=np.int64)
    actions = np.tile(np.arange(M, dtype=np.int64), N + 1)
    imdp = IMDP.from_csr(state_ptr, row_ptr, col, lower, upper, floor=floor, actions=actions)
    first = chunks[0]

    def cat(name, axis=1):
        return np.concatenate([getattr(c, name) for c in chunks], axis=axis)

    return Abstraction(
        imdp=imdp, partition=partition, eps_rule=first.eps_rule, combine=first.combine, eta=first.eta,
        floor_tol=first.floor_tol, floor_eps=cat("floor_eps"), floor_eta=cat("floor_eta"),
        lower_eps=cat("lower_eps"), lower_eta=cat("lower_eta"), containing_cell=cat("containing"),
        nnz_per_row=row_len, transitions=_same_transitions(chunks),
    )


def _check_rows(row_ptr, lower, upper, floor, n_states, M):
    """Raise SoundnessError naming the first row with sum(lower) > 1 or sum(upper)+floor*unlisted < 1.

    Exact float sums are not available, so the comparison allows the summation error
    ``len(row) * u`` (entries are in [0, 1]); anything beyond is a bug.
    """
    n = np.diff(row_ptr)
    s_low = np.add.reduceat(lower, row_ptr[:-1]) if lower.size else np.zeros(n.size)
    s_up = np.add.reduceat(upper, row_ptr[:-1]) + floor * (n_states - n)
    tol = (n + 2) * 4 * U
    bad = np.flatnonzero((s_low > 1 + tol) | (s_up < 1 - tol))
    if bad.size:
        r = int(bad[0])
        raise SoundnessError(
            f"row {r} (state {r // M}, mode {r % M}): sum(lower) = {s_low[r]!r}, "
            f"sum(upper) + floor x unlisted = {s_up[r]!r}; expected sum(lower) <= 1 <= sum(upper) + floor x unlisted"
        )
