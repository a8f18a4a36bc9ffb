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
tape (a list of instructions in topological order, common subexpressions shared).

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

import math
import re
from dataclasses import dataclass
from fractions import Fraction
from typing import Sequence

import numpy as np

from robust_imdp.errors import DimensionError, ExpressionDomainError, ExpressionError, InvalidInputError

__all__ = ["KnownDynamics", "ImageBounds", "AchievedRange", "Residuals", "FUNCTIONS", "MARGIN_ULP"]

#: Ulps by which every transcendental result is widened (then one more nextafter).  numpy's
#: AVX-512 SVML paths document up to 4 ulp; twice that covers |impl(t) - exact(t)| and the
#: distance of any other <= 4-ulp implementation's value from ours.
MARGIN_ULP = 8

#: Functions of the grammar and their number of arguments (None: 2 or more).
FUNCTIONS = {"sin": 1, "cos": 1, "tan": 1, "exp": 1, "log": 1, "sqrt": 1, "abs": 1, "tanh": 1,
             "min": None, "max": None}

_PI_LO = math.pi                                # math.pi < pi (pi = 3.14159265358979323846...)
_PI_HI = float(np.nextafter(math.pi, np.inf))
_TWO_PI = 2.0 * math.pi                         # used only inside slack-protected tests
_MAX_INT_EXPONENT = 1024                        # integer powers handled exactly up to this order
_TRANSCENDENTAL = frozenset({"sin", "cos", "tan", "exp", "log", "tanh"})


# --------------------------------------------------------------------------- rounding helpers
def _dn(x):
    """Round-to-nearest result moved one ulp towards -inf (a sound lower bound)."""
    return np.nextafter(x, -np.inf)


def _up(x):
    """Round-to-nearest result moved one ulp towards +inf (a sound upper bound)."""
    return np.nextafter(x, np.inf)


def _widen(r):
    """``[r - MARGIN_ULP ulp(r), r + MARGIN_ULP ulp(r)]`` rounded outward: encloses the exact value
    of a transcendental whose computed value is ``r`` (implementation error <= 4 ulp)."""
    s = MARGIN_ULP * np.spacing(np.abs(r))
    return _dn(r - s), _up(r + s)


# --------------------------------------------------------------------------- tape
@dataclass
class _Tape:
    """Instructions ``(op, a, b)`` in topological order; register ``k`` is instruction ``k``'s value.

    ``op`` is ``var`` (``a`` = dimension), ``const`` (``a`` = index into the constant table) or an
    operation on registers ``a`` (and ``b``).  ``outputs`` lists ``(column, register)``.
    """

    instrs: list
    outputs: list

    def __len__(self):
        return len(self.instrs)


class _Builder:
    """Emits instructions with common subexpressions shared; owns the constant table."""

    def __init__(self, consts):
        self.instrs = []
        self.memo = {}
        self.consts = consts  # list of (value, lo, hi) shared by every tape of one KnownDynamics

    def emit(self, op, a=-1, b=-1):
        if op in ("add", "mul", "min", "max") and a > b:
            a, b = b, a  # commutative: one register for x1*x2 and x2*x1
        key = (op, a, b)
        reg = self.memo.get(key)
        if reg is None:
            reg = len(self.instrs)
            self.instrs.append(key)
            self.memo[key] = reg
        return reg

    def const(self, value, lo, hi):
        key = ("cval", float(value), float(lo), float(hi))
        k = self.memo.get(key)
        if k is None:
            k = len(self.consts)
            self.consts.append((float(value), float(lo), float(hi)))
            self.memo[key] = k
        return self.emit("const", k)


def _decimal_interval(text):
    """(nearest double, lo, hi) with lo <= the exact decimal value <= hi (eq. for constants)."""
    value = float(text)
    if not math.isfinite(value):
        return None
    exact, got = Fraction(text), Fraction(value)
    if got == exact:
        return value, value, value
    if got > exact:
        return value, float(np.nextafter(value, -np.inf)), value
    return value, value, float(np.nextafter(value, np.inf))


# --------------------------------------------------------------------------- parser
_TOKEN = re.compile(r"\s*(?:(?P<num>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)|(?P<name>[A-Za-z_][A-Za-z_0-9]*)"
                    r"|(?P<op>\*\*|[-+*/^(),]))")


class _Parser:
    """Recursive descent over the grammar of ``docs/known_dynamics.md``::

        expr  := term (('+' | '-') term)*
        term  := unary (('*' | '/') unary)*
        unary := ('-' | '+') unary | power
        power := atom (('^' | '**') unary)?        right-associative, binds tighter than unary minus
        atom  := number | 'pi' | x<k> | func '(' expr (',' expr)* ')' | '(' expr ')'
    """

    def __init__(self, text, n_dims, builder, label):
        self.text, self.n, self.b, self.label = text, n_dims, builder, label
        self.tokens = []  # (kind, value, position)
        pos = 0
        while True:
            while pos < len(text) and text[pos].isspace():
                pos += 1
            if pos >= len(text):
                break
            m = _TOKEN.match(text, pos)
            if m is None or m.end() == pos:
                self.fail(pos, f"unexpected character {text[pos]!r}",
                          "a number, x1..x%d, pi, a function, an operator + - * / ^ ** or parentheses" % n_dims)
            kind = m.lastgroup
            self.tokens.append((kind, m.group(kind), m.start(kind)))
            pos = m.end()
        self.tokens.append(("end", "", len(text)))
        self.i = 0

    def fail(self, pos, what, expected):
        raise ExpressionError(f"{self.label}: {what} at position {pos} (expected {expected}):\n"
                              f"    {self.text}\n    {' ' * pos}^")

    def peek(self):
        return self.tokens[self.i]

    def take(self):
        tok = self.tokens[self.i]
        self.i += 1
        return tok

    def parse(self):
        if self.peek()[0] == "end":
            self.fail(0, "empty expression", "an expression in x1..x%d" % self.n)
        reg = self.expr()
        kind, value, pos = self.peek()
        if kind != "end":
            self.fail(pos, f"unexpected {value!r}", "an operator + - * / ^ or the end of the expression")
        return reg

    def expr(self):
        reg = self.term()
        while self.peek()[1] in ("+", "-") and self.peek()[0] == "op":
            op = "add" if self.take()[1] == "+" else "sub"
            reg = self.b.emit(op, reg, self.term())
        return reg

    def term(self):
        reg = self.unary()
        while self.peek()[0] == "op" and self.peek()[1] in ("*", "/"):
            op = "mul" if self.take()[1] == "*" else "div"
            reg = self.b.emit(op, reg, self.unary())
        return reg

    def unary(self):
        kind, value, _ = self.peek()
        if kind == "op" and value in ("-", "+"):
            self.take()
            reg = self.unary()
            if value == "+":
                return reg
            op, a, _ = self.b.instrs[reg]
            if op == "const":  # -c is the constant [-hi, -lo] (exact), so x^-2 has an integer exponent
                v, lo, hi = self.b.consts[a]
                return self.b.const(-v, -hi, -lo)
            return self.b.emit("neg", reg)
        return self.power()

    def power(self):
        base = self.atom()
        if self.peek()[0] == "op" and self.peek()[1] in ("^", "**"):
            self.take()
            return self.b.emit("pow", base, self.unary())
        return base

    def atom(self):
        kind, value, pos = self.take()
        if kind == "num":
            c = _decimal_interval(value)
            if c is None:
                self.fail(pos, f"constant {value} is out of the double range", "a finite number")
            return self.b.const(*c)
        if kind == "name":
            if value == "pi":
                return self.b.const(math.pi, _PI_LO, _PI_HI)
            m = re.fullmatch(r"x([1-9][0-9]*)", value)
            if m:
                k = int(m.group(1))
                if k > self.n:
                    self.fail(pos, f"unknown symbol {value!r} (the state has {self.n} dimensions)",
                              "x1..x%d" % self.n)
                return self.b.emit("var", k - 1)
            if value in FUNCTIONS:
                return self.call(value, pos)
            self.fail(pos, f"unknown symbol {value!r}",
                      "x1..x%d, pi or a function %s" % (self.n, ", ".join(FUNCTIONS)))
        if kind == "op" and value == "(":
            reg = self.expr()
            self.expect(")", "')' closing the '(' at position %d" % pos)
            return reg
        what = "end of the expression" if kind == "end" else f"{value!r}"
        self.fail(pos, f"unexpected {what}", "a number, x1..x%d, pi, a function or '('" % self.n)

    def expect(self, symbol, expected):
        kind, value, pos = self.peek()
        if not (kind == "op" and value == symbol):
            what = "end of the expression" if kind == "end" else f"{value!r}"
            self.fail(pos, f"unexpected {what}", expected)
        self.take()

    def call(self, name, pos):
        self.expect("(", f"'(' after the function {name!r}")
        args = [self.expr()]
        while self.peek()[0] == "op" and self.peek()[1] == ",":
            self.take()
            args.append(self.expr())
        self.expect(")", f"',' or ')' in the arguments of {name!r}")
        arity = FUNCTIONS[name]
        if arity is None and len(args) < 2:
            self.fail(pos, f"{name} takes 2 or more arguments, got {len(args)}", f"{name}(a, b, ...)")
        if arity is not None and len(args) != arity:
            self.fail(pos, f"{name} takes {arity} argument, got {len(args)}", f"{name}(a)")
        if arity is None:
            reg = args[0]
            for a in args[1:]:
                reg = self.b.emit(name, reg, a)
            return reg
        return self.b.emit(name, args[0])


# --------------------------------------------------------------------------- casadi bridge
_CASADI_OPS = {"OP_ADD": "add", "OP_SUB": "sub", "OP_MUL": "mul", "OP_DIV": "div", "OP_NEG": "neg",
               "OP_SQ": "sq", "OP_TWICE": "twice", "OP_INV": "inv", "OP_SQRT": "sqrt", "OP_SIN": "sin",
               "OP_COS": "cos", "OP_TAN": "tan", "OP_EXP": "exp", "OP_LOG": "log", "OP_TANH": "tanh",
               "OP_FABS": "abs", "OP_SIGN": "sign", "OP_FMIN": "min", "OP_FMAX": "max", "OP_POW": "pow",
               "OP_CONSTPOW": "pow", "OP_ASSIGN": "assign"}
_BINARY = frozenset({"add", "sub", "mul", "div", "pow", "min", "max"})


def _read_casadi(F, builder, *, widen_literals):
    """Tape of the SX function ``F(x[, p])``: ``x`` -> ``var``, ``p`` -> the builder's constants.

    Literal constants of ``F`` become point intervals, or (``widen_literals``: for casadi's own
    Jacobians, whose literals may come from constant folding in round-to-nearest) integers exact
    and anything else widened by two ulps each side.  Returns ``(tape, [(output nz, register)])``.
    """
    import casadi as ca

    names = {getattr(ca, k): k for k in dir(ca) if k.startswith("OP_")}
    work, outputs = {}, []
    for k in range(F.n_instructions()):
        op_id = F.instruction_id(k)
        ins, outs = F.instruction_input(k), F.instruction_output(k)
        name = names.get(op_id, str(op_id))
        if op_id == ca.OP_INPUT:
            reg = builder.emit("var", ins[1]) if ins[0] == 0 else builder.emit("const", ins[1])
        elif op_id == ca.OP_CONST:
            c = float(F.instruction_constant(k))
            if widen_literals and not (c == int(c) and abs(c) < 2.0 ** 53):
                lo, hi = c, c
                for _ in range(2):
                    lo, hi = float(_dn(lo)), float(_up(hi))
                reg = builder.const(c, lo, hi)
            else:
                reg = builder.const(c, c, c)
        elif op_id == ca.OP_OUTPUT:
            outputs.append((outs[1], work[ins[0]]))
            continue
        elif name in _CASADI_OPS:
            op = _CASADI_OPS[name]
            if op == "assign":
                reg = work[ins[0]]
            elif op in _BINARY:
                reg = builder.emit(op, work[ins[0]], work[ins[1]])
            else:
                reg = builder.emit(op, work[ins[0]])
        else:
            raise ExpressionError(f"casadi operation {name} is not supported; supported: "
                                  + ", ".join(sorted(set(_CASADI_OPS) - {"OP_ASSIGN"})))
        work[outs[0]] = reg
    return builder.instrs, outputs


def _to_casadi(instrs, consts, x, p, *, diff_form):
    """casadi SX value of every register of ``instrs``.

    Constants are the symbols ``p`` (so casadi cannot fold them in round-to-nearest) except
    integer exponents, kept literal so that casadi differentiates ``x^n`` as ``n x^(n-1)``.
    ``diff_form``: ``min(a, b) = (a + b - |a - b|)/2`` and ``max(a, b) = (a + b + |a - b|)/2``,
    whose derivatives (with ``sign``) are a.e. those of min/max and enclose the one-sided ones
    at ties; casadi's own derivative of fmin divides by a sum of comparisons that interval
    arithmetic cannot bound away from 0.
    """
    import casadi as ca

    vals = []
    for op, a, b in instrs:
        if op == "var":
            v = x[a]
        elif op == "const":
            v = p[a] if p is not None else ca.SX(consts[a][0])
        elif op == "pow":
            e_op, e_a, _ = instrs[b]
            if e_op == "const" and _is_int_point(consts[e_a]):
                v = vals[a] ** float(consts[e_a][0])
            else:
                v = ca.power(vals[a], vals[b])
        else:
            A = vals[a]
            B = vals[b] if b >= 0 else None
            if op in ("min", "max") and diff_form:
                s = -1.0 if op == "min" else 1.0
                v = 0.5 * ((A + B) + s * ca.fabs(A - B))
            else:
                v = {"add": lambda: A + B, "sub": lambda: A - B, "mul": lambda: A * B, "div": lambda: A / B,
                     "neg": lambda: -A, "sq": lambda: A * A, "twice": lambda: 2 * A, "inv": lambda: 1 / A,
                     "sqrt": lambda: ca.sqrt(A), "sin": lambda: ca.sin(A), "cos": lambda: ca.cos(A),
                     "tan": lambda: ca.tan(A), "exp": lambda: ca.exp(A), "log": lambda: ca.log(A),
                     "tanh": lambda: ca.tanh(A), "abs": lambda: ca.fabs(A), "sign": lambda: ca.sign(A),
                     "min": lambda: ca.fmin(A, B), "max": lambda: ca.fmax(A, B)}[op]()
        vals.append(v)
    return vals


def _is_int_point(c):
    value, lo, hi = c
    return lo == hi == value and value == int(value) and abs(value) <= _MAX_INT_EXPONENT


# --------------------------------------------------------------------------- interval operations
# Each takes (lo, hi) arrays of its arguments and returns (lo, hi, bad) with bad a boolean array
# (the operation is undefined somewhere on the argument interval) or None.
def _i_add(al, ah, bl, bh):
    return _dn(al + bl), _up(ah + bh), None


def _i_sub(al, ah, bl, bh):
    return _dn(al - bh), _up(ah - bl), None


def _i_mul(al, ah, bl, bh):
    p = (al * bl, al * bh, ah * bl, ah * bh)
    return _dn(np.minimum(np.minimum(p[0], p[1]), np.minimum(p[2], p[3]))), \
        _up(np.maximum(np.maximum(p[0], p[1]), np.maximum(p[2], p[3]))), None


def _i_div(al, ah, bl, bh):
    bad = (bl <= 0) & (bh >= 0)
    bl, bh = np.where(bad, 1.0, bl), np.where(bad, 1.0, bh)
    q = (al / bl, al / bh, ah / bl, ah / bh)
    return _dn(np.minimum(np.minimum(q[0], q[1]), np.minimum(q[2], q[3]))), \
        _up(np.maximum(np.maximum(q[0], q[1]), np.maximum(q[2], q[3]))), bad


def _i_sq(al, ah):
    # x^2 is decreasing on x <= 0, increasing on x >= 0: minimum 0 when 0 is inside
    lo2, hi2 = al * al, ah * ah
    inside = (al <= 0) & (ah >= 0)
    lo = np.where(inside, 0.0, _dn(np.minimum(lo2, hi2)))
    return np.maximum(lo, 0.0), _up(np.maximum(lo2, hi2)), None  # x^2 >= 0: clamp is exact


def _i_abs(al, ah):
    inside = (al <= 0) & (ah >= 0)
    m = np.maximum(np.abs(al), np.abs(ah))
    return np.where(inside, 0.0, np.minimum(np.abs(al), np.abs(ah))), m, None  # exact


def _i_sqrt(al, ah):
    bad = al < 0
    # sqrt is correctly rounded (IEEE 754): one nextafter suffices; sqrt >= 0 makes the clamp safe
    return np.maximum(_dn(np.sqrt(np.where(bad, 0.0, al))), 0.0), _up(np.sqrt(np.where(bad, 0.0, ah))), bad


def _i_monotone(fun, al, ah, lower_limit=None, upper_limit=None):
    """Increasing ``fun``: ``[fun(al), fun(ah)]`` widened by the transcendental margin."""
    lo, _ = _widen(fun(al))
    _, hi = _widen(fun(ah))
    if lower_limit is not None:  # the exact function is >= lower_limit: the clamp is safe
        lo = np.maximum(lo, lower_limit)
    if upper_limit is not None:
        hi = np.minimum(hi, upper_limit)
    return lo, hi


def _i_exp(al, ah):
    return (*_i_monotone(np.exp, al, ah, lower_limit=0.0), None)


def _i_tanh(al, ah):
    return (*_i_monotone(np.tanh, al, ah, -1.0, 1.0), None)


def _i_log(al, ah):
    bad = al <= 0
    lo, hi = _i_monotone(np.log, np.where(bad, 1.0, al), np.where(bad, 1.0, ah))
    return lo, hi, bad


def _grid_hit(al, ah, phase, period):
    """Does ``[al, ah]`` possibly contain a point ``phase + k period`` (k integer)?

    ``q = (t - phase)/period`` is computed with a relative error of a few ulps; the slack
    ``1e-13 (1 + |q|)`` is far larger, so a wrong answer can only be "yes" (which is sound: an
    extremum or a pole is assumed inside).
    """
    qa = (al - phase) / period
    qb = (ah - phase) / period
    return np.ceil(qa - 1e-13 * (1.0 + np.abs(qa))) <= np.floor(qb + 1e-13 * (1.0 + np.abs(qb)))


def _i_trig(fun, al, ah, phase_max, phase_min):
    """sin/cos: endpoints widened; 1 / -1 where a maximum / minimum may lie inside."""
    la, ua = _widen(fun(al))
    lb, ub = _widen(fun(ah))
    lo, hi = np.minimum(la, lb), np.maximum(ua, ub)
    full = (ah - al) >= 6.28  # at least (almost) a period: both extrema inside
    hi = np.where(full | _grid_hit(al, ah, phase_max, _TWO_PI), 1.0, hi)
    lo = np.where(full | _grid_hit(al, ah, phase_min, _TWO_PI), -1.0, lo)
    # sin, cos take values in [-1, 1]: the clamps are safe
    return np.maximum(lo, -1.0), np.minimum(hi, 1.0), None


def _i_sin(al, ah):
    return _i_trig(np.sin, al, ah, 0.5 * math.pi, -0.5 * math.pi)


def _i_cos(al, ah):
    return _i_trig(np.cos, al, ah, 0.0, math.pi)


def _i_tan(al, ah):
    bad = ((ah - al) >= 3.14) | _grid_hit(al, ah, 0.5 * math.pi, math.pi)
    lo, hi = _i_monotone(np.tan, np.where(bad, 0.0, al), np.where(bad, 0.0, ah))
    return lo, hi, bad


def _i_sign(al, ah):
    return np.sign(al), np.sign(ah), None  # non-decreasing, exact


def _i_min(al, ah, bl, bh):
    return np.minimum(al, bl), np.minimum(ah, bh), None  # exact


def _i_max(al, ah, bl, bh):
    return np.maximum(al, bl), np.maximum(ah, bh), None  # exact


def _i_powi(al, ah, n):
    """``x^n`` for an integer ``n >= 1``: even n has its minimum at 0 when 0 is inside."""
    if n == 1:
        return al, ah
    pl, ph = np.power(al, float(n)), np.power(ah, float(n))
    l1, u1 = _widen(pl)
    l2, u2 = _widen(ph)
    if n % 2:  # odd: increasing
        return l1, u2
    inside = (al <= 0) & (ah >= 0)
    lo = np.where(inside, 0.0, np.minimum(l1, l2))
    return np.maximum(lo, 0.0), np.maximum(u1, u2)  # x^(2k) >= 0: clamp is safe


def _i_pow(al, ah, bl, bh, int_exponent):
    """``x^y``: integer point exponents exactly (x^-n = 1/x^n); else a positive base.

    For ``x > 0``, ``x^y = exp(y log x)`` with ``y log x`` bilinear in ``(y, log x)``, so its
    extremes over a box are at the four corners; ``0^y = 0`` for ``y > 0`` extends this to x = 0.
    """
    if int_exponent is not None:
        n = int_exponent
        if n == 0:
            return np.ones_like(al), np.ones_like(al), None
        lo, hi = _i_powi(al, ah, abs(n))
        if n > 0:
            return lo, hi, None
        return _i_div(np.ones_like(lo), np.ones_like(hi), lo, hi)
    bad = ~((al > 0) | ((al >= 0) & (bl > 0)))
    al, ah = np.where(bad, 1.0, al), np.where(bad, 1.0, ah)
    los, his = [], []
    for x in (al, ah):
        for y in (bl, bh):
            lo, hi = _widen(np.power(x, y))
            los.append(lo)
            his.append(hi)
    return np.maximum(np.minimum.reduce(los), 0.0), np.maximum.reduce(his), bad  # x^y >= 0 here


_UNARY_I = {"neg": lambda al, ah: (-ah, -al, None), "sq": _i_sq, "abs": _i_abs, "sqrt": _i_sqrt,
            "exp": _i_exp, "log": _i_log, "tanh": _i_tanh, "sin": _i_sin, "cos": _i_cos, "tan": _i_tan,
            "sign": _i_sign, "twice": lambda al, ah: (2.0 * al, 2.0 * ah, None),
            "inv": lambda al, ah: _i_div(np.ones_like(al), np.ones_like(ah), al, ah)}
_BINARY_I = {"add": _i_add, "sub": _i_sub, "mul": _i_mul, "div": _i_div, "min": _i_min, "max": _i_max}

_WHY = {"div": "division by an interval that holds 0", "inv": "division by an interval that holds 0",
        "sqrt": "sqrt of an interval reaching below 0", "log": "log of an interval reaching 0 or below",
        "tan": "tan of an interval that may hold a pole (pi/2 + k pi)",
        "pow": "a power x^y undefined on the interval (non-integer y: the base reaches 0 or below; "
               "y = -n: the base holds 0)",
        "overflow": "the enclosure overflows the double range"}


def _interval_eval(tape, consts, lo, hi):
    """Interval values of ``tape``'s outputs over boxes ``[lo, hi]`` ((k, n) arrays).

    Returns ``(out_lo, out_hi, bad, why)``: ``(k, n_outputs)`` arrays, ``bad`` (k,) True where
    some operation is undefined on its argument interval or overflows, ``why`` ``(op, first box)``
    of the first such operation (or None).  Bad boxes carry placeholder values downstream.
    """
    k = lo.shape[0]
    rl, rh = [], []
    bad = np.zeros(k, dtype=bool)
    why = None
    with np.errstate(all="ignore"):
        for op, a, b in tape.instrs:
            if op == "var":
                vl, vh, nb = lo[:, a], hi[:, a], None
            elif op == "const":
                c = consts[a]
                vl, vh, nb = np.full(k, c[1]), np.full(k, c[2]), None
            elif op == "pow":
                e_op, e_a, _ = tape.instrs[b]
                n = int(consts[e_a][0]) if e_op == "const" and _is_int_point(consts[e_a]) else None
                vl, vh, nb = _i_pow(rl[a], rh[a], rl[b], rh[b], n)
            elif op == "mul" and a == b:
                vl, vh, nb = _i_sq(rl[a], rh[a])
            elif op in _BINARY_I:
                vl, vh, nb = _BINARY_I[op](rl[a], rh[a], rl[b], rh[b])
            else:
                vl, vh, nb = _UNARY_I[op](rl[a], rh[a])
            over = ~(np.isfinite(vl) & np.isfinite(vh))
            if nb is not None or over.any():
                new = (over if nb is None else (nb | over)) & ~bad
                if new.any():
                    if why is None:
                        first = int(np.flatnonzero(new)[0])
                        why = (op if nb is not None and nb[first] else "overflow", first)
                    bad |= new
                vl, vh = np.where(bad, 0.0, vl), np.where(bad, 0.0, vh)
            rl.append(vl)
            rh.append(vh)
    out_lo = np.stack([rl[r] for _, r in tape.outputs], axis=1) if tape.outputs else np.zeros((k, 0))
    out_hi = np.stack([rh[r] for _, r in tape.outputs], axis=1) if tape.outputs else np.zeros((k, 0))
    return out_lo, out_hi, bad, why


def _point_eval(tape, consts, x):
    """Floating-point values of ``tape``'s outputs at points ``x`` ((m, n) -> (m, n_outputs))."""
    m = x.shape[0]
    r = []
    with np.errstate(all="ignore"):
        for op, a, b in tape.instrs:
            if op == "var":
                v = x[:, a]
            elif op == "const":
                v = np.full(m, consts[a][0])
            elif op == "pow":
                v = np.power(r[a], r[b])
            else:
                A = r[a]
                B = r[b] if b >= 0 else None
                v = {"add": np.add, "sub": np.subtract, "mul": np.multiply, "div": np.divide,
                     "min": np.minimum, "max": np.maximum}[op](A, B) if op in _BINARY_I else \
                    {"neg": np.negative, "sq": lambda t: t * t, "abs": np.abs, "sqrt": np.sqrt, "exp": np.exp,
                     "log": np.log, "tanh": np.tanh, "sin": np.sin, "cos": np.cos, "tan": np.tan,
                     "sign": np.sign, "twice": lambda t: 2.0 * t, "inv": lambda t: 1.0 / t}[op](A)
            r.append(v)
    return np.stack([r[reg] for _, reg in tape.outputs], axis=1)


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

    Raises
    ------
    ExpressionError
        A syntax error, an unknown symbol or an unsupported casadi operation; the message names
        the component, the position and what was expected.
    """

    def __init__(self, f, x=None, *, name: str | None = None):
        self.name = name
        self._consts = []
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
                reg = _Parser(e, self.n_dims, b, self._label(i, colon=False).rstrip()).parse()
                self._tapes.append(_Tape(b.instrs, [(0, reg)]))
        self._jac = None  # built on first use (casadi)
        self._multi_use = np.array([_multi_use(t, self.n_dims) for t in self._tapes])  # (n_out, n) bool
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

        x = ca.SX.sym("x", self.n_dims)
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
        """(m, n, n) floating-point Jacobian ``d f_i / d x_j`` at points ``x`` (casadi's exact one)."""
        x = self._points(x, "x")
        out = np.zeros((x.shape[0], self.n_dims, self.n_dims))
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
        if x_next.shape != x.shape:
            raise DimensionError(f"{self._label(None)}x_next must have shape {x.shape} like x; got {x_next.shape}")
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
        cb = np.zeros((L.shape[0], self.n_dims, self.n_dims))
        loose = np.max(excess, axis=1) > tol
        if loose.any():
            cl, ch, cb_l = self._centred(L[loose], U[loose])
            el[loose] = np.maximum(el[loose], cl)  # both enclose f: so does the intersection
            eh[loose] = np.minimum(eh[loose], ch)
            cb[loose] = cb_l
            excess[loose] = (eh[loose] - el[loose]) - (sh[loose] - sl[loose])
        return el, eh, excess, cb

    def _sampled(self, lo, hi):
        """Min and max of the computed values at the centre and the vertices (face centres if n > 8)."""
        k, n = lo.shape
        c = 0.5 * lo + 0.5 * hi
        if n <= 8:
            corners = (np.arange(2 ** n)[:, None] >> np.arange(n)[None, :]) & 1  # (2^n, n)
            pts = np.where(corners[None].astype(bool), hi[:, None, :], lo[:, None, :])
        else:
            eye = np.eye(n, dtype=bool)
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
        if n <= 8:
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
        if x.ndim != 2 or x.shape[1] != self.n_dims:
            raise DimensionError(f"{self._label(None)}{what} must have shape (m, {self.n_dims}); got {x.shape}")
        return x

    def _boxes(self, lower, upper):
        lower = np.asarray(lower, dtype=float)
        upper = np.asarray(upper, dtype=float)
        for what, a in (("lower", lower), ("upper", upper)):
            if a.ndim != 2 or a.shape[1] != self.n_dims:
                raise DimensionError(f"{self._label(None)}{what} must have shape (k, {self.n_dims}); got {a.shape}")
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

    def __call__(self, x) -> np.ndarray:
        """``evaluate(x)``: ``(k, n) -> (k, n)`` floating-point values."""
        return self.evaluate(x)

    def fingerprint(self) -> str:
        """A digest of the expression graphs and the constants' enclosures (cache keys)."""
        import hashlib

        h = hashlib.sha256(b"KnownDynamics")
        h.update(repr([(t.instrs, t.outputs) for t in self._tapes]).encode())
        h.update(np.asarray(self._consts, dtype=float).tobytes())
        return h.hexdigest()

    def __repr__(self):
        return f"KnownDynamics({list(self.expressions)!r})"


def _multi_use(tape, n):
    """(n,) bool: does variable j reach the output along more than one path of the graph?"""
    paths = [0] * len(tape.instrs)
    for _, reg in tape.outputs:
        paths[reg] += 1
    for r in range(len(tape.instrs) - 1, -1, -1):
        op, a, b = tape.instrs[r]
        if op in ("var", "const") or paths[r] == 0:
            continue
        paths[a] += paths[r]
        if b >= 0 and not (op == "mul" and a == b):  # x*x is evaluated as x^2: one use
            paths[b] += paths[r]
    out = np.zeros(n, dtype=bool)
    for r, (op, a, _) in enumerate(tape.instrs):
        if op == "var" and paths[r] > 1:
            out[a] = True
    return out


def _is_casadi(obj):
    mod = type(obj).__module__ or ""
    return mod.startswith("casadi")


def _box_text(lo, hi):
    return " x ".join(f"[{a:.6g}, {b:.6g}]" for a, b in zip(lo, hi))


def _point_text(x):
    return "(" + ", ".join(f"{a:.6g}" for a in x) + ")"
