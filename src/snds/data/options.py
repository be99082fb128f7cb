r"""How a recording is read: its rate, quaternion order, length unit, idle samples, and where
in a bag, dataset or archive the motion is.

One :class:`ReadOptions` goes with a file to every reader (:func:`~snds.data.load_recording`).
Its defaults read every file as before these options existed: time from the file, lengths as
stored, nothing trimmed.

Units. A pose model works in metres and radians: the robots of :mod:`snds.sim`, the twist of
an exported controller and the ROS message types are in SI units. ``length_unit`` names the
unit the file's positions are in, and they are converted to metres; without it, positions
stay in the file's own units (LASA's millimetres stay millimetres, as the paper's figures
are), and a pose file is taken to be in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from snds.errors import DataError

__all__ = [
    "DataWarning",
    "LENGTH_UNITS",
    "QUATERNION_ORDERS",
    "ReadOptions",
    "to_xyzw",
]

#: Metres per unit of each accepted ``length_unit``.
LENGTH_UNITS = {
    "m": 1.0,
    "dm": 0.1,
    "cm": 0.01,
    "mm": 0.001,
    "um": 1e-6,
    "in": 0.0254,
    "ft": 0.3048,
}

#: Accepted orders of a quaternion's four numbers; snds works in (x, y, z, w) (SciPy, roma).
QUATERNION_ORDERS = ("xyzw", "wxyz")


class DataWarning(UserWarning):
    """Data that load but are probably not what the user meant (positions in centimetres
    read as metres, rotation blocks that needed projecting); the CLI prints it as one line."""


@dataclass(frozen=True, kw_only=True)
class ReadOptions:
    """How to read a recording (see docs/data.md for each kind of file).

    Attributes:
        rate: Sampling rate in Hz of a recording that stores no time stamps (a ``.npy``
            array, a ``.mat`` matrix without a time row or ``dt``, an ``.npz`` of transforms
            without ``t``/``dt``, an HDF5 file); None: such a file is refused, naming the
            option. Refused for a file whose samples carry times, and for the table files
            (CSV, NPZ ``pos``, LPV-DS ``.mat``), which state theirs.
        quaternion_order: Order of the four numbers of a quaternion in an array whose columns
            are not named (``.npy``, ``.mat``, HDF5, LeRobot columns), one of
            :data:`QUATERNION_ORDERS`. CSV headers, ROS messages and an ``.npz``'s ``quat``
            (documented (x, y, z, w)) name their order, so it does not apply to them. None:
            an error naming the option where the file cannot say.
        length_unit: The unit of the file's positions, one of :data:`LENGTH_UNITS`; they are
            converted to metres. None: positions stay as stored.
        trim_idle: Drop the samples at the start and end of each demonstration where it has
            not started or has already stopped: below this fraction of the demonstration's
            top speed (see :func:`~snds.data.idle.idle_span`). 0: keep every sample.
        topic: The topic of a ROS bag to read; None: the bag's only pose-like topic.
        frame: The parent frame of a ``tf2_msgs/TFMessage`` topic's transform to read.
        child_frame: The child frame of that transform.
        columns: The state columns of a LeRobot dataset (one vector column, or several
            scalar ones); None: ``observation.state``.
        key: The array to read: an HDF5 ``obs`` key (``data/demo_N/obs/<key>``), or a
            ``.mat`` variable or ``variable.field``; None: the only one that fits.
        split_rests: Split one recording into demonstrations wherever it rests (below
            ``trim_idle``, or 2 % of the top speed if that is 0) for at least this many
            seconds; None: one recording is one demonstration.
    """

    rate: float | None = None
    quaternion_order: str | None = None
    length_unit: str | None = None
    trim_idle: float = 0.0
    topic: str | None = None
    frame: str | None = None
    child_frame: str | None = None
    columns: tuple[str, ...] | None = None
    key: str | None = None
    split_rests: float | None = None

    def __post_init__(self) -> None:
        if self.rate is not None and not (np.isfinite(self.rate) and self.rate > 0):
            raise DataError(f"rate must be a positive number of Hz, got {self.rate}")
        if self.quaternion_order is not None and self.quaternion_order not in QUATERNION_ORDERS:
            raise DataError(
                f"unknown quaternion order {self.quaternion_order!r}; "
                f"choose from {list(QUATERNION_ORDERS)}"
            )
        if self.length_unit is not None and self.length_unit not in LENGTH_UNITS:
            raise DataError(
                f"unknown length unit {self.length_unit!r}; choose from {list(LENGTH_UNITS)}"
            )
        if not (np.isfinite(self.trim_idle) and 0 <= self.trim_idle < 1):
            raise DataError(f"trim_idle must be a fraction in [0, 1), got {self.trim_idle}")
        if self.split_rests is not None and not (
            np.isfinite(self.split_rests) and self.split_rests > 0
        ):
            raise DataError(f"split_rests must be a positive duration, got {self.split_rests}")
        if (self.frame is None) != (self.child_frame is None):
            raise DataError("a /tf transform is named by both frame and child_frame")
        if isinstance(self.columns, str):
            object.__setattr__(self, "columns", (self.columns,))
        elif self.columns is not None:
            object.__setattr__(self, "columns", tuple(self.columns))

    @property
    def metres(self) -> float:
        """Metres per unit of the file's positions (1 when no unit is given)."""
        return 1.0 if self.length_unit is None else LENGTH_UNITS[self.length_unit]

    def uniform_times(self, count: int, *, what: str) -> np.ndarray:
        """Times (count,) at the stated rate, for ``what`` (a file's layout) that has none.

        Raises:
            DataError: Naming the option, if no rate was given.
        """
        if self.rate is None:
            raise DataError(
                f"{what} stores no time stamps: give its sampling rate (--rate HZ, "
                "ReadOptions(rate=...))"
            )
        return np.arange(count, dtype=np.float64) / self.rate

    def record(self) -> dict:
        """The options that differ from the defaults, JSON-ready (a model's ``data`` block)."""
        fields = {
            "rate": self.rate,
            "quaternion_order": self.quaternion_order,
            "length_unit": self.length_unit,
            "trim_idle": self.trim_idle or None,
            "topic": self.topic,
            "frame": self.frame,
            "child_frame": self.child_frame,
            "columns": None if self.columns is None else list(self.columns),
            "key": self.key,
            "split_rests": self.split_rests,
        }
        return {name: value for name, value in fields.items() if value is not None}

    @classmethod
    def from_record(cls, record: dict) -> ReadOptions:
        """The options a :meth:`record` (or a whole ``data`` block) describes."""
        names = cls.__dataclass_fields__
        chosen = {name: record[name] for name in names if record.get(name) is not None}
        return cls(**chosen)


def to_xyzw(quaternions: np.ndarray, order: str | None, *, what: str) -> np.ndarray:
    """Quaternions (..., 4) in ``order`` reordered to (x, y, z, w).

    The order of unnamed columns cannot be found from the numbers: reading (w, x, y, z) as
    (x, y, z, w) permutes the four coordinates, which keeps every quaternion's norm and the
    angle between any two of them (:math:`|q_a \\cdot q_b|`), so the misread path turns at
    exactly the demonstrated angular speeds, only about other axes. It must be stated.

    Raises:
        DataError: Naming the option, if ``order`` is None.
    """
    if order is None:
        raise DataError(
            f"{what} holds quaternions in unnamed columns: state their order with "
            f"--quaternion-order {' or '.join(QUATERNION_ORDERS)} "
            "(ReadOptions(quaternion_order=...))"
        )
    return quaternions if order == "xyzw" else np.roll(quaternions, -1, axis=-1)
