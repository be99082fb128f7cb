"""The common target of a set of demonstrations, and the shift that puts every end on it."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from snds.data.demonstrations import Demonstration
from snds.errors import DataError

MAX_END_SPREAD = 0.25
"""Default largest distance of a demonstration's end from the common target, in extents."""


def common_target(
    demos: Sequence[Demonstration], *, max_end_spread: float
) -> tuple[np.ndarray, tuple[Demonstration, ...]]:
    r"""Picks one target for all demonstrations and moves each end exactly onto it.

    The target :math:`x^*` is the mean of the end points: with no other knowledge of where the
    demonstrator aimed, it is the point closest (least squares) to every end. A stable policy
    has a single equilibrium, so each demonstration must end at :math:`x^*`, not near it.

    Each demonstration gets the offset :math:`s(t) \, (x^* - x_T)` with
    :math:`s(t) = (t - t_0) / (t_T - t_0)`: it is zero at the first sample (the start stays
    where it was demonstrated) and moves the last sample onto the target. A linear ramp is the
    smallest smooth correction with these two ends; it adds the constant
    :math:`(x^* - x_T) / (t_T - t_0)` to the velocities, so positions and velocities stay
    consistent. A demonstration that ended at rest then ends with that small velocity; that is
    fine, as ends need not be at rest (only LASA-like data are).

    Arguments:
        demos: The demonstrations, all of dimension n, each ending at position x_T, shape (n,).
        max_end_spread: Largest accepted distance of an end from the target, as a fraction of
            the motion's extent (the largest distance of any position from the target).

    Returns:
        The target, shape (n,), and the shifted demonstrations in the same order. Demonstrations
        already ending at the target are returned unchanged.

    Raises:
        DataError: If there are no demonstrations, their dimensions differ, or the ends are
            farther apart than ``max_end_spread`` allows.
    """
    if not (np.isfinite(max_end_spread) and max_end_spread >= 0):
        raise DataError(f"max_end_spread must be a non-negative number, got {max_end_spread}")
    if not demos:
        raise DataError("no demonstrations given")
    dims = sorted({demo.dim for demo in demos})
    if len(dims) != 1:
        raise DataError(f"demonstrations have different dimensions: {dims}")
    ends = np.stack([demo.positions[-1] for demo in demos])
    with np.errstate(over="ignore", invalid="ignore"):
        # The mean of equal ends can be an ulp off them; ends that agree must stay untouched.
        target = ends[0] if np.all(ends == ends[0]) else ends.mean(axis=0)
        spread = float(np.linalg.norm(ends - target, axis=-1).max())
        extent = max(
            float(np.linalg.norm(demo.positions - target, axis=-1).max()) for demo in demos
        )
    if not (np.isfinite(spread) and np.isfinite(extent)):
        raise DataError("positions are too large to compare their end points (overflow)")
    if spread > max_end_spread * extent:
        raise DataError(
            f"demonstrations do not end at a common target: ends lie up to {spread:.4g} from "
            f"their mean, {spread / extent:.0%} of the motion's extent {extent:.4g}, more than "
            f"max_end_spread={max_end_spread:g} allows; raise it (--max-end-spread) if the ends "
            f"should be merged"
        )
    return target, tuple(_end_at(demo, target) for demo in demos)


def _end_at(demo: Demonstration, target: np.ndarray) -> Demonstration:
    """Adds the linear-in-time offset that moves the last position of ``demo`` onto ``target``."""
    offset = target - demo.positions[-1]
    if not offset.any():
        return demo
    # Overflow becomes inf, which Demonstration rejects with a DataError.
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        ramp = (demo.times - demo.times[0]) / demo.duration
        positions = demo.positions + ramp[:, None] * offset
        velocities = demo.velocities + offset / demo.duration
    # Rounding can leave the last sample an ulp away; the target must be hit exactly.
    positions[-1] = target
    return Demonstration(positions, velocities, demo.times)
