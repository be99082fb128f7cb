r"""The re-check's own bounds: second-order Taylor models with interval coefficients.

Written apart from :mod:`snds.certify.interval`, :mod:`~snds.certify.affine`,
:mod:`~snds.certify.quadratic` and :mod:`~snds.certify.jets` (the search's bounds) and sharing
none of their code, so that a bug in one does not hide in both. The arithmetic differs too:
intervals are [lo, hi] pairs whose every float result is pushed outward by one ulp with
``np.nextafter`` (plus the summation-error bound of a dot product), where the search's are
midpoint-radius pairs inflated by relative error bounds; its models keep interval
coefficients (Makino and Berz's Taylor models) where the search's keep float coefficients.

A :class:`TM` stands for functions on the cells :math:`|x - c| \le w` with

.. math:: q(x) \in C + \sum_i L_i u_i + \sum_{ij} Q_{ij} u_i u_j + [-R, R], \qquad u = x - c,

C, L, Q intervals and :math:`R \ge 0`. V's gradient and Hessian are carried as models too
(a jet), so one class serves the nominal field and V.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TM", "Pair", "derivative_models", "jet_variable", "variable"]

_INF = np.inf
_EPS = 2.0**-52


def _down(x: np.ndarray) -> np.ndarray:
    return np.nextafter(x, -_INF)


def _up(x: np.ndarray) -> np.ndarray:
    return np.nextafter(x, _INF)


@dataclass(frozen=True, eq=False)
class Pair:
    """Intervals [lo, hi] (arrays of one shape)."""

    lo: np.ndarray
    hi: np.ndarray

    @property
    def mag(self) -> np.ndarray:
        return np.maximum(np.abs(self.lo), np.abs(self.hi))

    def __add__(self, other: Pair) -> Pair:
        return Pair(_down(self.lo + other.lo), _up(self.hi + other.hi))

    def __neg__(self) -> Pair:
        return Pair(-self.hi, -self.lo)

    def __sub__(self, other: Pair) -> Pair:
        return self + (-other)

    def __mul__(self, other: Pair) -> Pair:
        p = [self.lo * other.lo, self.lo * other.hi, self.hi * other.lo, self.hi * other.hi]
        return Pair(_down(np.minimum.reduce(p)), _up(np.maximum.reduce(p)))

    def times(self, c: np.ndarray) -> Pair:
        """Times exact floats."""
        a, b = self.lo * c, self.hi * c
        return Pair(_down(np.minimum(a, b)), _up(np.maximum(a, b)))

    def dot(self, weight: np.ndarray) -> Pair:
        """self @ W over the last axis, W (k, j) floats: sign-split products, each widened by
        the dot product's error bound (k + 2) eps sum |a_i w_i|."""
        positive, negative = np.maximum(weight, 0.0), np.minimum(weight, 0.0)
        k = weight.shape[0]
        slack = _up(((k + 2) * _EPS) * (self.mag @ np.abs(weight))) + 1e-300
        lo = self.lo @ positive + self.hi @ negative
        hi = self.hi @ positive + self.lo @ negative
        return Pair(_down(lo - slack), _up(hi + slack))

    def __getitem__(self, index) -> Pair:  # noqa: ANN001
        return Pair(self.lo[index], self.hi[index])


def _point(x: np.ndarray) -> Pair:
    x = np.asarray(x, dtype=np.float64)
    return Pair(x, x)


def _grow(x: Pair, r: np.ndarray) -> Pair:
    return Pair(_down(x.lo - r), _up(x.hi + r))


def _sum_up(parts: list[np.ndarray]) -> np.ndarray:
    total = parts[0]
    for part in parts[1:]:
        total = _up(total + part)
    return total


@dataclass(frozen=True, eq=False)
class TM:
    """C (C, ..., k), L (C, n, ..., k), Q (C, n, n, ..., k), R (C, ..., k); w (C, n)."""

    c: Pair
    lin: Pair
    quad: Pair | None
    rem: np.ndarray
    w: np.ndarray

    def _wl(self) -> np.ndarray:
        extra = self.c.lo.ndim - 1
        return self.w.reshape(self.w.shape + (1,) * extra)

    def spread_linear(self) -> np.ndarray:
        """Upper bound of |L u|."""
        return _up((self.lin.mag * self._wl()).sum(1) * (1 + 4 * _EPS))

    def spread_square(self) -> np.ndarray:
        """Upper bound of |u^T Q u| (0 for a first-order model, quad None)."""
        if self.quad is None:
            return np.zeros_like(self.rem)
        w = self._wl()
        return _up((self.quad.mag * w[:, :, None] * w[:, None, :]).sum((1, 2)) * (1 + 8 * _EPS))

    def range(self) -> Pair:
        """The values' enclosure over the cells."""
        spread = _sum_up([self.spread_linear(), self.spread_square(), self.rem])
        return _grow(self.c, spread)

    def __add__(self, other: TM) -> TM:
        return TM(
            self.c + other.c,
            self.lin + other.lin,
            None if self.quad is None or other.quad is None else self.quad + other.quad,
            _up(self.rem + other.rem),
            self.w,
        )

    def __neg__(self) -> TM:
        quad = None if self.quad is None else -self.quad
        return TM(-self.c, -self.lin, quad, self.rem, self.w)

    def __sub__(self, other: TM) -> TM:
        return self + (-other)

    def plus(self, constant: Pair) -> TM:
        """Plus constant intervals."""
        return TM(self.c + constant, self.lin, self.quad, self.rem, self.w)

    def dot(self, weight: np.ndarray) -> TM:
        """Over the last axis, W (k, j) floats."""
        k = weight.shape[0]
        rem = _up((self.rem @ np.abs(weight)) * (1 + (k + 2) * _EPS)) + 1e-300
        quad = None if self.quad is None else self.quad.dot(weight)
        return TM(self.c.dot(weight), self.lin.dot(weight), quad, rem, self.w)

    def dot_pair(self, weight: Pair) -> TM:
        """Over the last axis, W (k, j) intervals: mid W plus the radius's worst case."""
        mid = 0.5 * weight.lo + 0.5 * weight.hi
        radius = _up(np.maximum(weight.hi - mid, mid - weight.lo))
        exact = self.dot(mid)
        extra = _up((self.range().mag @ radius) * (1 + (weight.lo.shape[0] + 2) * _EPS))
        return TM(exact.c, exact.lin, exact.quad, _up(exact.rem + extra), self.w)

    def __mul__(self, other: TM) -> TM:
        """The product, truncated at second order (the rest to the remainder)."""
        a, b = self, other
        c = a.c * b.c
        lin = a.lin * b.c[:, None] + b.lin * a.c[:, None]
        la, qa, lb, qb = a.spread_linear(), a.spread_square(), b.spread_linear(), b.spread_square()
        full_a = _sum_up([a.c.mag, la, qa, a.rem])
        full_b = _sum_up([b.c.mag, lb, qb, b.rem])
        if a.quad is None or b.quad is None:
            # First order: the product of the linear parts joins the remainder.
            quad = None
            rem = _sum_up([la * lb, la * qb, qa * lb, qa * qb, full_a * b.rem, full_b * a.rem])
        else:
            outer = a.lin[:, :, None] * b.lin[:, None, :]
            quad = a.quad * b.c[:, None, None] + b.quad * a.c[:, None, None] + outer
            rem = _sum_up([la * qb, qa * lb, qa * qb, full_a * b.rem, full_b * a.rem])
        return TM(c, lin, quad, _up(rem * (1 + 8 * _EPS)), self.w)

    def __getitem__(self, index) -> TM:  # noqa: ANN001
        """Index the value's axes (cells first)."""
        if not isinstance(index, tuple):
            index = (index,)
        rest = index[1:]
        first = index[0]
        return TM(
            self.c[(first, *rest)],
            self.lin[(first, slice(None), *rest)],
            None if self.quad is None else self.quad[(first, slice(None), slice(None), *rest)],
            self.rem[(first, *rest)],
            self.w,
        )


def variable(center: np.ndarray, half: np.ndarray) -> TM:
    """x on the cells: C = c, L = I."""
    c, n = center.shape
    eye = np.broadcast_to(np.eye(n), (c, n, n)).copy()
    zero = np.zeros((c, n, n, n))
    return TM(_point(center), _point(eye), _point(zero), np.zeros((c, n)), half)


def _constant(values: np.ndarray, half: np.ndarray) -> TM:
    c, n = half.shape
    shape = values.shape[1:]
    return TM(_point(values), _point(np.zeros((c, n, *shape))), None, np.zeros(values.shape), half)


def jet_variable(center: np.ndarray, half: np.ndarray, *, second: bool = False) -> tuple:
    """x, its gradient (the identity, (C, n, n): derivative index then component) and its
    Hessian (zero, (C, n, n, n)), each a first-order model (V's jets are carried to first
    order, their second-order terms in the remainder with global derivative bounds, unless
    ``second``)."""
    c, n = center.shape
    eye = np.broadcast_to(np.eye(n), (c, n, n)).copy()
    x = variable(center, half)
    grad, hess = _constant(eye, half), _constant(np.zeros((c, n, n, n)), half)
    if second:
        return x, _second(grad), _second(hess)
    return TM(x.c, x.lin, None, x.rem, half), grad, hess


def _second(x: TM) -> TM:
    """A first-order model with zero second-order coefficients."""
    n = x.w.shape[1]
    shape = (x.c.lo.shape[0], n, n, *x.c.lo.shape[1:])
    return TM(x.c, x.lin, _point(np.zeros(shape)), x.rem, x.w)


def _sig(v: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-v))


def _leaky_derivatives(c: float) -> tuple[list, list]:
    def d0(v):  # noqa: ANN001, ANN202
        return c * v + (1 - c) * np.logaddexp(0.0, v)

    def d1(v):  # noqa: ANN001, ANN202
        return c + (1 - c) * _sig(v)

    def d2(v):  # noqa: ANN001, ANN202
        s = _sig(v)
        return (1 - c) * s * (1 - s)

    def d3(v):  # noqa: ANN001, ANN202
        s = _sig(v)
        return (1 - c) * s * (1 - s) * (1 - 2 * s)

    def d4(v):  # noqa: ANN001, ANN202
        s = _sig(v)
        return (1 - c) * s * (1 - s) * (1 - 6 * s + 6 * s * s)

    # sup |softplus^(k)|, k = 1..5: 1, 1/4, 0.09623, 1/8, 0.12768 (maxima on a grid of step
    # 1e-4 over [-40, 40], padded past the grid's error); c's linear part only moves k = 1.
    bounds = [1.0, (1 - c) * 0.2501, (1 - c) * 0.0963, (1 - c) * 0.1251, (1 - c) * 0.1278]
    return [d0, d1, d2, d3, d4], bounds


def _silu_derivatives() -> tuple[list, list]:
    def d0(v):  # noqa: ANN001, ANN202
        return v * _sig(v)

    def d1(v):  # noqa: ANN001, ANN202
        s = _sig(v)
        return s * (1 + v * (1 - s))

    def d2(v):  # noqa: ANN001, ANN202
        s = _sig(v)
        return s * (1 - s) * (2 + v * (1 - 2 * s))

    # sup |silu'''| = 0.30818, sup |silu''''| = 1/2 (grid of step 1e-4 over [-40, 40]).
    return [d0, d1, d2], [1.1, 0.5001, 0.3083]


def _trig_derivatives(start: int) -> tuple[list, list]:
    cycle = [np.sin, np.cos, lambda v: -np.sin(v), lambda v: -np.cos(v)]
    return [cycle[(start + j) % 4] for j in range(5)], [1.0] * 5


#: Elementwise functions: their derivatives g^(0..) and sup |g^(k+1)| (k = 0..).
FUNCTIONS = {
    "sin": _trig_derivatives(0),
    "cos": _trig_derivatives(1),
    "silu": _silu_derivatives(),
    "smooth_leaky": _leaky_derivatives(0.1),
    "softplus": _leaky_derivatives(0.0),
}


def _at(fn, bound_next: float, x: Pair) -> Pair:  # noqa: ANN001
    """fn over narrow intervals x: fn(mid) plus |fn'| <= bound_next times the half-width,
    widened by 2^-40 relative for the C library."""
    mid = 0.5 * x.lo + 0.5 * x.hi
    half = _up(np.maximum(x.hi - mid, mid - x.lo))
    value = fn(mid)
    slack = _up(bound_next * half + np.abs(value) * 2.0**-40 + 1e-300)
    return Pair(_down(value - slack), _up(value + slack))


def _apply_one(x: TM, fns: list, bounds: list, j: int) -> TM:
    """g^(j)(q) as a model, from g^(j), g^(j+1), g^(j+2) at C and sup |g^(j+3)|
    (``bounds[k]`` = sup |g^(k)|)."""
    g0 = _at(fns[j], bounds[j + 1], x.c)
    g1 = _at(fns[j + 1], bounds[j + 2], x.c)
    g2 = _at(fns[j + 2], bounds[j + 3], x.c)
    third = bounds[j + 3]
    linear, square = x.spread_linear(), x.spread_square()
    tail = _up(square + x.rem)
    reach = _up(linear + tail)
    lin = x.lin * g1[:, None]
    if x.quad is None:
        # First order: g^(j)(q) = g0 + g1 delta + g^(j+2)(xi) delta^2 / 2, |g^(j+2)| bounded.
        rem = _sum_up([g1.mag * x.rem, (0.5 * bounds[j + 2]) * reach * reach])
        return TM(g0, lin, None, _up(rem * (1 + 16 * _EPS)), x.w)
    outer = x.lin[:, :, None] * x.lin[:, None, :]
    half_g2 = Pair(g2.lo * 0.5, g2.hi * 0.5)
    quad = x.quad * g1[:, None, None] + outer * half_g2[:, None, None]
    rem = _sum_up(
        [
            g1.mag * x.rem,
            0.5 * g2.mag * _up(tail * tail + 2 * linear * tail),
            (third / 6) * reach * reach * reach,
        ]
    )
    return TM(g0, lin, quad, _up(rem * (1 + 16 * _EPS)), x.w)


def derivative_models(x: TM, name: str, count: int) -> list[TM]:
    """g(q), g'(q), ... (``count`` of them) for a name of :data:`FUNCTIONS`."""
    fns, bounds = FUNCTIONS[name]
    return [_apply_one(x, fns, [None, *bounds], j) for j in range(count)]
