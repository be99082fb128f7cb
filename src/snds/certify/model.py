r"""A stable policy's networks as plain float64 arrays, and their interval jets.

The certificate is about the real-arithmetic functions that these weights define (the float
weights taken as exact numbers): the nominal field :math:`f(x) = net(x) - net(0)`, the warped
Lyapunov function :math:`V(x) = V_c(\phi(x) - \phi(0))` and the decay rate of
:meth:`snds.policy.StablePolicy.decay`, in model coordinates. The rounding of a
deployed evaluation is covered separately (see :mod:`snds.certify.bounds`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from snds.certify import affine, jets, quadratic
from snds.certify import interval as ia
from snds.certify.interval import Iv
from snds.certify.jets import Jet
from snds.errors import NotCertifiable
from snds.nn import MLP, FourierFeatures, WarpedLyapunov
from snds.policy import Policy, StablePolicy, float64_copy

__all__ = [
    "NotCertifiable",
    "PolicyModel",
    "f_jet",
    "f_quadratic",
    "rate_bounds",
    "v_forms",
    "v_jet",
]

#: The ICNN activations this module bounds, with their linear slope c (s = c u + (1-c) sp(u)).
_ICNN_SLOPES = {"smooth_leaky": 0.1, "softplus": 0.0}


@dataclass(frozen=True, eq=False)
class PolicyModel:
    """The weights of a default SNDS position policy, float64, model coordinates.

    Attributes:
        dim: n.
        fourier: 2 pi B of the nominal net's Fourier features, (n, m).
        layers: The nominal net's linear layers after the features, each (W^T (k, j), b (j,)).
        icnn_skips: The ICNN's input skips, each (A_k^T (n, h), b_k (h,)).
        icnn_prev: Its non-negative weights on the previous layer, each W_k^T (h_k, h_k+1).
        icnn_out: Output weights (h_K, 1) and the linear term (n, 1).
        icnn_slope: c of its activation.
        quadratic: d.
        warp: The coupling layers, each (Omega (n, m), beta (m,), W (m, n), bias (n,)).
        rho, rho_far, rho_near, near_radius, drop, data_radius: The decay's constants.
        anchors: The anchors (M, n), or an empty array.
        length, time: The normalisation's scales (user units per model unit, s).
        projected: Whether the policy is the projection (False for behavioural cloning,
            pi = f, which has no decrease to prove).
        net0, phi0, g0, grad_g0: net(0), phi(0), g(0) and grad g(0) as intervals.
    """

    dim: int
    fourier: np.ndarray
    layers: tuple
    icnn_skips: tuple
    icnn_prev: tuple
    icnn_out: tuple
    icnn_slope: float
    quadratic: float
    warp: tuple
    rho: float
    rho_far: float
    rho_near: float
    near_radius: float
    drop: float
    data_radius: float
    anchors: np.ndarray
    length: float
    time: float
    projected: bool
    net0: Iv
    phi0: Iv
    g0: Iv
    grad_g0: Iv

    @classmethod
    def from_policy(cls, policy: Policy) -> PolicyModel:
        """Reads the weights of a stable SNDS position policy; raises :class:`NotCertifiable`
        with the reason for any other."""
        _check(policy)
        p = float64_copy(policy)
        config = p.config

        def arr(t: torch.Tensor) -> np.ndarray:
            return t.detach().cpu().numpy().astype(np.float64).copy()

        modules = list(p.nominal_net)
        features = modules[0]
        fourier = arr(features.frequencies) * (2 * math.pi)
        linears = [m for m in modules[1:] if isinstance(m, torch.nn.Linear)]
        layers = tuple((arr(m.weight).T.copy(), arr(m.bias)) for m in linears)
        lyapunov = p.lyapunov
        warp = ()
        if isinstance(lyapunov, WarpedLyapunov):
            warp = tuple(
                (
                    arr(layer.frequencies),
                    arr(layer.phases),
                    arr(layer.weight * layer.scaled_columns),
                    arr(layer.bias * layer.columns),
                )
                for layer in lyapunov.warp.layers
            )
            lyapunov = lyapunov.convex
        icnn = lyapunov.icnn
        skips = tuple((arr(s.weight).T.copy(), arr(s.bias)) for s in icnn.skips)
        prev = tuple(arr(w).T.copy() for w in icnn.weights())
        out = (arr(F.softplus(icnn.raw_out))[:, None], arr(icnn.linear_out)[:, None])
        anchors = arr(p.anchors) if p.anchors is not None else np.zeros((0, p.dim))
        partial = dict(
            dim=p.dim,
            fourier=fourier,
            layers=layers,
            icnn_skips=skips,
            icnn_prev=prev,
            icnn_out=out,
            icnn_slope=_ICNN_SLOPES[icnn.activation],
            quadratic=float(lyapunov.quadratic),
            warp=warp,
            rho=float(config.decay_rate),
            rho_far=float(config.decay_far),
            rho_near=float(config.decay_near),
            near_radius=float(config.near_radius),
            drop=float(config.data_rate_drop),
            data_radius=float(config.data_radius),
            anchors=anchors,
            length=float(p.length),
            time=float(p.time),
            projected=bool(config.stable),
        )
        zero = np.zeros((1, p.dim))
        point = jets.variable(zero, zero, order=1)
        net0 = _net(layers, fourier, point, _interval_fns).value
        phi0 = _flow(warp, point, _interval_fns).value
        g_at0 = _icnn(skips, prev, out, partial["icnn_slope"], point, _interval_fns)
        return cls(**partial, net0=net0, phi0=phi0, g0=g_at0.value, grad_g0=g_at0.grad[0])


def _check(policy: Policy) -> None:
    if type(policy) is not StablePolicy:
        raise NotCertifiable(
            f"a {type(policy).__name__} is not certified: only position policies of method "
            "snds (StablePolicy); a pose policy steps on SO(3), which these bounds do not cover"
        )
    config = policy.config
    if config.phase_dim:
        raise NotCertifiable(
            "a model with a phase is not certified: its phase is a state that the controller "
            "holds back or resets (snds.phase), not a free coordinate of a box"
        )
    if config.rectifier != "relu":
        raise NotCertifiable(f"rectifier {config.rectifier!r} is not certified; only relu")
    if config.activation != "silu" or config.fourier_features <= 0:
        raise NotCertifiable(
            f"nominal activation {config.activation!r} without Fourier features is not "
            "certified; only the default silu on Fourier features"
        )
    modules = list(policy.nominal_net)
    if not isinstance(policy.nominal_net, MLP) or not isinstance(modules[0], FourierFeatures):
        raise NotCertifiable("the nominal network is not the default MLP on Fourier features")
    lyapunov = policy.lyapunov
    if isinstance(lyapunov, WarpedLyapunov):
        if any(layer.affine for layer in lyapunov.warp.layers):
            raise NotCertifiable("affine coupling layers in V's warp are not certified")
        lyapunov = lyapunov.convex
    if lyapunov.icnn.activation not in _ICNN_SLOPES:
        raise NotCertifiable(f"ICNN activation {lyapunov.icnn.activation!r} is not certified")


def _interval_fns(name: str, slope: float = 0.0):  # noqa: ANN202
    """(s, s', s'') enclosures over intervals for an elementwise function."""
    if name == "sin":
        return lambda u: (ia.sin(u), ia.cos(u), -ia.sin(u))
    if name == "cos":
        return lambda u: (ia.cos(u), -ia.sin(u), -ia.cos(u))
    if name == "silu":
        return lambda u: (ia.silu(u), ia.silu_slope(u), None)
    return lambda u: ia.smooth_leaky(u, slope)


def _affine_fns(name: str, slope: float = 0.0):  # noqa: ANN202
    """(s, s', s'') as Taylor models (:mod:`snds.certify.affine`)."""
    if name not in ("sin", "cos", "silu"):
        name = "smooth_leaky" if slope else "softplus"
    orders = 2 if name == "silu" else 3

    def fns(u: affine.Aff) -> tuple:
        forms = affine.derivative_forms(name, u, orders)
        return tuple(forms) + (None,) * (3 - orders)

    return fns


def _net(layers: tuple, fourier: np.ndarray, x: Jet, fns) -> Jet:  # noqa: ANN001
    angles = jets.linear(x, fourier)
    h = jets.concat([x, jets.elementwise(angles, fns("sin")), jets.elementwise(angles, fns("cos"))])
    for k, (weight, bias) in enumerate(layers):
        h = jets.linear(h, weight, bias)
        if k + 1 < len(layers):
            h = jets.elementwise(h, fns("silu"))
    return h


def _flow(warp: tuple, x: Jet, fns) -> Jet:  # noqa: ANN001
    for frequencies, phases, weight, bias in warp:
        angles = jets.linear(x, frequencies, phases)
        x = x + jets.linear(jets.elementwise(angles, fns("cos")), weight, bias)
    return x


def _icnn(skips: tuple, prev: tuple, out: tuple, slope: float, z: Jet, fns) -> Jet:  # noqa: ANN001
    act = fns("leaky", slope)
    h = None
    for k, (skip, bias) in enumerate(skips):
        u = jets.linear(z, skip, bias)
        if h is not None:
            u = u + jets.linear(h, prev[k - 1])
        h = jets.elementwise(u, act)
    return jets.linear(h, out[0]) + jets.linear(z, out[1])


def f_jet(model: PolicyModel, lo: np.ndarray, hi: np.ndarray) -> Jet:
    """First-order interval jet of the nominal field f(x) = net(x) - net(0) over boxes."""
    net = _net(model.layers, model.fourier, jets.variable(lo, hi, order=1), _interval_fns)
    return net.shift(-model.net0)


def f_quadratic(model: PolicyModel, center: np.ndarray, half: np.ndarray) -> quadratic.Quad:
    """f over the cells |x - c| <= w as second-order Taylor models, values (C, n)."""
    x = quadratic.variable(center, half)
    angles = x.matmul(model.fourier)
    h = quadratic.concat([x, quadratic.apply(angles, "sin"), quadratic.apply(angles, "cos")])
    for k, (weight, bias) in enumerate(model.layers):
        h = h.matmul(weight).shift(ia.point(bias))
        if k + 1 < len(model.layers):
            h = quadratic.apply(h, "silu")
    return h.shift(-model.net0)


def _lyapunov(model: PolicyModel, x: Jet, fns) -> Jet:  # noqa: ANN001
    z = _flow(model.warp, x, fns).shift(-model.phi0)
    g = _icnn(model.icnn_skips, model.icnn_prev, model.icnn_out, model.icnn_slope, z, fns)
    tangent = jets.linear(z, model.grad_g0)
    quadratic = jets.linear(jets.product(z, z), np.full((model.dim, 1), model.quadratic))
    return (g - tangent).shift(-model.g0) + quadratic


def v_jet(model: PolicyModel, lo: np.ndarray, hi: np.ndarray, *, order: int = 2) -> Jet:
    r"""Interval jet of :math:`V(x) = V_c(\phi(x) - \phi(0))` over boxes (C, n), k = 1, with
    :math:`V_c(z) = g(z) - g(0) - \nabla g(0)^\top z + d |z|^2`."""
    return _lyapunov(model, jets.variable(lo, hi, order=order), _interval_fns)


def v_forms(model: PolicyModel, center: np.ndarray, half: np.ndarray, *, order: int = 2) -> Jet:
    """V's jet over the cells |x - c| <= w with Taylor models for its entries."""
    return _lyapunov(model, jets.affine_variable(center, half, order=order), _affine_fns)


def rate_bounds(model: PolicyModel, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, ...]:
    r"""Bounds (C,) of the decay rate :math:`a(x) / V(x)` of
    :meth:`~snds.policy.StablePolicy.decay` over boxes (C, n): lower, upper."""
    nearest = np.minimum(np.abs(lo), np.abs(hi)) * ((lo > 0) | (hi < 0))
    farthest = np.maximum(np.abs(lo), np.abs(hi))
    r_lo = ia.sqrt(ia.point((nearest**2).sum(-1) * (1 - 8 * ia.UNIT))).lo
    r_hi = ia.sqrt(ia.point((farthest**2).sum(-1) * (1 + 8 * ia.UNIT))).hi
    near = model.rho_near * np.maximum(1.0 - r_hi / model.near_radius, 0.0)
    near_hi = model.rho_near * np.maximum(1.0 - r_lo / model.near_radius, 0.0)
    low = model.rho + model.rho_far * np.maximum(r_lo - 1.0, 0.0) + near
    high = model.rho + model.rho_far * np.maximum(r_hi - 1.0, 0.0) + near_hi
    if len(model.anchors) and model.drop > 0:
        a = model.anchors[None]
        # Distance from each box to each anchor: nearest and farthest points of the box.
        gap = np.maximum(np.maximum(lo[:, None] - a, a - hi[:, None]), 0.0)
        span = np.maximum(np.abs(lo[:, None] - a), np.abs(hi[:, None] - a))
        d_lo = (gap**2).sum(-1).min(-1) * (1 - 8 * ia.UNIT)
        d_hi = (span**2).sum(-1).min(-1) * (1 + 8 * ia.UNIT)
        scale = 2.0 * model.data_radius**2
        kernel_hi = ia.exp(ia.point(-d_lo / scale * (1 - 4 * ia.UNIT))).hi
        kernel_lo = ia.exp(ia.point(-d_hi / scale * (1 + 4 * ia.UNIT))).lo
        low = low - model.drop * np.minimum(kernel_hi, 1.0)
        high = high - model.drop * np.maximum(kernel_lo, 0.0)
    # The additions above round; a relative allowance covers them (the rates are O(1)).
    return low - np.abs(low) * 1e-12 - 1e-300, high + np.abs(high) * 1e-12 + 1e-300
