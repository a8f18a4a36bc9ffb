"""The factored interval MDP (models/factored.py) and its solver (solvers/factored.py): docs/factored.md.

Independent references, each with the tolerance it is accurate to:

* the operator against an exact-rational (``fractions.Fraction``) evaluation of the same nested
  O-maximisation: ``lower <= exact <= upper`` with no tolerance (the outward rounding must cover
  every rounding error), and ``upper - lower <= 1e-12`` (the rounding margins are ~1e-14);
* the operator against the exact optimum over the product set, by vertex enumeration of each
  axis's polytope (the objective is multilinear in the per-axis laws, so the optimum is at a
  combination of vertices): the factored value is never above it (minimising adversary) / below
  it (maximising), up to 1e-12 (float error of the enumeration, ~1e-15);
* the joint IMDP of ``to_joint`` solved by the joint solver and by Storm: where every axis lists
  its whole support the factored lower value is never below the joint one (and the optimistic
  upper never above), up to the solvers' precision (1e-9 requested; 1e-6 for Storm);
* closed forms on hand-built models (derivations in the comments).
"""

from __future__ import annotations

import inspect
import itertools
import warnings
from fractions import Fraction

import numpy as np
import pytest

from robust_imdp.errors import (ConvergenceWarning, DimensionError, InvalidInputError, InvalidIntervalError,
                                InvalidModelError, ResourceError)
from robust_imdp.models.factored import AxisMarginals, FactoredIMDP
from robust_imdp.solvers.api import evaluate_strategy, solve_reachability
from robust_imdp.solvers.factored import (factored_bellman, factored_operator, solve_factored_product,
                                          solve_factored_reachability)
from robust_imdp.solvers.product import solve_product
from robust_imdp.spec.api import to_dfa


# --------------------------------------------------------------------------- model builders
def random_axis(rng, n, M, N, k, periodic, *, rest=True, width=0.1, axis=None):
    """Per (mode, cell) a random law over k listed intervals, outside and rest, widened by up to
    ``width`` on each side (bounds clipped to [0, 1]): every interval vector contains that law."""
    start = rng.integers(0, n, size=(M, N))
    p = rng.dirichlet(np.ones(k + 2), size=(M, N))
    past = (start[..., None] + np.arange(k) >= n) & (not periodic)
    p[..., :k][past] = 0.0
    if periodic:
        p[..., k] = 0.0
    # rest mass only where an unlisted in-grid interval exists
    n_listed = k if periodic else (~past).sum(axis=-1)
    if not rest:
        p[..., k + 1] = 0.0
    else:
        p[..., k + 1] = np.where(n_listed < n, p[..., k + 1], 0.0)
    p /= p.sum(axis=-1, keepdims=True)
    w = rng.uniform(0.0, width, size=p.shape)
    lo, up = np.clip(p - w, 0.0, 1.0), np.clip(p + w, 0.0, 1.0)
    lo[..., :k][past] = 0.0
    up[..., :k][past] = 0.0
    if periodic:
        lo[..., k] = up[..., k] = 0.0
    up[..., k + 1] = np.where(p[..., k + 1] > 0, up[..., k + 1], 0.0)
    return AxisMarginals(n=n, periodic=periodic, start=start, lower=lo[..., :k], upper=up[..., :k],
                         out_lower=lo[..., k], out_upper=up[..., k], rest_upper=up[..., k + 1], axis=axis)


def random_model(rng, shape, M=2, *, rest=True, width=0.1, periodic=None, full=False):
    """A random FactoredIMDP; ``full``: every axis lists all its intervals from 0 (no rest)."""
    N = int(np.prod(shape))
    axes = []
    for i, n in enumerate(shape):
        per = bool(rng.random() < 0.4) if periodic is None else bool(periodic[i])
        if full:
            ax = random_axis(rng, n, M, N, n, per, rest=False, width=width, axis=i)
            ax = AxisMarginals(n=n, periodic=per, start=np.zeros((M, N), np.int64), lower=ax.lower, upper=ax.upper,
                               out_lower=ax.out_lower, out_upper=ax.out_upper, rest_upper=ax.rest_upper, axis=i)
        else:
            ax = random_axis(rng, n, M, N, int(rng.integers(1, n + 1)), per, rest=rest, width=width, axis=i)
        axes.append(ax)
    return FactoredIMDP(shape=tuple(shape), axes=tuple(axes))


def one_axis(n, start, lower, upper, out_lower, out_upper, rest_upper=None, periodic=False):
    """AxisMarginals of one mode from per-cell lists."""
    N = len(start)
    return AxisMarginals(n=n, periodic=periodic, start=np.array([start]), lower=np.array([lower], float),
                         upper=np.array([upper], float), out_lower=np.array([out_lower], float),
                         out_upper=np.array([out_upper], float),
                         rest_upper=np.zeros((1, N)) if rest_upper is None else np.array([rest_upper], float))


# --------------------------------------------------------------------------- references
def _greedy(vals, lo, up, adv_max, one):
    """Optimal p.vals over {lo <= p <= up, sum p = 1} (the O-maximisation), exact in ``one``'s type."""
    val = sum(l * v for l, v in zip(lo, vals))
    rem = one - sum(lo)
    if rem <= 0:
        return val
    for i in sorted(range(len(vals)), key=lambda i: vals[i], reverse=adv_max):
        c = up[i] - lo[i]
        if c >= rem:
            return val + rem * vals[i]
        val += c * vals[i]
        rem -= c
    return val


def exact_operator(model, w, adv_max):
    """The factored operator (nested O-maximisation, rest valued at min/max of w) in exact rational
    arithmetic on the floats given: (n_modes, n_cells) Fractions."""
    N, d = model.n_cells, model.dim
    ww = [x if isinstance(x, Fraction) else Fraction(float(x)) for x in w]
    w_rest = max(ww) if adv_max else min(ww)
    grid = np.array(ww[:N], dtype=object).reshape(model.shape)
    pos = [ax.positions() for ax in model.axes]

    def rec(u, q, axis, prefix):
        ax = model.axes[axis]
        vals, lo, up = [], [], []
        for j, p in enumerate(pos[axis][u, q]):
            if p < 0:
                continue
            vals.append(grid[tuple(prefix) + (p,)] if axis == d - 1 else rec(u, q, axis + 1, prefix + [p]))
            lo.append(Fraction(float(ax.lower[u, q, j])))
            up.append(Fraction(float(ax.upper[u, q, j])))
        vals += [ww[N], w_rest]
        lo += [Fraction(float(ax.out_lower[u, q])), Fraction(0)]
        up += [Fraction(float(ax.out_upper[u, q])), Fraction(float(ax.rest_upper[u, q]))]
        return _greedy(vals, lo, up, adv_max, Fraction(1))

    return np.array([[rec(u, q, 0, []) for q in range(N)] for u in range(model.n_modes)], dtype=object)


def axis_vertices(ax, u, q):
    """Vertices of axis ``ax``'s polytope at (mode u, cell q) with the unlisted intervals explicit:
    (n_vertices, n + 1) array over the grid intervals and (last) outside.  The constraints form a
    laminar family (singletons, the unlisted set, everything), so the greedy fillings over all
    orders of the entries are all the vertices (Edmonds)."""
    n = ax.n
    pos = ax.positions()[u, q]
    listed = [(int(p), float(ax.lower[u, q, j]), float(ax.upper[u, q, j])) for j, p in enumerate(pos) if p >= 0]
    unl = sorted(set(range(n)) - {p for p, _, _ in listed})
    ru = float(ax.rest_upper[u, q])
    entries = listed + [(n, float(ax.out_lower[u, q]), float(ax.out_upper[u, q]))]
    entries += [(p, 0.0, ru) for p in unl] if ru > 0 else []
    verts = set()
    for order in itertools.permutations(range(len(entries))):
        p = np.zeros(n + 1)
        for e, lo, _ in entries:
            p[e] += lo
        rem = 1.0 - p.sum()
        used_unl = 0.0
        for i in order:
            e, lo, up = entries[i]
            cap = up - lo
            if e in unl:
                cap = min(cap, ru - used_unl)
            c = max(0.0, min(cap, rem))
            p[e] += c
            rem -= c
            if e in unl:
                used_unl += c
        if rem <= 1e-12:
            verts.add(tuple(np.round(p, 15)))
    return np.array(sorted(verts))


def product_set_optimum(model, w, u, q, adv_max):
    """``min`` (or ``max``) over the product set of E[w] by vertex enumeration (module docstring)."""
    d = model.dim
    V = [axis_vertices(model.axes[i], u, q) for i in range(d)]
    # values on the extended grid: index n_i on any axis is outside
    ext = np.full(tuple(n + 1 for n in model.shape), float(w[-1]))
    ext[tuple(slice(0, n) for n in model.shape)] = np.asarray(w[:-1]).reshape(model.shape)
    best = None
    for combo in itertools.product(*[range(len(v)) for v in V]):
        t = ext
        for i in range(d - 1, -1, -1):  # contract the last axis first
            t = t @ V[i][combo[i]]
        best = t if best is None else (max(best, t) if adv_max else min(best, t))
    return float(best)


# --------------------------------------------------------------------------- the model type
def test_constructor_rejects_invalid_models_naming_axis_mode_and_cell():
    rng = np.random.default_rng(0)
    good = random_axis(rng, 3, 1, 4, 2, False, axis=0)
    kw = {a: getattr(good, a) for a in ("start", "lower", "upper", "out_lower", "out_upper", "rest_upper")}

    def axis(**change):
        return AxisMarginals(n=3, periodic=False, axis=0, **{**kw, **change})

    lo = kw["lower"].copy()
    lo[0, 2, 1] = kw["upper"][0, 2, 1] + 0.1
    with pytest.raises(InvalidIntervalError, match=r"axis 0: \(mode 0, cell 2\), listed entry 1"):
        axis(lower=lo)
    with pytest.raises(InvalidIntervalError, match=r"axis 0: \(mode 0, cell 1\): sum of lower bounds"):
        lo = kw["lower"].copy()
        lo[0, 1] = 0.6
        axis(lower=lo, upper=np.maximum(kw["upper"], lo))
    with pytest.raises(InvalidIntervalError, match=r"sum of upper bounds .* < 1"):
        axis(upper=kw["lower"], out_upper=kw["out_lower"], rest_upper=np.zeros((1, 4)))
    with pytest.raises(DimensionError, match="upper must have shape"):
        axis(upper=kw["upper"][:, :3])
    with pytest.raises(InvalidModelError, match=r"start\(mode 0, cell 0\) = 3 is not a grid interval"):
        st = kw["start"].copy()
        st[0, 0] = 3
        axis(start=st)
    with pytest.raises(InvalidIntervalError, match="past the last interval"):
        st = np.full((1, 4), 2)
        up = np.full((1, 4, 2), 0.6)
        axis(start=st, lower=np.zeros((1, 4, 2)), upper=up)
    with pytest.raises(InvalidIntervalError, match="periodic axis has no outside"):
        AxisMarginals(n=3, periodic=True, **kw)
    with pytest.raises(InvalidModelError, match="k <= n"):
        AxisMarginals(n=1, periodic=True, start=np.zeros((1, 1), int), lower=np.zeros((1, 1, 2)),
                      upper=np.ones((1, 1, 2)), out_lower=np.zeros((1, 1)), out_upper=np.zeros((1, 1)),
                      rest_upper=np.zeros((1, 1)))
    with pytest.raises(InvalidIntervalError, match="rest_upper"):
        axis(rest_upper=np.full((1, 4), np.nan))
    # the model: one AxisMarginals per axis of the right size
    with pytest.raises(DimensionError, match=r"axes\[0\].n = 3 must equal shape\[0\] = 2"):
        FactoredIMDP(shape=(2, 2), axes=(good, good))
    with pytest.raises(DimensionError, match="one AxisMarginals per axis"):
        FactoredIMDP(shape=(2, 2), axes=(good,))
    with pytest.raises(InvalidModelError, match=r"axes\[1\] says it is the marginals of axis 0"):
        FactoredIMDP(shape=(3, 3), axes=(random_axis(rng, 3, 1, 9, 2, False, axis=0),
                                         random_axis(rng, 3, 1, 9, 2, False, axis=0)))


def test_sizes_and_save_load_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    m = random_model(rng, (3, 4), M=2)
    assert m.n_states == 13 and m.n_modes == 2 and m.outside_state == 12
    assert m.entries_per_row == sum(k + 1 for k in m.k)
    assert m.numbers_per_row == sum(2 * k + 4 for k in m.k)
    assert m.nbytes == sum(ax.start.nbytes + ax.lower.nbytes * 2 + ax.out_lower.nbytes * 3 for ax in m.axes)
    path = tmp_path / "model.npz"
    m.save(path)
    back = FactoredIMDP.load(path)
    assert back.shape == m.shape and back.periodic == m.periodic
    for a, b in zip(m.axes, back.axes):
        for name in ("start", "lower", "upper", "out_lower", "out_upper", "rest_upper"):
            assert np.array_equal(getattr(a, name), getattr(b, name))
    # a file that is not a model: the error names the file
    np.savez(tmp_path / "other.npz", x=np.zeros(2))
    with pytest.raises(InvalidModelError, match="other.npz: not a FactoredIMDP file"):
        FactoredIMDP.load(tmp_path / "other.npz")
    # a corrupted bound is refused on load, naming the file and the axis
    with np.load(path) as z:
        data = dict(z)
    data["axis1_upper"] = data["axis1_upper"] * 0.0
    np.savez(tmp_path / "bad.npz", **data)
    with pytest.raises(InvalidIntervalError, match=r"bad.npz: axis 1: \(mode 0, cell 0\), listed entry"):
        FactoredIMDP.load(tmp_path / "bad.npz")


# --------------------------------------------------------------------------- to_joint
def _sample_product_laws(model, u, q, rng, n):
    """``n`` random product laws of (mode u, cell q): per axis a random vertex (greedy in a random
    order, unlisted mass spread over the unlisted intervals), outer product over the axes.
    Returns (n, n_cells + 1) joint laws (last: outside)."""
    laws = []
    for _ in range(n):
        per_axis = []
        for ax in model.axes:
            V = axis_vertices(ax, u, q)
            per_axis.append(V[rng.integers(len(V))])
        ext = per_axis[0]
        for p in per_axis[1:]:
            ext = np.multiply.outer(ext, p)
        inside = ext[tuple(slice(0, n_) for n_ in model.shape)].reshape(-1)
        out = 1.0 - np.prod([1.0 - p[-1] for p in per_axis])  # exactly 0 when no axis can leave X
        laws.append(np.r_[inside, out])
    return np.array(laws)


def test_to_joint_rows_contain_every_product_law():
    rng = np.random.default_rng(2)
    for shape in [(3,), (2, 3), (3, 2, 2)]:
        m = random_model(rng, shape, M=2, rest=True, width=0.15)
        J = m.to_joint()
        assert J.n_states == m.n_states and J.n_choices == 2 * m.n_cells + 1
        lo, up = J.to_dense()  # unlisted cells at the floor
        for q in range(m.n_cells):
            for u in range(2):
                r = q * 2 + u
                laws = _sample_product_laws(m, u, q, rng, 25)
                # 1e-15: the float error of the sampled products (a few ulps of numbers <= 1)
                assert np.all(laws >= lo[r] - 1e-15) and np.all(laws <= up[r] + 1e-15), (shape, q, u)


def test_to_joint_bounds_are_the_documented_products_rounded_outward():
    # each bound against its formula in exact rational arithmetic: lower <= exact <= upper
    rng = np.random.default_rng(3)
    m = random_model(rng, (3, 3), M=1, rest=True, width=0.2, periodic=(False, True))
    J = m.to_joint()
    F = Fraction
    for q in range(m.n_cells):
        r = q
        cols = J.col[J.row_ptr[r]:J.row_ptr[r + 1]]
        lo = J.lower[J.row_ptr[r]:J.row_ptr[r + 1]]
        up = J.upper[J.row_ptr[r]:J.row_ptr[r + 1]]
        pos = [ax.positions()[0, q] for ax in m.axes]
        in_lo, in_hi, m_side, rest = [], [], [], []
        for i, ax in enumerate(m.axes):
            L = [F(float(x)) for x, p in zip(ax.lower[0, q], pos[i]) if p >= 0]
            H = [F(float(x)) for x, p in zip(ax.upper[0, q], pos[i]) if p >= 0]
            ol, ou, ru = (F(float(getattr(ax, a)[0, q])) for a in ("out_lower", "out_upper", "rest_upper"))
            in_lo.append(min(1, max(1 - ou, sum(L))))
            in_hi.append(min(1 - ol, sum(H) + ru))
            has_rest = ru > 0 and (pos[i] >= 0).sum() < ax.n
            rest.append(ru if has_rest else F(0))
            m_side.append(max(max(H), ru if has_rest else F(0)))
        for c, l_, h_ in zip(cols, lo, up):
            if c == m.n_cells:  # outside: 1 - prod(in_hi) <= p(out) <= 1 - prod(in_lo)
                assert F(l_) <= 1 - in_hi[0] * in_hi[1] and F(h_) >= 1 - in_lo[0] * in_lo[1]
                assert F(h_) - F(l_) <= (in_hi[0] * in_hi[1] - in_lo[0] * in_lo[1]) + F(1, 10**13)
                continue
            j = np.unravel_index(c, m.shape)
            ex_lo = ex_hi = F(1)
            for i, ax in enumerate(m.axes):
                jj = int(np.flatnonzero(pos[i] == j[i])[0])
                ex_lo *= F(float(ax.lower[0, q, jj]))
                ex_hi *= F(float(ax.upper[0, q, jj]))
            assert F(l_) <= ex_lo and F(h_) >= ex_hi
            assert ex_lo - F(l_) <= F(1, 10**14) and F(h_) - ex_hi <= F(1, 10**14)  # tight: rounding only
        floor = max(rest[0] * m_side[1], rest[1] * m_side[0])
        assert F(J.floor[r]) >= floor and F(J.floor[r]) - floor <= F(1, 10**14)


def test_to_joint_refuses_models_above_the_entry_limit():
    m = random_model(np.random.default_rng(4), (3, 3), M=1)
    with pytest.raises(ResourceError, match="max_entries"):
        m.to_joint(max_entries=5)


# --------------------------------------------------------------------------- the operator
@pytest.mark.parametrize("seed", range(4))
def test_operator_brackets_its_exact_rational_value(seed):
    rng = np.random.default_rng(10 + seed)
    for shape in [(4,), (3, 4), (3, 2, 3)]:
        m = random_model(rng, shape, M=2, rest=True, width=0.15)
        w = rng.random(m.n_states)
        if seed % 2:
            w = np.round(w, 1)  # ties between values
        for adv in ("pessimistic", "optimistic"):
            lo = factored_bellman(m, w, adversary=adv, rounding="down")
            up = factored_bellman(m, w, adversary=adv, rounding="up")
            ex = exact_operator(m, w, adv == "optimistic")
            below = [(u, q) for u in range(2) for q in range(m.n_cells) if not Fraction(lo[u, q]) <= ex[u, q]]
            above = [(u, q) for u in range(2) for q in range(m.n_cells) if not Fraction(up[u, q]) >= ex[u, q]]
            assert not below and not above, (shape, adv, below[:3], above[:3])
            assert np.max(up - lo) <= 1e-12  # the rounding margins are a few 1e-14


def test_operator_with_shared_marginals_matches_the_exact_value():
    # a linear system x' = A x + w on 4^3 cells: axis i's marginal depends on the cell's coordinates
    # i and i+1 only, so the prefix tree shares work; the shared sweep must give the exact value
    from scipy.special import ndtr
    d, n, sigma = 3, 4, 0.3
    A = 0.7 * np.eye(d) - 0.1 * np.roll(np.eye(d), 1, axis=1)
    edges = np.linspace(-1, 1, n + 1)
    idx = np.indices((n,) * d).reshape(d, -1)
    cl, ch = edges[idx], edges[idx + 1]
    axes = []
    for i in range(d):
        ylo = np.clip(A[i], 0, None) @ cl + np.clip(A[i], None, 0) @ ch
        yhi = np.clip(A[i], 0, None) @ ch + np.clip(A[i], None, 0) @ cl
        f = lambda a, b, y: ndtr((b - y) / sigma) - ndtr((a - y) / sigma)  # noqa: E731
        L = np.stack([np.minimum(f(a, b, ylo), f(a, b, yhi)) for a, b in zip(edges[:-1], edges[1:])], -1)
        H = np.stack([f(a, b, np.clip((a + b) / 2, ylo, yhi)) for a, b in zip(edges[:-1], edges[1:])], -1)
        fin_lo, fin_hi = np.minimum(f(-1, 1, ylo), f(-1, 1, yhi)), f(-1, 1, np.clip(0.0, ylo, yhi))
        axes.append(AxisMarginals(n=n, periodic=False, start=np.zeros((1, n ** d), int), lower=L[None] * 0.999,
                                  upper=np.minimum(H[None] * 1.001, 1), out_lower=(1 - fin_hi)[None] * 0.999,
                                  out_upper=np.minimum((1 - fin_lo)[None] * 1.001, 1), rest_upper=np.zeros((1, n ** d))))
    m = FactoredIMDP(shape=(n,) * d, axes=tuple(axes))
    op = factored_operator(m)
    assert op.n_marginals == (16, 16, 16) and op.groups == (16, 64, 64)
    assert op.work < op.unshared_work
    rng = np.random.default_rng(5)
    w = rng.random(m.n_states)
    for adv in ("pessimistic", "optimistic"):
        lo = factored_bellman(m, w, adversary=adv, rounding="down")
        up = factored_bellman(m, w, adversary=adv, rounding="up")
        ex = exact_operator(m, w, adv == "optimistic")
        assert all(Fraction(lo[0, q]) <= ex[0, q] <= Fraction(up[0, q]) for q in range(m.n_cells))
        assert np.max(up - lo) <= 1e-12


@pytest.mark.slow
@pytest.mark.parametrize("rest", [True, False])
@pytest.mark.parametrize("shape", [(2, 3), (3, 2), (2, 2, 2)])
def test_operator_is_a_relaxation_of_the_product_set(shape, rest):
    # never above the product set's minimum (sound), never below its maximum; how far: printed (with
    # rest mass most of the gap is the rest entry valued at the global min / max; without it, the
    # adversary's choice per outer outcome; measured: <= 1e-13 on these 2-D models, 0.033 in 3-D)
    rng = np.random.default_rng(sum(shape))
    m = random_model(rng, shape, M=1, rest=rest, width=0.2)
    gaps = []
    for trial in range(3):
        w = rng.random(m.n_states)
        for adv in ("pessimistic", "optimistic"):
            f = factored_bellman(m, w, adversary=adv, rounding="down" if adv == "pessimistic" else "up")
            for q in range(m.n_cells):
                ex = product_set_optimum(m, w, 0, q, adv == "optimistic")
                if adv == "pessimistic":
                    assert f[0, q] <= ex + 1e-12, (q, f[0, q], ex)
                    gaps.append(ex - f[0, q])
                else:
                    assert f[0, q] >= ex - 1e-12, (q, f[0, q], ex)
                    gaps.append(f[0, q] - ex)
    print(f"factored vs product set on {shape} (rest mass: {rest}): max gap {max(gaps):.3g}, mean {np.mean(gaps):.3g}")


def test_operator_is_exact_on_a_box_target_closed_form():
    # One step to the box A_0 x A_1 (value 1 there, 0 elsewhere and outside): the nested reduction
    # gives m_0 m_1 with m_i the least mass axis i can put on A_i,
    #   m_i = max(sum_{A_i} lower, 1 - sum_{not A_i} upper - out_upper - rest_upper),
    # which is also the minimum over the product set (a product of per-axis masses).  Optimistic,
    # without rest mass: M_0 M_1 with M_i = min(sum_{A_i} upper, 1 - sum_{not A_i} lower - out_lower)
    # (with rest mass the rest counts the largest value 1 at every level: no product form).
    rng = np.random.default_rng(6)
    A = [np.array([False, True, True]), np.array([False, False, True])]
    for rest in (True, False):
        m = random_model(rng, (3, 3), M=2, rest=rest, width=0.15, periodic=(False, False))
        _check_box_target(m, A, exact_too=not rest)


def _check_box_target(m, A, exact_too):
    w = np.zeros(m.n_states)
    w[:-1] = np.logical_and.outer(*A).reshape(-1)
    lo = factored_bellman(m, w, adversary="pessimistic", rounding="down")
    up = factored_bellman(m, w, adversary="optimistic", rounding="up")
    for u in range(2):
        for q in range(m.n_cells):
            mm, MM = 1.0, 1.0
            for i, ax in enumerate(m.axes):
                pos = ax.positions()[u, q]
                inA = np.array([p >= 0 and A[i][p] for p in pos])
                ok = pos >= 0
                L, H = ax.lower[u, q], ax.upper[u, q]
                mm *= max(L[inA].sum(), 1 - H[ok & ~inA].sum() - ax.out_upper[u, q] - ax.rest_upper[u, q])
                MM *= min(H[inA].sum(), 1 - L[ok & ~inA].sum() - ax.out_lower[u, q])
            # 1e-13: the float sums of the formula and the kernel's outward margins (~1e-14)
            assert lo[u, q] == pytest.approx(mm, abs=1e-13) and lo[u, q] <= mm + 1e-15
            if exact_too:
                assert up[u, q] == pytest.approx(MM, abs=1e-13) and up[u, q] >= MM - 1e-15
            if exact_too and u == 0 and q < 4:  # without rest mass the product set attains it (vertex enumeration)
                assert product_set_optimum(m, w, u, q, False) == pytest.approx(mm, abs=1e-12)
                assert product_set_optimum(m, w, u, q, True) == pytest.approx(MM, abs=1e-12)


def test_k_step_bracket_contains_the_exact_rational_k_step_value():
    # V_t = max over modes of the exact operator (Fractions) on V_{t-1}, targets 1, outside 0: the
    # k-step bracket (one plain sweep per step and a global rounding budget) must contain it
    rng = np.random.default_rng(7)
    m = random_model(rng, (3, 3), M=2, rest=True, width=0.15)
    N = m.n_cells
    target = np.zeros(N + 1, bool)
    target[[2, 6]] = True
    for adv in ("pessimistic", "optimistic"):
        for objective in ("maximize", "minimize"):
            r = solve_factored_reachability(m, target, avoid=[N], adversary=adv, objective=objective, horizon=3)
            adv_max = (adv == "optimistic") == (objective == "maximize")
            V = [Fraction(int(t)) for t in target]
            for _ in range(3):
                rows = exact_operator(m, V, adv_max)
                best = [max(rows[:, q]) if objective == "maximize" else min(rows[:, q]) for q in range(N)]
                V = [Fraction(1) if target[q] else best[q] for q in range(N)] + [Fraction(0)]
            bad = [q for q in range(N + 1) if not Fraction(r.lower[q]) <= V[q] <= Fraction(r.upper[q])]
            assert not bad, (adv, objective, bad)
            assert r.precision <= 1e-10


# --------------------------------------------------------------------------- closed forms of the solver
def _chain():
    """1-D, 3 cells: from cell q < 2 move to q + 1 w.p. [0.6, 0.8], stay w.p. [0.1, 0.3], leave X
    w.p. 0.1; cell 2 (the target) stays w.p. 0.9."""
    return FactoredIMDP(shape=(3,), axes=(one_axis(
        3, start=[0, 1, 1], lower=[[0.1, 0.6], [0.1, 0.6], [0.0, 0.9]], upper=[[0.3, 0.8], [0.3, 0.8], [0.0, 0.9]],
        out_lower=[0.1] * 3, out_upper=[0.1] * 3),))


def test_chain_closed_form_values():
    m = _chain()
    target = [2]
    # pessimistic: the free 0.2 goes to the lowest value. Cell 1: V = 0.6 + 0.3 V (stay is below the
    # target) -> V_1 = 0.6, V_2 = 0.78, V = 6/7. Cell 0: V = 0.6 V(1) + 0.3 V(0) -> V_2 = 0.36, V = 36/49.
    r2 = solve_factored_reachability(m, target, avoid=[3], horizon=2)
    # k steps: the bracket's global rounding budget is ~1e-12 per step (ROW_SUM_TOL per level)
    np.testing.assert_allclose(r2.lower[:2], [0.36, 0.78], atol=1e-10)
    assert r2.precision <= 1e-10
    assert np.all(r2.lower <= r2.upper) and r2.lower[0] <= 0.36 <= r2.upper[0]
    r = solve_factored_reachability(m, target, avoid=[3], precision=1e-12)
    assert r.converged
    np.testing.assert_allclose(r.lower[:2], [36 / 49, 6 / 7], atol=1e-11)
    assert r.lower[0] <= 36 / 49 <= r.upper[0] and r.lower[1] <= 6 / 7 <= r.upper[1]
    # optimistic: the free 0.2 goes to the highest value. Cell 1: V = 0.8 + 0.1 V -> 8/9; cell 0:
    # V = 0.8 V(1) + 0.1 V(0) -> 64/81
    o = solve_factored_reachability(m, target, avoid=[3], adversary="optimistic", precision=1e-12)
    assert o.lower[0] <= 64 / 81 <= o.upper[0] and o.lower[1] <= 8 / 9 <= o.upper[1]
    np.testing.assert_allclose(o.upper[:2], [64 / 81, 8 / 9], atol=1e-11)
    # the joint expansion of a 1-D model is the same IMDP: same values
    j = solve_reachability(m.to_joint(), target, avoid=[3], precision=1e-12)
    np.testing.assert_allclose(j.lower, r.lower, atol=1e-11)


def test_unbounded_upper_side_reports_an_end_component_honestly():
    # cell 0: mode 0 stays for ever, mode 1 reaches the target (cell 1) or leaves X w.p. 1/2 each.
    # Maximising: value 1/2; the upper iterates keep 1 through the self-loop (no deflation), so the
    # result must say converged=False with the achieved gap 1/2, and stay sound.
    ax = AxisMarginals(n=2, periodic=False, start=np.array([[0, 1], [1, 1]]),
                       lower=np.array([[[1.0], [1.0]], [[0.5], [1.0]]]), upper=np.array([[[1.0], [1.0]], [[0.5], [1.0]]]),
                       out_lower=np.array([[0.0, 0.0], [0.5, 0.0]]), out_upper=np.array([[0.0, 0.0], [0.5, 0.0]]),
                       rest_upper=np.zeros((2, 2)))
    m = FactoredIMDP(shape=(2,), axes=(ax,))
    with pytest.warns(ConvergenceWarning, match="sound but loose"):
        r = solve_factored_reachability(m, [1], avoid=[2], precision=1e-9, max_iterations=50)
    assert not r.converged and r.precision == pytest.approx(0.5, abs=1e-12)
    assert r.lower[0] == pytest.approx(0.5, abs=1e-12) and r.upper[0] == 1.0 and r.strategy[0] == 1
    # a minimising controller can stay away for ever: the support pre-computation proves value 0
    mn = solve_factored_reachability(m, [1], avoid=[2], objective="minimize", precision=1e-9)
    assert mn.converged and mn.upper[0] == 0.0 and mn.strategy[0] == 0


def test_maximising_strategy_makes_progress_among_tied_modes():
    # cell 0: mode 0 stays for ever, mode 1 reaches the target for sure. Both rows have lower value 1
    # at the fixed point (a tie); the first-row choice would stay for ever (value 0). The progress
    # attractor must pick mode 1, and evaluating the strategy gives 1.
    ax = AxisMarginals(n=2, periodic=False, start=np.array([[0, 1], [1, 1]]),
                       lower=np.ones((2, 2, 1)), upper=np.ones((2, 2, 1)), out_lower=np.zeros((2, 2)),
                       out_upper=np.zeros((2, 2)), rest_upper=np.zeros((2, 2)))
    m = FactoredIMDP(shape=(2,), axes=(ax,))
    r = solve_factored_reachability(m, [1], avoid=[2])
    assert r.lower[0] >= 1.0 - 1e-12 and r.strategy[0] == 1  # 1 up to the outward rounding (~1e-14)
    ev = solve_factored_reachability(m, [1], avoid=[2], strategy=r.strategy)
    assert ev.lower[0] >= 1.0 - 1e-12
    bad = solve_factored_reachability(m, [1], avoid=[2], strategy=np.array([0, 0, 0]))
    assert bad.upper[0] == 0.0  # the staying mode never reaches (support pre-computation)


# --------------------------------------------------------------------------- against the joint solvers
@pytest.mark.slow
@pytest.mark.parametrize("seed", range(3))
def test_factored_values_lie_between_the_joint_imdp_and_the_truth(seed):
    # every axis lists its whole support (rest 0): the factored adversary's law lies in the joint
    # polytope, so pessimistic factored >= joint and optimistic factored <= joint (docs/factored.md)
    rng = np.random.default_rng(20 + seed)
    shape = [(3, 3), (2, 3, 2), (4, 3)][seed]
    m = random_model(rng, shape, M=2, width=0.15, full=seed != 1, rest=False)
    J = m.to_joint()
    n = m.n_states
    target = np.zeros(n, bool)
    target[rng.choice(m.n_cells, 2, replace=False)] = True
    avoid = np.zeros(n, bool)
    avoid[-1] = True
    for objective in ("maximize", "minimize"):
        for adversary in ("pessimistic", "optimistic"):
            for horizon in (None, 4):
                kw = dict(avoid=avoid, adversary=adversary, objective=objective, horizon=horizon, precision=1e-10)
                f = solve_factored_reachability(m, target, **kw)
                j = solve_reachability(J, target, **kw)
                adv_max = (adversary == "optimistic") == (objective == "maximize")
                if adv_max:
                    assert np.all(f.upper <= j.upper + 1e-9), (objective, adversary, horizon)
                else:
                    assert np.all(f.lower >= j.lower - 1e-9), (objective, adversary, horizon)
                # the strategy achieves the reported side
                ev = solve_factored_reachability(m, target, avoid=avoid, adversary=adversary, objective=objective,
                                                 horizon=horizon, strategy=f.strategy, precision=1e-10)
                if objective == "maximize":
                    assert np.all(ev.lower >= f.lower - 1e-8)
                else:
                    assert np.all(ev.upper <= f.upper + 1e-8)


@pytest.mark.stormpy
def test_factored_lower_value_is_never_below_storms_joint_value():
    from robust_imdp.io.formats import storm_reachability
    pytest.importorskip("stormpy")
    rng = np.random.default_rng(30)
    m = random_model(rng, (3, 3), M=2, width=0.15, full=True, rest=False)
    J = m.to_joint()
    target = np.zeros(m.n_states, bool)
    target[[1, 5]] = True
    avoid = np.zeros(m.n_states, bool)
    avoid[-1] = True
    for horizon in (3, 8):  # Storm's unbounded robust VI refuses intervals with lower bound 0
        for adversary in ("pessimistic", "optimistic"):
            storm = storm_reachability(J, target, avoid=avoid, adversary=adversary, horizon=horizon, precision=1e-10)
            f = solve_factored_reachability(m, target, avoid=avoid, adversary=adversary, horizon=horizon,
                                            precision=1e-10)
            if adversary == "pessimistic":
                assert np.all(f.lower >= storm - 1e-6)  # Storm stops on a 1e-10 residual: 1e-6 as elsewhere
            else:
                assert np.all(f.upper <= storm + 1e-6)


def test_product_matches_the_joint_product_ordering_and_synthesis_contract():
    rng = np.random.default_rng(40)
    dfa = to_dfa("(!b U a)", ["a", "b"])
    m = random_model(rng, (3, 3), M=3, width=0.15, full=True, rest=False)
    J = m.to_joint()
    N = m.n_cells
    letters = np.r_[rng.integers(0, 4, size=N), 0]
    for horizon in (None, 4):
        kw = dict(avoid=[N], horizon=horizon, precision=1e-10)
        opt = solve_factored_product(m, letters, dfa, adversary="optimistic", **kw)
        rob = solve_factored_product(m, letters, dfa, adversary="pessimistic", tie_break=opt, **kw)
        ev = solve_factored_product(m, letters, dfa, adversary="pessimistic", strategy=rob.strategy, **kw)
        ev_up = solve_factored_product(m, letters, dfa, adversary="optimistic", strategy=rob.strategy, **kw)
        jr = solve_product(J, letters, dfa, adversary="pessimistic", **kw)
        jo = solve_product(J, letters, dfa, adversary="optimistic", **kw)
        assert rob.strategy.shape == ((dfa.n_states, N + 1) if horizon is None else (4, dfa.n_states, N + 1))
        assert np.all(rob.initial_lower >= jr.initial_lower - 1e-9)
        assert np.all(opt.initial_upper <= jo.initial_upper + 1e-9)
        assert np.all(ev.initial_lower >= rob.initial_lower - 1e-8)  # the strategy keeps the optimal lower value
        assert np.all(ev.initial_lower <= ev_up.initial_upper) and np.all(ev_up.initial_upper <= opt.initial_upper + 1e-9)
        np.testing.assert_array_equal(rob.initial_state, jr.initial_state)


def test_safety_reading_is_the_complement_of_a_minimised_reach():
    rng = np.random.default_rng(41)
    dfa = to_dfa("G !b", ["b"])
    m = random_model(rng, (3, 3), M=2, width=0.15, full=True, rest=False)
    N = m.n_cells
    letters = np.r_[rng.integers(0, 2, size=N), 0]
    bad = np.r_[letters[:N] == 1, True]  # the cells labelled b and the outside state
    for horizon in (None, 5):
        s = solve_factored_product(m, letters, dfa, avoid=[N], horizon=horizon, semantics="safety", precision=1e-10)
        r = solve_factored_reachability(m, bad, objective="minimize", adversary="pessimistic", horizon=horizon,
                                        precision=1e-10)
        # satisfaction from cell q = 1 - P(reach bad) from q, with q's own label read first
        one_minus = np.where(bad, 0.0, 1.0 - r.upper)
        # k steps: both within their rounding budget (~1e-11); unbounded: within the precision 1e-10
        np.testing.assert_allclose(s.initial_lower, one_minus, atol=1e-9)
        assert np.all(s.initial_lower <= s.initial_upper)
    if "semantics" in inspect.signature(solve_product).parameters:  # the joint product's safety reading
        J = m.to_joint()
        for horizon in (None, 5):
            js = solve_product(J, letters, dfa, avoid=[N], horizon=horizon, semantics="safety", precision=1e-10)
            fs = solve_factored_product(m, letters, dfa, avoid=[N], horizon=horizon, semantics="safety",
                                        precision=1e-10)
            assert np.all(fs.initial_lower >= js.initial_lower - 1e-9)


# --------------------------------------------------------------------------- invalid input
def test_solver_rejects_bad_input_with_clear_errors():
    m = _chain()
    dfa = to_dfa("F a", ["a"])
    with pytest.raises(DimensionError, match=r"letters must have shape \(4,\)"):
        solve_factored_product(m, np.zeros(3, int), dfa)
    with pytest.raises(InvalidInputError, match="control must be 'maximize' or 'minimize'"):
        solve_factored_product(m, np.zeros(4, int), dfa, control="sideways")
    with pytest.raises(InvalidInputError, match="not a mode"):
        solve_factored_product(m, np.zeros(4, int), dfa, strategy=np.ones((dfa.n_states, 4), int))
    with pytest.raises(InvalidInputError, match="outside state 3 has one choice"):
        solve_factored_reachability(m, [2], strategy=np.array([0, 0, 0, 1]))
    with pytest.raises(InvalidInputError, match="tie_break applies to a maximising controller"):
        opt = solve_factored_product(m, np.zeros(4, int), dfa, adversary="optimistic")
        solve_factored_product(m, np.zeros(4, int), dfa, control="minimize", tie_break=opt)
    with pytest.raises(InvalidInputError, match="semantics must be"):
        solve_factored_product(m, np.zeros(4, int), dfa, semantics="liveness")
    with pytest.raises(InvalidInputError, match="adversary must be one of"):
        solve_factored_reachability(m, [2], adversary="neutral")
    with pytest.raises(DimensionError, match=r"values must have shape \(4,\)"):
        factored_bellman(m, np.zeros(3))
    with pytest.raises(InvalidInputError, match="model must be a FactoredIMDP"):
        solve_factored_reachability(m.to_joint(), [2])
    with pytest.raises(DimensionError, match="needs horizon=2"):
        solve_factored_reachability(m, [2], strategy=np.zeros((2, 4), int))


def test_evaluate_strategy_agrees_with_the_joint_solver_on_one_dimension():
    # 1-D: the factored model is the joint IMDP (no relaxation with rest 0): fixed-strategy values agree
    m = _chain()
    J = m.to_joint()
    st = np.zeros(4, int)
    for adversary in ("pessimistic", "optimistic"):
        f = solve_factored_reachability(m, [2], avoid=[3], adversary=adversary, strategy=st, precision=1e-12)
        j = evaluate_strategy(J, [2], st, avoid=[3], adversary=adversary, precision=1e-12)
        np.testing.assert_allclose(f.lower, j.lower, atol=1e-10)
        np.testing.assert_allclose(f.upper, j.upper, atol=1e-10)


def test_operator_is_cached_per_model_and_reports_its_work():
    m = _chain()
    op = factored_operator(m)
    assert factored_operator(m) is op
    assert op.n_marginals == (3,) and op.groups == (3,) and op.work == 2 * 3 and op.nbytes > 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solve_factored_reachability(m, [2], avoid=[3], horizon=3)
