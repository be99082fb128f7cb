r"""One step of a rollout: the system stepped, and the steppers (plain Euler, RK4, guarded Euler).

A :class:`Dynamics` is what a rollout integrates: a velocity field, how a state moves along a
velocity (a space's :meth:`~snds.spaces.Space.advance`), and optionally a Lyapunov function V
with its promised decrease rate and an obstacle scene that modulates the field. A
:class:`Stepper` maps a batch of states and step lengths to the next states; every stepper
serves every state shape (positions, poses, a phase after either; one state or a batch) through
the dynamics' ``advance``. :func:`snds.rollout.rollout` loops over a stepper.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, final

import torch
from torch import Tensor

from snds.policy import Policy
from snds.spaces import Euclidean, Space

__all__ = [
    "RK4",
    "Advance",
    "Dynamics",
    "Euler",
    "Field",
    "GuardedEuler",
    "Lyapunov",
    "Rate",
    "Step",
    "Stepper",
    "euclidean_advance",
    "guarded_step",
    "policy_guard",
    "safe_velocity",
    "speed_scale",
]

#: A velocity field, states (B, m) -> velocities (B, k).
Field = Callable[[Tensor], Tensor]
#: V, states (B, m) -> values (B,).
Lyapunov = Callable[[Tensor], Tensor]
#: The promised decrease rate of V per unit time at states (B, m) with values (B,).
Rate = Callable[[Tensor, Tensor], Tensor]
#: One step of each state (B, m) for its own duration (B,) along its velocity (B, k).
Advance = Callable[[Tensor, Tensor, Tensor], Tensor]


def euclidean_advance(x: Tensor, h: Tensor, velocity: Tensor) -> Tensor:
    """The Euler step :math:`x + h v` of states in R^n."""
    return x + h.unsqueeze(-1) * velocity


def policy_guard(policy: Policy) -> tuple[Lyapunov, Rate]:
    """A stable policy's V and promised decrease rate in user units, for :func:`guarded_step`.

    V is read in model coordinates (positive rescaling leaves the Armijo condition as it is);
    the rate :math:`a(x)` is per unit of model time, so per user second it is divided by the
    normalisation's time scale.
    """

    def lyapunov(x: Tensor) -> Tensor:
        return policy.lyapunov(policy.to_model(x))

    def rate(x: Tensor, value: Tensor) -> Tensor:
        return policy.decay(value, policy.to_model(x)) / policy.time

    return lyapunov, rate


@dataclass(frozen=True, kw_only=True)
class Dynamics:
    """What a rollout integrates.

    Attributes:
        field: The velocity field, (B, m) -> (B, k).
        advance: How a state moves along a velocity; by default :math:`x + h v`.
        lyapunov: V, or None (no guard: the guarded stepper takes plain steps).
        rate: The promised decrease rate of V (None: V must only drop).
        scene: Obstacles (:class:`snds.obstacles.Scene`) that modulate the field and that no
            guarded step may end in, or None.
        target: The point the modulation turns the field towards near an obstacle, shape (n,).
        velocity_and_value: The field and V at states from one pass, if the policy has it
            (:meth:`snds.policy.Policy.velocity_and_value`): the adaptive rollout then reads
            V at a step's end from the pass that gives the velocity there.
    """

    field: Field
    advance: Advance = euclidean_advance
    lyapunov: Lyapunov | None = None
    rate: Rate | None = None
    scene: Any = None
    target: Tensor | None = None
    velocity_and_value: Callable[[Tensor], tuple[Tensor, Tensor]] | None = None

    @classmethod
    def of(cls, policy: Policy, *, scene: Any = None, guard: bool = True) -> Dynamics:
        """A policy's dynamics along its space, guarded by its V if it is stable and ``guard``,
        modulated by ``scene`` (turned towards the policy's target) if given."""
        lyapunov = rate = None
        if guard and policy.stable:
            lyapunov, rate = policy_guard(policy)
        return cls(
            field=policy,
            # R^n keeps the plain function: RK4 recognises it.
            advance=euclidean_advance
            if isinstance(policy.space, Euclidean)
            else policy.space.advance,
            lyapunov=lyapunov,
            rate=rate,
            scene=scene,
            target=None if scene is None else policy.center,
            velocity_and_value=policy.velocity_and_value if lyapunov is not None else None,
        )

    def velocity(self, x: Tensor, t: float = 0.0) -> tuple[Tensor, Tensor | None]:
        r"""The velocities at states x (B, m), modulated by the scene at time t, and every
        body's :math:`\Gamma` there, (B, K) (None without a scene)."""
        if self.scene is None:
            return self.field(x), None
        target = None if self.target is None else self.target.to(x.dtype)
        return self.scene.at(t).modulate_and_gammas(x, self.field(x), target)


@dataclass(frozen=True)
class Step:
    """One step of a batch.

    Attributes:
        states: The next states, (B, m).
        taken: The step each state took, (B,); 0 where a guard held the state.
        value: V at the next states, (B,), if the stepper computed it (else None).
        velocity: The velocities used at the states stepped from, (B, k).
    """

    states: Tensor
    taken: Tensor
    value: Tensor | None
    velocity: Tensor


class Stepper(ABC):
    """A one-step integrator: (dynamics, states (B, m), steps (B,)) -> :class:`Step`."""

    @abstractmethod
    def step(
        self,
        dynamics: Dynamics,
        x: Tensor,
        h: Tensor,
        *,
        t: float = 0.0,
        velocity: Tensor | None = None,
        gammas: Tensor | None = None,
        value: Tensor | None = None,
        first: tuple[Tensor, Tensor] | None = None,
        held: Tensor | None = None,
    ) -> Step:
        """One step of each state for its own duration h.

        Arguments:
            dynamics: The system.
            x: States, (B, m).
            h: Step lengths, (B,).
            t: Time of the states (moving obstacles).
            velocity: The (modulated) velocities at x, (B, k), if known.
            gammas: With them and a scene, every body's Gamma at x, (B, K).
            value: V at x, (B,), if known.
            first: The full steps ``advance(x, h, velocity)`` and V there, if known.
            held: Rows, (B,) bool, that a static scene's guard held at this same state
                before: the same state, velocity and scene hold them again, so they are
                held without trying the halvings (steppers without a scene ignore it).
        """


@final
@dataclass(frozen=True)
class Euler(Stepper):
    """The explicit Euler step along the space: :math:`x \\oplus h \\pi(x)`."""

    def step(self, dynamics, x, h, *, t=0.0, velocity=None, **unused):
        if velocity is None:
            velocity, _ = dynamics.velocity(x, t)
        return Step(dynamics.advance(x, h, velocity), h, None, velocity)


@final
@dataclass(frozen=True)
class RK4(Stepper):
    """The classical fourth-order Runge-Kutta step, for states in R^n without a scene."""

    def step(self, dynamics, x, h, *, velocity=None, **unused):
        if dynamics.advance is not euclidean_advance or dynamics.scene is not None:
            raise ValueError("RK4 integrates states in R^n only; use Euler on other spaces")
        field, dt = dynamics.field, h.unsqueeze(-1)
        k1 = field(x) if velocity is None else velocity
        k2 = field(x + 0.5 * dt * k1)
        k3 = field(x + 0.5 * dt * k2)
        k4 = field(x + dt * k3)
        return Step(x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4), h, None, k1)


@final
@dataclass(frozen=True)
class GuardedEuler(Stepper):
    r"""The Euler step, halved per state until it is safe (:func:`guarded_step`).

    Without a scene a step is safe when V falls by Armijo's condition; with a scene when it
    ends in free space (every :math:`\Gamma > 1` of the scene at t + h, or for a state already
    within a margin no deeper) and, outside every body's influence, V falls so too; a state no
    halving makes safe stays where it is (step 0). Dynamics without V take plain Euler steps
    (with a scene, still guarded against the obstacles).

    Attributes:
        sufficient: The fraction c of the promised decrease a step must achieve.
        max_halvings: Halvings tried; then the step is taken as it is (without a scene) or
            the state held (with one).
    """

    sufficient: float = 0.5
    max_halvings: int = 30

    def step(
        self,
        dynamics,
        x,
        h,
        *,
        t=0.0,
        velocity=None,
        gammas=None,
        value=None,
        first=None,
        held=None,
    ):
        if dynamics.scene is not None:
            return self._avoiding(dynamics, x, h, t=t, velocity=velocity, gammas=gammas, held=held)
        if velocity is None:
            velocity = dynamics.field(x)
        if dynamics.lyapunov is None:
            return Step(dynamics.advance(x, h, velocity), h, None, velocity)
        states, taken, new = guarded_step(
            lambda _: velocity,
            dynamics.lyapunov,
            x,
            dt=h,
            rate=dynamics.rate,
            sufficient=self.sufficient,
            max_halvings=self.max_halvings,
            value=value,
            advance=dynamics.advance,
            first=first,
        )
        return Step(states, taken, new, velocity)

    def _avoiding(
        self,
        dynamics: Dynamics,
        x: Tensor,
        h: Tensor,
        *,
        t: float,
        velocity: Tensor | None,
        gammas: Tensor | None,
        held: Tensor | None,
    ) -> Step:
        now = dynamics.scene.at(t)
        if velocity is None or gammas is None:
            velocity, gammas = dynamics.velocity(x, t)
        h = h.to(x).clone()
        free_far = ~(gammas < 2.0).any(dim=-1)
        value = required = None
        lyapunov = dynamics.lyapunov
        if lyapunov is not None:
            value = lyapunov(x)
            required = torch.zeros_like(value) if dynamics.rate is None else dynamics.rate(x, value)
            required = self.sufficient * required

        def safe(index: Tensor, candidate: Tensor) -> Tensor:
            # Free, or for a state already within a margin (a robot that lagged behind its
            # command) no deeper: it may slide along or out, never further in.
            later = now.gammas_after(candidate, h[index])
            ok = ((later > 1.0) | (later >= gammas[index])).all(dim=-1)
            if value is not None:
                new = lyapunov(candidate)
                old = value[index]
                decrease = (new <= old - h[index] * required[index]) & (new < old)
                ok = ok & (decrease | ~free_far[index] | (old <= 0))
            return ok

        candidate = x + h.unsqueeze(-1) * velocity
        pending = torch.arange(len(x))
        if held is not None:
            pending = pending[~held]
        pending = pending[~safe(pending, candidate[pending])]
        for _ in range(self.max_halvings):
            if len(pending) == 0:
                break
            h[pending] = 0.5 * h[pending]
            candidate[pending] = x[pending] + h[pending].unsqueeze(-1) * velocity[pending]
            pending = pending[~safe(pending, candidate[pending])]
        if held is not None:
            pending = torch.cat([pending, held.nonzero()[:, 0]])
        h[pending] = 0.0
        candidate[pending] = x[pending]
        return Step(candidate, h, None, velocity)


@torch.no_grad()
def guarded_step(
    field: Field,
    lyapunov: Lyapunov,
    x: Tensor,
    *,
    dt: float | Tensor,
    rate: Rate | None = None,
    sufficient: float = 0.5,
    max_halvings: int = 30,
    value: Tensor | None = None,
    advance: Advance = euclidean_advance,
    first: tuple[Tensor, Tensor] | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    r"""One Euler step per state, halved until it decreases V enough.

    A continuous-time decrease :math:`\dot V \le -a` does not make every Euler step
    :math:`x + h \pi(x)` decrease V: where the field is stiff, a step of the control period
    can overshoot, and rollouts may circle on a discrete cycle at constant V. Since V is smooth
    and :math:`\pi` a descent direction, a short enough step always decreases V, so each
    state's step is halved until the sufficient-decrease (Armijo) condition

    .. math:: V(x + h \pi(x)) \le V(x) - c \, h \, a(x), \qquad V(x + h \pi) < V(x)

    holds, with :math:`c` = ``sufficient`` < 1 and :math:`a` = ``rate``. A smooth V makes the
    accepted step bounded below on every sublevel set, so with :math:`a = \rho V` the
    discrete V falls at least geometrically: the discrete-time counterpart of the guarantee.
    A state at the target (V = 0) takes the plain step. A state that does not live in a
    vector space (a pose: position and unit quaternion) passes its own ``advance``, such as
    the exponential map on SO(3); the condition is then tested at the state it really reaches.

    Arguments:
        field: The velocity field, (B, n) -> (B, n).
        lyapunov: V, (B, n) -> (B,).
        x: States, shape (B, n).
        dt: The nominal step, one for all states or one per state, shape (B,).
        rate: The promised decrease rate a(x) of V per unit of time, given the states and
            their values; None asks only that V drop.
        sufficient: The fraction c of the promised decrease a step must achieve.
        max_halvings: Give up shortening after this many halvings (then the step is taken).
        value: V at ``x``, shape (B,), if known (the previous step returned it); else computed.
        advance: The step (x, h, velocity) -> next state; by default :math:`x + h v`.
        first: The full steps ``advance(x, dt, field(x))``, shape (B, n), and V there, (B,),
            if the caller has them; else computed.

    Returns:
        The next states, shape (B, n), the steps taken, shape (B,), and V at the next states,
        shape (B,), to pass to the next step.
    """
    velocity = field(x)
    if value is None:
        value = lyapunov(x)
    required = torch.zeros_like(value) if rate is None else sufficient * rate(x, value)
    h = dt.to(value).clone() if isinstance(dt, Tensor) else torch.full_like(value, dt)
    if first is None:
        candidate = advance(x, h, velocity)
        new = lyapunov(candidate)
    else:
        candidate, new = (t.clone() for t in first)

    def failing(index: Tensor) -> Tensor:
        old = value[index]
        return ~((new[index] <= old - h[index] * required[index]) & (new[index] < old))

    pending = (value > 0).nonzero().squeeze(-1)
    pending = pending[failing(pending)]
    for _ in range(max_halvings):
        if len(pending) == 0:
            break
        h[pending] = 0.5 * h[pending]
        candidate[pending] = advance(x[pending], h[pending], velocity[pending])
        new[pending] = lyapunov(candidate[pending])
        pending = pending[failing(pending)]
    return candidate, h, new


def speed_scale(space: Space, velocity: Tensor, max_speed: float | None) -> Tensor:
    r"""The factor :math:`s = \min(1, v_{max} / |v_p|)` of each velocity (B, tangent_dim)
    that brings the speed of its positions :math:`|v_p|` (the first ``space.position_dim``
    numbers: a pose's linear velocity, a phase model's positions) down to ``max_speed``, shape
    (B,); 1 everywhere for None.

    Scaling the whole velocity by :math:`s > 0` keeps the guarantee: :math:`\nabla V^\top
    (s \pi) \le -s a(x) < 0` (docs/guarantee.md, "Speed limit").
    """
    if max_speed is None:
        return torch.ones_like(velocity[:, 0])
    if not max_speed > 0:
        raise ValueError(f"max_speed must be positive, got {max_speed}")
    speed = velocity[:, : space.position_dim].norm(dim=-1)
    return torch.where(speed > max_speed, max_speed / torch.where(speed > 0, speed, 1.0), 1.0)


@torch.no_grad()
def safe_velocity(
    policy: Policy, x: Tensor, dt: float, *, max_speed: float | None = None, scene=None
) -> tuple[Tensor, Tensor]:
    """The policy's velocities at states x (B, space.dim), each scaled by h / dt for the
    guarded step h <= dt along its space (:class:`~snds.steppers.GuardedEuler`), and first,
    with ``max_speed``, by :func:`speed_scale`; with a ``scene`` (positions only), modulated
    around its obstacles and shortened so that the step stays out of them.

    A controller that holds a velocity for one period dt moves the state by about
    ``policy.space.advance(x, dt, velocity)``; scaled so, that step meets the guard's
    condition, and a stiff field cannot make a robot chatter on a discrete cycle at constant
    V. A policy without V keeps its velocities (h = dt) unless a scene shortens them. Under a
    speed limit the velocity s pi promises the decrease rate s a(x), and the guard asks that
    of it.

    Arguments:
        policy: The policy.
        x: States, shape (B, space.dim), user units.
        dt: The control period, seconds.
        max_speed: Largest speed of the positions, user units per second (None: no limit).
        scene: Obstacles (:class:`snds.obstacles.Scene`), or None.

    Returns:
        The scaled velocities, shape (B, space.tangent_dim), and h, shape (B,).
    """
    h = torch.full_like(x[:, 0], dt)
    if scene is not None:
        step = GuardedEuler(max_halvings=40).step(Dynamics.of(policy, scene=scene), x, h)
        return step.velocity * (step.taken / dt).unsqueeze(-1), step.taken
    velocity = policy(x)
    scale = speed_scale(policy.space, velocity, max_speed)
    velocity = velocity * scale.unsqueeze(-1)
    if policy.stable:
        lyapunov, rate = policy_guard(policy)
        # The velocity is evaluated once: the guarded step only asks for it at x.
        scaled = Dynamics(
            field=lambda _: velocity,
            advance=policy.space.advance,
            lyapunov=lyapunov,
            rate=lambda states, value: scale * rate(states, value),
        )
        h = GuardedEuler().step(scaled, x, h).taken
    return velocity * (h / dt).unsqueeze(-1), h
