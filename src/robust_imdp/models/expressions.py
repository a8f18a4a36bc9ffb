"""Expressions of ``models.known``: the safe parser, the tape and the casadi bridge.

Expressions are never passed to ``eval``: a recursive-descent parser accepts exactly the
grammar of ``docs/known_dynamics.md`` and builds a tape (a list of instructions in topological
order, common subexpressions shared).  A decimal constant that is not a double (``0.15``) is the
interval between its two neighbouring doubles; ``pi`` is ``[math.pi, nextafter(math.pi, inf)]``.
casadi expressions are read into the same tapes, and tapes written back as casadi expressions
(for casadi's exact Jacobian and for local optimisation).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from robust_imdp.errors import ExpressionError
from robust_imdp.models.intervals import _dn, _is_int_point, _up

__all__ = ["FUNCTIONS"]

#: Functions of the grammar and their number of arguments (None: 2 or more).
FUNCTIONS = {"sin": 1, "cos": 1, "tan": 1, "exp": 1, "log": 1, "sqrt": 1, "abs": 1, "tanh": 1,
             "min": None, "max": None}

_PI_LO = math.pi                                # math.pi < pi (pi = 3.14159265358979323846...)
_PI_HI = float(np.nextafter(math.pi, np.inf))


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
        atom  := number | 'pi' | x<k> | u<k> | func '(' expr (',' expr)* ')' | '(' expr ')'

    ``x<k>`` is state dimension k (1 .. n_dims), ``u<k>`` input k (1 .. n_inputs; none by default): the
    variables are numbered x1..xn, then u1..um (a known part ``f(x, u)`` of an input grid, ``models.inputs``).
    """

    def __init__(self, text, n_dims, builder, label, n_inputs=0):
        self.text, self.n, self.b, self.label = text, n_dims, builder, label
        self.m = int(n_inputs)  # inputs u1..um are the variables n .. n + m - 1 (after x1..xn)
        self.symbols = "x1..x%d" % n_dims + (", u1..u%d" % self.m if self.m else "")
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
                          f"a number, {self.symbols}, pi, a function, an operator + - * / ^ ** or parentheses")
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
            self.fail(0, "empty expression", f"an expression in {self.symbols}")
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
                    self.fail(pos, f"unknown symbol {value!r} (the state has {self.n} dimensions)", self.symbols)
                return self.b.emit("var", k - 1)
            m = re.fullmatch(r"u([1-9][0-9]*)", value)
            if m:
                k = int(m.group(1))
                if k > self.m:
                    why = (f"there are {self.m} inputs" if self.m else
                           "no inputs: u1..um come with an [inputs] table and one [dynamics] f")
                    self.fail(pos, f"unknown symbol {value!r} ({why})", self.symbols)
                return self.b.emit("var", self.n + k - 1)
            if value in FUNCTIONS:
                return self.call(value, pos)
            self.fail(pos, f"unknown symbol {value!r}", f"{self.symbols}, pi or a function {', '.join(FUNCTIONS)}")
        if kind == "op" and value == "(":
            reg = self.expr()
            self.expect(")", "')' closing the '(' at position %d" % pos)
            return reg
        what = "end of the expression" if kind == "end" else f"{value!r}"
        self.fail(pos, f"unexpected {what}", f"a number, {self.symbols}, pi, a function or '('")

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
