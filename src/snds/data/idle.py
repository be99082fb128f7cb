r"""Idle samples of a recording: before the demonstrator starts, after they stop, and the
rests that separate several demonstrations in one long recording.

A step :math:`k` (from sample :math:`k` to :math:`k+1`) moves when its speed
:math:`\|x_{k+1} - x_k\| / (t_{k+1} - t_k)` is above a fraction :math:`f` of the recording's
top position speed (the caller passes the speeds; orientations are left out, see
:mod:`snds.data.tracks`). The fraction is relative so that it needs no unit.

It is off by default: a speed threshold cannot tell a rest from the slow start of a motion
that accelerates smoothly from rest, as LASA's and the LPV-DS arm recordings do. At
:math:`f = 0.01` it would drop 268 samples from the starts of LASA's 210 demonstrations (up to
21 from one) and up to 34 from the 3-D arm files, which are motion, not rests; on a
kinesthetic recording that starts with the arm held still (the Panda pose recording) it
drops 178 samples (0.33 s) at the start and 60 at the end.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["DEFAULT_REST_SPEED", "idle_span", "moving_steps", "rest_splits"]

#: Fraction of the top speed below which a step rests, for splitting at rests when no
#: ``trim_idle`` fraction is given.
DEFAULT_REST_SPEED = 0.02


def moving_steps(speeds: Sequence[np.ndarray], fraction: float) -> np.ndarray:
    """Which steps move: above ``fraction`` of its own top in any of ``speeds``.

    Arguments:
        speeds: Step speeds, each shape (T - 1,) (e.g. linear and angular).
        fraction: The fraction f of each top speed.

    Returns:
        A boolean array, shape (T - 1,).
    """
    moving = np.zeros(len(speeds[0]), dtype=bool)
    for speed in speeds:
        top = float(np.max(speed)) if len(speed) else 0.0
        if top > 0:
            moving |= speed > fraction * top
    return moving


def idle_span(speeds: Sequence[np.ndarray], fraction: float) -> tuple[int, int]:
    """The samples to keep when the idle start and end are trimmed.

    The kept span runs from the last sample at rest before the first moving step to the first
    sample at rest after the last one, so the demonstration still starts and ends where the
    demonstrator held it.

    Arguments:
        speeds: Step speeds, each (T - 1,), see :func:`moving_steps`.
        fraction: The fraction f of the top speed; 0 keeps every sample.

    Returns:
        ``(first, stop)``: keep samples ``first:stop`` (the whole recording if nothing moves).
    """
    count = len(speeds[0]) + 1
    if fraction <= 0:
        return 0, count
    moving = np.flatnonzero(moving_steps(speeds, fraction))
    if len(moving) == 0:
        return 0, count
    return int(moving[0]), int(moving[-1]) + 2


def rest_splits(
    speeds: Sequence[np.ndarray], times: np.ndarray, fraction: float, min_rest: float
) -> list[tuple[int, int]]:
    """The motions of one long recording, separated by rests of at least ``min_rest`` seconds.

    Arguments:
        speeds: Step speeds, each (T - 1,), see :func:`moving_steps`.
        times: Sample times, shape (T,).
        fraction: A step rests below this fraction of the recording's top speed.
        min_rest: Shortest rest (seconds) that ends a motion; shorter pauses stay inside it.

    Returns:
        ``(first, stop)`` sample spans, one per motion, in time order, each from its last
        sample at rest to its first sample at rest again.
    """
    moving = moving_steps(speeds, fraction)
    spans: list[tuple[int, int]] = []
    steps = np.flatnonzero(moving)
    if len(steps) == 0:
        return spans
    first = last = int(steps[0])
    for step in steps[1:]:
        # Steps last..step rest between two moving steps: a long enough rest ends a motion.
        if times[step] - times[last + 1] >= min_rest:
            spans.append((first, last + 2))
            first = int(step)
        last = int(step)
    spans.append((first, last + 2))
    return spans
