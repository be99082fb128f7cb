"""Demonstrations: immutable containers for demonstrated motions and their normalisation."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from snds.errors import DataError

__all__ = [
    "Demonstration",
    "DemonstrationSet",
    "Demonstrations",
    "Normalization",
    "Split",
    "no_split",
    "split_demos",
    "split_samples",
]

_FLOAT32_TINY = float(np.finfo(np.float32).tiny)
_FLOAT32_MAX = float(np.finfo(np.float32).max)


def _as_float_array(value: np.ndarray, name: str, ndim: int) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != ndim:
        raise DataError(f"{name} must have {ndim} dimension(s), got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise DataError(f"{name} contains NaN or inf values")
    array = array.copy()
    array.setflags(write=False)
    return array


@dataclass(frozen=True)
class Demonstration:
    """One demonstrated motion, sampled in time.

    Attributes:
        positions: States along the motion, shape (T, n).
        velocities: Their time derivatives, shape (T, n).
        times: Strictly increasing sample times in seconds, shape (T,).
    """

    positions: np.ndarray
    velocities: np.ndarray
    times: np.ndarray

    def __post_init__(self) -> None:
        positions = _as_float_array(self.positions, "positions", 2)
        velocities = _as_float_array(self.velocities, "velocities", 2)
        times = _as_float_array(self.times, "times", 1)
        if positions.shape[0] < 2:
            raise DataError(f"a demonstration needs at least 2 samples, got {positions.shape[0]}")
        if velocities.shape != positions.shape:
            raise DataError(
                f"velocities shape {velocities.shape} differs from positions shape "
                f"{positions.shape}"
            )
        if times.shape[0] != positions.shape[0]:
            raise DataError(f"times has {times.shape[0]} samples, positions {positions.shape[0]}")
        if np.any(np.diff(times) <= 0):
            raise DataError("times must be strictly increasing (duplicated or unsorted stamps)")
        object.__setattr__(self, "positions", positions)
        object.__setattr__(self, "velocities", velocities)
        object.__setattr__(self, "times", times)

    @property
    def dim(self) -> int:
        """State dimension n."""
        return self.positions.shape[1]

    @property
    def duration(self) -> float:
        """Time from the first to the last sample, in seconds."""
        return float(self.times[-1] - self.times[0])

    @property
    def states(self) -> np.ndarray:
        """The states along the motion, shape (T, n): the positions themselves."""
        return self.positions

    @property
    def dt(self) -> np.ndarray:
        """Time steps between consecutive samples, shape (T - 1,)."""
        return np.diff(self.times)


class DemonstrationSet:
    """What every set of demonstrations of one task has, whatever its states: a sequence of
    demonstrations (``demos``, each with ``positions`` (T, p), ``velocities`` (T, m) whose
    first p columns are the positions' own, and ``times`` (T,)) and a ``target`` state whose
    first p numbers are the target position. :class:`Demonstrations` (positions) and
    :class:`~snds.data.poses.PoseDemonstrations` (poses) are its two kinds."""

    demos: tuple
    target: np.ndarray

    def __len__(self) -> int:
        return len(self.demos)

    def __getitem__(self, index: int):
        return self.demos[index]

    def __iter__(self):
        return iter(self.demos)

    def select(self, indices: list[int] | tuple[int, ...] | range) -> DemonstrationSet:
        """The demonstrations at ``indices``, in that order, with the same target."""
        raise NotImplementedError

    def with_phase(self, phases: Sequence[np.ndarray]) -> DemonstrationSet:
        """The same demonstrations with a phase of shape (T_d, m) appended to each state
        (:mod:`snds.phase`)."""
        raise NotImplementedError

    def first(self, k: int) -> DemonstrationSet:
        """The first ``k`` demonstrations."""
        if not 1 <= k <= len(self.demos):
            raise DataError(f"asked for {k} demonstrations, the set has {len(self.demos)}")
        return self.select(range(k))

    def _check_indices(self, indices: list[int]) -> None:
        for i in indices:
            if not 0 <= i < len(self.demos):
                raise DataError(f"demonstration index {i} out of range 0..{len(self.demos) - 1}")

    @property
    def position_dim(self) -> int:
        """How many leading numbers of a state are its position, p."""
        return self.demos[0].positions.shape[1]

    def positions(self) -> np.ndarray:
        """All positions stacked, shape (sum T, p) (a phase left out)."""
        return np.concatenate([demo.positions[:, : self.position_dim] for demo in self.demos])

    def velocities(self) -> np.ndarray:
        """All velocities stacked, shape (sum T, m)."""
        return np.concatenate([demo.velocities for demo in self.demos])

    def extent(self) -> float:
        """Largest distance of a demonstrated position from the target position (the task's
        size)."""
        positions = self.positions()
        return float(np.linalg.norm(positions - self.target[: self.position_dim], axis=-1).max())

    def max_speed(self) -> float:
        """Largest demonstrated speed of the positions, user units per second."""
        return float(
            max(
                np.linalg.norm(demo.velocities[:, : self.position_dim], axis=-1).max()
                for demo in self.demos
            )
        )

    def max_duration(self) -> float:
        """Duration of the longest demonstration, in seconds."""
        return max(float(demo.times[-1] - demo.times[0]) for demo in self.demos)

    def mean_dt(self) -> float:
        """Mean sampling step over all demonstrations, in seconds."""
        return float(np.mean(np.concatenate([np.diff(demo.times) for demo in self.demos])))


@dataclass(frozen=True)
class Demonstrations(DemonstrationSet):
    """A set of demonstrations of one task, all ending at a common target.

    Attributes:
        demos: The demonstrated motions, each of dimension n.
        target: The common end point x*, shape (n,).
        name: A label for plots and reports.
        phase_dim: How many trailing numbers of each state are a phase rather than a
            position (0: none; see :mod:`snds.phase`). The extent and the top speed are the
            positions' own.
    """

    demos: tuple[Demonstration, ...]
    target: np.ndarray
    name: str = ""
    phase_dim: int = 0

    def __post_init__(self) -> None:
        demos = tuple(self.demos)
        if not demos:
            raise DataError("no demonstrations given")
        dims = {demo.dim for demo in demos}
        if len(dims) != 1:
            raise DataError(f"demonstrations have different dimensions: {sorted(dims)}")
        target = _as_float_array(self.target, "target", 1)
        if target.shape[0] != demos[0].dim:
            raise DataError(
                f"target has dimension {target.shape[0]}, demonstrations {demos[0].dim}"
            )
        if type(self.phase_dim) is not int or not 0 <= self.phase_dim < demos[0].dim:
            raise DataError(
                f"phase_dim must be an integer in [0, {demos[0].dim}), got {self.phase_dim!r}"
            )
        object.__setattr__(self, "demos", demos)
        object.__setattr__(self, "target", target)

    @property
    def dim(self) -> int:
        """State dimension n."""
        return self.demos[0].dim

    @property
    def position_dim(self) -> int:  # type: ignore[override]
        """How many leading numbers of a state are its position: n less the phase."""
        return self.dim - self.phase_dim

    def state_scales(self) -> tuple[float, float]:
        """The largest distance of a demonstrated state from the target and the largest
        demonstrated speed of the states, a phase included (the positions' own without one):
        the scales of :meth:`Normalization.fit`."""
        states = np.concatenate([demo.states for demo in self.demos])
        speed = max(np.linalg.norm(demo.velocities, axis=-1).max() for demo in self.demos)
        return float(np.linalg.norm(states - self.target, axis=-1).max()), float(speed)

    def select(self, indices: list[int] | tuple[int, ...] | range) -> Demonstrations:
        """The demonstrations at ``indices``, in that order, with the same target."""
        indices = list(indices)
        self._check_indices(indices)
        return Demonstrations(
            tuple(self.demos[i] for i in indices), self.target, self.name, self.phase_dim
        )

    def with_phase(self, phases: Sequence[np.ndarray]) -> Demonstrations:
        """The same demonstrations with a phase appended to each state, shapes (T_d, m), and
        its rate to each velocity (second-order differences against the times); the target
        then ends in m zeros (:mod:`snds.phase`).

        Raises:
            DataError: If the demonstrations carry a phase already.
        """
        if self.phase_dim:
            raise DataError(f"{self.name or 'the demonstrations'} carry a phase already")
        out = []
        for demo, phase in zip(self.demos, phases, strict=True):
            edge = 2 if len(demo.times) > 2 else 1
            rate = np.gradient(phase, demo.times, axis=0, edge_order=edge)
            out.append(
                Demonstration(
                    np.column_stack([demo.positions, phase]),
                    np.column_stack([demo.velocities, rate]),
                    demo.times,
                )
            )
        m = np.shape(phases[0])[1]
        return Demonstrations(tuple(out), np.append(self.target, np.zeros(m)), self.name, m)


@dataclass(frozen=True)
class Normalization:
    r"""One affine map of space and time shared by all demonstrations of a task.

    Model coordinates are :math:`\tilde x = (x - x^*) / L` and :math:`\tilde t = t / \tau`, so
    velocities map as :math:`\tilde v = v \tau / L`. One isotropic length scale keeps the shape
    of the motion (scaling each axis or each demonstration separately would distort it).

    Attributes:
        center: The target x* in user units, shape (n,).
        length: Length scale L > 0 (user units).
        time: Time scale tau > 0 (seconds).
        extent: The positions' extent (user units), what tolerances and scale-free figures
            are fractions of: L itself (None) unless a phase is in the state.
    """

    center: np.ndarray
    length: float
    time: float
    extent: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _as_float_array(self.center, "center", 1))
        if not (np.isfinite(self.length) and self.length > 0):
            raise DataError(f"normalisation length must be positive and finite, got {self.length}")
        if self.extent is None:
            object.__setattr__(self, "extent", float(self.length))
        if not (np.isfinite(self.extent) and self.extent > 0):
            raise DataError(f"normalisation extent must be positive and finite, got {self.extent}")
        if not (np.isfinite(self.time) and self.time > 0):
            raise DataError(f"normalisation time must be positive and finite, got {self.time}")

    @classmethod
    def fit(cls, demos: Demonstrations) -> Normalization:
        """Maps the target to 0, the extent to 1, and the fastest demonstrated speed to 1: of
        the whole state, so that a phase (:mod:`snds.phase`) is scaled with the positions
        (:meth:`Demonstrations.state_scales`)."""
        length, speed = demos.state_scales()
        named = f"{demos.name}: " if demos.name else ""
        if length <= 0:
            raise DataError(
                f"{named}demonstrations have zero extent (every sample is at the target)"
            )
        if speed <= 0:
            raise DataError(f"{named}demonstrations never move (every velocity is zero)")
        # A float32 policy holds the scales as float32 numbers: one that rounds to 0 or inf
        # there would turn every state into NaN.
        # A phase scales with the positions: the state's length is theirs times a constant, so
        # the message names the positions' own extent, the number a user knows.
        for what, value, shown in (
            ("extent", length, demos.extent()),
            ("top speed", speed, speed),
            ("time scale", length / speed, length / speed),
        ):
            if not _FLOAT32_TINY <= value <= _FLOAT32_MAX:
                raise DataError(
                    f"{named}the demonstrations' {what} is {shown:.3g}, outside the float32 "
                    f"range [{_FLOAT32_TINY:.3g}, {_FLOAT32_MAX:.3g}]: give the data in other "
                    "units"
                )
        return cls(center=demos.target, length=length, time=length / speed, extent=demos.extent())

    def positions_to_model(self, x: np.ndarray) -> np.ndarray:
        """User positions (*, n) to model coordinates (*, n)."""
        return (np.asarray(x) - self.center) / self.length

    def positions_from_model(self, x: np.ndarray) -> np.ndarray:
        """Model coordinates (*, n) to user positions (*, n)."""
        return np.asarray(x) * self.length + self.center

    def velocities_to_model(self, v: np.ndarray) -> np.ndarray:
        """User velocities (*, n) to model velocities (*, n)."""
        return np.asarray(v) * (self.time / self.length)

    def velocities_from_model(self, v: np.ndarray) -> np.ndarray:
        """Model velocities (*, n) to user velocities (*, n)."""
        return np.asarray(v) * (self.length / self.time)

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return {
            "center": self.center.tolist(),
            "length": self.length,
            "time": self.time,
            "extent": self.extent,
        }

    @classmethod
    def from_dict(cls, data: dict) -> Normalization:
        """Inverse of :meth:`to_dict`."""
        try:
            return cls(
                center=np.asarray(data["center"], dtype=np.float64),
                length=float(data["length"]),
                time=float(data["time"]),
                # Records before the phase: the extent was the length.
                extent=None if data.get("extent") is None else float(data["extent"]),
            )
        except (KeyError, TypeError) as error:
            raise DataError(f"malformed normalisation record: {error}") from error


@dataclass(frozen=True)
class Split:
    """Which samples of each demonstration are used for training.

    Attributes:
        train: One boolean mask per demonstration, shape (T_d,); False marks a test sample.
    """

    train: tuple[np.ndarray, ...] = field(default_factory=tuple)

    def test(self) -> tuple[np.ndarray, ...]:
        """The complementary masks of the test samples."""
        return tuple(~mask for mask in self.train)


def split_samples(demos: Demonstrations, *, test_fraction: float, seed: int) -> Split:
    """Random split of samples (the paper's protocol: 0.8 / 0.2 of all samples).

    Arguments:
        demos: The demonstrations to split.
        test_fraction: Fraction of the samples of each demonstration held out, in [0, 1).
        seed: Seed of the random choice.
    """
    if not 0.0 <= test_fraction < 1.0:
        raise DataError(f"test_fraction must be in [0, 1), got {test_fraction}")
    rng = np.random.default_rng(seed)
    masks = []
    for demo in demos:
        length = demo.positions.shape[0]
        mask = np.ones(length, dtype=bool)
        mask[rng.permutation(length)[: int(round(test_fraction * length))]] = False
        masks.append(mask)
    return Split(tuple(masks))


def split_demos(demos: Demonstrations, *, test_demos: list[int] | tuple[int, ...]) -> Split:
    """Hold out whole demonstrations: every sample of ``test_demos`` is a test sample."""
    held_out = set(test_demos)
    for i in held_out:
        if not 0 <= i < len(demos):
            raise DataError(f"test demonstration {i} out of range 0..{len(demos) - 1}")
    if len(held_out) == len(demos):
        raise DataError("every demonstration is held out: nothing left to train on")
    return Split(
        tuple(
            np.full(demo.positions.shape[0], i not in held_out, dtype=bool)
            for i, demo in enumerate(demos)
        )
    )


def no_split(demos: Demonstrations) -> Split:
    """Train on every sample."""
    return Split(tuple(np.ones(demo.positions.shape[0], dtype=bool) for demo in demos))
