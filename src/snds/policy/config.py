"""The architecture of a :class:`~snds.policy.StablePolicy` (:class:`PolicyConfig`), saved
beside its weights."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, ClassVar

from snds.errors import ConfigError
from snds.policy.projection import RECTIFIERS

__all__ = ["DEFAULT_WARP_LAYERS", "PolicyConfig"]

#: Coupling layers of V's warp when :attr:`PolicyConfig.warp_layers` is None and n >= 2.
DEFAULT_WARP_LAYERS = 4


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
            :attr:`~snds.policy.Policy.space` is then :class:`~snds.spaces.Phased`.
    """

    hidden: tuple[int, ...] = (128, 128)
    activation: str = "silu"
    fourier_features: int = 128
    fourier_scale: float = 5.0
    lyapunov_hidden: tuple[int, ...] = (32, 32)
    lyapunov_activation: str = "smooth_leaky"
    quadratic: float = 0.05
    decay_rate: float = 0.75
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
