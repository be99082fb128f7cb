r"""What "arrived" and "recovered" mean: one definition for the check, the simulator and the page.

- **Arrived**: within a tolerance of the target, :data:`ARRIVAL_TOLERANCE` of the
  demonstrations' extent by default, and staying there. The time to arrive is the first time
  from which the motion stays within it (:func:`arrival_time`).
- **Recovered** (after a push): back on the path, within :data:`PATH_TOLERANCE` of the extent
  of the rest of the path the motion was meant to follow (the demonstrated path, or the
  rollout from the same start without the push, from where the push took it on), and staying
  on it. The time to recover counts from the push
  (:func:`recovery_time`). Being "as close to the target as before the push" is not
  recovering: a push sideways along a level set of the distance leaves the motion off its
  path at the same distance.

Both read a sampled motion, so a state space only has to give the distances.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "ARRIVAL_TOLERANCE",
    "PATH_TOLERANCE",
    "arrival_time",
    "distance_to_path",
    "recovery_time",
]

#: Arrival tolerance, in extents (the largest distance of a demonstrated position from the
#: target): 1 % is where a drawn stroke's end and a recorded arm's final jitter sit.
ARRIVAL_TOLERANCE = 0.01
#: Recovery tolerance, in extents: back within 5 % of the path counts as on it, a leash about
#: as wide as the spread between demonstrations of one task in LASA.
PATH_TOLERANCE = 0.05


def _first_time_staying(times: np.ndarray, inside: np.ndarray) -> float:
    """The first time from which ``inside`` holds to the end (NaN if it fails at the end)."""
    if len(inside) == 0 or not inside[-1]:
        return float("nan")
    outside = np.flatnonzero(~inside)
    return float(times[outside[-1] + 1] if outside.size else times[0])


def arrival_time(times: np.ndarray, distances: np.ndarray, tolerance: float) -> float:
    """The time from which a motion stays within ``tolerance`` of the target.

    Arguments:
        times: Sample times, shape (T,), increasing.
        distances: Distance to the target at each sample, shape (T,); several error
            components (a pose's distance and angle) as (T, k) with a tolerance each.
        tolerance: The arrival tolerance (or one per component, shape (k,)).

    Returns:
        The arrival time, in the units of ``times``; NaN if the motion ends outside the
        tolerance (it has not arrived) or any distance is not finite.
    """
    distances = np.asarray(distances, dtype=float)
    inside = np.asarray(distances <= tolerance)
    if inside.ndim > 1:
        inside = inside.all(axis=-1)
    return _first_time_staying(np.asarray(times, dtype=float), inside)


def distance_to_path(points: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Distance of each point to a polyline (its segments, not only its vertices).

    Arguments:
        points: Shape (T, n).
        path: The polyline's vertices, shape (S, n), S >= 1.

    Returns:
        Distances, shape (T,).
    """
    points = np.asarray(points, dtype=float)
    path = np.asarray(path, dtype=float)
    if len(path) == 1:
        return np.linalg.norm(points - path[0], axis=-1)
    start, segment = path[:-1], np.diff(path, axis=0)  # (S-1, n)
    length2 = (segment**2).sum(-1)
    best = np.full(len(points), np.inf)
    # In chunks of points: (chunk, S-1, n) stays small for paths of thousands of samples.
    for begin in range(0, len(points), 256):
        p = points[begin : begin + 256, None, :] - start  # (c, S-1, n)
        along = np.where(length2 > 0, (p * segment).sum(-1) / np.maximum(length2, 1e-300), 0.0)
        nearest = p - along.clip(0.0, 1.0)[..., None] * segment
        best[begin : begin + 256] = np.linalg.norm(nearest, axis=-1).min(axis=-1)
    return best


def recovery_time(
    times: np.ndarray,
    positions: np.ndarray,
    path: np.ndarray,
    *,
    push_time: float,
    tolerance: float,
) -> float | None:
    """Seconds from a push until the motion is back on its path for good.

    Arguments:
        times: Sample times, shape (T,), increasing.
        positions: The pushed motion's positions, shape (T, n).
        path: The rest of the path it was meant to follow, shape (S, n): the demonstrated
            path, or the rollout from the same start without the push, from the point nearest
            to where the push took it on (a leg already passed is not the path).
        push_time: When the push happened, in the units of ``times``.
        tolerance: Distance to the path counted as on it (:data:`PATH_TOLERANCE` x the extent).

    Returns:
        The time from the push to the first sample from which every later one is within
        ``tolerance`` of the path (0 for a push that stays within it); None if the motion ends
        off the path.
    """
    times = np.asarray(times, dtype=float)
    after = times >= push_time
    if not after.any():
        return None
    off = distance_to_path(np.asarray(positions)[after], path)
    back = _first_time_staying(times[after], off <= tolerance)
    return None if np.isnan(back) else float(back - push_time)
