r""":class:`StablePolicy`: a network's velocity field projected onto a Lyapunov decrease
(SNDS), or left unconstrained (behavioural cloning)."""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from snds.data.demonstrations import Normalization
from snds.errors import ConfigError
from snds.nn import MLP, EuclideanizingFlow, Lyapunov, WarpedLyapunov
from snds.policy.base import FieldTerms, Policy
from snds.policy.config import DEFAULT_WARP_LAYERS, PolicyConfig
from snds.policy.projection import project
from snds.spaces import Euclidean, Phased, Space

__all__ = ["StablePolicy"]


#: Where anchors sit before :meth:`StablePolicy.set_anchors`: far enough (model coordinates)
#: that the kernel is exactly 0, near enough that its square stays finite.
_NO_ANCHOR = 1e3


class StablePolicy(Policy):
    r"""A velocity field :math:`\pi(x)` in user units that provably reaches the target, or,
    with ``config.stable`` False, the unconstrained network of behavioural cloning, which
    has no such guarantee.

    Internally it works in model coordinates (target at 0, extent 1, top speed 1; see
    :class:`~snds.data.Normalization`): :math:`\pi` there is :func:`~snds.policy.project`
    applied to the nominal :math:`f(x) - f(0)` (so that the target is an equilibrium) with the
    :class:`~snds.nn.Lyapunov` function :math:`V` (a :class:`~snds.nn.WarpedLyapunov` with
    ``warp_layers`` > 0) and decay :math:`a \ge \rho V`. Behavioural cloning
    (``config.stable`` False, :data:`snds.methods.BC`) skips the projection: :math:`\pi` is
    :math:`f(x) - f(0)`, which may stop short of the target, circle or diverge; it keeps V's
    unused weights so that both share one file layout.

    Arguments:
        dim: State dimension n.
        normalization: The task's affine map of space and time.
        config: The architecture.
        seed: Seed of the initial weights.
    """

    kind = "stable"
    config_class = PolicyConfig

    def __init__(
        self, *, dim: int, normalization: Normalization, config: PolicyConfig, seed: int = 0
    ) -> None:
        super().__init__(dim=dim, normalization=normalization)
        torch.manual_seed(seed)
        if config.warp_layers is None:
            # Behavioural cloning never evaluates V, so its warp would be dead weight.
            wanted = dim >= 2 and config.stable
            config = replace(config, warp_layers=DEFAULT_WARP_LAYERS if wanted else 0)
        if type(config.phase_dim) is not int or not 0 <= config.phase_dim < dim:
            raise ConfigError(
                f"phase_dim must be an integer in [0, {dim}), got {config.phase_dim!r}"
            )
        self.config = config
        self.nominal_net = MLP(
            dim,
            dim,
            hidden=config.hidden,
            activation=config.activation,
            fourier_features=config.fourier_features,
            fourier_scale=config.fourier_scale,
            seed=seed,
        )
        # The unconstrained policy (behavioural cloning) keeps V's weights, unused, so that
        # both variants share one architecture and one file layout.
        lyapunov = Lyapunov(
            dim,
            hidden=config.lyapunov_hidden,
            activation=config.lyapunov_activation,
            quadratic=config.quadratic,
        )
        if config.warp_layers:
            if dim < 2:
                raise ConfigError(
                    f"warp_layers needs a state of dimension >= 2 (coupling layers split it "
                    f"in two), got {dim}; in 1-D a convex V fits every motion that reaches "
                    "the target"
                )
            warp = EuclideanizingFlow(
                dim,
                layers=config.warp_layers,
                features=config.warp_features,
                scale=config.warp_scale,
                seed=seed,
            )
            lyapunov = WarpedLyapunov(lyapunov, warp)
        self.lyapunov = lyapunov
        # Until set_anchors, far from every state, so that k(x) = 0 and the rate is rho.
        if config.anchors:
            self.register_buffer("anchors", torch.full((config.anchors, dim), _NO_ANCHOR))
        else:
            self.anchors = None

    @property
    def space(self) -> Space:
        """:math:`\\mathbb{R}^n`, or positions then a phase (:class:`~snds.spaces.Phased`)."""
        positions = Euclidean(self.dim - self.config.phase_dim)
        return Phased(positions, self.config.phase_dim) if self.config.phase_dim else positions

    def set_anchors(self, positions: Tensor) -> None:
        """Places the anchors on ``config.anchors`` of the training states (model coordinates,
        shape (N, n)), evenly spaced in their order, so along the demonstrations."""
        if self.anchors is None or len(positions) == 0:
            return
        index = torch.linspace(0, len(positions) - 1, len(self.anchors)).round().long()
        self.anchors.copy_(positions[index.to(positions.device)].detach())

    def _data_kernel(self, x: Tensor) -> Tensor:
        """k(x) = exp(-d(x)^2 / (2 r^2)), d(x) the distance to the nearest anchor, shape (*,)."""
        anchors = self.anchors.to(x.dtype)
        flat = x.reshape(-1, self.dim)
        # min_a |x - a|^2 = min_a (|a|^2 - 2 x.a) + |x|^2: one (B, M) product-and-add (addmm)
        # and its row minima, without a (B, M, n) tensor; several times faster than forming
        # |x|^2 - 2 x.a + |a|^2 in full and taking min's values and indices.
        closest = torch.addmm((anchors * anchors).sum(-1), flat, anchors.T, alpha=-2.0).amin(-1)
        nearest = (closest + (flat * flat).sum(-1)).clamp_min(0.0)
        return torch.exp(-nearest / (2.0 * self.config.data_radius**2)).reshape(x.shape[:-1])

    @property
    def method(self) -> str:
        """ "snds", or "bc" for the unconstrained variant."""
        return "snds" if self.stable else "bc"

    @property
    def stable(self) -> bool:
        """Whether the policy carries the Lyapunov guarantee."""
        return self.config.stable

    def nominal(self, x: Tensor) -> Tensor:
        """The nominal field f(x) - f(0) in model coordinates, (*, n) -> (*, n)."""
        # One pass over the batch and the target together: half the calls of two passes.
        flat = x.reshape(-1, self.dim)
        out = self.nominal_net(torch.cat([flat, flat.new_zeros(1, self.dim)]))
        return (out[:-1] - out[-1]).reshape(x.shape)

    def decay(self, v: Tensor, x: Tensor) -> Tensor:
        """The required decrease rate, shape (*,):
        a(x) = V (rho (1 - k(x)) + min(rho, rho_data) k(x) + rho_far (|x| - 1)_+
        + rho_near (1 - |x| / r_near)_+), with k(x) the data kernel of
        :attr:`~snds.policy.PolicyConfig.data_rate` (0 without anchors).

        Arguments:
            v: V at the states, shape (*,).
            x: The states in model coordinates, shape (*, n).
        """
        config = self.config
        radius = x.norm(dim=-1)
        rate = config.decay_rate + config.decay_far * (radius - 1.0).clamp_min(0.0)
        if self.anchors is not None:
            rate = rate - config.data_rate_drop * self._data_kernel(x)
        if config.decay_near:
            rate = rate + config.decay_near * (1.0 - radius / config.near_radius).clamp_min(0.0)
        return v * rate

    def field(self, x: Tensor) -> Tensor:
        """The policy in model coordinates, (*, n) -> (*, n)."""
        return self.field_and_nominal(x)[0]

    def field_and_nominal(self, x: Tensor) -> tuple[Tensor, Tensor | None]:
        """The policy and the nominal field it projects, both (*, n), from one pass of f
        (None for the nominal of the unconstrained variant, which projects nothing)."""
        terms = self.field_terms(x)
        return terms.field, terms.nominal

    def field_terms(self, x: Tensor) -> FieldTerms:
        """The policy with its nominal field, V and grad V (see
        :class:`~snds.policy.FieldTerms`), from one pass of f and one of V."""
        f = self.nominal(x)
        if not self.stable:
            return FieldTerms(f, None, None, None)
        v, grad_v = self.lyapunov.value_and_grad(x)
        return FieldTerms(
            project(f, grad_v, self.decay(v, x), rectifier=self.config.rectifier), f, v, grad_v
        )

    def _field_and_value(self, z: Tensor) -> tuple[Tensor, Tensor]:
        terms = self.field_terms(z)
        return terms.field, terms.value
