r"""Sound interval arithmetic on NumPy arrays: midpoint-radius form with outward rounding.

An :class:`Iv` holds arrays ``m`` and ``r >= 0`` and stands for every real number in
:math:`[m - r, m + r]`, elementwise. Every operation returns an interval that contains the
exact real result of the operation on any numbers of its inputs' intervals, whatever the
rounding of the float64 arithmetic that computes it:

- a sum, product or dot product of length k computed in float64 is within
  :math:`\gamma_k \sum |a_i b_i|`, :math:`\gamma_k = k u / (1 - k u)`, :math:`u = 2^{-53}`, of
  the exact one, in any summation order and with or without fused multiply-adds (Higham,
  *Accuracy and Stability of Numerical Algorithms*, 2002, Sec. 3.1); radii add that bound,
  and every radius is itself inflated by :func:`up` for the rounding of its own computation;
- the elementary functions (exp, log1p, sin, cos) of the C library are trusted to within
  :data:`LIBM_RELATIVE` (2^-40, thousands of times glibc's documented few-ulp errors), and
  their enclosures over an interval use their monotone pieces.

Operations run over whole arrays at once, so that a branch and bound bounds many cells of a
box in one pass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "LIBM_RELATIVE",
    "Iv",
    "cos",
    "exp",
    "from_bounds",
    "matmul",
    "matmul_iv",
    "point",
    "sigmoid",
    "silu",
    "silu_slope",
    "sin",
    "smooth_leaky",
    "sqrt",
    "up",
]

#: The unit roundoff of float64.
UNIT = 2.0**-53
#: An absolute allowance that covers underflow in every operation (far below any bound used).
TINY = 2.0**-1000
#: Relative error allowed to the C library's exp, log1p, sin and cos.
LIBM_RELATIVE = 2.0**-40


def up(x: np.ndarray, ops: int = 4) -> np.ndarray:
    """An upper bound of a non-negative quantity computed in ``ops`` rounded operations."""
    return x * (1.0 + 2.0 * ops * UNIT) + TINY


def _gamma(k: int) -> float:
    return 1.01 * (k + 2) * UNIT


@dataclass(frozen=True)
class Iv:
    """Intervals :math:`[m - r, m + r]`, elementwise over arrays of one shape."""

    m: np.ndarray
    r: np.ndarray

    @property
    def lo(self) -> np.ndarray:
        """Lower ends, rounded down."""
        low = self.m - self.r
        return low - np.abs(low) * (2 * UNIT) - TINY

    @property
    def hi(self) -> np.ndarray:
        """Upper ends, rounded up."""
        high = self.m + self.r
        return high + np.abs(high) * (2 * UNIT) + TINY

    @property
    def mag(self) -> np.ndarray:
        """Upper bounds of the absolute values."""
        return up(np.abs(self.m) + self.r, 1)

    @property
    def mig(self) -> np.ndarray:
        """Lower bounds of the absolute values (0 where an interval holds 0)."""
        low = np.abs(self.m) - self.r
        return np.maximum(low - np.abs(low) * (2 * UNIT) - TINY, 0.0)

    def __getitem__(self, index) -> Iv:  # noqa: ANN001
        return Iv(self.m[index], self.r[index])

    def __add__(self, other: Iv) -> Iv:
        m = self.m + other.m
        return Iv(m, up(self.r + other.r + UNIT * np.abs(m)))

    def __sub__(self, other: Iv) -> Iv:
        m = self.m - other.m
        return Iv(m, up(self.r + other.r + UNIT * np.abs(m)))

    def __neg__(self) -> Iv:
        return Iv(-self.m, self.r)

    def __mul__(self, other: Iv) -> Iv:
        m = self.m * other.m
        r = np.abs(self.m) * other.r + self.r * (np.abs(other.m) + other.r) + UNIT * np.abs(m)
        return Iv(m, up(r, 6))

    def scale(self, c: float | np.ndarray) -> Iv:
        """Times exact float constants c (broadcast)."""
        m = self.m * c
        return Iv(m, up(np.abs(c) * self.r + UNIT * np.abs(m)))

    def shift(self, c: float | np.ndarray) -> Iv:
        """Plus exact float constants c (broadcast)."""
        m = self.m + c
        return Iv(m, up(self.r + UNIT * np.abs(m)))

    def sum(self, axis: int) -> Iv:
        """Sum along an axis."""
        k = self.m.shape[axis]
        m = self.m.sum(axis)
        r = self.r.sum(axis) + _gamma(k) * np.abs(self.m).sum(axis)
        return Iv(m, up(r, k + 2))

    def square(self) -> Iv:
        """x^2, which is never negative (tighter than x * x for an interval holding 0)."""
        low, high = np.abs(self.m) - self.r, np.abs(self.m) + self.r
        low = np.maximum(low, 0.0)
        return from_bounds(low * low * (1 - 4 * UNIT), high * high * (1 + 4 * UNIT) + TINY)

    def matmul(self, weight: np.ndarray | Iv) -> Iv:
        """self @ W over the last axis, W (k, j) exact floats or intervals."""
        return matmul_iv(self, weight) if isinstance(weight, Iv) else matmul(self, weight)

    def swap12(self) -> Iv:
        """Axes 1 and 2 exchanged."""
        return Iv(np.swapaxes(self.m, 1, 2), np.swapaxes(self.r, 1, 2))

    def hull(self, other: Iv) -> Iv:
        """The smallest interval holding both."""
        return from_bounds(np.minimum(self.lo, other.lo), np.maximum(self.hi, other.hi))


def point(x: np.ndarray) -> Iv:
    """Float numbers as intervals of zero width (exact)."""
    x = np.asarray(x, dtype=np.float64)
    return Iv(x, np.zeros_like(x))


def from_bounds(lo: np.ndarray, hi: np.ndarray) -> Iv:
    """The interval [lo, hi] (or one holding it), lo <= hi."""
    lo, hi = np.broadcast_arrays(np.asarray(lo, np.float64), np.asarray(hi, np.float64))
    m = 0.5 * lo + 0.5 * hi
    r = np.maximum(hi - m, m - lo)
    return Iv(m, up(np.maximum(r, 0.0) + UNIT * np.abs(m), 3))


def matmul(x: Iv, weight: np.ndarray) -> Iv:
    """x @ W for intervals x (..., k) and exact float weights W (k, j)."""
    k = weight.shape[0]
    absolute = np.abs(weight)
    m = x.m @ weight
    r = x.r @ absolute + _gamma(k) * (np.abs(x.m) @ absolute)
    return Iv(m, up(r, k + 4))


def matmul_iv(x: Iv, weight: Iv) -> Iv:
    """x @ W for intervals x (..., k) and W (k, j)."""
    k = weight.m.shape[0]
    m = x.m @ weight.m
    mag_x = np.abs(x.m) + x.r
    r = x.r @ np.abs(weight.m) + mag_x @ weight.r + _gamma(k) * (np.abs(x.m) @ np.abs(weight.m))
    return Iv(m, up(r, 2 * k + 6))


def _widened(lo: np.ndarray, hi: np.ndarray) -> Iv:
    """[lo, hi] of values computed by the C library, widened by its allowed error."""
    return from_bounds(
        lo - np.abs(lo) * LIBM_RELATIVE - TINY, hi + np.abs(hi) * LIBM_RELATIVE + TINY
    )


def _increasing(x: Iv, fn) -> Iv:  # noqa: ANN001
    return _widened(fn(x.lo), fn(x.hi))


def exp(x: Iv) -> Iv:
    """exp(x)."""
    return _increasing(x, np.exp)


def sqrt(x: Iv) -> Iv:
    """sqrt(x) of non-negative intervals (a negative part is cut off)."""
    return _increasing(x, lambda v: np.sqrt(np.maximum(v, 0.0)))


def sigmoid(x: Iv) -> Iv:
    """The logistic function 1 / (1 + exp(-x))."""
    return _increasing(x, lambda v: 0.5 * (1.0 + np.tanh(0.5 * v)))


def _softplus(v: np.ndarray) -> np.ndarray:
    return np.logaddexp(0.0, v)


def smooth_leaky(x: Iv, slope: float) -> tuple[Iv, Iv, Iv]:
    r"""s(x) = c x + (1 - c) softplus(x) with c = ``slope``, and its first two derivatives
    :math:`s' = c + (1 - c)\sigma` (increasing), :math:`s'' = (1 - c)\sigma(1 - \sigma)`
    (largest, (1 - c)/4, at 0)."""
    value = _increasing(x, lambda v: slope * v + (1 - slope) * _softplus(v))
    first = sigmoid(x).scale(1 - slope).shift(slope)

    def second(v: np.ndarray) -> np.ndarray:
        s = 0.5 * (1.0 + np.tanh(0.5 * v))
        return (1 - slope) * s * (1 - s)

    lo, hi = x.lo, x.hi
    a, b = second(lo), second(hi)
    top = np.where((lo <= 0) & (hi >= 0), (1 - slope) / 4, np.maximum(a, b))
    return value, first, _widened(np.minimum(a, b), top)


def _unimodal(x: Iv, fn, turns: list[tuple[float, float, str]]) -> Iv:  # noqa: ANN001
    """Enclosure of fn over intervals from its end values and its extreme values at known
    turning points: each (where, value, "min"|"max"), ``where`` known to 1e-6 and ``value``
    already padded outward."""
    lo, hi = x.lo, x.hi
    a, b = fn(lo), fn(hi)
    low, high = np.minimum(a, b), np.maximum(a, b)
    for where, value, kind in turns:
        inside = (lo <= where + 1e-6) & (hi >= where - 1e-6)
        if kind == "min":
            low = np.where(inside, np.minimum(low, value), low)
        else:
            high = np.where(inside, np.maximum(high, value), high)
    return _widened(low, high)


def _silu(v: np.ndarray) -> np.ndarray:
    return v * 0.5 * (1.0 + np.tanh(0.5 * v))


def _silu_slope(v: np.ndarray) -> np.ndarray:
    s = 0.5 * (1.0 + np.tanh(0.5 * v))
    return s * (1.0 + v * (1.0 - s))


def _newton(fn, slope, start: float) -> float:  # noqa: ANN001
    x = start
    for _ in range(60):
        x -= fn(x) / slope(x)
    return x


def _turns() -> tuple[list, list]:
    # silu' = s (1 + x (1 - s)) vanishes once, at x0 ~ -1.2785 (silu's minimum); silu'' =
    # s (1 - s) (2 + x (1 - 2 s)) vanishes at +-x1 ~ 2.3994 (silu''s extremes). Newton in
    # float64 finds them to ~1e-15; the enclosures test membership with 1e-6 slack and pad the
    # values by 1e-9, far beyond both errors and the values' curvature over 1e-6.
    def sig(v: float) -> float:
        return 1.0 / (1.0 + math.exp(-v))

    x0 = _newton(
        lambda v: 1 + v * (1 - sig(v)),
        lambda v: (1 - sig(v)) - v * sig(v) * (1 - sig(v)),
        -1.3,
    )
    x1 = _newton(lambda v: 2 + v * (1 - 2 * sig(v)), lambda v: 1e-12 + _d_inner(v, sig), 2.4)
    silu_min = float(_silu(np.float64(x0))) - 1e-9
    top = float(_silu_slope(np.float64(x1))) + 1e-9
    bottom = float(_silu_slope(np.float64(-x1))) - 1e-9
    return [(x0, silu_min, "min")], [(x1, top, "max"), (-x1, bottom, "min")]


def _d_inner(v: float, sig) -> float:  # noqa: ANN001
    s = sig(v)
    return (1 - 2 * s) - 2 * v * s * (1 - s)


_SILU_TURNS, _SILU_SLOPE_TURNS = _turns()


def silu(x: Iv) -> Iv:
    """silu(x) = x sigma(x)."""
    return _unimodal(x, _silu, _SILU_TURNS)


def silu_slope(x: Iv) -> Iv:
    """silu'(x) = sigma(x) (1 + x (1 - sigma(x)))."""
    return _unimodal(x, _silu_slope, _SILU_SLOPE_TURNS)


def _periodic_extremes(lo: np.ndarray, hi: np.ndarray, offset: float) -> tuple:
    """Whether [lo, hi] holds a point offset + k pi with k even (a maximum of cos(x - offset))
    or odd (a minimum), with 1e-9 slack on both sides."""
    k_lo = np.ceil((lo - offset) / math.pi - 1e-9)
    k_hi = np.floor((hi - offset) / math.pi + 1e-9)
    some = k_lo <= k_hi
    even_first = np.mod(k_lo, 2) == 0
    two = k_lo + 1 <= k_hi
    has_even = some & (even_first | two)
    has_odd = some & (~even_first | two)
    return has_even, has_odd


def _cos_shifted(x: Iv, offset: float) -> Iv:
    """cos(x - offset) over intervals (offset 0: cos; pi/2: sin)."""
    lo, hi = x.lo, x.hi
    a, b = np.cos(lo - offset), np.cos(hi - offset)
    has_max, has_min = _periodic_extremes(lo, hi, offset)
    high = np.where(has_max, 1.0, np.maximum(a, b))
    low = np.where(has_min, -1.0, np.minimum(a, b))
    # lo - offset rounds, and cos is 1-Lipschitz: the rounding moves the value by at most the
    # argument's own rounding error, 2 u |lo - offset|, plus pi/2's representation error.
    slack = (np.abs(lo) + np.abs(hi) + 2.0) * (4 * UNIT)
    return _widened(np.maximum(low - slack, -1.0), np.minimum(high + slack, 1.0))


def cos(x: Iv) -> Iv:
    """cos(x)."""
    return _cos_shifted(x, 0.0)


def sin(x: Iv) -> Iv:
    """sin(x) = cos(x - pi/2)."""
    return _cos_shifted(x, math.pi / 2)
