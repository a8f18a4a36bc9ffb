"""Known nonlinear dynamics ``f_u(x)``: a safe expression parser and certified image bounds.

The paper's system is ``x' = f_u(x) + g_u(x) + v`` with ``f_u`` any known continuous function.
This module turns ``f_u``, given as one expression per component in ``x1..xn`` (or as a casadi
expression of a casadi symbol vector), into

* ``KnownDynamics.evaluate(x)``: the floating-point values, vectorised over points;
* ``KnownDynamics.image_bounds(lower, upper)``: certified, outward-rounded enclosures of every
  component over every box (natural interval extension intersected with the centred form, boxes
  bisected where the dependency effect is large);
* ``KnownDynamics.residual_rounding_bound(x)`` / ``residuals(x, x_next)``: sound bounds on the
  rounding error of the computed values, for the data-noise allowance of ``y = x_next - f(x)``;
* ``KnownDynamics.achieved_range(lower, upper)``: values attained by dense sampling plus local
  optimisation (IPOPT through casadi), to report the gap to the certified range.

Grammar, soundness argument and margins: ``docs/known_dynamics.md``.  Expressions are never
passed to ``eval``: a recursive-descent parser accepts exactly the grammar below and builds a
tape (a list of instructions in topological order, common subexpressions shared).  The parser, the
tape and the casadi bridge are ``models.expressions``; the interval arithmetic is
``models.intervals``.

Soundness conventions
---------------------
* Every interval operation rounds outward (``np.nextafter`` of the round-to-nearest result, which
  is at most half an ulp from the exact one).  Transcendentals (sin cos tan exp log tanh and
  non-square powers) are widened by ``MARGIN_ULP`` ulps of the result before that: numpy's SIMD
  paths document errors up to 4 ulp; 8 ulp also covers the distance between two implementations'
  values, so a computed value at a point of the box lies inside the box's enclosure.  The margin
  is checked against mpmath in ``tests/test_known.py``.
* A decimal constant that is not a double (``0.15``) is the interval between its two neighbouring
  doubles; ``pi`` is ``[math.pi, nextafter(math.pi, inf)]``.
* A function that is undefined on part of a box (log or sqrt reaching below their domain,
  division by an interval holding 0, a tan pole, a non-integer power of a non-positive base) is an
  error naming the component, the box and the operation, never a silently clipped value.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robust_imdp.errors import DimensionError, ExpressionDomainError, ExpressionError, InvalidInputError
from robust_imdp.models.expressions import (FUNCTIONS, _Builder, _is_casadi, _multi_use, _Parser,  # noqa: F401
                                            _read_casadi, _Tape, _to_casadi)
from robust_imdp.models.intervals import (MARGIN_ULP, _WHY, _dn, _i_mul, _interval_eval,  # noqa: F401
                                          _point_eval, _up, _widen)

__all__ = ["KnownDynamics", "ImageBounds", "AchievedRange", "Residuals", "FUNCTIONS", "MARGIN_ULP"]

#: Boxes of up to this many dimensions are sampled at all their 2^n vertices (256 at most);
#: larger ones are not (the bisection's sampled range takes their face centres instead).
_MAX_VERTEX_DIMS = 8

# --------------------------------------------------------------------------- results
@dataclass(frozen=True)
class ImageBounds:
    """Certified enclosures of ``f`` over boxes: ``lower <= f(x) <= upper`` for every x in a box.

    ``lower``, ``upper`` : (k, n) float arrays; ``leaves`` : (k,) int, boxes the cell was
    bisected into (1 = not bisected).
    """

    lower: np.ndarray
    upper: np.ndarray
    leaves: np.ndarray


@dataclass(frozen=True)
class AchievedRange:
    """Values ``f`` attains on each box (sampling plus local optimisation): an inner range.

    ``lower``, ``upper`` : (k, n) float arrays of computed values at points of the box;
    ``argmin``, ``argmax`` : (k, n, n) the points.
    """

    lower: np.ndarray
    upper: np.ndarray
    argmin: np.ndarray
    argmax: np.ndarray

    def gap_to(self, bounds: ImageBounds) -> np.ndarray:
        """(k, n) distance by which the certified range exceeds the attained one on either side."""
        return np.maximum(np.maximum(self.lower - bounds.lower, bounds.upper - self.upper), 0.0)


@dataclass(frozen=True)
class Residuals:
    """``y = x_next - fl(f(x))`` and ``bound`` with ``|y - (x_next - f(x))| <= bound`` ((m, n))."""

    y: np.ndarray
    bound: np.ndarray


# --------------------------------------------------------------------------- the object
class KnownDynamics:
    """A known map ``f : R^n -> R^n`` given by one expression per component.

    Parameters
    ----------
    f : sequence of n str, or a casadi SX/MX expression of shape (n, 1)
        Expressions in ``x1..xn`` (grammar in ``docs/known_dynamics.md``), or a casadi expression
        of the symbol vector ``x``.
    x : casadi SX/MX symbol of shape (n, 1), only with a casadi ``f``
    name : str, optional
        Prefix of every error message (e.g. the mode: ``mode "left"``).
    n_inputs : int, optional
        Inputs ``u1..um`` the expressions may use besides ``x1..xn`` (an input grid's ``f(x, u)``,
        :mod:`robust_imdp.models.inputs`): the points and boxes of every method then have ``n + m``
        columns, the state's then the inputs', and the values ``n`` (string expressions only).

    Raises
    ------
    ExpressionError
        A syntax error, an unknown symbol or an unsupported casadi operation; the message names
        the component, the position and what was expected.
    """

    def __init__(self, f, x=None, *, name: str | None = None, n_inputs: int = 0):
        self.name = name
        self._consts = []
        if isinstance(n_inputs, bool) or not isinstance(n_inputs, (int, np.integer)) or n_inputs < 0:
            raise InvalidInputError(self._label(None) + f"n_inputs must be an integer >= 0; got {n_inputs!r}")
        self.n_inputs = int(n_inputs)
        if self.n_inputs and (x is not None or _is_casadi(f)):
            raise InvalidInputError(self._label(None) + "inputs (n_inputs > 0) need f as expression strings in "
                                    "x1..xn, u1..um; a casadi f has no inputs")
        if isinstance(f, str):
            raise InvalidInputError(self._label(None) + "f must be a sequence of expressions, one per "
                                    f"component; got the single string {f!r} (write [{f!r}])")
        if x is not None or _is_casadi(f):
            self._init_casadi(f, x)
        else:
            exprs = list(f)
            if not exprs:
                raise DimensionError(self._label(None) + "f must have at least one component; got []")
            for i, e in enumerate(exprs):
                if not isinstance(e, str):
                    raise InvalidInputError(f"{self._label(i)}must be a string expression in x1..x{len(exprs)}; "
                                            f"got {type(e).__name__} {e!r}")
            self.n_dims = len(exprs)
            self.expressions = tuple(exprs)
            self._tapes = []
            for i, e in enumerate(exprs):
                b = _Builder(self._consts)
                reg = _Parser(e, self.n_dims, b, self._label(i, colon=False).rstrip(), self.n_inputs).parse()
                self._tapes.append(_Tape(b.instrs, [(0, reg)]))
        self._jac = None  # built on first use (casadi)
        self._multi_use = np.array([_multi_use(t, self.n_vars) for t in self._tapes])  # (n_out, n + m) bool
        self._solvers = {}

    # ------------------------------------------------------------------ construction helpers
    def _label(self, i, colon=True):
        head = f"{self.name}: " if self.name else ""
        if i is None:
            return head
        expr = self.expressions[i] if hasattr(self, "expressions") else "?"
        return f'{head}f[{i + 1}] = "{expr}"' + (": " if colon else " ")

    def _init_casadi(self, f, x):
        import casadi as ca

        if x is None or not _is_casadi(x) or not x.is_symbolic() or x.size2() != 1:
            raise InvalidInputError(self._label(None) + "a casadi f needs x, a casadi symbol column vector "
                                    f"(e.g. casadi.SX.sym('x', n)); got {x!r}")
        n = x.size1()
        if not _is_casadi(f) or f.shape != (n, 1):
            raise DimensionError(self._label(None) + f"a casadi f must have shape ({n}, 1) like x; got "
                                 f"{getattr(f, 'shape', type(f).__name__)}")
        try:
            F = ca.Function("f", [x], [f])
        except RuntimeError as exc:
            raise ExpressionError(self._label(None) + f"f must depend only on the symbol x: {exc}") from None
        if isinstance(f, ca.MX):
            F = F.expand()
        xs = ca.SX.sym("x", n)
        fs = F(xs)
        self.n_dims = n
        self.expressions = tuple(str(fs[i]) for i in range(n))
        self._tapes = []
        for i in range(n):
            b = _Builder(self._consts)
            Fi = ca.Function("fi", [xs], [fs[i]])
            try:
                instrs, outs = _read_casadi(Fi, b, widen_literals=False)
            except ExpressionError as exc:
                raise ExpressionError(self._label(i) + str(exc)) from None
            reg = outs[0][1] if outs else b.const(0.0, 0.0, 0.0)  # a structural zero
            self._tapes.append(_Tape(b.instrs, [(0, reg)]))

    def _casadi_parts(self):
        """(x, p, per-component SX for differentiation, per-component SX with float constants)."""
        import casadi as ca

        x = ca.SX.sym("x", self.n_vars)
        p = ca.SX.sym("p", max(len(self._consts), 1))
        diff, plain = [], []
        for t in self._tapes:
            reg = t.outputs[0][1]
            diff.append(_to_casadi(t.instrs, self._consts, x, p, diff_form=True)[reg])
            plain.append(_to_casadi(t.instrs, self._consts, x, None, diff_form=False)[reg])
        return x, p, diff, plain

    def _jacobian_tapes(self):
        """Per component i a tape with outputs ``(j, d f_i / d x_j)`` from casadi's exact Jacobian."""
        if self._jac is None:
            import casadi as ca

            x, p, diff, _ = self._casadi_parts()
            tapes = []
            for fi in diff:
                J = ca.Function("J", [x, p], [ca.jacobian(fi, x)])
                _, cols = J.sparsity_out(0).get_triplet()
                b = _Builder(self._consts)
                instrs, outs = _read_casadi(J, b, widen_literals=True)
                tapes.append(_Tape(instrs, [(cols[nz], reg) for nz, reg in outs]))
            self._jac = tapes
        return self._jac

    # ------------------------------------------------------------------ point values
    def evaluate(self, x) -> np.ndarray:
        """Floating-point values ``fl(f(x))``.

        Parameters
        ----------
        x : (m, n) float array of points

        Returns
        -------
        (m, n) float array; raises ``ExpressionDomainError`` where a value is not finite.
        """
        x = self._points(x, "x")
        out = self._evaluate(x)
        bad = ~np.isfinite(out)
        if bad.any():
            r, i = np.argwhere(bad)[0]
            raise ExpressionDomainError(f"{self._label(int(i), colon=False)}is undefined or overflows at the point "
                                        f"x = {_point_text(x[r])} (row {r}): value {out[r, i]}")
        return out

    def _evaluate(self, x):
        if x.shape[0] == 0:
            return np.zeros((0, self.n_dims))
        return np.concatenate([_point_eval(t, self._consts, x) for t in self._tapes], axis=1)

    def jacobian(self, x) -> np.ndarray:
        """(m, n, n + n_inputs) floating-point Jacobian ``d f_i / d x_j`` at points ``x`` (casadi's exact one)."""
        x = self._points(x, "x")
        out = np.zeros((x.shape[0], self.n_dims, self.n_vars))
        for i, t in enumerate(self._jacobian_tapes()):
            if t.outputs:
                vals = _point_eval(t, self._consts, x)
                for k, (j, _) in enumerate(t.outputs):
                    out[:, i, j] = vals[:, k]
        return out

    def residual_rounding_bound(self, x) -> np.ndarray:
        """(m, n) ``b`` with ``|evaluate(x) - f(x)| <= b``: the interval evaluation at ``[x, x]``
        encloses the exact ``f(x)`` in ``[L, U]``, so ``|v - f(x)| <= max(U - v, v - L)``."""
        x = self._points(x, "x")
        v = self.evaluate(x)
        lo, hi = self._natural(x, x)
        return _up(np.maximum(hi - v, v - lo))

    def residuals(self, x, x_next) -> Residuals:
        """``y = x_next - fl(f(x))`` with a bound on its total rounding error.

        ``|y - (x_next - f(x))| <= |fl(x_next - v) - (x_next - v)| + |v - f(x)|``; the first term
        is at most half an ulp of ``|y|`` (bounded by one ``spacing``), the second
        ``residual_rounding_bound``.
        """
        x = self._points(x, "x")
        x_next = np.asarray(x_next, dtype=float)
        if x_next.shape != (x.shape[0], self.n_dims):
            like = "like x" if not self.n_inputs else f"(the state part of x's {self.n_vars} columns)"
            raise DimensionError(f"{self._label(None)}x_next must have shape {(x.shape[0], self.n_dims)} {like}; got "
                                 f"{x_next.shape}")
        v = self.evaluate(x)
        y = x_next - v
        return Residuals(y=y, bound=_up(self.residual_rounding_bound(x) + np.spacing(np.abs(y))))

    # ------------------------------------------------------------------ certified image bounds
    def image_bounds(self, lower, upper, *, form: str = "best", max_leaves: int = 16,
                     split_tolerance: float = 1e-3, chunk: int = 16384) -> ImageBounds:
        """Certified enclosures of every component of ``f`` over every box ``[lower, upper]``.

        Parameters
        ----------
        lower, upper : (k, n) float arrays, ``lower <= upper``
        form : {"best", "natural", "centred"}
            ``natural``: interval arithmetic over the expression graph; ``centred``: the
            mean-value form ``f([c, c]) + sum_j J_j(X) (X_j - c_j)`` (eq. MV of
            ``docs/known_dynamics.md``); ``best``: their intersection, with bisection.
        max_leaves : int
            ``best`` only: a box whose enclosure exceeds its sampled range (centre and vertices)
            by more than ``split_tolerance`` times its largest edge is bisected (along the edge
            with the largest ``|J| * width``), up to this many leaves; the enclosure is the union
            of the leaves' enclosures intersected with the box's own.
        chunk : boxes evaluated at once (memory: ~ chunk x tape length x 16 bytes)

        Returns
        -------
        ImageBounds
        """
        lower, upper = self._boxes(lower, upper)
        if form not in ("best", "natural", "centred"):
            raise InvalidInputError(f"{self._label(None)}form must be 'best', 'natural' or 'centred'; got {form!r}")
        if int(max_leaves) < 1:
            raise InvalidInputError(f"{self._label(None)}max_leaves must be >= 1; got {max_leaves}")
        k = lower.shape[0]
        out_lo = np.empty((k, self.n_dims))
        out_hi = np.empty((k, self.n_dims))
        leaves = np.ones(k, dtype=np.int64)
        for s in range(0, k, chunk):
            sl = slice(s, min(k, s + chunk))
            if form == "natural":
                out_lo[sl], out_hi[sl] = self._natural(lower[sl], upper[sl])
            elif form == "centred":
                nl, nh = self._natural(lower[sl], upper[sl])  # checks the domain; values unused
                cl, ch, _ = self._centred(lower[sl], upper[sl])
                out_lo[sl], out_hi[sl] = cl, ch
            else:
                out_lo[sl], out_hi[sl], leaves[sl] = self._best(lower[sl], upper[sl], int(max_leaves),
                                                                float(split_tolerance))
        return ImageBounds(lower=out_lo, upper=out_hi, leaves=leaves)

    def _natural(self, lo, hi):
        """Natural interval extension, raising on an undefined operation."""
        out_l = np.empty((lo.shape[0], self.n_dims))
        out_h = np.empty_like(out_l)
        for i, t in enumerate(self._tapes):
            l, h, bad, why = _interval_eval(t, self._consts, lo, hi)
            if why is not None:
                op, r = why
                raise ExpressionDomainError(f"{self._label(i, colon=False)}is undefined on the box {_box_text(lo[r], hi[r])}: "
                                            f"{_WHY.get(op, op)}")
            out_l[:, i], out_h[:, i] = l[:, 0], h[:, 0]
        return out_l, out_h

    def _centred(self, lo, hi):
        """Mean-value form (eq. MV): ``f([c,c]) + sum_j J_ij(X) [lo_j - c_j, hi_j - c_j]``.

        Valid because ``f(x) - f(c) = int_0^1 grad f(c + t(x - c)) . (x - c) dt`` and the
        gradient lies in ``J(X)`` wherever it exists (a.e. on the segment; at kinks of abs/min/max
        the interval of ``sign`` holds every one-sided value).  Boxes where ``J(X)`` is undefined
        or unbounded (e.g. sqrt at 0) get ``[-inf, inf]``.  Returns also ``contrib`` (k, n, n):
        ``|J_ij| * width_j`` (inf where ``J_i`` is unusable), the split criterion.
        """
        k, n = lo.shape
        c = np.minimum(np.maximum(0.5 * lo + 0.5 * hi, lo), hi)  # a point of the box
        fcl, fch = self._natural(c, c)
        dl, dh = _dn(lo - c), _up(hi - c)  # X_j - c_j, contains 0
        cl, ch = fcl.copy(), fch.copy()
        contrib = np.zeros((k, self.n_dims, n))
        for i, t in enumerate(self._jacobian_tapes()):
            if not t.outputs:
                continue
            jl, jh, bad, _ = _interval_eval(t, self._consts, lo, hi)
            with np.errstate(all="ignore"):
                for col, (j, _) in enumerate(t.outputs):
                    pl, ph, _ = _i_mul(jl[:, col], jh[:, col], dl[:, j], dh[:, j])
                    cl[:, i], ch[:, i] = _dn(cl[:, i] + pl), _up(ch[:, i] + ph)
                    contrib[:, i, j] = np.maximum(np.abs(jl[:, col]), np.abs(jh[:, col])) * (hi[:, j] - lo[:, j])
            unusable = bad | ~(np.isfinite(cl[:, i]) & np.isfinite(ch[:, i]))
            cl[unusable, i], ch[unusable, i] = -np.inf, np.inf
            contrib[unusable, i, :] = np.inf
        return cl, ch, contrib

    def _best(self, lo, hi, max_leaves, tol):
        """Natural extension, intersected with the centred form where it is loose; loose boxes
        bisected up to ``max_leaves`` leaves per cell.

        A leaf is loose when its enclosure exceeds the range sampled at its centre and vertices by
        more than ``tol`` times the cell's largest edge in some component.  It is split at the
        midpoint of the edge with the largest ``|J_ij| * width_j`` for its loosest component i,
        among the variables that reach f_i along more than one path of the graph (the others
        cause no dependency effect in the natural extension) where there are any.  The leaves
        cover the cell, so the union of their enclosures encloses f over it.
        """
        k, n = lo.shape
        leaves = np.ones(k, dtype=np.int64)
        scale = np.max(hi - lo, axis=1)  # the cell's largest edge
        L, U, owner = lo, hi, np.arange(k)
        res_l = res_h = None
        done_l = np.full((k, self.n_dims), np.inf)
        done_h = np.full((k, self.n_dims), -np.inf)
        while True:
            el, eh, excess_i, cb = self._tightened(L, U, tol * scale[owner])
            if res_l is None:
                res_l, res_h = el, eh  # the cell's own enclosure
            split = ((np.max(excess_i, axis=1) > tol * scale[owner]) & (2 * leaves[owner] <= max_leaves)
                     & (np.max(U - L, axis=1) > 0))
            keep = ~split
            np.minimum.at(done_l, owner[keep], el[keep])
            np.maximum.at(done_h, owner[keep], eh[keep])
            if not split.any():
                break
            Ls, Us, os_ = L[split], U[split], owner[split]
            rows = np.arange(Ls.shape[0])
            comp = np.argmax(excess_i[split], axis=1)
            cs = cb[split][rows, comp]  # (m, n) |J_ij| * width_j of the loosest component
            widths = Us - Ls
            score = np.where(np.isfinite(cs).all(axis=1)[:, None], cs, widths)
            score = score * np.where(self._multi_use[comp], 1.0, 1e-6)
            dim = np.argmax(np.where(widths > 0, score, -1.0), axis=1)  # never an edge of width 0
            mid = 0.5 * Ls[rows, dim] + 0.5 * Us[rows, dim]
            left_U, right_L = Us.copy(), Ls.copy()
            left_U[rows, dim] = mid
            right_L[rows, dim] = mid
            L = np.concatenate([Ls, right_L])
            U = np.concatenate([left_U, Us])
            owner = np.concatenate([os_, os_])
            np.add.at(leaves, os_, 1)
        # union of the leaves, intersected with the cell's own enclosure (both are sound)
        return np.maximum(res_l, done_l), np.minimum(res_h, done_h), leaves

    def _tightened(self, L, U, tol):
        """Natural extension, intersected with the centred form on boxes whose natural enclosure
        exceeds the sampled range by more than ``tol`` ((k,)); returns the enclosure, its excess
        over the sampled range (k, n) and the split scores (k, n, n; 0 where not computed)."""
        el, eh = self._natural(L, U)
        sl, sh = self._sampled(L, U)
        excess = (eh - el) - (sh - sl)
        cb = np.zeros((L.shape[0], self.n_dims, self.n_vars))
        loose = np.max(excess, axis=1) > tol
        if loose.any():
            cl, ch, cb_l = self._centred(L[loose], U[loose])
            el[loose] = np.maximum(el[loose], cl)  # both enclose f: so does the intersection
            eh[loose] = np.minimum(eh[loose], ch)
            cb[loose] = cb_l
            excess[loose] = (eh[loose] - el[loose]) - (sh[loose] - sl[loose])
        return el, eh, excess, cb

    def _sampled(self, lo, hi):
        """Min and max of the computed values at the centre and the vertices (face centres if n > 8).

        Only the dimensions some box of the batch is wide in span the vertices: a column that is a point in
        every box (an input of an input grid, ``models.inputs``) would only repeat each vertex."""
        k, n = lo.shape
        c = 0.5 * lo + 0.5 * hi
        free = np.flatnonzero(np.any(hi > lo, axis=0))  # the other columns are points: lo = hi = c
        nf = free.size
        if nf <= _MAX_VERTEX_DIMS:
            corners = np.zeros((2 ** nf, n), dtype=bool)
            corners[:, free] = ((np.arange(2 ** nf)[:, None] >> np.arange(nf)[None, :]) & 1).astype(bool)
            pts = np.where(corners[None], hi[:, None, :], lo[:, None, :])  # (k, 2^nf, n)
        else:
            eye = np.eye(n, dtype=bool)[free]
            pts = np.concatenate([np.where(eye[None], lo[:, None, :], c[:, None, :]),
                                  np.where(eye[None], hi[:, None, :], c[:, None, :])], axis=1)
        pts = np.concatenate([c[:, None, :], pts], axis=1)
        v = self._evaluate(pts.reshape(-1, n)).reshape(k, -1, self.n_dims)
        return np.nanmin(v, axis=1), np.nanmax(v, axis=1)

    # ------------------------------------------------------------------ achieved range (diagnostics)
    def achieved_range(self, lower, upper, *, n_samples: int = 64, optimise: bool = True,
                       rng=0) -> AchievedRange:
        """Values attained on each box: the centre, the vertices, ``n_samples`` uniform points,
        then (``optimise``) a local optimisation of each component in each direction from the best
        sample (casadi's IPOPT; scipy's L-BFGS-B with casadi's gradient where IPOPT is missing).

        Every reported value is ``evaluate`` at a point of the box (IPOPT's solution is clipped
        into the box), so ``lower``/``upper`` are attained up to rounding: an inner range to
        compare with ``image_bounds``.
        """
        lower, upper = self._boxes(lower, upper)
        k, n = lower.shape
        gen = np.random.default_rng(rng)
        c = 0.5 * lower + 0.5 * upper
        parts = [c[:, None, :]]
        if n <= _MAX_VERTEX_DIMS:
            corners = ((np.arange(2 ** n)[:, None] >> np.arange(n)[None, :]) & 1).astype(bool)
            parts.append(np.where(corners[None], upper[:, None, :], lower[:, None, :]))
        if n_samples > 0:
            u = gen.random((k, int(n_samples), n))
            parts.append(np.minimum(lower[:, None, :] + u * (upper - lower)[:, None, :], upper[:, None, :]))
        pts = np.concatenate(parts, axis=1)
        v = self._evaluate(pts.reshape(-1, n)).reshape(k, pts.shape[1], self.n_dims)
        imin, imax = np.argmin(v, axis=1), np.argmax(v, axis=1)  # (k, n_out)
        rows = np.arange(k)[:, None]
        lo_v, hi_v = np.take_along_axis(v, imin[:, None, :], 1)[:, 0], np.take_along_axis(v, imax[:, None, :], 1)[:, 0]
        argmin = pts[rows, imin]  # (k, n_out, n)
        argmax = pts[rows, imax]
        if optimise:
            for i in range(self.n_dims):
                for sign, vals, args in ((1.0, lo_v, argmin), (-1.0, hi_v, argmax)):
                    for r in range(k):
                        xs = self._local_opt(i, sign, args[r, i], lower[r], upper[r])
                        if xs is None:
                            continue
                        val = self._evaluate(xs[None])[0, i]
                        if np.isfinite(val) and sign * val < sign * vals[r, i]:
                            vals[r, i] = val
                            args[r, i] = xs
        return AchievedRange(lower=lo_v, upper=hi_v, argmin=argmin, argmax=argmax)

    def _local_opt(self, i, sign, x0, lb, ub):
        solver = self._solver(i, sign)
        if solver is None:
            return None
        kind, s = solver
        try:
            if kind == "ipopt":
                sol = s(x0=x0, lbx=lb, ubx=ub)
                xs = np.asarray(sol["x"], dtype=float).ravel()
            else:
                from scipy.optimize import minimize

                fun, grad = s
                res = minimize(lambda z: float(fun(z)), x0, jac=lambda z: np.asarray(grad(z), float).ravel(),
                               method="L-BFGS-B", bounds=list(zip(lb, ub)))
                xs = np.asarray(res.x, dtype=float)
        except Exception:  # a failed local solve only means no improvement of the inner range
            return None
        if not np.all(np.isfinite(xs)):
            return None
        return np.minimum(np.maximum(xs, lb), ub)

    def _solver(self, i, sign):
        key = (i, sign)
        if key not in self._solvers:
            import casadi as ca

            x, _, _, plain = self._casadi_parts()
            obj = sign * plain[i]
            try:
                s = ca.nlpsol("s", "ipopt", {"x": x, "f": obj},
                              {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
                               "ipopt.max_iter": 60, "ipopt.tol": 1e-10, "error_on_fail": False})
                self._solvers[key] = ("ipopt", s)
            except RuntimeError:  # casadi built without IPOPT
                fun = ca.Function("f", [x], [obj])
                grad = ca.Function("g", [x], [ca.gradient(obj, x)])
                self._solvers[key] = ("scipy", (fun, grad))
        return self._solvers[key]

    # ------------------------------------------------------------------ input checks
    def _points(self, x, what):
        x = np.asarray(x, dtype=float)
        if x.ndim != 2 or x.shape[1] != self.n_vars:
            raise DimensionError(f"{self._label(None)}{what} must have shape (m, {self.n_vars}){self._columns()}; got "
                                 f"{x.shape}")
        return x

    def _columns(self) -> str:
        return f" (x1..x{self.n_dims}, then u1..u{self.n_inputs})" if self.n_inputs else ""

    def _boxes(self, lower, upper):
        lower = np.asarray(lower, dtype=float)
        upper = np.asarray(upper, dtype=float)
        for what, a in (("lower", lower), ("upper", upper)):
            if a.ndim != 2 or a.shape[1] != self.n_vars:
                raise DimensionError(f"{self._label(None)}{what} must have shape (k, {self.n_vars}){self._columns()}; "
                                     f"got {a.shape}")
        if lower.shape != upper.shape:
            raise DimensionError(f"{self._label(None)}upper must have shape {lower.shape} like lower; got {upper.shape}")
        bad = ~(np.isfinite(lower) & np.isfinite(upper) & (lower <= upper))
        if bad.any():
            r = int(np.argwhere(bad)[0][0])
            raise InvalidInputError(f"{self._label(None)}boxes must be finite with lower <= upper; box {r} is "
                                    f"lower {lower[r].tolist()}, upper {upper[r].tolist()}")
        return lower, upper

    # ------------------------------------------------------------------ the known-part interface
    # (shared with system.AffineMap: what the pipeline needs of a mode's known part)
    @property
    def dim(self) -> int:
        """The state dimension n."""
        return int(self.n_dims)

    @property
    def n_vars(self) -> int:
        """The variables: the state's n, then the ``n_inputs`` inputs."""
        return int(self.n_dims) + getattr(self, "n_inputs", 0)

    def __call__(self, x) -> np.ndarray:
        """``evaluate(x)``: ``(k, n) -> (k, n)`` floating-point values."""
        return self.evaluate(x)

    def fingerprint(self) -> str:
        """A digest of the expression graphs and the constants' enclosures (cache keys)."""
        import hashlib

        h = hashlib.sha256(b"KnownDynamics")
        if self.n_inputs:  # only then: the digests of known parts without inputs are unchanged
            h.update(f"inputs {self.n_inputs}".encode())
        h.update(repr([(t.instrs, t.outputs) for t in self._tapes]).encode())
        h.update(np.asarray(self._consts, dtype=float).tobytes())
        return h.hexdigest()

    def __repr__(self):
        extra = f", n_inputs={self.n_inputs}" if self.n_inputs else ""
        return f"KnownDynamics({list(self.expressions)!r}{extra})"


def _box_text(lo, hi):
    return " x ".join(f"[{a:.6g}, {b:.6g}]" for a, b in zip(lo, hi))


def _point_text(x):
    return "(" + ", ".join(f"{a:.6g}" for a in x) + ")"
