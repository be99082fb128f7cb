r"""Policies: velocity fields in user units; SNDS projects a network onto a Lyapunov decrease.

:class:`Policy` is what every method of the library learns (SNDS and the baselines): a
velocity field over normalised model coordinates, with a Lyapunov function where the method
has one. The guarantee of SNDS is :func:`project`; :class:`StablePolicy` wires networks to it.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from dataclasses import asdict, dataclass, replace
from typing import Any, ClassVar, NamedTuple, Protocol

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from snds.data.demonstrations import Normalization
from snds.errors import ConfigError
from snds.nn import MLP, EuclideanizingFlow, Lyapunov, WarpedLyapunov
from snds.spaces import Euclidean, Phased, Space

__all__ = [
    "DEFAULT_WARP_LAYERS",
    "RECTIFIERS",
    "FieldTerms",
    "LyapunovFunction",
    "Policy",
    "PolicyConfig",
    "StablePolicy",
    "float64_copy",
    "project",
]

#: Coupling layers of V's warp when :attr:`PolicyConfig.warp_layers` is None and n >= 2.
DEFAULT_WARP_LAYERS = 4


#: Where anchors sit before :meth:`StablePolicy.set_anchors`: far enough (model coordinates)
#: that the kernel is exactly 0, near enough that its square stays finite.
_NO_ANCHOR = 1e3


def _relu(u: Tensor) -> Tensor:
    return F.relu(u)


def _softplus(u: Tensor, sharpness: float = 50.0) -> Tensor:
    # softplus(k u) / k >= max(u, 0) for every u, so the decrease bound still holds exactly.
    return F.softplus(u, beta=sharpness)


#: Rectifiers r with r(u) >= max(u, 0): ReLU (the paper) or a smooth softplus.
RECTIFIERS = {"relu": _relu, "softplus": _softplus}


def project(f: Tensor, grad_v: Tensor, decay: Tensor, *, rectifier: str = "relu") -> Tensor:
    r"""Removes the part of a velocity field that would let V decrease too slowly.

    .. math:: \pi = f - \nabla V \, \frac{r(\nabla V^\top f + a)}{\|\nabla V\|^2}

    With :math:`r(u) \ge \max(u, 0)`, :math:`\nabla V^\top \pi = \nabla V^\top f -
    r(\nabla V^\top f + a) \le -a` holds exactly wherever :math:`\nabla V \ne 0`; where
    :math:`f` already decreases V fast enough (and r is ReLU), :math:`\pi = f`. No regulariser
    is added to the denominator, since one would break the inequality; where
    :math:`\nabla V = 0` (only at the target, for a strongly convex V) :math:`\pi = f`.

    Arguments:
        f: Nominal velocities, shape (*, n).
        grad_v: Gradient of the Lyapunov function at the same states, shape (*, n).
        decay: Required decrease rate a(x) >= 0, shape (*,).
        rectifier: A key of :data:`RECTIFIERS`.

    Returns:
        The projected velocities, shape (*, n).
    """
    norm2 = (grad_v * grad_v).sum(-1)
    excess = RECTIFIERS[rectifier]((grad_v * f).sum(-1) + decay)
    safe = torch.where(norm2 > 0, norm2, 1.0)
    return f - grad_v * (excess / safe).unsqueeze(-1)


@dataclass(frozen=True, kw_only=True)
class PolicyConfig:
    """Architecture of a policy; saved beside its weights.

    Attributes:
        hidden: Hidden widths of the nominal MLP f.
        activation: Activation of f (a key of :data:`snds.nn.ACTIVATIONS`).
        fourier_features: Random Fourier features of the input of f (0: raw input).
        fourier_scale: Standard deviation of their frequencies, per unit of model coordinates
            (the demonstrations span about [-1, 1]).
        lyapunov_hidden: Hidden widths of the ICNN in V.
        lyapunov_activation: Convex activation of the ICNN.
        quadratic: Coefficient d of the quadratic floor of V.
        decay_rate: rho in a(x) = rho V(x), per unit of model time (0, with decay_far and
            decay_near 0 too: the paper's relaxed mode, which only gives dV/dt <= 0 and does
            not rule out spurious equilibria).
        decay_far: Extra decay rate per unit of distance beyond the demonstrations' extent:
            a(x) = V(x) (rho + decay_far max(|x| - 1, 0)) in model coordinates. It speeds up
            the return from far away without constraining the fit on the data (|x| <= 1).
        decay_near: Extra decay rate at the target, fading linearly to 0 at ``near_radius``:
            a(x) gains V decay_near (1 - |x| / near_radius)_+. With rho alone the final
            approach from directions the data do not cover crawls at the floor
            |x| ~ exp(-rho t / 2); the default binds only where the data say nothing
            (docs/design.md; 0: off).
        near_radius: Radius of that region, in model coordinates.
        data_rate: rho_data, the decay rate that replaces rho on the demonstrations if it is
            lower: rho becomes rho (1 - k(x)) + min(rho, rho_data) k(x), with
            k(x) = exp(-d(x)^2 / (2 data_radius^2)) and d(x) the distance from x to the
            nearest of the policy's anchors, ``anchors`` training states spread along the
            demonstrations (set by :func:`snds.train.fit`). A demonstration that starts or
            lingers at rest then keeps its own slow pace instead of being pushed across its
            path towards the target at rate rho, while states away from the data keep rho.
            The rate stays at least min(rho, rho_data) everywhere, so the guarantee's
            exponential decrease holds unchanged.
        data_radius: The kernel's radius, in model coordinates.
        anchors: Number of anchors (0: none; rho everywhere). Pose policies take none.
        warp_layers: Coupling layers of a learned diffeomorphism inside V (0: none, V convex;
            see :class:`~snds.nn.WarpedLyapunov`; needs n >= 2). None (the default) takes
            :data:`DEFAULT_WARP_LAYERS` for n >= 2 and 0 in 1-D, where a convex V fits every
            motion that reaches the target, and for ``stable=False``; a policy stores the
            number it took. A convex V cannot follow a demonstration that winds back and
            forth; the warp bends V's sublevel sets to follow it (the measured reasons for the
            default are in docs/design.md).
        warp_features: Random Fourier features per coupling layer.
        warp_scale: Standard deviation of their frequencies, per unit of model coordinates.
        rectifier: r in the projection ("relu" as in the paper, or "softplus").
        stable: False gives the unconstrained policy pi = f (behavioural cloning).
        phase_dim: How many trailing numbers of a state are a phase (:mod:`snds.phase`;
            0: none). :func:`snds.make_policy` takes it from the demonstrations; the policy's
            :attr:`~Policy.space` is then :class:`~snds.spaces.Phased`.
    """

    hidden: tuple[int, ...] = (128, 128)
    activation: str = "silu"
    fourier_features: int = 128
    fourier_scale: float = 5.0
    lyapunov_hidden: tuple[int, ...] = (32, 32)
    lyapunov_activation: str = "smooth_leaky"
    quadratic: float = 0.05
    decay_rate: float = 0.5
    decay_far: float = 2.0
    decay_near: float = 2.0
    near_radius: float = 0.2
    data_rate: float = 0.1
    data_radius: float = 0.1
    anchors: int = 256
    warp_layers: int | None = None
    warp_features: int = 32
    warp_scale: float = 1.0
    rectifier: str = "relu"
    stable: bool = True
    phase_dim: int = 0

    #: Fields added after models were first saved, with the value that reproduces those models
    #: (a model.json without the field predates it): the near-target decay and the warp were
    #: off before, and so was the rate on the data (no anchors).
    BEFORE_ADDED: ClassVar[dict[str, Any]] = {"decay_near": 0.0, "warp_layers": 0, "anchors": 0}

    def __post_init__(self) -> None:
        object.__setattr__(self, "hidden", tuple(self.hidden))
        object.__setattr__(self, "lyapunov_hidden", tuple(self.lyapunov_hidden))
        if not (self.decay_rate >= 0 and self.decay_far >= 0):
            raise ConfigError(
                f"decay_rate and decay_far must be >= 0, got {self.decay_rate} and {self.decay_far}"
            )
        if not (self.decay_near >= 0 and self.near_radius > 0):
            raise ConfigError(
                f"need decay_near >= 0 and near_radius > 0, got {self.decay_near} and "
                f"{self.near_radius}"
            )
        # bool is an int to Python: only a true integer counts anchors.
        if type(self.anchors) is not int:
            raise ConfigError(f"anchors must be an integer, got {self.anchors!r}")
        if not (self.data_rate >= 0 and self.data_radius > 0 and self.anchors >= 0):
            raise ConfigError(
                f"need data_rate >= 0, data_radius > 0 and anchors >= 0, got {self.data_rate}, "
                f"{self.data_radius} and {self.anchors}"
            )
        layers = 0 if self.warp_layers is None else self.warp_layers
        if layers < 0 or self.warp_features < 1 or not self.warp_scale > 0:
            raise ConfigError(
                f"need warp_layers >= 0, warp_features >= 1 and warp_scale > 0, got "
                f"{self.warp_layers}, {self.warp_features} and {self.warp_scale}"
            )
        if self.rectifier not in RECTIFIERS:
            raise ConfigError(
                f"unknown rectifier {self.rectifier!r}; choose from {list(RECTIFIERS)}"
            )

    @property
    def data_rate_drop(self) -> float:
        """rho - min(rho, rho_data): how far the data kernel lowers the rate on an anchor
        (never raises it, so relaxed mode stays relaxed)."""
        return self.decay_rate - min(self.decay_rate, self.data_rate)

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return asdict(self)


class FieldTerms(NamedTuple):
    """A policy's field at states in model coordinates and what it is made of.

    Attributes:
        field: The policy, shape (*, n).
        nominal: The nominal field it projects, (*, n); None if it projects none.
        value: V, shape (*,); None without a Lyapunov function.
        grad: The gradient of V, (*, n); None without a Lyapunov function.
    """

    field: Tensor
    nominal: Tensor | None
    value: Tensor | None
    grad: Tensor | None


class LyapunovFunction(Protocol):
    r"""What a policy's Lyapunov function offers the checks, in model coordinates.

    Attributes:
        quadratic: A floor :math:`d \ge 0` with :math:`V(x) \ge d \|x\|^2` (0 if none is
            known); the stability check stops integrating a rollout once it is provably
            settled in :math:`\{V < d r^2\}`, which needs :math:`d > 0`.
    """

    quadratic: float

    def value_and_grad(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """V, shape (*,), and its gradient, shape (*, n), at states (*, n)."""
        ...

    def __call__(self, x: Tensor) -> Tensor:
        """V at states (*, n), shape (*,)."""
        ...


class Policy(nn.Module, ABC):
    r"""A velocity field in user units, computed in the task's model coordinates.

    States live in :attr:`space` (positions in :math:`\mathbb{R}^n` by default; poses for
    :class:`~snds.se3.PosePolicy`). Model coordinates put the target at 0 with extent 1 and
    top speed 1 (see :class:`~snds.data.Normalization`); :meth:`forward` maps user states
    there (:meth:`to_model`), evaluates :meth:`field` and maps the velocities back
    (:meth:`velocity_to_user`). A subclass implements :meth:`field`; one
    with a stability guarantee sets :attr:`lyapunov` to its Lyapunov function and
    :attr:`stable` to True, and states its guarantee, which the stability checks test:
    :math:`\nabla V^\top \pi \le -a(x)` with :meth:`decay` :math:`a \ge 0`.

    A subclass is saved and loaded by :mod:`snds.io` from its :attr:`kind`, its ``config``
    (a frozen dataclass with ``to_dict``, the class in :attr:`config_class`) and its state
    dict: ``cls(dim=..., normalization=..., config=...)`` must rebuild every tensor shape.

    Arguments:
        dim: Dimension n of the model coordinates (the state dimension for positions).
        normalization: The task's affine map of space and time.
    """

    #: Key of the class in :data:`snds.methods.POLICY_KINDS`, written into model.json.
    kind: ClassVar[str]
    #: The frozen dataclass of the constructor's ``config``.
    config_class: ClassVar[type]
    config: Any
    # Set by subclasses (a submodule, or None); not a class default, which would shadow the
    # submodule that nn.Module keeps outside the instance dict.
    lyapunov: LyapunovFunction | None

    def __init__(self, *, dim: int, normalization: Normalization) -> None:
        super().__init__()
        self.dim = dim
        self.normalization = normalization
        self.register_buffer("center", torch.tensor(normalization.center, dtype=torch.float32))
        self.length = normalization.length
        self.time = normalization.time

    @property
    def method(self) -> str:
        """The name of the method that made it (a key of :data:`snds.methods.METHODS`)."""
        return self.kind

    @property
    def space(self) -> Space:
        r"""The space of the states :meth:`forward` takes: :math:`\mathbb{R}^n` by default."""
        return Euclidean(self.dim)

    @property
    def stable(self) -> bool:
        """Whether the policy carries a Lyapunov function (and so a guarantee to check)."""
        return getattr(self, "lyapunov", None) is not None

    @abstractmethod
    def field(self, x: Tensor) -> Tensor:
        """The policy in model coordinates, (*, n) -> (*, n)."""

    def nominal(self, x: Tensor) -> Tensor:
        """The field before any stabilisation, (*, n) -> (*, n); the field itself by default.

        The decrease check scales its rounding tolerance by it (see
        :func:`snds.stability.decrease_violations`).
        """
        return self.field(x)

    def field_and_nominal(self, x: Tensor) -> tuple[Tensor, Tensor | None]:
        """The field, (*, n), and the nominal field it projects (None if it projects none)."""
        return self.field(x), None

    def field_terms(self, x: Tensor) -> FieldTerms:
        """The field at states (*, n) in model coordinates with what it is made of, from one
        pass where the field needs V anyway: V and its gradient for a policy with a Lyapunov
        function (None otherwise), and the nominal field (None if it projects none)."""
        field = self.field(x)
        if not self.stable:
            return FieldTerms(field, None, None, None)
        value, grad = self.lyapunov.value_and_grad(x)
        return FieldTerms(field, None, value, grad)

    def velocity_and_value(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`forward`'s velocities (*, space.tangent_dim) and V in model coordinates
        (*,) at user states (*, space.dim), in the policy's dtype: what a guarded step needs
        at the state it reaches (see :func:`snds.rollout.policy_guard`). Only for a policy
        with a Lyapunov function."""
        z = self.to_model(x)
        field, value = self._field_and_value(z)
        return self.velocity_to_user(z, field), value

    def _field_and_value(self, z: Tensor) -> tuple[Tensor, Tensor]:
        """The field and V at model states z, without V's gradient where the field does not
        need it (two passes here; one for a policy whose field is made from V)."""
        return self.field(z), self.lyapunov(z)

    def decay(self, v: Tensor, x: Tensor) -> Tensor:
        """The guaranteed decrease rate a(x) >= 0 of V, shape (*,); 0 by default.

        Arguments:
            v: V at the states, shape (*,).
            x: The states in model coordinates, shape (*, n).
        """
        return torch.zeros_like(v)

    def set_anchors(self, positions: Tensor) -> None:
        """Shows the policy its training states in model coordinates, shape (N, n), before a
        fit (see :attr:`PolicyConfig.anchors`); a policy without anchors ignores them."""

    def to_model(self, x: Tensor) -> Tensor:
        """User states (*, space.dim) to model coordinates (*, n)."""
        return (x - self.center.to(x.dtype)) / self.length

    @property
    def target(self) -> np.ndarray:
        """The target state x* in user units, shape (space.dim,), float64."""
        return np.asarray(self.normalization.center, dtype=np.float64)

    def extents(self) -> np.ndarray:
        """The demonstrations' extent in each error component of :attr:`space`
        (:meth:`~snds.spaces.Space.errors`), user units, shape (k,): the positions' first."""
        return np.array([self.normalization.extent])

    def chart_scales(self) -> np.ndarray:
        """User units per unit of the chart that :attr:`normalization` maps, one per error
        component of :attr:`space`, shape (k,): 1 for positions (the chart is the user
        space itself)."""
        return np.ones(len(self.space.error_names))

    def model_scale(self) -> np.ndarray:
        """How far one unit of model coordinates reaches in each error component of
        :attr:`space` (:meth:`~snds.spaces.Space.errors`), user units, shape (k,): a state
        within model distance r of the target is within r times this of it."""
        return self.chart_scales() * self.length

    def velocity_to_user(self, z: Tensor, velocity: Tensor) -> Tensor:
        """Model velocities (*, n) at model coordinates z (*, n) to user velocities
        (*, space.tangent_dim)."""
        return velocity * (self.length / self.time)

    def training_demonstrations(self, demos: Any) -> Any:
        """The demonstrations in the coordinates that :attr:`normalization` maps to model
        coordinates, as :func:`snds.train.fit` trains on them: ``demos`` themselves for
        positions."""
        return demos

    def forward(self, x: Tensor) -> Tensor:
        """Velocities (*, space.tangent_dim) in user units at states (*, space.dim) in user
        units.

        The policy computes in its own precision (that of its weights); states of another
        dtype (float32 into a float64 model, integers, ...) are cast to it, so the velocities
        are in the model's precision.
        """
        dtype = self.center.dtype
        # A Python-level test, so an export traced in the model's dtype holds no Cast node.
        if x.dtype != dtype:
            x = x.to(dtype)
        z = self.to_model(x)
        return self.velocity_to_user(z, self.field(z))

    @torch.no_grad()
    def predict(self, x: np.ndarray, *, chunk: int = 65_536) -> np.ndarray:
        """NumPy convenience: velocities (*, space.tangent_dim) at states (*, space.dim), both
        in user units, evaluated ``chunk`` states at a time (bounds the memory of the
        networks' activations)."""
        dtype, device = self.center.dtype, self.center.device
        array = np.asarray(x)
        flat = array.reshape(-1, array.shape[-1])
        width = self.space.tangent_dim
        out = np.empty((len(flat), width), dtype=torch.empty(0, dtype=dtype).numpy().dtype)
        for begin in range(0, len(flat), chunk):
            # A copy: demonstrations' arrays are read-only, which torch.as_tensor warns about.
            rows = torch.tensor(flat[begin : begin + chunk], dtype=dtype, device=device)
            out[begin : begin + chunk] = self(rows).cpu().numpy()
        return out.reshape(*array.shape[:-1], width)


class StablePolicy(Policy):
    r"""A velocity field :math:`\pi(x)` in user units that provably reaches the target, or,
    with ``config.stable`` False, the unconstrained network of behavioural cloning, which
    has no such guarantee.

    Internally it works in model coordinates (target at 0, extent 1, top speed 1; see
    :class:`~snds.data.Normalization`): :math:`\pi` there is :func:`project` applied to the
    nominal :math:`f(x) - f(0)` (so that the target is an equilibrium) with the
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
        :attr:`PolicyConfig.data_rate` (0 without anchors).

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
        """The policy with its nominal field, V and grad V (see :class:`FieldTerms`), from one
        pass of f and one of V."""
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


def float64_copy(policy: Policy) -> Policy:
    """A float64 copy of a policy in eval mode, for checks; the original is not changed."""
    return copy.deepcopy(policy).to(torch.float64).eval()
