"""The common target of a set of demonstrations, and the shift that puts every end on it."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from snds.data.demonstrations import Demonstration
from snds.errors import DataError

__all__ = ["MAX_END_SPREAD", "common_target", "end_at", "end_spread_message"]

MAX_END_SPREAD = 0.25
"""Default largest distance of a demonstration's end from the common target, in extents."""


def common_target(
    demos: Sequence[Demonstration],
    *,
    max_end_spread: float,
    indices: Sequence[int] | None = None,
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
        indices: The demonstrations' numbers in their file (0-based), which the error names;
            None: 0, 1, ...

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
        numbers = list(range(len(demos))) if indices is None else list(indices)
        starts = np.stack([demo.positions[0] for demo in demos])
        raise DataError(
            f"demonstrations do not end at a common target: ends lie up to {spread:.4g} from "
            f"their mean, {spread / extent:.0%} of the motion's extent {extent:.4g}, more than "
            f"max_end_spread={max_end_spread:g} allows; "
            + end_spread_message(ends, starts, target, extent, max_end_spread, numbers)
        )
    return target, tuple(end_at(demo, target) for demo in demos)


def end_at(demo: Demonstration, target: np.ndarray) -> Demonstration:
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


def end_spread_message(
    ends: np.ndarray,
    starts: np.ndarray,
    target: np.ndarray,
    extent: float,
    max_end_spread: float,
    numbers: list[int],
) -> str:
    """Which demonstrations end too far from the others, and the fixes.

    The outliers are the ends farther than ``max_end_spread`` extents from the median of the
    ends (per coordinate): unlike the mean, one far end does not drag it away from the rest,
    so the message names that one, not all. A far end that lies where another
    demonstration starts (within a tenth of the allowed spread), whose own end is not far,
    is most likely one stroke recorded as two: the message says so.

    Arguments:
        ends: End positions, shape (k, n).
        starts: Start positions, shape (k, n).
        target: The mean of the ends, shape (n,) (a fallback when no end is an outlier).
        extent: The motion's extent.
        max_end_spread: The limit, in extents.
        numbers: The demonstrations' numbers in their file.
    """
    distances = np.linalg.norm(ends - np.median(ends, axis=0), axis=-1) / extent
    far = [int(i) for i in np.argsort(-distances) if distances[i] > max_end_spread]
    if not far:
        distances = np.linalg.norm(ends - target, axis=-1) / extent
        far = [int(i) for i in np.argsort(-distances) if distances[i] > max_end_spread]
    named = ", ".join(f"demonstration {numbers[i]} ({distances[i]:.2f} extents)" for i in far)
    kept = [numbers[i] for i in range(len(numbers)) if i not in far]
    fixes = []
    for i in far:
        gaps = np.linalg.norm(starts - ends[i], axis=-1) / extent
        gaps[far] = np.inf
        j = int(np.argmin(gaps))
        if gaps[j] <= 0.1 * max_end_spread:
            fixes.append(
                f"demonstration {numbers[i]} ends where demonstration {numbers[j]} starts: one "
                "stroke split in two? (in a CSV, give both parts one demo label)"
            )
    if kept:
        fixes.append(
            f"drop {'it' if len(far) == 1 else 'them'} (--demos {','.join(map(str, kept))})"
        )
    # The limit applies to the distance from the mean, which is what must be raised.
    needed = np.ceil(np.linalg.norm(ends - target, axis=-1).max() / extent * 100) / 100
    fixes.append(f"raise --max-end-spread to {needed:.2f} if the ends should be merged")
    return f"outlying: {named}; " + "; or ".join(fixes)
