r"""A diffeomorphism of :math:`\mathbb{R}^n` from coupling layers, with analytic Jacobians.

Used twice: as SDS-EF's Euclideanizing flow (:mod:`snds.baselines.sdsef`) and as the warp of
SNDS's Lyapunov function (:class:`snds.nn.WarpedLyapunov`). Both need :math:`J_\phi^\top g`
(the gradient of a function of :math:`\phi(x)`) in every training step; here it is one
triangular step per layer, without autograd, so training differentiates it once rather than
twice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from snds.nn import fused

__all__ = ["EuclideanizingFlow", "LayerCache", "RFFCoupling"]


@dataclass
class LayerCache:
    """What a coupling layer's Jacobian needs from its forward pass (B rows).

    For an additive layer (s = 0) ``stretched``, ``stretch`` and ``slope`` are None: the
    Jacobian is then :math:`I + C` and needs only the angles.
    """

    stretched: Tensor | None  # (B, n) x * exp(s), x the layer's input
    angles: Tensor  # (B, m) the Fourier angles
    stretch: Tensor | None  # (B, n) exp(s), 1 on the conditioning coordinates
    slope: Tensor | None  # (B, n) ds/d(raw s) = 1 - tanh^2
    weight: Tensor  # (m, k) W with the amplitude and the mask of x_b's columns applied
    sines: Tensor | None = None  # (B, m) sin of the angles, computed once when first needed

    def sin(self) -> Tensor:
        """sin of the Fourier angles, (B, m); the Jacobian products need it, V alone does not."""
        if self.sines is None:
            self.sines = torch.sin(self.angles)
        return self.sines


class RFFCoupling(nn.Module):
    r"""One affine coupling layer with random-Fourier-feature conditioners.

    A fixed split of the coordinates into a conditioning part :math:`x_a` (kept) and a
    transformed part :math:`x_b`:

    .. math::

        y_a = x_a, \qquad y_b = x_b \odot e^{s(x_a)} + t(x_a), \qquad
        [s_{raw}, t] = h(x_a) W + c, \qquad s = S \tanh(s_{raw} / S),

    with :math:`h(u) = \sqrt{2/m} \cos(2 \pi u \Omega + \beta)`, :math:`\Omega` and
    :math:`\beta` fixed random buffers. Its inverse is :math:`x_b = (y_b - t(y_a)) \odot
    e^{-s(y_a)}`, so the layer is a bijection of :math:`\mathbb{R}^n` onto itself (for any
    weights), and its Jacobian is block lower triangular with a positive diagonal
    :math:`e^{s}`:

    .. math:: J = \begin{pmatrix} I & 0 \\ C & \mathrm{diag}(e^s) \end{pmatrix}, \qquad
        C = \mathrm{diag}(x_b \odot e^s) \, \partial s / \partial x_a
            + \partial t / \partial x_a.

    The split is written with masks rather than gathers (fewer, larger tensor operations):
    the rows of :math:`\Omega` for :math:`x_b` are zero, so :math:`h` sees only :math:`x_a`,
    and s and t are zeroed on :math:`x_a`. W starts at zero, so the layer starts as the
    identity.

    Arguments:
        dim: State dimension n >= 2.
        layer: Index of the layer; the split rotates the coordinates by it, so that in a
            stack every coordinate is both transformed and conditioned on.
        features: m, the number of random features.
        scale: Standard deviation of :math:`\Omega`, in cycles per unit.
        max_log_scale: S (0: additive coupling, s = 0).
        generator: Source of the random buffers.
    """

    def __init__(
        self,
        dim: int,
        layer: int,
        *,
        features: int,
        scale: float,
        max_log_scale: float,
        generator: torch.Generator,
    ) -> None:
        super().__init__()
        conditioning = torch.roll(torch.arange(dim), -layer)[: dim // 2]
        mask = torch.zeros(dim)
        mask[conditioning] = 1.0
        # Derived from (dim, layer), so not saved: a model file rebuilds it from the config.
        self.register_buffer("transformed", 1.0 - mask, persistent=False)
        columns = 1.0 - mask if max_log_scale <= 0 else torch.cat([1.0 - mask, 1.0 - mask])
        # Mask of W's columns that act on x_b, (2n,) or (n,) if additive, and the same with
        # the features' amplitude sqrt(2/m), which multiplies the weights rather than being
        # addmm's alpha: ONNX exports alpha as Gemm's float32 attribute, which rounded it and
        # put a float64 export of a warped policy 1e-3 (relative) off the library.
        self.amplitude = math.sqrt(2.0 / features)
        self.register_buffer("columns", columns, persistent=False)
        self.register_buffer("scaled_columns", columns * self.amplitude, persistent=False)
        self.dim = dim
        self.max_log_scale = max_log_scale
        self.affine = max_log_scale > 0
        frequencies = torch.randn(dim, features, generator=generator) * (2 * math.pi * scale)
        self.register_buffer("frequencies", frequencies * mask.unsqueeze(-1))
        self.register_buffer("phases", torch.rand(features, generator=generator) * 2 * math.pi)
        # Columns [0, n) give s_raw and [n, 2n) give t (only t, n columns, if additive);
        # those of x_a are masked out (and so get no gradient).
        outputs = 2 * dim if self.affine else dim
        self.weight = nn.Parameter(torch.zeros(features, outputs))
        self.bias = nn.Parameter(torch.zeros(outputs))

    def _conditioner(self, x: Tensor) -> tuple[Tensor | None, Tensor, Tensor | None, LayerCache]:
        """s (None if additive), t (each (B, n), zero on x_a), the slope 1 - tanh^2 of s
        (B, n; None if additive) and the cache's angles and weights."""
        # Masking W's columns (not the (B, n) outputs) zeroes s and t on x_a at the cost of
        # one small product per call, and those columns then get no gradient.
        angles = torch.addmm(self.phases, x, self.frequencies)
        if fused.active():
            # Training: W in the (k, m) layout, used through its transposed view. A product
            # (B, m) @ (m, k) with k = n or 2n, a handful of columns, is several times slower
            # on the CPU with a row-major (m, k) operand than with a column-major one, in the
            # forward and the backward pass (docs/design.md); and sin is needed anyway by the
            # Jacobian products, so sin and cos come from one pass.
            weight = (self.weight.T * self.scaled_columns.unsqueeze(-1)).contiguous().T
            sines, cosines = fused.sincos(angles)
            cache = LayerCache(None, angles, None, None, weight, sines)
        else:
            weight = self.weight * self.scaled_columns
            cosines = torch.cos(angles)
            cache = LayerCache(None, angles, None, None, weight)
        raw = torch.addmm(self.bias * self.columns, cosines, weight)
        if not self.affine:
            return None, raw, None, cache
        squashed = torch.tanh(raw[:, : self.dim] / self.max_log_scale)
        return self.max_log_scale * squashed, raw[:, self.dim :], 1.0 - squashed * squashed, cache

    def forward(self, x: Tensor) -> tuple[Tensor, LayerCache]:
        """Maps states (B, n) to (B, n) and keeps what the Jacobian needs."""
        s, t, slope, cache = self._conditioner(x)
        if s is None:
            return x + t, cache
        stretch = torch.exp(s)
        stretched = x * stretch
        cache.stretched, cache.stretch, cache.slope = stretched, stretch, slope
        return stretched + t, cache

    def inverse(self, y: Tensor) -> Tensor:
        """The inverse map, (B, n) -> (B, n): :math:`x_b = (y_b - t(y_a)) e^{-s(y_a)}`."""
        s, t, _, _ = self._conditioner(y)
        return y - t if s is None else (y - t) * torch.exp(-s)

    def _c_times(self, cache: LayerCache, w: Tensor) -> Tensor:
        """C w_a, shape (B, n), zero on x_a; only w_a matters (Omega's x_b rows are zero)."""
        d_features = cache.sin() * (w @ self.frequencies)
        d_raw = -(d_features @ cache.weight)
        if cache.stretch is None:
            return d_raw
        return cache.stretched * cache.slope * d_raw[:, : self.dim] + d_raw[:, self.dim :]

    def jvp(self, cache: LayerCache, w: Tensor) -> Tensor:
        """J w for tangents w (B, n) at the layer's input: :math:`(w_a, e^s w_b + C w_a)`."""
        if cache.stretch is None:
            return w + self._c_times(cache, w)
        return cache.stretch * w + self._c_times(cache, w)

    def solve(self, cache: LayerCache, v: Tensor) -> Tensor:
        r"""J^{-1} v for v (B, n) by forward substitution: :math:`w_a = v_a`,
        :math:`w_b = e^{-s} (v_b - C v_a)`."""
        if cache.stretch is None:
            return v - self._c_times(cache, v)
        return (v - self._c_times(cache, v)) / cache.stretch

    def vjp(self, cache: LayerCache, g: Tensor) -> Tensor:
        r"""J^T g for cotangents g (B, n): :math:`(g_a + C^\top g_b, e^s g_b)`."""
        if cache.stretch is None:
            d_features = cache.sin() * (g @ cache.weight.T)
            return g - d_features @ self.frequencies.T
        grad_raw = torch.cat([g * cache.stretched * cache.slope, g], -1)
        d_features = cache.sin() * (grad_raw @ cache.weight.T)
        return cache.stretch * g - d_features @ self.frequencies.T


class EuclideanizingFlow(nn.Module):
    r"""The diffeomorphism :math:`\phi = \ell_L \circ \dots \circ \ell_1` of coupling layers.

    With :math:`J = J_L \cdots J_1` (each :math:`J_l` at the layer's own input),
    :math:`J^{-1} v = J_1^{-1} \cdots J_L^{-1} v` and :math:`J^\top g = J_1^\top \cdots
    J_L^\top g` are one triangular step per layer, from the last to the first.
    :math:`\det J = \prod_l \prod e^{s_l} > 0` everywhere.

    Arguments:
        dim: State dimension n >= 2.
        layers: L, the number of coupling layers.
        features: Random Fourier features per layer.
        scale: Standard deviation of their frequencies, in cycles per unit.
        max_log_scale: S of every layer (0: additive couplings).
        seed: Seed of the random Fourier buffers.
    """

    def __init__(
        self,
        dim: int,
        *,
        layers: int,
        features: int,
        scale: float,
        max_log_scale: float = 0.0,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if dim < 2:
            raise ValueError(f"coupling layers split the state in two: need dim >= 2, got {dim}")
        generator = torch.Generator().manual_seed(seed)
        self.layers = nn.ModuleList(
            RFFCoupling(
                dim,
                layer,
                features=features,
                scale=scale,
                max_log_scale=max_log_scale,
                generator=generator,
            )
            for layer in range(layers)
        )

    def forward_with_caches(self, x: Tensor) -> tuple[Tensor, list[LayerCache]]:
        """:math:`\\phi(x)` for states (B, n), and each layer's Jacobian cache."""
        caches = []
        for layer in self.layers:
            x, cache = layer(x)
            caches.append(cache)
        return x, caches

    def centred(self, x: Tensor) -> tuple[Tensor, list[LayerCache]]:
        r""":math:`e = \phi(x) - \phi(0)` for states (B, n), with the target's row added last.

        The target goes through the flow in the same batch as the states. Its own row and a
        state's row at exactly the target may still round apart by an ulp in the matrix
        products (seen: V = 2e-31 at the target in 3-D), so such a state gets e = 0 exactly.

        Returns:
            e, shape (B + 1, n) (its last row is 0), and the layers' caches.
        """
        y, caches = self.forward_with_caches(torch.cat([x, x.new_zeros(1, x.shape[-1])]))
        at_target = torch.cat([(x == 0).all(-1, keepdim=True), x.new_ones(1, 1, dtype=bool)])
        return torch.where(at_target, torch.zeros_like(y), y - y[-1:]), caches

    def forward(self, x: Tensor) -> Tensor:
        """:math:`\\phi(x)`, (B, n) -> (B, n)."""
        return self.forward_with_caches(x)[0]

    def inverse(self, y: Tensor) -> Tensor:
        r""":math:`\phi^{-1}(y)`, (B, n) -> (B, n)."""
        for layer in reversed(self.layers):
            y = layer.inverse(y)
        return y

    def solve(self, caches: list[LayerCache], v: Tensor) -> Tensor:
        """:math:`J_\\phi^{-1} v` for v (B, n), with the caches of :meth:`forward_with_caches`."""
        for layer, cache in zip(reversed(self.layers), reversed(caches)):
            v = layer.solve(cache, v)
        return v

    def vjp(self, caches: list[LayerCache], g: Tensor) -> Tensor:
        """:math:`J_\\phi^\\top g` for g (B, n)."""
        for layer, cache in zip(reversed(self.layers), reversed(caches)):
            g = layer.vjp(cache, g)
        return g

    def jvp(self, caches: list[LayerCache], w: Tensor) -> Tensor:
        """:math:`J_\\phi w` for w (B, n)."""
        for layer, cache in zip(self.layers, caches):
            w = layer.jvp(cache, w)
        return w

    def jacobian(self, x: Tensor) -> Tensor:
        """The full Jacobian :math:`J_\\phi(x)`, shape (B, n, n), from n Jacobian-vector
        products (for tests and analysis; the policy never forms it)."""
        _, caches = self.forward_with_caches(x)
        eye = torch.eye(x.shape[-1], dtype=x.dtype, device=x.device)
        columns = [self.jvp(caches, e.expand_as(x)) for e in eye]
        return torch.stack(columns, dim=-1)
