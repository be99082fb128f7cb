"""How a pushed run came back to its path: the rest of the path the policy takes from the same
start without the push (:func:`unpushed_path`, :func:`rest_of_path`), and the time the
measured path took to rejoin it for good (:func:`push_recovery`)."""

from __future__ import annotations

import numpy as np
import torch

from snds.arrival import PATH_TOLERANCE, distance_to_path, recovery_time
from snds.policy import Policy
from snds.rollout import rollout
from snds.steppers import GuardedEuler

__all__ = ["push_recovery", "rest_of_path", "unpushed_path"]


def push_recovery(
    policy: Policy,
    start: np.ndarray,
    states: np.ndarray,
    times: np.ndarray,
    push_time: float | None,
    dt: float,
) -> dict:
    """The recovery after a push (the fields of :class:`~snds.sim.result.SimResult`): the
    time until the measured path (task positions, (T, n)) is back on the rest of the path the
    policy takes from the same start without the push (:func:`rest_of_path`), within
    :data:`~snds.arrival.PATH_TOLERANCE` of the extent."""
    if push_time is None:
        return {"recovery_time": None}
    tolerance = PATH_TOLERANCE * float(policy.extents()[0])
    after = times >= push_time
    path = rest_of_path(
        unpushed_path(policy, start, dt=dt, steps=len(times) - 1), states[~after][-1]
    )
    return {
        "recovery_time": recovery_time(
            times, states, path, push_time=push_time, tolerance=tolerance
        ),
        "path_tolerance": tolerance,
        "off_path": float(distance_to_path(states[after], path).max()) if after.any() else 0.0,
    }


def rest_of_path(path: np.ndarray, position: np.ndarray) -> np.ndarray:
    """The part of a path (S, n) from its sample nearest to ``position`` (n,) on: where the
    motion was when it was pushed, so that coming back near a part already passed (a loop, an
    earlier leg) is not counted as being back on the path."""
    return path[int(np.linalg.norm(path - position, axis=-1).argmin()) :]


@torch.no_grad()
def unpushed_path(policy: Policy, start: np.ndarray, *, dt: float, steps: int) -> np.ndarray:
    """The positions (T, n) of the policy's own rollout from a start, as the commander drives
    it without a push: each step the velocity :func:`~snds.rollout.safe_velocity` gives for a
    period dt, at most ``steps`` steps, stopping within 1e-4 of the extent of the target."""
    space = policy.space
    target = torch.as_tensor(space.positions(policy.target))
    close = 1e-4 * float(policy.extents()[0])

    def near(x: torch.Tensor) -> torch.Tensor:
        position = x[:, : space.position_dim]
        return ~torch.isfinite(position).all(dim=-1) | ((position - target).norm(dim=-1) <= close)

    x = torch.tensor(np.asarray(start, dtype=np.float64))[None]
    result = rollout(policy, x, dt=dt, steps=steps, stepper=GuardedEuler(), until=near)
    return space.positions(result.states[:, 0].numpy())
