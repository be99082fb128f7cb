r"""Pose demonstrations: positions with unit-quaternion orientations, their loaders, and
synthetic orientations for position-only demonstrations.

A pose is a position :math:`p \in \mathbb{R}^3` and a unit quaternion :math:`q` in the
``(x, y, z, w)`` order (the order of SciPy and roma); :math:`q` and :math:`-q` are the same
orientation. This module is NumPy and SciPy only; :mod:`snds.se3` turns poses into the
learned state (position and rotation vector relative to the target).

The target pose of a set of demonstrations is chosen as for positions (see
:func:`~snds.data.targets.common_target`): the mean of the end positions, and the chordal
mean of the end orientations (:meth:`scipy.spatial.transform.Rotation.mean`, the rotation
closest in the least-squares sense to every end, sign-blind). Each demonstration is moved
onto it by a correction that grows linearly in time from zero at its start.

File layouts (one row per sample, rows of one demonstration together and in time order):

* CSV: header ``demo,t,x,y,z,qx,qy,qz,qw``;
* NPZ: ``pos`` (demos, samples, 3), ``quat`` (demos, samples, 4), optional ``t`` (demos,
  samples) or (samples,), or a scalar ``dt`` (default 0.01 s).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from snds.data.demonstrations import Demonstration, Demonstrations, DemonstrationSet
from snds.data.files import (
    DEFAULT_DT,
    csv_number,
    error_context,
    existing_file,
    read_csv_rows,
    real_array,
)
from snds.data.targets import MAX_END_SPREAD, common_target
from snds.errors import DataError

__all__ = [
    "MAX_END_ANGLE",
    "POSE_CSV_HEADER",
    "POSE_NPZ_KEYS",
    "SYNTHETIC_START",
    "PoseDemonstration",
    "PoseDemonstrations",
    "angles_to",
    "angular_velocities",
    "common_pose_target",
    "is_pose_file",
    "load_poses",
    "with_synthetic_orientations",
]

POSE_CSV_HEADER = ("demo", "t", "x", "y", "z", "qx", "qy", "qz", "qw")
POSE_NPZ_KEYS = ("pos", "quat", "t", "dt")

#: Largest accepted angle (radians) between a demonstration's end orientation and the target's.
MAX_END_ANGLE = 0.35

#: Default start of synthetic orientations relative to the target: 1.56 rad (89 degrees)
#: about a tilted axis, so that every axis of rotation is exercised.
SYNTHETIC_START = (0.6, -0.8, 1.2)


def _unit_quaternions(value: np.ndarray, name: str) -> np.ndarray:
    """Quaternions (T, 4) normalised to unit length, with consecutive signs made continuous."""
    q = np.array(value, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 4:
        raise DataError(f"{name} must have shape (T, 4) (qx, qy, qz, qw), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise DataError(f"{name} contains NaN or inf values")
    norms = np.linalg.norm(q, axis=1)
    if np.any(norms < 1e-6):
        raise DataError(f"{name} has a zero quaternion (row {int(np.argmin(norms))})")
    # Recorded quaternions are unit up to rounding of the logger; far from unit means a
    # wrong column order or not quaternions at all.
    if np.any(np.abs(norms - 1) > 1e-2):
        raise DataError(
            f"{name} are not unit quaternions (norms {norms.min():.3g}..{norms.max():.3g}); "
            "expected columns qx, qy, qz, qw"
        )
    q = q / norms[:, None]
    # q and -q are one orientation; a continuous sign keeps plots and interpolation smooth.
    flips = np.cumprod(np.where(np.sum(q[1:] * q[:-1], axis=1) < 0, -1.0, 1.0))
    q[1:] *= flips[:, None]
    q.setflags(write=False)
    return q


def angular_velocities(orientations: np.ndarray, times: np.ndarray) -> np.ndarray:
    r"""World-frame angular velocities :math:`\omega` of a sampled orientation path.

    Central differences on SO(3), :math:`\omega_k = \log(q_{k+1} q_{k-1}^{-1}) /
    (t_{k+1} - t_{k-1})` (one-sided at the ends): each log is of a small rotation, so the
    double cover never enters.

    Arguments:
        orientations: Unit quaternions, shape (T, 4), T >= 2.
        times: Sample times, shape (T,).

    Returns:
        Angular velocities in rad/s, shape (T, 3).
    """
    rotations = Rotation.from_quat(orientations)
    ahead = np.r_[1 : len(times), len(times) - 1]
    behind = np.r_[0, 0 : len(times) - 1]
    turn = (rotations[ahead] * rotations[behind].inv()).as_rotvec()
    return turn / (times[ahead] - times[behind])[:, None]


@dataclass(frozen=True)
class PoseDemonstration:
    """One demonstrated motion of a pose, sampled in time.

    Attributes:
        positions: Positions along the motion, shape (T, 3).
        orientations: Unit quaternions (x, y, z, w), shape (T, 4); signs made continuous.
        times: Strictly increasing sample times in seconds, shape (T,).
        phase: A phase appended to each state (:mod:`snds.phase`), shape (T, m); None: none.
    """

    positions: np.ndarray
    orientations: np.ndarray
    times: np.ndarray
    phase: np.ndarray | None = None

    def __post_init__(self) -> None:
        # Demonstration validates positions and times (shape, finiteness, monotonic times).
        check = Demonstration(self.positions, np.zeros_like(self.positions), self.times)
        if check.dim != 3:
            raise DataError(f"pose positions must have 3 coordinates, got {check.dim}")
        orientations = _unit_quaternions(self.orientations, "orientations")
        if len(orientations) != len(check.positions):
            raise DataError(
                f"orientations have {len(orientations)} samples, positions {len(check.positions)}"
            )
        if self.phase is not None:
            phase = np.asarray(self.phase, dtype=np.float64)
            if phase.ndim != 2 or len(phase) != len(check.positions):
                raise DataError(f"a phase has shape (T, m) with T={len(check.positions)}")
            object.__setattr__(self, "phase", phase)
        object.__setattr__(self, "positions", check.positions)
        object.__setattr__(self, "orientations", orientations)
        object.__setattr__(self, "times", check.times)

    @property
    def duration(self) -> float:
        """Time from the first to the last sample, in seconds."""
        return float(self.times[-1] - self.times[0])

    @property
    def states(self) -> np.ndarray:
        """The poses as rows (x, y, z, qx, qy, qz, qw), then the phase if any, shape
        (T, 7 + m)."""
        return np.concatenate([self.positions, self.orientations, *self._phase()], axis=1)

    def _phase(self) -> list[np.ndarray]:
        return [] if self.phase is None else [self.phase]

    @cached_property
    def velocities(self) -> np.ndarray:
        """The demonstrated twists (linear velocity, world-frame angular velocity), then the
        phase's rate if any, shape (T, 6 + m): second-order differences of the positions (and
        the phase) against the times, and :func:`angular_velocities`."""
        edge = 2 if len(self.times) > 2 else 1
        linear, *rate = (
            np.gradient(part, self.times, axis=0, edge_order=edge)
            for part in [self.positions, *self._phase()]
        )
        angular = angular_velocities(self.orientations, self.times)
        return np.concatenate([linear, angular, *rate], axis=1)


@dataclass(frozen=True)
class PoseDemonstrations(DemonstrationSet):
    """A set of pose demonstrations of one task, all ending at a common target pose.

    Attributes:
        demos: The demonstrated motions.
        target_position: The common end position p*, shape (3,).
        target_orientation: The common end orientation q* (x, y, z, w), shape (4,).
        name: A label for plots and reports.
    """

    demos: tuple[PoseDemonstration, ...]
    target_position: np.ndarray
    target_orientation: np.ndarray
    name: str = ""

    def __post_init__(self) -> None:
        demos = tuple(self.demos)
        if not demos:
            raise DataError("no demonstrations given")
        position = np.array(self.target_position, dtype=np.float64).reshape(-1)
        if position.shape != (3,) or not np.all(np.isfinite(position)):
            raise DataError(f"target position must be 3 finite numbers, got {position}")
        orientation = _unit_quaternions(np.reshape(self.target_orientation, (1, -1)), "target")
        object.__setattr__(self, "demos", demos)
        object.__setattr__(self, "target_position", position)
        object.__setattr__(self, "target_orientation", orientation[0])

    def select(self, indices: Sequence[int]) -> PoseDemonstrations:
        """The demonstrations at ``indices``, in that order, with the same target."""
        indices = list(indices)
        self._check_indices(indices)
        return PoseDemonstrations(
            tuple(self.demos[i] for i in indices),
            self.target_position,
            self.target_orientation,
            self.name,
        )

    @property
    def phase_dim(self) -> int:
        """How many numbers of a phase each state carries after its pose (0: none)."""
        phase = self.demos[0].phase
        return 0 if phase is None else phase.shape[1]

    def with_phase(self, phases: Sequence[np.ndarray]) -> PoseDemonstrations:
        """The same demonstrations with a phase appended to each, shapes (T_d, m); the
        target state then ends in m zeros (:mod:`snds.phase`)."""
        demos = tuple(
            replace(demo, phase=phase) for demo, phase in zip(self.demos, phases, strict=True)
        )
        return PoseDemonstrations(demos, self.target_position, self.target_orientation, self.name)

    def angle_extent(self) -> float:
        """Largest angle (radians) of a demonstrated orientation from the target orientation."""
        return float(
            max(angles_to(demo.orientations, self.target_orientation).max() for demo in self)
        )

    @property
    def target(self) -> np.ndarray:
        """The target state as one row (x, y, z, qx, qy, qz, qw), then a phase's m zeros,
        shape (7 + m,)."""
        return np.concatenate(
            [self.target_position, self.target_orientation, np.zeros(self.phase_dim)]
        )


def angles_to(orientations: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Geodesic angles (radians, in [0, pi]) from each of ``orientations`` (*, 4) to ``target``.

    The angle of :math:`q \\, q^{*-1}`, i.e. :math:`2 \\arccos |q \\cdot q^*|`, blind to signs.
    """
    dots = np.abs(np.asarray(orientations) @ np.asarray(target))
    return 2.0 * np.arccos(np.clip(dots, 0.0, 1.0))


def common_pose_target(
    demos: Sequence[PoseDemonstration],
    *,
    max_end_spread: float = MAX_END_SPREAD,
    max_end_angle: float = MAX_END_ANGLE,
    indices: Sequence[int] | None = None,
) -> tuple[np.ndarray, np.ndarray, tuple[PoseDemonstration, ...]]:
    r"""One target pose for all demonstrations, and each demonstration moved onto it.

    Positions as in :func:`~snds.data.targets.common_target` (mean of the ends, linear-in-time
    offset). Orientations: the target :math:`q^*` is the chordal mean of the end orientations;
    each demonstration's orientations are rotated by :math:`\exp(s(t) \log(q^* q_T^{-1}))`
    (applied on the left, in the world frame), with :math:`s` rising linearly from 0 at the
    start to 1 at the end, so starts stay as demonstrated and the last sample is exactly
    :math:`q^*`.

    Arguments:
        demos: The demonstrations.
        max_end_spread: Largest distance of an end position from the target, as a fraction of
            the motion's extent.
        max_end_angle: Largest angle (radians) of an end orientation from the target's.
        indices: The demonstrations' numbers in their file, which errors name; None: 0, 1, ...

    Returns:
        The target position (3,), target orientation (4,), and the moved demonstrations.

    Raises:
        DataError: If the ends are farther apart than the limits allow.
    """
    if not demos:
        raise DataError("no demonstrations given")
    position_demos = [
        Demonstration(d.positions, np.zeros_like(d.positions), d.times) for d in demos
    ]
    target_position, moved = common_target(
        position_demos, max_end_spread=max_end_spread, indices=indices
    )
    ends = Rotation.from_quat(np.stack([d.orientations[-1] for d in demos]))
    target = ends.mean()
    angles = (ends * target.inv()).magnitude()
    if angles.max() > max_end_angle:
        numbers = list(range(len(demos))) if indices is None else list(indices)
        far = ", ".join(
            f"demonstration {numbers[i]} ({angles[i]:.3g} rad)"
            for i in np.argsort(-angles)
            if angles[i] > max_end_angle
        )
        raise DataError(
            f"demonstrations do not end at a common orientation: an end is {angles.max():.3g} rad "
            f"from their mean, more than max_end_angle={max_end_angle:g}: {far}; drop it with "
            "--demos, or check the quaternion order (--quaternion-order)"
        )
    shifted = []
    for demo, position_demo in zip(demos, moved):
        ramp = (demo.times - demo.times[0]) / demo.duration
        correction = Rotation.from_rotvec(
            ramp[:, None] * (target * Rotation.from_quat(demo.orientations[-1]).inv()).as_rotvec()
        )
        orientations = (correction * Rotation.from_quat(demo.orientations)).as_quat()
        # Rounding leaves the last sample an ulp away; the target must be hit exactly.
        orientations[-1] = target.as_quat()
        shifted.append(PoseDemonstration(position_demo.positions, orientations, demo.times))
    return target_position, target.as_quat(), tuple(shifted)


def with_synthetic_orientations(
    demos: Demonstrations,
    *,
    start: Sequence[float] = SYNTHETIC_START,
    spread: float = 0.1,
    target_orientation: Sequence[float] = (0.0, 0.0, 0.0, 1.0),
    seed: int = 0,
) -> PoseDemonstrations:
    r"""Lifts position demonstrations (2-D or 3-D) to poses with synthetic orientations.

    As in the paper's SE(3) experiments, whose demonstrations hold positions only. A 2-D
    motion is placed on the plane z = 0. Demonstration d starts at orientation
    :math:`q_{0,d} = \exp(r_0 + \epsilon_d) \, q^*`, with :math:`\epsilon_d \sim
    \mathcal{N}(0, \sigma^2 I)` (a little variation per demonstration), and turns to
    :math:`q^*` by spherical linear interpolation, at the fraction of its path length
    travelled: the orientation arrives when the position does, and turns fastest where the
    motion is fastest.

    Arguments:
        demos: Position demonstrations of dimension 2 or 3, ending at their target.
        start: The mean start rotation vector :math:`r_0` relative to the target (radians).
        spread: Standard deviation :math:`\sigma` of the per-demonstration variation (radians).
        target_orientation: The target orientation :math:`q^*` (x, y, z, w).
        seed: Seed of the variation.

    Returns:
        Pose demonstrations with the same times and positions (lifted to 3-D).
    """
    if demos.dim not in (2, 3):
        raise DataError(f"synthetic orientations need 2-D or 3-D positions, got {demos.dim}-D")
    rng = np.random.default_rng(seed)
    target = Rotation.from_quat(np.asarray(target_orientation, dtype=np.float64))
    lift = (lambda x: np.pad(x, ((0, 0), (0, 1)))) if demos.dim == 2 else (lambda x: x)
    poses = []
    for demo in demos:
        rotvec = np.asarray(start, dtype=np.float64) + spread * rng.standard_normal(3)
        key = Rotation.concatenate([Rotation.from_rotvec(rotvec) * target, target])
        steps = np.linalg.norm(np.diff(demo.positions, axis=0), axis=1)
        travelled = np.concatenate([[0.0], np.cumsum(steps)])
        fraction = (
            travelled / travelled[-1] if travelled[-1] > 0 else np.linspace(0, 1, len(steps) + 1)
        )
        orientations = Slerp([0.0, 1.0], key)(np.clip(fraction, 0.0, 1.0)).as_quat()
        orientations[-1] = target.as_quat()
        poses.append(PoseDemonstration(lift(demo.positions), orientations, demo.times))
    return PoseDemonstrations(
        tuple(poses), lift(demos.target[None])[0], target.as_quat(), demos.name
    )


# Loaders.


def is_pose_file(path: str | Path) -> bool:
    """Whether a demonstrations file holds poses: a CSV whose header names ``qw``, or an NPZ
    archive with a ``quat`` array. Used by the CLI to choose the SE(3) policy by itself."""
    path = Path(path)
    try:
        if path.suffix.lower() == ".csv":
            with path.open(encoding="utf-8-sig") as file:
                header = file.readline()
            return "qw" in [name.strip().lower() for name in header.split(",")]
        if path.suffix.lower() == ".npz":
            with np.load(path, allow_pickle=False) as archive:
                return "quat" in archive.files
    except (OSError, ValueError, UnicodeDecodeError):
        return False
    return False


def load_poses(
    path: str | Path,
    *,
    max_end_spread: float = MAX_END_SPREAD,
    max_end_angle: float = MAX_END_ANGLE,
    select: Sequence[int] | None = None,
) -> PoseDemonstrations:
    """Loads pose demonstrations from a ``.csv`` or ``.npz`` file (layouts in the module doc).

    Arguments:
        path: The file.
        max_end_spread: See :func:`common_pose_target`.
        max_end_angle: See :func:`common_pose_target`.
        select: Keep only these demonstrations (0-based, in this order) before the target is
            chosen, so that a subset with a common end can be used from a file whose
            demonstrations end at several places.

    Raises:
        DataError: If the file cannot be used; the message starts with its path.
    """
    path = existing_file(path)
    readers = {".csv": _read_pose_csv, ".npz": _read_pose_npz}
    reader = readers.get(path.suffix.lower())
    if reader is None:
        raise DataError(f"{path}: pose demonstrations must be .csv or .npz, got {path.suffix!r}")
    with error_context(str(path)):
        demos = reader(path)
        if select is not None:
            for i in select:
                if not 0 <= i < len(demos):
                    raise DataError(f"demonstration index {i} out of range 0..{len(demos) - 1}")
            demos = [demos[i] for i in select]
        target_position, target_orientation, moved = common_pose_target(
            demos, max_end_spread=max_end_spread, max_end_angle=max_end_angle, indices=select
        )
        return PoseDemonstrations(moved, target_position, target_orientation, path.stem)


def _read_pose_csv(path: Path) -> list[PoseDemonstration]:
    rows = read_csv_rows(path)
    header = [name.strip().lower() for name in rows[0][1]]
    if tuple(header) != POSE_CSV_HEADER:
        raise DataError(f"header is {','.join(header)!r}, expected {','.join(POSE_CSV_HEADER)!r}")
    groups: dict[str, list[list[float]]] = {}
    for line, row in rows[1:]:
        if len(row) != len(POSE_CSV_HEADER):
            raise DataError(f"line {line} has {len(row)} fields, the header {len(POSE_CSV_HEADER)}")
        values = [csv_number(field, line) for field in row[1:]]
        groups.setdefault(row[0].strip(), []).append(values)
    demos = []
    for label, values in groups.items():
        with error_context(f"demo {label!r}"):
            array = np.asarray(values)
            demos.append(PoseDemonstration(array[:, 1:4], array[:, 4:8], array[:, 0]))
    return demos


def _read_pose_npz(path: Path) -> list[PoseDemonstration]:
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {key: archive[key] for key in archive.files}
    # numpy raises several kinds of error for a damaged archive; all mean the same to a user.
    except Exception as error:
        raise DataError(f"not a readable .npz archive: {error}") from error
    unknown = sorted(set(arrays) - set(POSE_NPZ_KEYS))
    if unknown or "pos" not in arrays or "quat" not in arrays:
        raise DataError(
            f"expected arrays 'pos' and 'quat' (optional 't' or 'dt'), found {sorted(arrays)}"
        )
    arrays = {key: real_array(value, repr(key)) for key, value in arrays.items()}
    positions, quats = arrays["pos"], arrays["quat"]
    if positions.ndim != 3 or positions.shape[2] != 3:
        raise DataError(f"'pos' must have shape (demos, samples, 3), got {positions.shape}")
    if quats.shape != positions.shape[:2] + (4,):
        raise DataError(f"'quat' must have shape {positions.shape[:2] + (4,)}, got {quats.shape}")
    shape = positions.shape[:2]
    if "t" in arrays:
        times = (
            np.broadcast_to(arrays["t"], shape) if arrays["t"].shape in (shape, shape[1:]) else None
        )
        if times is None:
            raise DataError(f"'t' must have shape {shape} or {shape[1:]}, got {arrays['t'].shape}")
    else:
        dt = float(arrays["dt"].item()) if "dt" in arrays else DEFAULT_DT
        if not (np.isfinite(dt) and dt > 0):
            raise DataError(f"'dt' must be one positive number, got {dt}")
        times = np.broadcast_to(dt * np.arange(shape[1]), shape)
    demos = []
    for i in range(shape[0]):
        with error_context(f"demonstration {i}"):
            demos.append(PoseDemonstration(positions[i], quats[i], times[i]))
    return demos
