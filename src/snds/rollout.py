r"""Rollouts: batched fixed-step integration of a velocity field, and the guarded Euler step."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from snds.policy import Policy
from snds.spaces import Space

Field = Callable[[Tensor], Tensor]


Lyapunov = Callable[[Tensor], Tensor]
#: The promised decrease rate of V per unit time at states (B, n) with values (B,).
Rate = Callable[[Tensor, Tensor], Tensor]
#: One step of each state (B, m) along its velocity (B, k) for its own duration (B,).
Advance = Callable[[Tensor, Tensor, Tensor], Tensor]


def _euler_advance(x: Tensor, h: Tensor, velocity: Tensor) -> Tensor:
    return x + h.unsqueeze(-1) * velocity


def _euler(field: Field, x: Tensor, dt: float, advance: Advance) -> Tensor:
    return advance(x, torch.full_like(x[..., 0], dt), field(x))


def _rk4(field: Field, x: Tensor, dt: float, advance: Advance) -> Tensor:
    if advance is not _euler_advance:
        raise ValueError("rk4 integrates states in R^n only; use euler on other spaces")
    k1 = field(x)
    k2 = field(x + 0.5 * dt * k1)
    k3 = field(x + 0.5 * dt * k2)
    k4 = field(x + dt * k3)
    return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


#: Fixed-step integrators, each mapping (field, x, dt, advance) to the next state.
INTEGRATORS: dict[str, Callable[[Field, Tensor, float, Advance], Tensor]] = {
    "euler": _euler,
    "rk4": _rk4,
}


@torch.no_grad()
def rollout(
    field: Field,
    x0: Tensor,
    *,
    dt: float,
    steps: int,
    method: str = "euler",
    advance: Advance = _euler_advance,
) -> Tensor:
    """Integrates :math:`\\dot x = \\pi(x)` from a batch of starts with a fixed step.

    Arguments:
        field: The velocity field, (B, m) -> (B, k).
        x0: Start states, shape (B, m).
        dt: Time step.
        steps: Number of steps.
        method: A key of :data:`INTEGRATORS` ("rk4" in R^n only).
        advance: How a state moves along a velocity (a space's
            :meth:`~snds.spaces.Space.advance`); by default :math:`x + h v`.

    Returns:
        The states, shape (steps + 1, B, m), starting with ``x0``.
    """
    step = INTEGRATORS[method]
    states = [x0]
    x = x0
    for _ in range(steps):
        x = step(field, x, dt, advance)
        states.append(x)
    return torch.stack(states)


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
    advance: Advance = _euler_advance,
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
        advance: The step (x, h, velocity) -> next state; by default the Euler step
            :math:`x + h v`.
        first: The full steps ``advance(x, dt, field(x))``, shape (B, n), and V there, (B,),
            if the caller has them (it may have evaluated V there together with the field it
            needs next: :meth:`snds.policy.Policy.velocity_and_value`); else computed.

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


@dataclass(frozen=True)
class GuardedRollout:
    """Result of :func:`guarded_rollout`.

    Attributes:
        states: The states, shape (steps + 1, B, n).
        steps_taken: The step actually used at each step and start, shape (steps, B).
    """

    states: Tensor
    steps_taken: Tensor


@torch.no_grad()
def guarded_rollout(
    field: Field,
    lyapunov: Lyapunov,
    x0: Tensor,
    *,
    dt: float,
    steps: int,
    rate: Rate | None = None,
    max_halvings: int = 30,
    advance: Advance = _euler_advance,
) -> GuardedRollout:
    """Rollouts of :func:`guarded_step`: every discrete step decreases V.

    Arguments:
        field: The velocity field, (B, n) -> (B, n).
        lyapunov: V, (B, n) -> (B,).
        x0: Start states, shape (B, n).
        dt: The nominal time step.
        steps: Number of steps.
        rate: The promised decrease rate (see :func:`guarded_step`); None: V must only drop.
        max_halvings: Give up shortening after this many halvings (then the step is taken).
        advance: How a state moves along a velocity (see :func:`guarded_step`).
    """
    x, value = x0, None
    states, taken = [x0], []
    for _ in range(steps):
        x, h, value = guarded_step(
            field,
            lyapunov,
            x,
            dt=dt,
            rate=rate,
            max_halvings=max_halvings,
            value=value,
            advance=advance,
        )
        states.append(x)
        taken.append(h)
    return GuardedRollout(torch.stack(states), torch.stack(taken))


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
    policy: Policy, x: Tensor, dt: float, *, max_speed: float | None = None
) -> tuple[Tensor, Tensor]:
    """The policy's velocities at states x (B, space.dim), each scaled by h / dt for the
    guarded step h <= dt along its space (:func:`guarded_step`), and first, with
    ``max_speed``, by :func:`speed_scale`.

    A controller that holds a velocity for one period dt moves the state by about
    ``policy.space.advance(x, dt, velocity)``; scaled so, that step meets the guard's
    sufficient-decrease condition, and a stiff field cannot make a robot chatter on a
    discrete cycle at constant V. A policy without V keeps its velocities (h = dt). Under a
    speed limit the velocity s pi promises the decrease rate s a(x), and the guard asks that
    of it.

    Arguments:
        policy: The policy.
        x: States, shape (B, space.dim), user units.
        dt: The control period, seconds.
        max_speed: Largest speed of the positions, user units per second (None: no limit).

    Returns:
        The scaled velocities, shape (B, space.tangent_dim), and h, shape (B,).
    """
    velocity = policy(x)
    scale = speed_scale(policy.space, velocity, max_speed)
    velocity = velocity * scale.unsqueeze(-1)
    h = torch.full_like(velocity[:, 0], dt)
    if policy.stable:
        lyapunov, rate = policy_guard(policy)
        # The velocity is evaluated once: the guarded step only asks for it at x.
        _, h, _ = guarded_step(
            lambda _: velocity,
            lyapunov,
            x,
            dt=dt,
            rate=lambda states, value: scale * rate(states, value),
            advance=policy.space.advance,
        )
    return velocity * (h / dt).unsqueeze(-1), h


def converged_at(states: Tensor, target: Tensor, tolerance: float) -> Tensor:
    """First step index from which each rollout stays within ``tolerance`` of the target.

    Arguments:
        states: Rollouts, shape (T + 1, B, n).
        target: The target, shape (n,).
        tolerance: Distance counted as arrived.

    Returns:
        Indices, shape (B,); -1 for rollouts that do not end within the tolerance.
    """
    inside = (states - target).norm(dim=-1) <= tolerance  # (T + 1, B)
    # The last index at which a rollout was outside, plus one; 0 if it never was.
    outside = ~inside
    steps = torch.arange(states.shape[0], device=states.device).unsqueeze(-1)
    last_out = torch.where(outside, steps, torch.full_like(steps, -1)).max(dim=0).values
    first_in = last_out + 1
    return torch.where(inside[-1], first_in, torch.full_like(first_in, -1))


def rollout_numpy(
    policy: Policy,
    x0: np.ndarray,
    *,
    dt: float,
    steps: int,
    method: str = "euler",
    dtype: torch.dtype = torch.float64,
) -> np.ndarray:
    """NumPy convenience: rollouts of a policy in user units, along its space.

    Arguments:
        policy: The policy (evaluated in ``dtype`` if it is in that precision already; a
            float64 copy is the caller's choice).
        x0: Start states, shape (B, space.dim).
        dt: Time step in seconds.
        steps: Number of steps.
        method: A key of :data:`INTEGRATORS`.
        dtype: Precision of the integration.

    Returns:
        The rollouts, shape (B, steps + 1, space.dim).
    """
    x = torch.tensor(np.asarray(x0, dtype=np.float64), dtype=dtype)
    states = rollout(policy, x, dt=dt, steps=steps, method=method, advance=policy.space.advance)
    return states.transpose(0, 1).cpu().numpy()
