r"""Second-order Taylor jets of interval arithmetic: value, gradient and Hessian over boxes.

A :class:`Jet` of k functions of :math:`x \in \mathbb{R}^n` over a batch of C boxes holds
intervals of their values (C, k), their gradients (C, n, k) and, for a second-order jet, their
Hessians (C, n, n, k), each containing every value the exact function takes over its box.
Forward-mode chain rules carry them through linear maps and elementwise functions
(:math:`\nabla s(u) = s'(u) \nabla u`, :math:`\nabla^2 s(u) = s'(u) \nabla^2 u + s''(u)
\nabla u \nabla u^\top`), so a network's jet comes from one forward pass with no symbolic
Hessian. The state dimension n is small (2 or 3 here), so a Hessian is a handful of numbers.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from snds.certify import affine
from snds.certify import interval as ia
from snds.certify.interval import Iv

__all__ = ["Jet", "affine_variable", "concat", "elementwise", "linear", "product", "variable"]


@dataclass(frozen=True)
class Jet:
    """Value (C, k), gradient (C, n, k) and Hessian (C, n, n, k, or None) intervals."""

    value: Iv
    grad: Iv
    hess: Iv | None

    def __add__(self, other: Jet) -> Jet:
        hess = None if self.hess is None or other.hess is None else self.hess + other.hess
        return Jet(self.value + other.value, self.grad + other.grad, hess)

    def __sub__(self, other: Jet) -> Jet:
        hess = None if self.hess is None or other.hess is None else self.hess - other.hess
        return Jet(self.value - other.value, self.grad - other.grad, hess)

    def shift(self, constant: Iv) -> Jet:
        """Plus constants (broadcast over the value's shape)."""
        return Jet(self.value + constant, self.grad, self.hess)

    def sum(self) -> Jet:
        """The sum of the k functions, a jet of one function."""
        hess = None if self.hess is None else self.hess.sum(-1)[..., None]
        return Jet(self.value.sum(-1)[..., None], self.grad.sum(-1)[..., None], hess)


def affine_variable(center: np.ndarray, half: np.ndarray, *, order: int = 2) -> Jet:
    """The identity over the cells |x - c| <= w (C, n) as Taylor models
    (:mod:`snds.certify.affine`): value x, gradient I, Hessian 0, all exact."""
    c, n = center.shape
    zeros = np.zeros

    def constant(array: np.ndarray) -> affine.Aff:
        return affine.Aff(array, zeros((*array.shape, n)), zeros(array.shape), half)

    eye = np.broadcast_to(np.eye(n), (c, n, n)).copy()
    hess = constant(zeros((c, n, n, n))) if order == 2 else None
    return Jet(affine.variable(center, half), constant(eye), hess)


def variable(lo: np.ndarray, hi: np.ndarray, *, order: int = 2) -> Jet:
    """The identity :math:`x \\mapsto x` over boxes [lo, hi] (C, n): its value the box, its
    gradient the identity matrix."""
    c, n = lo.shape
    eye = np.broadcast_to(np.eye(n), (c, n, n)).copy()
    hess = ia.point(np.zeros((c, n, n, n))) if order == 2 else None
    return Jet(ia.from_bounds(lo, hi), ia.point(eye), hess)


def linear(x: Jet, weight: np.ndarray | Iv, bias: np.ndarray | Iv | None = None) -> Jet:
    """The jet of x @ W + b, W (k, j) exact floats or intervals."""
    value = x.value.matmul(weight)
    if bias is not None:
        value = value + (bias if isinstance(bias, Iv) else ia.point(bias))
    hess = None if x.hess is None else x.hess.matmul(weight)
    return Jet(value, x.grad.matmul(weight), hess)


def elementwise(x: Jet, derivatives: Callable[[Iv], tuple[Iv, Iv, Iv | None]]) -> Jet:
    """The jet of s(x) elementwise, from enclosures (s, s', s'') over the value's intervals
    (s'' may be None for a first-order jet)."""
    s0, s1, s2 = derivatives(x.value)
    grad = x.grad * s1[:, None, :]
    hess = None
    if x.hess is not None:
        g = x.grad
        outer = g[:, :, None, :] * g[:, None, :, :]
        hess = x.hess * s1[:, None, None, :] + outer * s2[:, None, None, :]
    return Jet(s0, grad, hess)


def product(a: Jet, b: Jet) -> Jet:
    """The jet of a * b elementwise."""
    value = a.value * b.value
    grad = a.grad * b.value[:, None, :] + b.grad * a.value[:, None, :]
    hess = None
    if a.hess is not None and b.hess is not None:
        cross = a.grad[:, :, None, :] * b.grad[:, None, :, :]
        cross_t = cross.swap12()
        hess = (
            a.hess * b.value[:, None, None, :]
            + b.hess * a.value[:, None, None, :]
            + cross
            + cross_t
        )
    return Jet(value, grad, hess)


def concat(jets: list[Jet]) -> Jet:
    """Jets side by side (their k's add up)."""

    def cat(parts: list):
        if not isinstance(parts[0], Iv):
            return affine.concat(parts)
        return Iv(
            np.concatenate([p.m for p in parts], -1), np.concatenate([p.r for p in parts], -1)
        )

    hess = None if any(j.hess is None for j in jets) else cat([j.hess for j in jets])
    return Jet(cat([j.value for j in jets]), cat([j.grad for j in jets]), hess)
