r"""First-order Taylor models over boxes: an affine form in the offset plus a sound remainder.

Plain interval arithmetic through a network forgets that its neurons depend on the same
input: over a cell of width 1e-3 the interval Jacobian of the nominal field came out 100
times the true one (docs/guarantee.md, "Certificate"). A Taylor model keeps that dependence:
an :class:`Aff` stands for functions :math:`q(x)` on the cells :math:`|x - c| \le w`
(componentwise) with

.. math:: q(x) \in q_0 + L (x - c) + [-\rho, \rho],

where :math:`q_0` and L are float arrays and the remainder :math:`\rho \ge 0` collects what
the affine part does not carry: second-order terms (through a global bound of the next
derivative of every elementwise function) and every rounding error of the float arithmetic
(bounded as in :mod:`snds.certify.interval`). Linear layers act exactly on the affine part,
so the enclosures are tight to second order in the cell's width.

Arrays have the cells first (C, ...); L has one more, last axis: the n offsets.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from snds.certify import interval as ia
from snds.certify.interval import Iv

__all__ = ["Aff", "ELEMENTWISE", "apply", "variable"]

_U = ia.UNIT
#: Relative slack for the float evaluation of an elementwise function and its derivative
#: (libm's errors are a few ulps; see :data:`snds.certify.interval.LIBM_RELATIVE`).
_FN_SLACK = 4 * ia.LIBM_RELATIVE


def _gamma(k: int) -> float:
    return 1.01 * (k + 4) * _U


@dataclass(frozen=True, eq=False)
class Aff:
    """q0 (C, ...), L (C, ..., n), remainder (C, ...) and the cells' half-widths w (C, n)."""

    c0: np.ndarray
    lin: np.ndarray
    rem: np.ndarray
    w: np.ndarray

    def spread(self) -> np.ndarray:
        """An upper bound of |L (x - c)| over the cells, (C, ...)."""
        lin = np.abs(self.lin)
        shape = (len(self.w),) + (1,) * (lin.ndim - 2) + (self.w.shape[1],)
        return ia.up((lin * self.w.reshape(shape)).sum(-1), self.w.shape[1] + 2)

    def radius(self) -> np.ndarray:
        """Upper bound of |q(x) - q0| over the cells."""
        return ia.up(self.spread() + self.rem, 2)

    def _with(self, c0: np.ndarray, lin: np.ndarray, rem: np.ndarray, ops: int = 2) -> Aff:
        # Rounding of q0 and L: relative to their size (ops float operations deep).
        lin_size = np.abs(lin)
        shape = (len(self.w),) + (1,) * (lin.ndim - 2) + (self.w.shape[1],)
        size = np.abs(c0) + (lin_size * self.w.reshape(shape)).sum(-1)
        return Aff(c0, lin, ia.up(rem + (2.02 * ops * _U) * size, ops + 4), self.w)

    @property
    def lo(self) -> np.ndarray:
        """Lower bounds over the cells."""
        low = self.c0 - self.radius()
        return low - np.abs(low) * (2 * _U) - ia.TINY

    @property
    def hi(self) -> np.ndarray:
        """Upper bounds over the cells."""
        high = self.c0 + self.radius()
        return high + np.abs(high) * (2 * _U) + ia.TINY

    @property
    def mag(self) -> np.ndarray:
        """Upper bounds of the absolute values."""
        return ia.up(np.abs(self.c0) + self.radius(), 2)

    def interval(self) -> Iv:
        """The enclosure as intervals."""
        return ia.from_bounds(self.lo, self.hi)

    def __getitem__(self, index) -> Aff:  # noqa: ANN001
        if not isinstance(index, tuple):
            index = (index,)
        return Aff(self.c0[index], self.lin[(*index, slice(None))], self.rem[index], self.w)

    def __add__(self, other: Aff | Iv) -> Aff:
        if isinstance(other, Iv):
            c0 = self.c0 + other.m
            return self._with(
                c0,
                np.broadcast_to(self.lin, (*c0.shape, self.lin.shape[-1])),
                self.rem + other.r,
                1,
            )
        return self._with(self.c0 + other.c0, self.lin + other.lin, self.rem + other.rem, 1)

    def __sub__(self, other: Aff | Iv) -> Aff:
        return self + (-other)

    def __neg__(self) -> Aff:
        return Aff(-self.c0, -self.lin, self.rem, self.w)

    def __mul__(self, other: Aff) -> Aff:
        a0, b0 = self.c0, other.c0
        lin = a0[..., None] * other.lin + b0[..., None] * self.lin
        cross = ia.up(self.radius() * other.radius(), 2)
        rem = np.abs(a0) * other.rem + np.abs(b0) * self.rem + cross
        return self._with(a0 * b0, lin, rem, 3)

    def square(self) -> Aff:
        """q^2."""
        return self * self

    def scale(self, c: float) -> Aff:
        """Times an exact float."""
        return self._with(self.c0 * c, self.lin * c, self.rem * abs(c), 1)

    def shift(self, c: Iv) -> Aff:
        """Plus constant intervals."""
        return self + c

    def sum(self, axis: int) -> Aff:
        """Sum along an axis of the value's shape (a negative axis counts from its end)."""
        axis = axis % self.c0.ndim
        k = self.c0.shape[axis]
        return self._with(
            self.c0.sum(axis), self.lin.sum(axis), self.rem.sum(axis) * (1 + _gamma(k)), k + 2
        )

    def swap12(self) -> Aff:
        """Axes 1 and 2 of the value exchanged."""
        return Aff(
            np.swapaxes(self.c0, 1, 2),
            np.swapaxes(self.lin, 1, 2),
            np.swapaxes(self.rem, 1, 2),
            self.w,
        )

    def matmul(self, weight: np.ndarray | Iv) -> Aff:
        """q @ W over the last axis of the value, W (k, j) floats or intervals."""
        if isinstance(weight, Iv):
            exact = self.matmul(weight.m)
            extra = (np.abs(self.c0) + self.radius()) @ weight.r
            return Aff(exact.c0, exact.lin, ia.up(exact.rem + extra, weight.m.shape[0] + 2), self.w)
        k = weight.shape[0]
        absolute = np.abs(weight)
        c0 = self.c0 @ weight
        lin = np.swapaxes(np.swapaxes(self.lin, -1, -2) @ weight, -1, -2)
        size = np.abs(self.c0) + self.spread()
        rem = self.rem @ absolute + _gamma(k) * (size @ absolute)
        return Aff(c0, lin, ia.up(rem, k + 4), self.w)


def concat(parts: Sequence[Aff]) -> Aff:
    """Forms side by side along the value's last axis."""
    return Aff(
        np.concatenate([p.c0 for p in parts], -1),
        np.concatenate([p.lin for p in parts], -2),
        np.concatenate([p.rem for p in parts], -1),
        parts[0].w,
    )


def variable(center: np.ndarray, half: np.ndarray) -> Aff:
    """x itself on the cells |x - c| <= w: q0 = c, L = I, no remainder."""
    c, n = center.shape
    eye = np.broadcast_to(np.eye(n), (c, n, n)).copy()
    return Aff(center.copy(), eye, np.zeros((c, n)), half)


def apply(x: Aff, fns: Sequence[Callable[[np.ndarray], np.ndarray]], bound: float) -> Aff:
    r"""g(q) for g with derivative g' (``fns`` = [g, g']) and :math:`|g''| \le` ``bound``
    everywhere: :math:`g(q_0) + g'(q_0)(L u + \rho') + \tfrac12 g''(\xi) (\dots)^2`."""
    g, dg = fns
    v0, d0 = g(x.c0), dg(x.c0)
    reach = x.radius()
    rem = np.abs(d0) * x.rem + 0.5 * bound * reach * reach
    rem = rem + _FN_SLACK * (np.abs(v0) + np.abs(d0) * reach) + ia.TINY
    return x._with(v0, d0[..., None] * x.lin, rem, 3)


def _sig(v: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * v))


def _leaky(c: float) -> list:
    """s = c u + (1 - c) softplus(u) and its derivatives, with global bounds of |s''|,
    |s'''| and |s''''|: (1 - c) times 1/4, 1/(6 sqrt 3) and 1/8 (maxima of sigma (1 - sigma),
    of its derivative and of its second derivative)."""

    def d2(v: np.ndarray) -> np.ndarray:
        s = _sig(v)
        return (1 - c) * s * (1 - s)

    def d3(v: np.ndarray) -> np.ndarray:
        s = _sig(v)
        return (1 - c) * s * (1 - s) * (1 - 2 * s)

    def d4(v: np.ndarray) -> np.ndarray:
        s = _sig(v)
        return (1 - c) * s * (1 - s) * (1 - 6 * s + 6 * s * s)

    fns = [lambda v: c * v + (1 - c) * np.logaddexp(0.0, v), lambda v: c + (1 - c) * _sig(v)]
    fns += [d2, d3, d4]
    bounds = [None, None, (1 - c) * 0.2501, (1 - c) * 0.0963, (1 - c) * 0.1251]
    return [fns, bounds]


def _trig(first: str) -> list:
    order = ["sin", "cos", "-sin", "-cos"]
    table = {
        "sin": np.sin,
        "cos": np.cos,
        "-sin": lambda v: -np.sin(v),
        "-cos": lambda v: -np.cos(v),
    }
    start = order.index(first)
    fns = [table[order[(start + j) % 4]] for j in range(5)]
    return [fns, [None, None, 1.0, 1.0, 1.0]]


def _silu() -> list:
    def silu(v: np.ndarray) -> np.ndarray:
        return v * _sig(v)

    def slope(v: np.ndarray) -> np.ndarray:
        s = _sig(v)
        return s * (1 + v * (1 - s))

    def curve(v: np.ndarray) -> np.ndarray:
        s = _sig(v)
        return s * (1 - s) * (2 + v * (1 - 2 * s))

    # |silu''| <= 1/2 (its maximum, at 0); |silu'''| <= 1/2 bounds it with room.
    return [[silu, slope, curve], [None, None, 0.5001, 0.5001]]


#: Elementwise functions by name: their derivatives g, g', g'', ... and global bounds of
#: |g^(k)| (None where unbounded or not needed).
ELEMENTWISE = {
    "sin": _trig("sin"),
    "cos": _trig("cos"),
    "silu": _silu(),
    "smooth_leaky": _leaky(0.1),
    "softplus": _leaky(0.0),
}


def derivative_forms(name: str, x: Aff, orders: int) -> list[Aff]:
    """g(q), g'(q), ... (``orders`` of them) as Taylor models, for a name of
    :data:`ELEMENTWISE`."""
    fns, bounds = ELEMENTWISE[name]
    return [apply(x, fns[j : j + 2], bounds[j + 2]) for j in range(orders)]
