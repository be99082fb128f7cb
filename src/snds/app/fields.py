"""A policy's field on the page's grid: the velocities and V the page draws, for a saved
model (:mod:`snds.app.results`) and for the live policy of a training
(:class:`snds.app.worker.Preview`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from snds.policy import Policy
from snds.rollout import policy_guard

__all__ = ["grid_field"]


@torch.no_grad()
def grid_field(
    policy: Policy,
    xs: np.ndarray,
    ys: np.ndarray,
    starts: Callable[[np.ndarray], np.ndarray] | None = None,
) -> dict:
    """Velocities (ny, nx, 2) and V (ny, nx; None without one) of a float64 policy on the grid
    ``xs`` (nx,) by ``ys`` (ny,).

    Arguments:
        policy: A float64 policy in eval mode (:func:`snds.policy.float64_copy`).
        xs: The grid's x values.
        ys: The grid's y values.
        starts: The state a start at each point (B, 2) takes (a model with a phase: the
            phase a new start there gets, :meth:`snds.phase.StartRule.start_states`); None:
            the point itself.
    """
    points = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    states = points if starts is None else starts(points)
    velocity = policy.predict(states)[:, :2].reshape(len(ys), len(xs), 2)
    value = None
    if policy.stable:
        lyapunov, _ = policy_guard(policy)
        value = lyapunov(torch.from_numpy(states)).numpy().reshape(len(ys), len(xs))
    return {"x": xs, "y": ys, "velocity": velocity, "V": value}
