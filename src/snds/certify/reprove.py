r"""The re-check's proof of many cells at once, on :mod:`snds.certify.retaylor`'s models.

The same inequality as the search's (:mod:`snds.certify.bounds`), reached by other code:
V, its gradient and Hessian, the nominal field and the decay rate are re-derived from the
weights with second-order Taylor models of interval coefficients; :math:`|\pi|` is bounded by
:math:`|f|^2 + (a / |\nabla V|)^2`, and the step's curvature by
:math:`\max_i (H_{ii} + \sum_{j \ne i} |H_{ij}|)`, the row-sum bound, times :math:`|\Delta|^2`.
"""

from __future__ import annotations

import numpy as np

from snds.certify import retaylor as rt
from snds.certify.model import PolicyModel
from snds.certify.retaylor import TM, Pair

__all__ = ["Reprover"]


def _up(x: np.ndarray) -> np.ndarray:
    return np.nextafter(x, np.inf)


def _down(x: np.ndarray) -> np.ndarray:
    return np.nextafter(x, -np.inf)


class Reprover:
    """The policy's networks on :class:`~snds.certify.retaylor.TM` models.

    Arguments:
        weights: The weights (only their float values are used).
    """

    def __init__(self, weights: PolicyModel) -> None:
        self.w = weights
        self.leaky = "smooth_leaky" if weights.icnn_slope else "softplus"
        zero, none = np.zeros((1, weights.dim)), np.zeros((1, weights.dim))
        self.net0 = self._net(rt.variable(zero, none)).range()
        self.phi0 = self._flow(rt.jet_variable(zero, none))[0].range()
        # g and its gradient at z = 0 (the ICNN's own input), not through the warp.
        g = self._icnn(rt.jet_variable(zero, none))
        self.g0 = g[0].range()
        self.grad_g0 = g[1].range()  # (1, n, 1)

    # The nominal field, values only.
    def _net(self, x: TM) -> TM:
        w = self.w
        angles = x.dot(w.fourier)
        sin = rt.derivative_models(angles, "sin", 1)[0]
        cos = rt.derivative_models(angles, "cos", 1)[0]
        h = _concat([x, sin, cos])
        for k, (weight, bias) in enumerate(w.layers):
            h = h.dot(weight).plus(Pair(bias, bias))
            if k + 1 < len(w.layers):
                h = rt.derivative_models(h, "silu", 1)[0]
        return h

    def nominal(self, center: np.ndarray, half: np.ndarray) -> Pair:
        """Enclosures (C, n) of f over the cells."""
        net = self._net(rt.variable(center, half))
        return net.range() - self.net0

    # Jets (value, gradient, Hessian), each a model.
    @staticmethod
    def _linear(jet: tuple, weight: np.ndarray, bias: np.ndarray | None = None) -> tuple:
        value = jet[0].dot(weight)
        if bias is not None:
            value = value.plus(Pair(bias, bias))
        return value, jet[1].dot(weight), jet[2].dot(weight)

    @staticmethod
    def _add(a: tuple, b: tuple, sign: int = 1) -> tuple:
        if sign > 0:
            return a[0] + b[0], a[1] + b[1], a[2] + b[2]
        return a[0] - b[0], a[1] - b[1], a[2] - b[2]

    @staticmethod
    def _elementwise(jet: tuple, name: str) -> tuple:
        value, grad, hess = jet
        s0, s1, s2 = rt.derivative_models(value, name, 3)
        outer = grad[:, :, None] * grad[:, None, :]
        return s0, grad * s1[:, None], hess * s1[:, None, None] + outer * s2[:, None, None]

    def _flow_free(self, jet: tuple) -> tuple:
        for frequencies, phases, weight, bias in self.w.warp:
            angles = self._linear(jet, frequencies, phases)
            jet = self._add(jet, self._linear(self._elementwise(angles, "cos"), weight, bias))
        return jet

    def _flow(self, jet: tuple) -> tuple:
        return self._flow_free(jet)

    def _icnn(self, z: tuple) -> tuple:
        w = self.w
        h = None
        for k, (skip, bias) in enumerate(w.icnn_skips):
            u = self._linear(z, skip, bias)
            if h is not None:
                u = self._add(u, self._linear(h, w.icnn_prev[k - 1]))
            h = self._elementwise(u, self.leaky)
        return self._add(self._linear(h, w.icnn_out[0]), self._linear(z, w.icnn_out[1]))

    def lyapunov(
        self, center: np.ndarray, half: np.ndarray, *, second: bool = False
    ) -> tuple[Pair, Pair, Pair]:
        """Enclosures of V (C,), grad V (C, n) and its Hessian (C, n, n) over the cells, from
        first-order models (second-order with ``second``: tighter, about twice the cost)."""
        z = self._flow(rt.jet_variable(center, half, second=second))
        z = (z[0].plus(-self.phi0), z[1], z[2])
        g = self._icnn(z)
        d = self.w.quadratic
        tangent = z[0].dot_pair(self.grad_g0[0])
        grad_tangent = z[1].dot_pair(self.grad_g0[0])
        hess_tangent = z[2].dot_pair(self.grad_g0[0])
        # d |z|^2 and its derivatives: 2 d z . dz and 2 d (dz dz^T + z d2z), summed over z.
        zv, zg, zh = z
        square = (zv * zv).dot(np.full((self.w.dim, 1), d))
        square_g = (zg * zv[:, None]).dot(np.full((self.w.dim, 1), 2 * d))
        pairs = zg[:, :, None] * zg[:, None, :]
        square_h = (pairs + zh * zv[:, None, None]).dot(np.full((self.w.dim, 1), 2 * d))
        value = (g[0] - tangent + square).plus(-self.g0)
        grad = g[1] - grad_tangent + square_g
        hess = g[2] - hess_tangent + square_h
        return value.range()[:, 0], grad.range()[..., 0], hess.range()[..., 0]

    def rate(self, lo: np.ndarray, hi: np.ndarray) -> Pair:
        """The decay rate a / V over boxes (C, n)."""
        w = self.w
        gap = np.where((lo <= 0) & (hi >= 0), 0.0, np.minimum(np.abs(lo), np.abs(hi)))
        far = np.maximum(np.abs(lo), np.abs(hi))
        r_lo = _down(np.sqrt(_down((gap * gap).sum(-1) * (1 - 4e-16))))
        r_hi = _up(np.sqrt(_up((far * far).sum(-1) * (1 + 4e-16))))
        low = (
            w.rho
            + w.rho_far * np.maximum(r_lo - 1, 0)
            + w.rho_near * np.maximum(1 - r_hi / w.near_radius, 0)
        )
        high = (
            w.rho
            + w.rho_far * np.maximum(r_hi - 1, 0)
            + w.rho_near * np.maximum(1 - r_lo / w.near_radius, 0)
        )
        if len(w.anchors) and w.drop > 0:
            near = np.full(len(lo), np.inf)
            farthest = np.full(len(lo), np.inf)
            for anchor in w.anchors:
                outside = np.maximum(np.maximum(lo - anchor, anchor - hi), 0.0)
                span = np.maximum(np.abs(lo - anchor), np.abs(hi - anchor))
                near = np.minimum(near, (outside * outside).sum(-1))
                farthest = np.minimum(farthest, (span * span).sum(-1))
            scale = 2 * w.data_radius**2
            k_hi = np.minimum(np.exp(-near * (1 - 1e-12) / scale) * (1 + 1e-12), 1.0)
            k_lo = np.exp(-farthest * (1 + 1e-12) / scale) * (1 - 1e-12)
            low, high = low - w.drop * k_hi, high - w.drop * k_lo
        return Pair(low - np.abs(low) * 1e-12 - 1e-300, high + np.abs(high) * 1e-12 + 1e-300)

    def prove(
        self, lo: np.ndarray, hi: np.ndarray, *, step: float, eta: float, second: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Which cells [lo, hi] (C, n) these bounds prove; also the descent -grad V . pi at
        the cells' centres and |pi| there (upper and lower estimates, to test the numbers a
        certificate records)."""
        center = 0.5 * lo + 0.5 * hi
        half = _up(np.maximum(hi - center, center - lo) * (1 + 1e-15))
        v, grad, _ = self.lyapunov(center, half, second=second)
        rate = self.rate(lo, hi)
        v_lo, v_hi = np.maximum(v.lo, 0.0), v.hi
        a_lo = np.maximum(v_lo * rate.lo * (1 - 1e-15), 0.0)
        a_hi = _up(v_hi * np.maximum(rate.hi, 0.0))
        gmig = np.where(
            (grad.lo > 0) | (grad.hi < 0), np.minimum(np.abs(grad.lo), np.abs(grad.hi)), 0.0
        )
        g_lo = np.sqrt((gmig * gmig).sum(-1)) * (1 - 1e-15)
        g_hi = _up(np.sqrt((grad.mag**2).sum(-1)) * (1 + 1e-15))
        f = self.nominal(center, half)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            ratio = np.where(g_lo > 0, _up(a_hi / g_lo), np.inf)
            speed = _up(np.sqrt((f.mag**2).sum(-1) + ratio * ratio) * (1 + 1e-15))
            reach = _up((1 + eta) * step * speed * (1 + 1e-15))
        ok = np.isfinite(reach) & (g_lo > 0) & (a_lo > 0)
        proven = np.zeros(len(lo), dtype=bool)
        if ok.any():
            grown = _up(half[ok] + reach[ok, None])
            _, _, hess = self.lyapunov(center[ok], grown, second=second)
            n = hess.lo.shape[-1]
            diag = np.arange(n)
            off = hess.mag.sum(-1) - hess.mag[:, diag, diag]
            top = np.maximum((hess.hi[:, diag, diag] + off).max(-1) * (1 + 1e-14), 0.0)
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                p2 = _up(speed[ok] ** 2)
                # Along the step: pi^T H pi with pi from the projection's formula in intervals.
                pi = _projection(f[ok], grad[ok], a_lo[ok], a_hi[ok])
                along = _sum_pairs(hess * pi[:, :, None] * pi[:, None, :]).hi
                rows = (hess.mag.sum(-1)).max(-1) * (1 + 1e-14)
                curve = np.minimum(np.maximum(along, 0.0), top * p2)
                curve = curve + (2 * eta + eta**2) * rows * p2
                loss = step * eta * g_hi[ok] * speed[ok] + 0.5 * step**2 * curve
                # -grad V . pi = max(a, -grad V . f) for the ReLU projection.
                dot = _sum_pairs((grad[ok] * f[ok])[:, :, None])
                descent = np.maximum(a_lo[ok], -dot.hi)
                proven[ok] = step * descent * (1 - 1e-14) > loss * (1 + 1e-14)
        # At the centres: a and |pi| in the same arithmetic.
        v_c, g_c, _ = self.lyapunov(center, np.zeros_like(half))
        rate_c = self.rate(center, center)
        a_c = Pair(v_c.lo * rate_c.lo, v_c.hi * rate_c.hi)
        f_c = self.nominal(center, np.zeros_like(half))
        gm = 0.5 * (g_c.lo + g_c.hi)
        fm = 0.5 * (f_c.lo + f_c.hi)
        norm2 = (gm * gm).sum(-1)
        excess = np.maximum((gm * fm).sum(-1) + 0.5 * (a_c.lo + a_c.hi), 0.0)
        pi = fm - gm * (excess / np.where(norm2 > 0, norm2, 1.0))[:, None]
        descent_c = np.maximum(a_c.hi, -(gm * fm).sum(-1))
        return proven, descent_c * (1 + 1e-9) + 1e-300, np.linalg.norm(pi, axis=1) * (1 - 1e-9)


def _sum_pairs(x: Pair) -> Pair:
    """Sum over the last two axes, rounded outward per addition."""
    flat_lo = x.lo.reshape(len(x.lo), -1)
    flat_hi = x.hi.reshape(len(x.hi), -1)
    lo, hi = flat_lo[:, 0], flat_hi[:, 0]
    for j in range(1, flat_lo.shape[1]):
        lo, hi = _down(lo + flat_lo[:, j]), _up(hi + flat_hi[:, j])
    return Pair(lo, hi)


def _projection(f: Pair, grad: Pair, a_lo: np.ndarray, a_hi: np.ndarray) -> Pair:
    """pi = f - g relu(g . f + a) / |g|^2 over intervals (C, n)."""
    dot = Pair(a_lo, a_hi)
    for i in range(f.lo.shape[1]):
        dot = dot + grad[:, i] * f[:, i]
    relu = Pair(np.maximum(dot.lo, 0.0), np.maximum(dot.hi, 0.0))
    straddles = (grad.lo <= 0) & (grad.hi >= 0)
    mig = np.where(straddles, 0.0, np.minimum(np.abs(grad.lo), np.abs(grad.hi)))
    n_lo = _down((mig * mig).sum(-1) * (1 - 1e-15))
    n_hi = _up((grad.mag**2).sum(-1) * (1 + 1e-15))
    with np.errstate(divide="ignore"):
        inverse = Pair(_down(1.0 / n_hi), np.where(n_lo > 0, _up(1.0 / n_lo), np.inf))
    scale = relu * inverse
    return f - grad * scale[:, None]


def _concat(parts: list[TM]) -> TM:
    def cat(pairs: list[Pair]) -> Pair:
        return Pair(
            np.concatenate([p.lo for p in pairs], -1), np.concatenate([p.hi for p in pairs], -1)
        )

    return TM(
        cat([p.c for p in parts]),
        cat([p.lin for p in parts]),
        cat([p.quad for p in parts]),
        np.concatenate([p.rem for p in parts], -1),
        parts[0].w,
    )
