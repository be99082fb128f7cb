"""The rollouts the plots draw, computed by the engine (:func:`snds.rollout.rollout`)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from snds.arrival import ARRIVAL_TOLERANCE
from snds.obstacles import Scene
from snds.policy import Policy
from snds.rollout import Arrival, rollout
from snds.stability import CheckConfig
from snds.steppers import Euler, Stepper

__all__ = ["rollouts_until_arrival"]


def rollouts_until_arrival(
    policy: Policy,
    demos: Any,
    starts: np.ndarray,
    *,
    dt: float,
    durations: float = CheckConfig().horizon_factor,
    stepper: Stepper = Euler(),
    scene: Scene | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Rollouts at the data's step until every one has arrived
    (:func:`snds.arrival.arrival_time`, within :data:`~snds.arrival.ARRIVAL_TOLERANCE` of
    each error scale) or is held by the scene's guard, in pieces of 1.5 longest-demonstration
    durations, for at most ``durations`` of them (the stability check's cap by default): every
    plot of a run shows the same rollouts, to the same end.

    Arguments:
        policy: The policy, float64.
        demos: Its demonstrations (target, extent, durations).
        starts: Start states, shape (B, space.dim).
        dt: The step, seconds.
        durations: The cap, in longest-demonstration durations.
        stepper: The one-step method (plain Euler by default).
        scene: Obstacles the rollouts go around (:class:`~snds.obstacles.Scene`), or None.

    Returns:
        The rollouts, shape (B, T, space.dim), and the step at which each arrived, shape
        (B,) (-1 for one that had not arrived at the cap).
    """
    duration = demos.max_duration()
    piece = max(1, int(1.5 * duration / dt))
    cap = int(durations * duration / dt)
    target = torch.tensor(np.asarray(demos.target, dtype=np.float64))
    arrival = Arrival.of(policy.space, target, demos.extent(), tolerance=ARRIVAL_TOLERANCE)
    x0 = torch.tensor(np.asarray(starts, dtype=np.float64))
    # Whole pieces until every rollout has arrived: the first piece that reaches the cap ends it.
    steps = piece * max(1, -(-cap // piece))
    result = rollout(
        policy,
        x0,
        dt=dt,
        steps=steps,
        stepper=stepper,
        scene=scene,
        until=arrival,
        check_every=piece,
    )
    return result.states.transpose(0, 1).cpu().numpy(), arrival.steps(result.states)
