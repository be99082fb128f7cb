r"""Rollouts: batched fixed-step integration of a velocity field, and the guarded Euler step."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

Field = Callable[[Tensor], Tensor]


def _euler(field: Field, x: Tensor, dt: float) -> Tensor:
    return x + dt * field(x)


def _rk4(field: Field, x: Tensor, dt: float) -> Tensor:
    k1 = field(x)
    k2 = field(x + 0.5 * dt * k1)
    k3 = field(x + 0.5 * dt * k2)
    k4 = field(x + dt * k3)
    return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


#: Fixed-step integrators, each mapping (field, x, dt) to the next state.
INTEGRATORS: dict[str, Callable[[Field, Tensor, float], Tensor]] = {"euler": _euler, "rk4": _rk4}


@torch.no_grad()
def rollout(field: Field, x0: Tensor, *, dt: float, steps: int, method: str = "euler") -> Tensor:
    """Integrates :math:`\\dot x = \\pi(x)` from a batch of starts with a fixed step.

    Arguments:
        field: The velocity field, (B, n) -> (B, n).
        x0: Start states, shape (B, n).
        dt: Time step.
        steps: Number of steps.
        method: A key of :data:`INTEGRATORS`.

    Returns:
        The states, shape (steps + 1, B, n), starting with ``x0``.
    """
    step = INTEGRATORS[method]
    states = [x0]
    x = x0
    for _ in range(steps):
        x = step(field, x, dt)
        states.append(x)
    return torch.stack(states)


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
    lyapunov: Callable[[Tensor], Tensor],
    x0: Tensor,
    *,
    dt: float,
    steps: int,
    max_halvings: int = 30,
) -> GuardedRollout:
    r"""Euler steps shortened until V drops, so every discrete step decreases V.

    A continuous-time decrease :math:`\dot V \le -a` does not make every Euler step
    :math:`x + \Delta t \, \pi(x)` decrease V. Since V is convex and :math:`\pi` is a descent
    direction, a short enough step always does: each step is halved (per start) until
    :math:`V(x_{k+1}) < V(x_k)` or the state is at the target.

    Arguments:
        field: The velocity field, (B, n) -> (B, n).
        lyapunov: V, (B, n) -> (B,).
        x0: Start states, shape (B, n).
        dt: The nominal time step.
        steps: Number of steps.
        max_halvings: Give up shortening after this many halvings (then the step is taken).
    """
    x = x0
    states, taken = [x0], []
    for _ in range(steps):
        velocity = field(x)
        v_now = lyapunov(x)
        h = torch.full_like(v_now, dt)
        candidate = x + h.unsqueeze(-1) * velocity
        for _ in range(max_halvings):
            bad = (lyapunov(candidate) >= v_now) & (v_now > 0)
            if not bad.any():
                break
            h = torch.where(bad, 0.5 * h, h)
            candidate = x + h.unsqueeze(-1) * velocity
        x = candidate
        states.append(x)
        taken.append(h)
    return GuardedRollout(torch.stack(states), torch.stack(taken))


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
    policy: torch.nn.Module,
    x0: np.ndarray,
    *,
    dt: float,
    steps: int,
    method: str = "euler",
    dtype: torch.dtype = torch.float64,
) -> np.ndarray:
    """NumPy convenience: rollouts of a policy in user units.

    Arguments:
        policy: A module mapping positions (B, n) to velocities (B, n), user units.
        x0: Start positions, shape (B, n).
        dt: Time step in seconds.
        steps: Number of steps.
        method: A key of :data:`INTEGRATORS`.
        dtype: Precision of the integration.

    Returns:
        The rollouts, shape (B, steps + 1, n).
    """
    x = torch.tensor(np.asarray(x0, dtype=np.float64), dtype=dtype)
    states = rollout(policy, x, dt=dt, steps=steps, method=method)
    return states.transpose(0, 1).cpu().numpy()
