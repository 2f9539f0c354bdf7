"""Safe parser for process expressions such as ``1.5*exp(-0.7*s)/(4*s+1)^2``.

A hand-written tokenizer and recursive-descent parser (never ``eval``).
Grammar::

    expr    := term (('+' | '-') term)*
    term    := unary (('*' | '/') unary)*
    unary   := ('+' | '-') unary | power
    power   := primary (('^' | '**') unary)?        exponent: integer constant >= 0
    primary := NUMBER | 's' | 'exp' '(' expr ')' | '(' expr ')'

Every sub-expression evaluates to ``num(s)/den(s) * exp(-delay*s)``; the
argument of ``exp`` must simplify to ``-L*s`` with ``L >= 0`` (seconds).
Implicit multiplication (``2s``) is rejected.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from autotuner.engine.plant.process import Process

_EPS = np.finfo(float).eps
_MAX_EXPONENT = 64  # beyond this the expanded coefficients lose all accuracy
_NUMBER = re.compile(r"(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_OPERATORS = ("**", "+", "-", "*", "/", "^", "(", ")")


class ExpressionError(ValueError):
    """A process expression that cannot be parsed or has no valid meaning.

    ``position`` is the 0-based character index of the offending ``token``
    in ``text``; the message shows both and a caret line under the input.

    ``reason``: what is wrong; ``detail``: more of it ("": nothing).
    """

    def __init__(self, reason: str, text: str, position: int, token: str,
                 detail: str = "") -> None:
        self.text = text
        self.position = position
        self.token = token
        self._args = (reason, text, position, token, detail)
        detail = f": {detail}" if detail else ""
        super().__init__(f"{reason} at position {position} in {text!r}{detail}\n"
                         f"  {text}\n  {' ' * position}^")

    def __reduce__(self) -> tuple:
        # Exceptions pickle through their args; these need the constructor's
        # (a worker process of the benchmark sends them back).
        return (type(self), self._args)


@dataclass(frozen=True)
class _Token:
    kind: str  # "num", "name", "op" or "end"
    text: str
    pos: int
    value: float = 0.0


def _tokenize(text: str) -> list[_Token]:
    tokens: list[_Token] = []
    i = 0
    while i < len(text):
        ch = text[i]
        if ch.isspace():
            i += 1
            continue
        if m := _NUMBER.match(text, i):
            # "2e-" or "2e" would otherwise split into a number and a name
            if re.match(r"[eE](?:[+-]|[^A-Za-z_]|$)", text[m.end():]):
                bad = re.match(r"[0-9.]*[eE][+-]?", text[i:]).group()
                raise ExpressionError(f"malformed number {bad!r}", text, i, bad,
                                      "an exponent needs digits, e.g. 2e-3")
            value = float(m.group())
            if not math.isfinite(value):
                raise ExpressionError(f"number {m.group()!r} is out of range", text, i, m.group())
            tokens.append(_Token("num", m.group(), i, value))
            i = m.end()
        elif m := _NAME.match(text, i):
            tokens.append(_Token("name", m.group(), i))
            i = m.end()
        else:
            op = next((o for o in _OPERATORS if text.startswith(o, i)), None)
            if op is None:
                raise ExpressionError(f"invalid character {ch!r}", text, i, ch)
            tokens.append(_Token("op", op, i))
            i += len(op)
    tokens.append(_Token("end", "", len(text)))
    return tokens


def _trim(p: np.ndarray) -> np.ndarray:
    nz = np.flatnonzero(p)
    return p[nz[0]:] if nz.size else p[-1:]


def _poly_add(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    n = max(len(a), len(b))
    a = np.pad(a, (n - len(a), 0))
    b = np.pad(b, (n - len(b), 0))
    total = a + b
    # Cancellation down to rounding level is an exact zero: keeps the degree
    # and the terms at s = 0 (integrators) right, e.g. in (s+1) - s.
    total[np.abs(total) <= 4 * _EPS * (np.abs(a) + np.abs(b))] = 0.0
    return _trim(total)


def _mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return _trim(np.convolve(a, b))


def _is_zero(p: np.ndarray) -> bool:
    return len(p) == 1 and p[0] == 0.0


@dataclass(frozen=True)
class _Value:
    """num(s)/den(s)*exp(-delay*s) of the source span text[start:end]."""

    num: np.ndarray
    den: np.ndarray
    delay: float
    start: int
    end: int

    def constant(self) -> float | None:
        if len(self.num) == 1 and len(self.den) == 1 and self.delay == 0.0:
            return float(self.num[0] / self.den[0])
        return None


class _Parser:
    def __init__(self, text: str) -> None:
        self.text = text
        self.tokens = _tokenize(text)
        self.i = 0

    # -- helpers -------------------------------------------------------------
    @property
    def tok(self) -> _Token:
        return self.tokens[self.i]

    def _error(self, reason: str, pos: int, token: str, detail: str = "") -> ExpressionError:
        return ExpressionError(reason, self.text, pos, token, detail)

    def _unexpected(self, detail: str = "") -> ExpressionError:
        t = self.tok
        if t.kind == "end":
            return self._error("unexpected end of expression", t.pos, "", detail)
        return self._error(f"unexpected token {t.text!r}", t.pos, t.text, detail)

    def _accept(self, *ops: str) -> _Token | None:
        if self.tok.kind == "op" and self.tok.text in ops:
            self.i += 1
            return self.tokens[self.i - 1]
        return None

    def _span(self, v: _Value) -> str:
        return self.text[v.start:v.end]

    # -- grammar -------------------------------------------------------------
    def parse(self) -> _Value:
        if self.tok.kind == "end":
            raise self._error("empty expression", 0, "")
        value = self.expr()
        if self.tok.kind != "end":
            if self.tok.text == ")":
                raise self._unexpected("unbalanced parentheses, no matching '('")
            raise self._unexpected(self._implicit_hint())
        return value

    def _implicit_hint(self) -> str:
        prev = self.tokens[self.i - 1]
        if self.tok.kind in ("num", "name") or self.tok.text == "(":
            if prev.kind in ("num", "name") or prev.text == ")":
                return "implicit multiplication is not allowed, write '*'"
        return ""

    def expr(self) -> _Value:
        left = self.term()
        while op := self._accept("+", "-"):
            right = self.term()
            left = self._add(left, right, op)
        return left

    def term(self) -> _Value:
        left = self.unary()
        while op := self._accept("*", "/"):
            right = self.unary()
            if op.text == "*":
                left = _Value(_mul(left.num, right.num), _mul(left.den, right.den),
                              left.delay + right.delay, left.start, right.end)
            else:
                if _is_zero(right.num):
                    raise self._error(f"division by zero {self._span(right)!r}",
                                      right.start, self._span(right))
                left = _Value(_mul(left.num, right.den), _mul(left.den, right.num),
                              left.delay - right.delay, left.start, right.end)
        return left

    def unary(self) -> _Value:
        if op := self._accept("-", "+"):
            v = self.unary()
            num = -v.num if op.text == "-" else v.num
            return _Value(num, v.den, v.delay, op.pos, v.end)
        return self.power()

    def power(self) -> _Value:
        base = self.primary()
        if not self._accept("^", "**"):
            return base
        exponent = self.unary()
        k = exponent.constant()
        span = self._span(exponent)
        if k is None or k < 0 or k != round(k):
            got = "got an expression of s or exp" if k is None else f"got {k:g}"
            raise self._error(f"invalid exponent {span!r}", exponent.start, span,
                              f"must be a non-negative integer constant, {got}")
        if k > _MAX_EXPONENT:
            raise self._error(f"exponent {span!r} too large", exponent.start, span,
                              f"at most {_MAX_EXPONENT}")
        num, den = np.ones(1), np.ones(1)
        for _ in range(int(k)):
            num, den = _mul(num, base.num), _mul(den, base.den)
        return _Value(num, den, base.delay * int(k), base.start, exponent.end)

    def primary(self) -> _Value:
        t = self.tok
        if t.kind == "num":
            self.i += 1
            return _Value(np.array([t.value]), np.ones(1), 0.0, t.pos, t.pos + len(t.text))
        if t.kind == "name":
            self.i += 1
            if t.text == "s":
                return _Value(np.array([1.0, 0.0]), np.ones(1), 0.0, t.pos, t.pos + 1)
            if t.text == "exp":
                return self._exp(t)
            if self.tok.text == "(":
                raise self._error(f"unknown function {t.text!r}", t.pos, t.text,
                                  "only exp(...) is supported")
            raise self._error(f"unknown identifier {t.text!r}", t.pos, t.text,
                              "the only variable is 's'")
        if open_ := self._accept("("):
            inner = self.expr()
            self._close(open_)
            return _Value(inner.num, inner.den, inner.delay, open_.pos, self.tokens[self.i - 1].pos + 1)
        raise self._unexpected()

    def _close(self, open_: _Token) -> None:
        if not self._accept(")"):
            if self.tok.kind == "end":
                raise self._error("unclosed '('", open_.pos, "(", "unbalanced parentheses")
            raise self._unexpected(self._implicit_hint() or "expected ')'")

    def _exp(self, name: _Token) -> _Value:
        open_ = self._accept("(")
        if open_ is None:
            raise self._unexpected("expected '(' after 'exp'")
        arg = self.expr()
        self._close(open_)
        end = self.tokens[self.i - 1].pos + 1
        span = self.text[name.pos:end]
        linear = (arg.delay == 0.0 and len(arg.den) == 1 and len(arg.num) <= 2
                  and (len(arg.num) == 1 or arg.num[1] == 0.0))
        if not linear or (len(arg.num) == 1 and arg.num[0] != 0.0):
            raise self._error(f"invalid dead time {span!r}", name.pos, span,
                              "the argument of exp must have the form -L*s with L >= 0")
        dead_time = -arg.num[0] / arg.den[0] if len(arg.num) == 2 else 0.0
        if dead_time < 0:
            raise self._error(f"positive exponent in {span!r}", name.pos, span,
                              f"a time advance (dead time {dead_time:g} s) is not realisable; "
                              "write exp(-L*s) with L >= 0")
        return _Value(np.ones(1), np.ones(1), dead_time, name.pos, end)

    def _add(self, left: _Value, right: _Value, op: _Token) -> _Value:
        sign = 1.0 if op.text == "+" else -1.0
        if _is_zero(left.num) or _is_zero(right.num):
            delay = right.delay if _is_zero(left.num) else left.delay
        elif math.isclose(left.delay, right.delay, rel_tol=1e-12, abs_tol=1e-15):
            delay = left.delay
        else:
            raise self._error(
                "sum of terms with different dead times", op.pos, op.text,
                f"{left.delay:g} s and {right.delay:g} s; such a sum is not a rational "
                "function times a delay")
        num = _poly_add(_mul(left.num, right.den), sign * _mul(right.num, left.den))
        return _Value(num, _mul(left.den, right.den), delay, left.start, right.end)


def parse_process(text: str) -> Process:
    """Parse a transfer-function expression in s (dead time in seconds) into a Process.

    Raises ExpressionError (a ValueError) with the position and token of the
    problem for syntax errors, unknown names, invalid exponents or dead
    times, division by zero and improper results.

    ``text``: the expression.
    """
    value = _Parser(text).parse()
    stripped = text.strip()
    if value.delay < 0:
        raise ExpressionError("negative net dead time", text, value.start, stripped,
                              f"{value.delay:g} s is a time advance, not realisable")
    num, den = value.num, value.den
    if len(num) > len(den):
        raise ExpressionError(
            "improper transfer function", text, value.start, stripped,
            f"numerator degree {len(num) - 1} > denominator degree {len(den) - 1}, "
            "not physically realisable")
    return Process.from_tf(num, den, value.delay, text=stripped)
