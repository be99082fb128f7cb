r"""From raw recorded tracks to demonstrations: times, units, idle samples, the common target.

Every reader of a recording (``.npy``, ``.mat`` pose matrices, ROS bags, LeRobot, HDF5)
gives a list of :class:`Track`: samples as the file stores them, in its units, with or
without times and orientations. :func:`assemble_tracks` applies the
:class:`~snds.data.options.ReadOptions` the same way for all of them:

1. times from the file, or from the stated rate (an error names ``--rate`` otherwise);
2. positions converted to metres when a length unit is given;
3. one long recording split at its rests, if asked;
4. idle starts and ends trimmed, if asked (:mod:`snds.data.idle`);
5. the chosen demonstrations kept, and all moved onto one target
   (:func:`~snds.data.targets.common_target`, :func:`~snds.data.poses.common_pose_target`).

A track with orientations gives poses, one without positions.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from snds.data.demonstrations import Demonstration, Demonstrations
from snds.data.idle import DEFAULT_REST_SPEED, idle_span, rest_splits
from snds.data.options import DataWarning, ReadOptions
from snds.data.poses import PoseDemonstration, PoseDemonstrations, common_pose_target
from snds.data.targets import MAX_END_SPREAD, common_target
from snds.errors import DataError

__all__ = ["POSE_REACH", "Track", "assemble_tracks", "labelled"]

#: Largest extent (metres) of a plausible pose recording: an arm's end effector, or a
#: mobile base in a room. Beyond it the positions are most likely in another unit.
POSE_REACH = 5.0


@dataclass(frozen=True)
class Track:
    """One recorded motion as a file stores it.

    Attributes:
        positions: Positions in the file's units, shape (T, n).
        orientations: Unit quaternions (x, y, z, w), shape (T, 4), or None for positions only.
        times: Sample times in seconds, shape (T,), or None when the file has none.
        label: How errors name it ("demonstration 3", "episode 7", a bag's name).
    """

    positions: np.ndarray
    orientations: np.ndarray | None = None
    times: np.ndarray | None = None
    label: str = ""


@contextlib.contextmanager
def labelled(where: str) -> Iterator[None]:
    """Prefixes DataErrors raised inside with ``where`` (a file, a demonstration)."""
    try:
        yield
    except DataError as error:
        raise DataError(f"{where}: {error}") from error


def assemble_tracks(
    tracks: Sequence[Track],
    *,
    options: ReadOptions = ReadOptions(),
    name: str = "",
    select: Sequence[int] | None = None,
    max_end_spread: float = MAX_END_SPREAD,
    what: str = "the file",
) -> Demonstrations | PoseDemonstrations:
    """The demonstrations of a recording's tracks (steps in the module doc).

    Arguments:
        tracks: The recorded motions, all with or all without orientations.
        options: How to read them.
        name: The task's name.
        select: Keep only these demonstrations (0-based, after any split at rests).
        max_end_spread: See :func:`~snds.data.targets.common_target`.
        what: The file's layout, for the message when it has no times.

    Raises:
        DataError: Naming the demonstration and the option that fixes it where one does.
    """
    if not tracks:
        raise DataError("no demonstrations in the file")
    if len({track.orientations is None for track in tracks}) != 1:
        raise DataError("some demonstrations have orientations and others not")
    timed = [_timed(track, options, what) for track in tracks]
    if options.split_rests is not None:
        timed = [part for track in timed for part in _split(track, options)]
    trimmed = [_trim(track, options.trim_idle) for track in timed]
    if select is not None:
        for i in select:
            if not 0 <= i < len(trimmed):
                raise DataError(f"demonstration index {i} out of range 0..{len(trimmed) - 1}")
        trimmed = [trimmed[i] for i in select]
    if trimmed[0].orientations is not None:
        return _poses(trimmed, options, name, select, max_end_spread)
    return _positions(trimmed, name, select, max_end_spread)


def _timed(track: Track, options: ReadOptions, what: str) -> Track:
    """The track with times and positions in the stated unit."""
    with labelled(track.label):
        positions = np.asarray(track.positions, dtype=np.float64)
        if positions.ndim != 2 or 0 in positions.shape:
            raise DataError(f"positions must have shape (samples, n), got {positions.shape}")
        if track.times is None:
            times = options.uniform_times(len(positions), what=what)
        elif options.rate is not None:
            raise DataError(
                "the recording stores its time stamps; --rate (ReadOptions.rate) is for files "
                "without them"
            )
        else:
            times = np.asarray(track.times, dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            positions = positions * options.metres
    return Track(positions, track.orientations, times, track.label)


def _speeds(track: Track) -> list[np.ndarray]:
    """Linear speed of each step, (T - 1,). Orientations do not count: differences of
    recorded quaternions at a high rate are mostly their rounding (on the Panda recording at
    540 Hz they keep 99 % of the samples "moving" at 1 % of the top angular speed)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        speed = np.linalg.norm(np.diff(track.positions, axis=0), axis=1) / np.diff(track.times)
    return [np.nan_to_num(speed, nan=0.0, posinf=0.0)]


def _part(track: Track, first: int, stop: int, label: str) -> Track:
    orientations = None if track.orientations is None else track.orientations[first:stop]
    return Track(track.positions[first:stop], orientations, track.times[first:stop], label)


def _trim(track: Track, fraction: float) -> Track:
    if fraction <= 0 or len(track.times) < 3:
        return track
    first, stop = idle_span(_speeds(track), fraction)
    return _part(track, first, stop, track.label)


def _split(track: Track, options: ReadOptions) -> list[Track]:
    fraction = options.trim_idle or DEFAULT_REST_SPEED
    spans = rest_splits(_speeds(track), track.times, fraction, options.split_rests)
    if not spans:
        raise DataError(f"{track.label}: the recording never moves, so it has no motion to split")
    return [
        _part(track, first, stop, f"{track.label} motion {k}")
        for k, (first, stop) in enumerate(spans)
    ]


def _positions(
    tracks: list[Track], name: str, select: Sequence[int] | None, max_end_spread: float
) -> Demonstrations:
    demos = []
    for track in tracks:
        with labelled(track.label):
            # Validates shapes, finiteness and increasing times before dividing by the steps.
            check = Demonstration(track.positions, np.zeros_like(track.positions), track.times)
            edge = 2 if len(check.times) > 2 else 1
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                velocities = np.gradient(check.positions, check.times, axis=0, edge_order=edge)
            demos.append(Demonstration(check.positions, velocities, check.times))
    target, shifted = common_target(demos, max_end_spread=max_end_spread, indices=select)
    assembled = Demonstrations(shifted, target, name)
    if assembled.extent() <= 0:
        raise DataError("demonstrations have zero extent (every sample is at the target)")
    return assembled


def _poses(
    tracks: list[Track],
    options: ReadOptions,
    name: str,
    select: Sequence[int] | None,
    max_end_spread: float,
) -> PoseDemonstrations:
    demos = []
    for track in tracks:
        with labelled(track.label):
            demos.append(PoseDemonstration(track.positions, track.orientations, track.times))
    _warn_if_not_metres(demos, options)
    target_position, target_orientation, moved = common_pose_target(
        demos, max_end_spread=max_end_spread, indices=select
    )
    return PoseDemonstrations(moved, target_position, target_orientation, name)


def _warn_if_not_metres(demos: list[PoseDemonstration], options: ReadOptions) -> None:
    """Warns when pose positions span more than :data:`POSE_REACH` metres and no unit was
    given: a pose model works in metres, so centimetres would make a 50 m task."""
    if options.length_unit is not None:
        return
    positions = np.concatenate([demo.positions for demo in demos])
    span = float(np.max(np.ptp(positions, axis=0)))
    if span > POSE_REACH:
        warnings.warn(
            f"pose positions span {span:.4g} m, more than a robot reaches; if they are in "
            "centimetres or millimetres, give --length-unit cm or mm "
            "(ReadOptions(length_unit=...))",
            DataWarning,
            stacklevel=2,
        )
