r"""SDS-EF: stable dynamical systems through Euclideanizing flows (Rana et al., L4DC 2020).

A learned diffeomorphism :math:`\phi: \mathbb{R}^n \to \mathbb{R}^n` maps the state into a
latent space where the motion is a straight, exponentially converging line,
:math:`\dot z = -k (z - z^*)` with :math:`z^* = \phi(x^*)`. Pulled back through the flow this
is the paper's natural-gradient system

.. math:: \dot x = -k(x) \, J_\phi(x)^{-1} \big(\phi(x) - \phi(x^*)\big),

whose Lyapunov function is :math:`V(x) = \|\phi(x) - \phi(x^*)\|^2`:
:math:`\dot V = 2 (\phi(x) - \phi(x^*))^\top J_\phi \dot x = -2 k(x) V(x)`.

:math:`\phi` is a stack of affine coupling layers (Dinh et al., RealNVP) whose log-scale and
translation are linear functions of random Fourier features of the conditioning coordinates,
the paper's choice. Every layer's Jacobian is block triangular, so the Jacobian solve and
:math:`\nabla V = 2 J_\phi^\top (\phi(x) - \phi(x^*))` are written analytically, one cheap
triangular step per layer, with no autograd (checked against autograd in the tests).

The default couplings are additive (:math:`y_b = x_b + t(x_a)`, NICE-style, a zero
log-scale), so that the Jacobian and its inverse stay bounded over all of
:math:`\mathbb{R}^n`. Affine couplings (``max_log_scale > 0``, the paper's) fit somewhat
better, but their field grows without bound away from the data (the term
:math:`x_b e^s \partial s / \partial x_a` compounds over the layers), so explicit Euler
rollouts with the demonstrations' time step can blow up (measured: docs/design.md, "The
baselines' defaults").

Everything here is in the task's model coordinates, where the target is the origin.

Reference: M. A. Rana, A. Li, D. Fox, B. Boots, F. Ramos, N. Ratliff, "Euclideanizing Flows:
Diffeomorphic Reduction for Learning Stable Dynamical Systems", L4DC 2020.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import ClassVar

import torch
from torch import Tensor, nn

from snds.data.demonstrations import Demonstrations, Normalization, Split
from snds.errors import DataError
from snds.fitting import Fitted, refuse_other_spaces, train_network
from snds.nn.flow import EuclideanizingFlow, LayerCache
from snds.policy import Policy
from snds.spaces import Euclidean, Space
from snds.train import TrainConfig

__all__ = ["SDSEF", "FlowLyapunov", "SDSEFConfig", "SDSEFPolicy", "SpeedGain"]


@dataclass(frozen=True, kw_only=True)
class SDSEFConfig:
    r"""Architecture of an SDS-EF policy; saved beside its weights.

    Attributes:
        layers: Number of coupling layers of :math:`\phi`.
        features: Random Fourier features per coupling layer (the paper: a linear layer on
            fixed random features of the conditioning coordinates).
        fourier_scale: Standard deviation of the random frequencies, in cycles per unit of
            model coordinates (the demonstrations span about [-1, 1]).
        max_log_scale: Bound S on each layer's log-scale, :math:`s = S \tanh(\cdot / S)`, so
            every layer stretches a coordinate by at most :math:`e^{\pm S}`; 0 gives additive
            (volume-preserving, NICE-style) couplings :math:`y_b = x_b + t(x_a)`.
        speed_features: Random Fourier features of a learned state-dependent gain
            :math:`k(x) = k_0 \exp(b \tanh(w^\top h(x) / b))` (0: a constant learned
            :math:`k_0`, the plain latent system).
        speed_scale: Standard deviation of the gain's random frequencies, cycles per unit.
        speed_range: b, the bound on the log of the gain's variation around :math:`k_0`.
        gain: Initial :math:`k_0`, per unit of model time.
    """

    layers: int = 10
    features: int = 64
    fourier_scale: float = 2.0
    max_log_scale: float = 0.0
    speed_features: int = 64
    speed_scale: float = 0.5
    speed_range: float = 2.0
    gain: float = 1.0

    def __post_init__(self) -> None:
        if self.layers < 1 or self.features < 1 or self.speed_features < 0:
            raise ValueError("need layers >= 1, features >= 1 and speed_features >= 0")
        if not (self.fourier_scale > 0 and self.speed_scale > 0 and self.max_log_scale >= 0):
            raise ValueError("need fourier_scale > 0, speed_scale > 0 and max_log_scale >= 0")
        if not (self.speed_range > 0 and self.gain > 0):
            raise ValueError("speed_range and gain must be positive")

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return asdict(self)


class FlowLyapunov(nn.Module):
    r""":math:`V(x) = \|\phi(x) - \phi(0)\|^2` and its analytic gradient.

    :math:`V(0) = 0` and :math:`V > 0` elsewhere since :math:`\phi` is injective; it is
    radially unbounded since :math:`\phi` is proper (each layer has bounded s and t, so
    :math:`\|y\| \to \infty` as :math:`\|x\| \to \infty`). It is not convex. No useful
    quadratic floor :math:`V \ge d \|x\|^2` is known, hence :attr:`quadratic` = 0: with affine
    couplings :math:`\phi^{-1}` need not be Lipschitz; with additive ones it is, but the
    product over the layers of their Lipschitz bounds makes d uselessly small.

    Arguments:
        flow: The diffeomorphism :math:`\phi`.
    """

    quadratic: float = 0.0

    def __init__(self, flow: EuclideanizingFlow) -> None:
        super().__init__()
        self.flow = flow

    def latent(self, x: Tensor) -> tuple[Tensor, list[LayerCache]]:
        r""":math:`e = \phi(x) - \phi(0)` for states (B, n), with a zero last row added
        (:meth:`~snds.nn.flow.EuclideanizingFlow.centred`: exactly 0 at the target).

        Returns:
            e with the target's row last, shape (B + 1, n), and the layers' caches.
        """
        return self.flow.centred(x)

    def value_and_grad(self, x: Tensor) -> tuple[Tensor, Tensor]:
        r""":math:`V` and :math:`\nabla V = 2 J_\phi^\top (\phi(x) - \phi(0))`, analytically.

        Arguments:
            x: States in model coordinates, shape (*, n).

        Returns:
            V, shape (*,), and its gradient, shape (*, n).
        """
        flat = x.reshape(-1, x.shape[-1])
        e, caches = self.latent(flat)
        grad = 2.0 * self.flow.vjp(caches, e)[:-1]
        return (e[:-1] * e[:-1]).sum(-1).reshape(x.shape[:-1]), grad.reshape(x.shape)

    def forward(self, x: Tensor) -> Tensor:
        """V at states (*, n), shape (*,)."""
        flat = x.reshape(-1, x.shape[-1])
        e = self.flow.centred(flat)[0][:-1]
        return (e * e).sum(-1).reshape(x.shape[:-1])


class SpeedGain(nn.Module):
    r"""A positive gain :math:`k(x) = k_0 \exp(b \tanh(w^\top h(x) / b))` of the latent system.

    :math:`h` are random Fourier features of the state; with none, :math:`k = k_0`. The gain
    lies in :math:`[k_0 e^{-b}, k_0 e^{b}]` for any weights, so the latent decrease rate never
    vanishes. It only rescales the speed along the flow's straight latent lines, never their
    direction, so it leaves :math:`V` and the guarantee unchanged.

    Arguments:
        dim: State dimension n.
        config: The architecture.
        generator: Source of the random buffers.
    """

    def __init__(self, dim: int, config: SDSEFConfig, generator: torch.Generator) -> None:
        super().__init__()
        self.log_gain = nn.Parameter(torch.tensor(math.log(config.gain)))
        self.range = config.speed_range
        m = config.speed_features
        self.amplitude = math.sqrt(2.0 / m) if m else 0.0
        frequencies = torch.randn(dim, m, generator=generator) * (2 * math.pi * config.speed_scale)
        self.register_buffer("frequencies", frequencies)
        self.register_buffer("phases", torch.rand(m, generator=generator) * 2 * math.pi)
        self.weight = nn.Parameter(torch.zeros(m))

    def forward(self, x: Tensor) -> Tensor:
        """k at states (B, n), shape (B,)."""
        if self.weight.numel() == 0:
            return torch.exp(self.log_gain).expand(x.shape[0])
        features = self.amplitude * torch.cos(x @ self.frequencies + self.phases)
        return torch.exp(
            self.log_gain + self.range * torch.tanh(features @ self.weight / self.range)
        )


class SDSEFPolicy(Policy):
    r"""SDS-EF: the natural-gradient flow of a learned diffeomorphism, in user units.

    In model coordinates (target at 0),

    .. math:: \pi(x) = -k(x) \, J_\phi(x)^{-1} \big(\phi(x) - \phi(0)\big), \qquad
        V(x) = \|\phi(x) - \phi(0)\|^2,

    with :math:`\phi` an :class:`EuclideanizingFlow` and :math:`k > 0` a :class:`SpeedGain`.

    **Guarantee.** :math:`\nabla V^\top \pi = 2 (\phi - \phi_0)^\top J_\phi \pi = -2 k(x) V(x)
    < 0` away from the target, and :math:`\phi` is a bijection of :math:`\mathbb{R}^n` onto
    itself (every coupling layer is), so :math:`V` is positive definite and radially
    unbounded: the system is globally asymptotically stable at the target, for any weights,
    with :math:`V(t) \le V(0) e^{-2 k_{min} t}` (exponential in the latent space). The
    policy claims half that rate, :math:`a(x) = k(x) V(x)` (:meth:`decay`), leaving the other
    half as room for rounding.

    **Limits.** The guarantee is for the continuous-time flow. The decrease is exact only up to
    the rounding of the Jacobian solve (one triangular step per layer); with affine couplings
    the Jacobian gets ill-conditioned far from the data, where the rounding can exceed the
    decrease and where explicit Euler steps of the demonstrations' size can overshoot and
    diverge, while additive couplings (the default) keep :math:`J_\phi` and :math:`J_\phi^{-1}`
    bounded. :math:`V` is not convex, so the stability check's largest-safe-Euler-step
    bisection, exact for a convex V, is only a heuristic here; and with no known quadratic floor
    (``quadratic = 0``) the check's early stop of settled rollouts rests on a sampled level (see
    :func:`snds.stability.settle_level`). Exponential decrease of V does not bound the time to
    reach a metric tolerance uniformly, since :math:`\phi^{-1}` may stretch. Near the target the
    field is :math:`\pi(x) \approx -k(0) x` (the Jacobians cancel): every motion ends on a
    straight, radial approach.

    Arguments:
        dim: State dimension n >= 2 (coupling layers split the state in two).
        normalization: The task's affine map of space and time.
        config: The architecture.
        seed: Seed of the random Fourier buffers (the weights start at the identity flow).
    """

    kind = "sdsef"
    config_class = SDSEFConfig

    def __init__(
        self, *, dim: int, normalization: Normalization, config: SDSEFConfig, seed: int = 0
    ) -> None:
        if dim < 2:
            raise DataError(
                f"SDS-EF needs a state of dimension >= 2 (its coupling layers split the state "
                f"in two), got {dim}; use snds for 1-D motions"
            )
        super().__init__(dim=dim, normalization=normalization)
        self.config = config
        # The flow lives only inside the Lyapunov function, so that its tensors are saved once
        # (safetensors refuses shared tensors under two names).
        flow = EuclideanizingFlow(
            dim,
            layers=config.layers,
            features=config.features,
            scale=config.fourier_scale,
            max_log_scale=config.max_log_scale,
            seed=seed,
        )
        self.lyapunov = FlowLyapunov(flow)
        self.gain = SpeedGain(dim, config, torch.Generator().manual_seed(seed + 1))

    @property
    def flow(self) -> EuclideanizingFlow:
        r"""The diffeomorphism :math:`\phi`."""
        return self.lyapunov.flow

    def decay(self, v: Tensor, x: Tensor) -> Tensor:
        """The claimed decrease rate a(x) = k(x) V(x), half the exact 2 k(x) V(x); shape (*,).

        Arguments:
            v: V at the states, shape (*,).
            x: The states in model coordinates, shape (*, n).
        """
        return self.gain(x.reshape(-1, self.dim)).reshape(v.shape) * v

    def field(self, x: Tensor) -> Tensor:
        """The policy in model coordinates, (*, n) -> (*, n)."""
        flat = x.reshape(-1, self.dim)
        e, caches = self.lyapunov.latent(flat)
        # The target's row has e = 0, so solving it too costs one row and gives exactly 0.
        velocity = -self.flow.solve(caches, e)[:-1] * self.gain(flat).unsqueeze(-1)
        return velocity.reshape(x.shape)


@dataclass(frozen=True)
class SDSEF:
    """SDS-EF trained on velocities by :func:`snds.train.fit` (MSE, as the paper).

    The optimiser of SNDS (:class:`~snds.train.TrainConfig`: Adam with warm-up and cosine
    decay, in model coordinates) with the budget SDS-EF was measured at, 3,000 steps at a
    peak rate of 0.01, on the demonstrated states as the paper (no ``position_noise``, no
    ``noise_correction``).

    Attributes:
        name: Its key in :data:`snds.methods.METHODS`.
        description: One line for tables.
        policy_config: The architecture.
        train_config: Optimiser settings (seed and steps are replaced per fit).
        has_lyapunov: True: the policy carries V.
    """

    name: str = "sdsef"
    description: str = "SDS-EF: Euclideanizing flows (coupling-layer diffeomorphism, Rana 2020)"
    policy_config: SDSEFConfig = field(default_factory=SDSEFConfig)
    train_config: TrainConfig = field(
        default_factory=lambda: TrainConfig(
            steps=3000, lr=1e-2, position_noise=0.0, noise_correction=0.0
        )
    )
    has_lyapunov: ClassVar[bool] = True
    spaces: ClassVar[tuple[type[Space], ...]] = (Euclidean,)

    def fit(
        self,
        demos: Demonstrations,
        split: Split,
        *,
        seed: int = 0,
        steps: int | None = None,
        progress: bool = False,
    ) -> Fitted:
        """Fits an :class:`SDSEFPolicy` to the training velocities (see
        :meth:`snds.methods.Method.fit`)."""
        refuse_other_spaces(self.name, self.spaces, demos)
        steps = self.train_config.steps if steps is None else steps
        config = replace(self.train_config, seed=seed, steps=steps)
        policy = SDSEFPolicy(
            dim=demos.dim,
            normalization=Normalization.fit(demos),
            config=self.policy_config,
            seed=seed,
        )
        return train_network(policy, demos, split, config=config, progress=progress)
