"""The time of a recording stored without one: its time step, estimated from positions and
velocities (:func:`estimate_time_step`), and its gaps, samples missing at that step, found
from the velocities and either put back or given the time they took (what
:func:`snds.data.load_mat` does with each demonstration, by :data:`GAP_MODES`).
"""

from __future__ import annotations

import numpy as np

from snds.errors import DataError

__all__ = [
    "DEFAULT_GAPS",
    "GAP_MODES",
    "check_gap_mode",
    "estimate_time_step",
    "fill_gaps",
    "gap_durations",
    "retime_gaps",
]

GAP_MODES = ("fill", "retime")
"""How :func:`~snds.data.files.load_mat` treats recording gaps (samples missing from a recording):
``"fill"`` puts the missing samples back (:func:`fill_gaps`, the default), ``"retime"`` only
gives the jump the time it took (:func:`retime_gaps`, how files were read before)."""

DEFAULT_GAPS = "fill"
"""The gap mode of :func:`~snds.data.files.load_mat`,
:func:`~snds.data.files.load_demonstrations` and :class:`~snds.data.DataSource` when none
is given."""


def check_gap_mode(gaps: str) -> None:
    """Raises a DataError naming the choices unless ``gaps`` is one of :data:`GAP_MODES`."""
    if gaps not in GAP_MODES:
        raise DataError(f"unknown gap mode {gaps!r}; choose from {list(GAP_MODES)}")


def gap_durations(positions: np.ndarray, velocities: np.ndarray, dt: float) -> np.ndarray:
    r"""The time each step of a recording at a fixed step took, longer where samples are
    missing.

    A recording that drops samples shows a position jump that its velocities cannot explain:
    every demonstration of the 3-D LPV-DS files has one such gap, 1-17 cm in one step early in
    the motion, after which the motion goes on from the new position (a step, not a spike).
    A step whose increment is more than 5 times what the trapezoidal rule
    :math:`\Delta t (v_k + v_{k+1}) / 2` explains (and more than 1e-3 of the motion's extent)
    gets the time that the velocities need to cover it,
    :math:`\Delta t_k = \Delta x \cdot \bar v / \|\bar v\|^2` (least squares), if that is
    longer than ``dt``; every other step takes ``dt``.

    Arguments:
        positions: Positions, shape (T, n).
        velocities: Recorded velocities, shape (T, n).
        dt: The nominal time step.

    Returns:
        The duration of each step, shape (T - 1,): ``dt``, or longer across a gap.
    """
    steps = np.full(len(positions) - 1, dt)
    increments = np.diff(positions, axis=0)
    mean_velocities = (velocities[1:] + velocities[:-1]) / 2
    extent = float(np.linalg.norm(positions - positions[-1], axis=1).max())
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        explained = dt * np.linalg.norm(mean_velocities, axis=1)
        gaps = np.linalg.norm(increments, axis=1) > 5 * explained + 1e-3 * extent
        speed2 = np.sum(mean_velocities**2, axis=1)
        needed = np.sum(increments * mean_velocities, axis=1) / speed2
    gaps &= np.isfinite(needed) & (needed > dt)
    steps[gaps] = needed[gaps]
    return steps


def retime_gaps(positions: np.ndarray, velocities: np.ndarray, dt: float) -> np.ndarray:
    """Sample times at a fixed step, with a longer step wherever samples are missing (the
    durations of :func:`gap_durations`).

    At a fixed step the rollout from the recorded start can never make a gap's jump, so it
    would lag the demonstration by the gap for the rest of the motion; with the gap's own
    duration it need not. The samples stay as recorded, so the demonstration still jumps
    across the gap: :func:`fill_gaps` puts the missing samples back.

    Arguments:
        positions: Positions, shape (T, n).
        velocities: Recorded velocities, shape (T, n).
        dt: The nominal time step.

    Returns:
        Strictly increasing times starting at 0, shape (T,).
    """
    return np.concatenate([[0.0], np.cumsum(gap_durations(positions, velocities, dt))])


def fill_gaps(
    positions: np.ndarray, velocities: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""A recording at a fixed step with the samples it dropped put back.

    Each gap (a step of duration :math:`h > \Delta t`, see :func:`gap_durations`) from
    :math:`(x_k, v_k)` to :math:`(x_{k+1}, v_{k+1})` becomes :math:`m = \lfloor h / \Delta t
    \rfloor` steps of :math:`h / m \ge \Delta t`, whose new samples lie on the cubic Hermite
    curve through both ends with both recorded velocities, and take its velocities: the
    smoothest motion that leaves and joins the recording as it moved, in the time the
    velocities need. Without them a gap is a hole, 2-27 % of the task's extent long in the
    3-D LPV-DS files, in the thin tube of the demonstrations: a policy has no data there and
    its rollouts leave the tube across it. The recorded samples are kept unchanged.

    Arguments:
        positions: Positions, shape (T, n).
        velocities: Recorded velocities, shape (T, n).
        dt: The nominal time step.

    Returns:
        The positions (T', n), velocities (T', n) and strictly increasing times from 0 (T',),
        T' >= T (T' = T when nothing is missing).
    """
    durations = gap_durations(positions, velocities, dt)
    # Sub-steps of each recorded step: 1, or h / dt rounded down (up to rounding error) across
    # a gap, so no filled step is shorter than the recording's own.
    counts = np.maximum(1, np.floor(durations / dt + 1e-9).astype(np.int64))
    step = np.repeat(np.arange(len(durations)), counts)
    first = np.repeat(np.cumsum(counts) - counts, counts)
    fraction = (np.arange(len(step)) - first + 1) / counts[step]
    h = durations[step]
    x, v = _hermite(
        positions[step], velocities[step], positions[step + 1], velocities[step + 1], h, fraction
    )
    # The recorded sample itself, not the curve's rounding of it, ends each step.
    recorded = fraction == 1.0
    x[recorded], v[recorded] = positions[1:], velocities[1:]
    starts = np.concatenate([[0.0], np.cumsum(durations)[:-1]])
    times = starts[step] + h * fraction
    return (
        np.concatenate([positions[:1], x]),
        np.concatenate([velocities[:1], v]),
        np.concatenate([[0.0], times]),
    )


def _hermite(
    x0: np.ndarray,
    v0: np.ndarray,
    x1: np.ndarray,
    v1: np.ndarray,
    h: np.ndarray,
    s: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Positions and velocities (N, n) at fractions ``s`` (N,) of steps of durations ``h``
    (N,) on the cubic Hermite curves from (x0, v0) to (x1, v1), each (N, n)."""
    s, h = s[:, None], h[:, None]
    basis = (2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2)
    slopes = (6 * s**2 - 6 * s, 3 * s**2 - 4 * s + 1, -6 * s**2 + 6 * s, 3 * s**2 - 2 * s)
    ends = (x0, h * v0, x1, h * v1)
    positions = sum(b * e for b, e in zip(basis, ends, strict=True))
    velocities = sum(d * e for d, e in zip(slopes, ends, strict=True)) / h
    return positions, velocities


def estimate_time_step(positions: np.ndarray, velocities: np.ndarray) -> float:
    r"""The time step that best explains the position increments by the recorded velocities.

    Fits :math:`x_{k+1} - x_k \approx \Delta t \, (v_k + v_{k+1}) / 2` (trapezoidal rule) by
    least squares over the moving samples, then fits again without the samples whose residual
    exceeds 5 times the median. The refit matters: recorded positions can jump by centimetres
    in one sample (every 3-D LPV-DS file has such a jump), which biases the plain fit by up to
    7%; on the LPV-DS files that store ``dt`` the refit recovers it to within 0.5%.

    Arguments:
        positions: Positions, shape (T, n).
        velocities: Recorded velocities, shape (T, n).

    Returns:
        The estimated time step in seconds.

    Raises:
        DataError: If the velocities cannot explain the motion (no positive step fits).
    """
    steps = np.diff(positions, axis=0)
    mean_velocities = (velocities[1:] + velocities[:-1]) / 2
    # Samples at rest fit any time step, so they carry no information about it.
    moving = np.any(mean_velocities != 0, axis=1)
    if not moving.any():
        raise DataError(
            "cannot infer the time step: every velocity is zero; store 'dt' in the file"
        )
    steps, mean_velocities = steps[moving], mean_velocities[moving]
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        dt = _least_squares_step(steps, mean_velocities)
        residuals = np.linalg.norm(steps - dt * mean_velocities, axis=1)
        # NaN residuals (overflow) leave no inlier, hence a NaN step and the error below.
        inliers = residuals <= 5 * np.median(residuals)
        dt = _least_squares_step(steps[inliers], mean_velocities[inliers])
    if not (np.isfinite(dt) and dt > 0):
        raise DataError(
            "cannot infer the time step: the velocities do not match the position increments; "
            "store 'dt' in the file"
        )
    return float(dt)


def _least_squares_step(steps: np.ndarray, mean_velocities: np.ndarray) -> float:
    """Minimiser of ||steps - dt * mean_velocities||^2 over dt (NaN if velocities are zero)."""
    scale = float(np.sum(mean_velocities * mean_velocities))
    return float(np.sum(steps * mean_velocities)) / scale if scale > 0 else float("nan")
