"""Where a task's demonstrations come from: one description for the CLI, the benchmark and
the saved model's record.

A :class:`DataSource` names a LASA motion or a file, which of its demonstrations to keep, and
whether the task is in SE(3). :meth:`DataSource.load` gives the demonstrations in the task's
space: positions (:class:`~snds.data.Demonstrations`), or poses
(:class:`~snds.data.poses.PoseDemonstrations`): a pose file as it is, position data lifted
with synthetic orientations (:func:`~snds.data.poses.with_synthetic_orientations`).
:meth:`DataSource.record` is the ``data`` block of ``model.json``, and
:meth:`DataSource.from_record` reads it back.

    DataSource(motion="Sine", demos=3).load()                     # 3 LASA Sine demonstrations
    DataSource(file=Path("arm.mat"), demos=(0, 2)).load()         # demonstrations 0 and 2
    DataSource(file=Path("Messy_snake.mat"), demos=1, poses=True).load()  # lifted to SE(3)
    DataSource(file=Path("3D_sink.mat"), phase=Phase(codes=3)).load()  # with a phase (snds.phase)
    DataSource(file=Path("pouring.npy"), rate=60, quaternion_order="wxyz", length_unit="cm")
    DataSource(file=Path("rec.mcap"), topic="/ee_pose").load()    # a ROS 2 bag's PoseStamped

The reading options (``rate`` to ``split_rests``) are those of
:class:`~snds.data.options.ReadOptions`, and go to :func:`~snds.data.load_recording`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from snds.data.demonstrations import Demonstrations
from snds.data.gaps import DEFAULT_GAPS, check_gap_mode
from snds.data.lasa import load_lasa
from snds.data.options import ReadOptions
from snds.data.poses import PoseDemonstrations, with_synthetic_orientations
from snds.data.recordings import holds_poses, load_recording
from snds.data.targets import MAX_END_SPREAD
from snds.errors import DataError
from snds.phase import Phase

__all__ = ["DataSource"]

#: How files were read before a model's data record named ``gaps``: gaps re-timed, not filled.
GAPS_BEFORE_RECORDED = "retime"


@dataclass(frozen=True, kw_only=True)
class DataSource:
    """The demonstrations of a task.

    Attributes:
        motion: A LASA motion name (case ignored); exactly one of ``motion`` and ``file``.
        file: A demonstrations file or folder: ``.mat``, ``.csv``, ``.npz``, ``.npy``, a ROS
            bag or a folder of them, a LeRobot dataset, an HDF5 file (docs/data.md).
        demos: Keep the first this many demonstrations, or these ones (0-based, in order);
            None: all. From a file they are selected before the common target is chosen,
            so that a subset ending at one place can be used from a file ending at several.
        max_end_spread: Largest accepted distance of a file's demonstration end from the
            common target, in extents (see :func:`~snds.data.targets.common_target`).
        gaps: How a ``.mat`` file's recording gaps are treated, one of
            :data:`~snds.data.gaps.GAP_MODES` (see :func:`~snds.data.files.load_mat`).
        poses: Whether the task is in SE(3). Automatic for a pose file; position data are
            then lifted with synthetic orientations.
        orientation_seed: Seed of the synthetic orientations.
        phase: A phase appended to the states, positions or poses
            (:class:`~snds.phase.Phase`); None: none.
        rate: Sampling rate (Hz) of a file without time stamps; see
            :class:`~snds.data.options.ReadOptions` for this and the fields below.
        quaternion_order: ``"xyzw"`` or ``"wxyz"``, for quaternions in unnamed columns.
        length_unit: The unit of the file's positions (``"m"``, ``"cm"``, ``"mm"``, ...),
            converted to metres; None: as stored.
        trim_idle: Trim each demonstration's idle start and end below this fraction of its
            top speed; 0: keep every sample.
        topic: A ROS bag's topic.
        frame: The parent frame of a ``/tf`` transform.
        child_frame: The child frame of that transform.
        columns: A LeRobot dataset's state columns.
        key: An HDF5 ``obs`` key, or a ``.mat`` pose matrix ``variable[.field]``.
        split_rests: Split one recording at rests of at least this many seconds.
    """

    motion: str | None = None
    file: Path | None = None
    demos: int | tuple[int, ...] | None = None
    max_end_spread: float = MAX_END_SPREAD
    gaps: str = DEFAULT_GAPS
    poses: bool = False
    orientation_seed: int = 0
    phase: Phase | None = None
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
        if (self.motion is None) == (self.file is None):
            raise DataError("a data source names either a LASA motion or a file, not both")
        options = self.options  # validates them
        if isinstance(self.columns, (list, str)):
            object.__setattr__(self, "columns", options.columns)
        if self.motion is not None and options.record():
            raise DataError("reading options (rate, unit, ...) are for files, not LASA motions")
        if self.file is not None:
            object.__setattr__(self, "file", Path(self.file))
            if holds_poses(self.file, options):
                object.__setattr__(self, "poses", True)
        check_gap_mode(self.gaps)
        if isinstance(self.demos, list):
            object.__setattr__(self, "demos", tuple(self.demos))
        if isinstance(self.demos, int) and self.demos < 1:
            raise DataError(f"demos must be >= 1, got {self.demos}")

    @property
    def options(self) -> ReadOptions:
        """How the file is read."""
        return ReadOptions(
            rate=self.rate,
            quaternion_order=self.quaternion_order,
            length_unit=self.length_unit,
            trim_idle=self.trim_idle,
            topic=self.topic,
            frame=self.frame,
            child_frame=self.child_frame,
            columns=self.columns,
            key=self.key,
            split_rests=self.split_rests,
        )

    @property
    def name(self) -> str:
        """The motion's name or the file's stem."""
        return self.motion if self.motion is not None else self.file.stem

    def load(self) -> Demonstrations | PoseDemonstrations:
        """The demonstrations, in the task's space.

        Raises:
            DataError: If the motion or file cannot be used (the message names it).
        """
        demos = self._states()
        return demos if self.phase is None else self.phase.apply(demos)

    def _states(self) -> Demonstrations | PoseDemonstrations:
        """The demonstrations without a phase."""
        if self.file is None:
            positions = self._lasa()
        else:
            positions = load_recording(
                self.file,
                options=self.options,
                select=self._indices(),
                max_end_spread=self.max_end_spread,
                gaps=self.gaps,
            )
            if isinstance(positions, PoseDemonstrations):
                return positions
        if not self.poses:
            return positions
        return with_synthetic_orientations(positions, seed=self.orientation_seed)

    def record(self) -> dict:
        """The JSON-ready description saved with a model (``model.json``'s ``data``)."""
        demos = list(self.demos) if isinstance(self.demos, tuple) else self.demos
        if self.motion is not None:
            record: dict = {"motion": self.motion, "demos": demos}
        else:
            record = {
                "file": str(self.file.resolve()),
                "demos": demos,
                "max_end_spread": self.max_end_spread,
                "gaps": self.gaps,
            } | self.options.record()
        if self.phase is not None:
            record["phase"] = self.phase.record()
        return record | ({"orientation_seed": self.orientation_seed} if self.poses else {})

    @classmethod
    def from_record(cls, record: dict, *, poses: bool = False) -> DataSource:
        """The source a :meth:`record` describes; ``poses`` for a pose model's data.

        A file record without ``gaps`` predates gap filling: its model was trained on
        re-timed gaps (:data:`GAPS_BEFORE_RECORDED`), and is evaluated on them.
        """
        if "motion" not in record and "file" not in record:
            raise DataError("the data record names neither a motion nor a file")
        spread = record.get("max_end_spread")
        return cls(
            motion=record.get("motion"),
            file=Path(record["file"]) if "file" in record else None,
            demos=record.get("demos"),
            max_end_spread=MAX_END_SPREAD if spread is None else float(spread),
            gaps=str(record.get("gaps", GAPS_BEFORE_RECORDED)),
            poses=poses,
            orientation_seed=int(record.get("orientation_seed", 0)),
            phase=Phase.from_record(record["phase"]) if "phase" in record else None,
            **dataclasses.asdict(ReadOptions.from_record(record)),
        )

    def _indices(self) -> list[int] | None:
        if self.demos is None:
            return None
        return list(range(self.demos)) if isinstance(self.demos, int) else list(self.demos)

    def _lasa(self) -> Demonstrations:
        loaded = load_lasa(self.motion)
        if self.demos is None:
            return loaded
        if isinstance(self.demos, int):
            return loaded.first(self.demos)
        return loaded.select(self.demos)
