r"""Second-order Taylor models of a network's values over boxes.

A :class:`Quad` stands for functions on the cells :math:`|x - c| \le w` with

.. math:: q(x) \in q_0 + L u + u^\top Q u + [-\rho, \rho], \qquad u = x - c,

so second-order terms keep their signs (a sum over hundreds of Fourier features of a nominal
field cancels in them) and only third-order terms and rounding go into the remainder. Used for
the nominal field f, whose Fourier features (about 100 radians per unit) make a first-order
remainder grow with the square of a cell's width times 1e4. Arrays: cells first; L has a last
axis of n, Q two.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from snds.certify import interval as ia
from snds.certify.interval import Iv

__all__ = ["THIRD_DERIVATIVE_BOUNDS", "Quad", "apply", "concat", "variable"]

_U = ia.UNIT
_FN_SLACK = 4 * ia.LIBM_RELATIVE

#: Global bounds of |g'''|: 1 for sin and cos; silu''' peaks at 0.30818 (on a grid of step
#: 1e-4 over [-40, 40], where |silu''''| <= 1/2 bounds the error of the grid's maximum by 5e-5;
#: beyond it, |silu'''| < 1e-15).
THIRD_DERIVATIVE_BOUNDS = {"sin": 1.0, "cos": 1.0, "silu": 0.31}


def _sig(v: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * v))


def _silu(v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    s = _sig(v)
    return v * s, s * (1 + v * (1 - s)), s * (1 - s) * (2 + v * (1 - 2 * s))


_FUNCTIONS: dict[str, Callable[[np.ndarray], tuple]] = {
    "sin": lambda v: (np.sin(v), np.cos(v), -np.sin(v)),
    "cos": lambda v: (np.cos(v), -np.sin(v), -np.cos(v)),
    "silu": _silu,
}


@dataclass(frozen=True, eq=False)
class Quad:
    """q0 (C, k), L (C, n, k), Q (C, n, n, k), remainder (C, k); half-widths w (C, n).

    The value's axis k is last everywhere, so a linear layer is one product per part."""

    c0: np.ndarray
    lin: np.ndarray
    quad: np.ndarray
    rem: np.ndarray
    w: np.ndarray

    def spreads(self) -> tuple[np.ndarray, np.ndarray]:
        """Upper bounds of |L u| and |u^T Q u| over the cells, each (C, k)."""
        w = self.w[:, :, None]
        linear = (np.abs(self.lin) * w).sum(1)
        square = (np.abs(self.quad) * w[:, :, None] * w[:, None, :]).sum((1, 2))
        n = self.w.shape[1]
        return ia.up(linear, n + 2), ia.up(square, n * n + 4)

    def radius(self) -> np.ndarray:
        """Upper bound of |q(x) - q0| over the cells."""
        linear, square = self.spreads()
        return ia.up(linear + square + self.rem, 3)

    def size(self) -> np.ndarray:
        """|q0| + radius: the scale that rounding errors are relative to."""
        return np.abs(self.c0) + self.radius()

    def interval(self) -> Iv:
        """The enclosure as intervals."""
        r = self.radius()
        return ia.from_bounds(
            self.c0 - r - np.abs(self.c0) * 2 * _U, self.c0 + r + np.abs(self.c0) * 2 * _U
        )

    def matmul(self, weight: np.ndarray) -> Quad:
        """q @ W over the value's last axis, W (k, j) exact floats."""
        k = weight.shape[0]
        absolute = np.abs(weight)
        c0 = self.c0 @ weight
        lin = self.lin @ weight
        quad = self.quad @ weight
        rem = self.rem @ absolute + (1.01 * (k + 4) * _U) * (self.size() @ absolute)
        return Quad(c0, lin, quad, ia.up(rem, k + 4), self.w)

    def shift(self, constant: Iv) -> Quad:
        """Plus constant intervals (broadcast over the cells)."""
        c0 = self.c0 + constant.m
        rem = self.rem + constant.r + _U * np.abs(c0) * 2
        return Quad(c0, self.lin, self.quad, ia.up(rem, 3), self.w)


def variable(center: np.ndarray, half: np.ndarray) -> Quad:
    """x on the cells |x - c| <= w: q0 = c, L = I, Q = 0."""
    c, n = center.shape
    eye = np.broadcast_to(np.eye(n), (c, n, n)).copy()
    return Quad(center.copy(), eye, np.zeros((c, n, n, n)), np.zeros((c, n)), half)


def concat(parts: Sequence[Quad]) -> Quad:
    """Models side by side along the value's last axis."""
    return Quad(
        np.concatenate([p.c0 for p in parts], -1),
        np.concatenate([p.lin for p in parts], -1),
        np.concatenate([p.quad for p in parts], -1),
        np.concatenate([p.rem for p in parts], -1),
        parts[0].w,
    )


def apply(x: Quad, name: str) -> Quad:
    r"""g(q) elementwise for g of :data:`THIRD_DERIVATIVE_BOUNDS`:

    .. math:: g(q_0 + \delta) = g(q_0) + g'(q_0) \delta + \tfrac12 g''(q_0) \delta^2
              + \tfrac16 g'''(\xi) \delta^3,

    with :math:`\delta = L u + u^\top Q u + r`; the terms in :math:`(L u)^2` join Q, the rest
    of :math:`\delta^2` and the cubic term join the remainder.
    """
    g0, g1, g2 = _FUNCTIONS[name](x.c0)
    linear, square = x.spreads()
    tail = ia.up(square + x.rem, 2)  # |u^T Q u + r|
    reach = ia.up(linear + tail, 2)
    lin = g1[:, None, :] * x.lin
    outer = x.lin[:, :, None, :] * x.lin[:, None, :, :]
    quad = g1[:, None, None, :] * x.quad + (0.5 * g2)[:, None, None, :] * outer
    rem = (
        np.abs(g1) * x.rem
        + 0.5 * np.abs(g2) * (tail * tail + 2 * linear * tail)
        + (THIRD_DERIVATIVE_BOUNDS[name] / 6) * reach**3
    )
    # Rounding of g0, g1, g2 (libm) and of the products that formed L and Q.
    rem = rem + _FN_SLACK * (np.abs(g0) + np.abs(g1) * reach + np.abs(g2) * reach * reach)
    rem = rem + (8 * _U) * (np.abs(g1) * reach + np.abs(g2) * linear * linear) + ia.TINY
    return Quad(g0, lin, quad, ia.up(rem, 8), x.w)
