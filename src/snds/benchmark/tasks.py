"""What a sweep runs: its tasks (a method trained on a motion with a seed), the settings every
run shares, and the named groups of motions.

    tasks = make_tasks(resolve_motions("paper8"), resolve_methods("snds,bc"), seeds=3)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from snds.data import LASA_NAMES, DataSource
from snds.data.files import LOADERS
from snds.data.poses import is_pose_file
from snds.errors import DataError, SNDSError
from snds.methods import METHODS, get_method
from snds.spaces import SE3, Euclidean, Space
from snds.stability import ROLLOUTS, SAMPLES

__all__ = [
    "MODELS_DIR",
    "MOTION_GROUPS",
    "SweepSettings",
    "Task",
    "check_task",
    "make_tasks",
    "resolve_methods",
    "resolve_motions",
]

#: Named groups of LASA motions; ``paper8`` are the eight of the paper's Fig. 4.
MOTION_GROUPS: dict[str, tuple[str, ...]] = {
    "paper8": (
        "Sine",
        "PShape",
        "Worm",
        "GShape",
        "NShape",
        "DoubleBendedLine",
        "CShape",
        "Angle",
    ),
    "multi": ("Multi_Models_1", "Multi_Models_2", "Multi_Models_3", "Multi_Models_4"),
    "all": LASA_NAMES,
}


#: Each run's trained model, under ``models/<motion>/<method>/seed=<s>-demos=<d>/``.
MODELS_DIR = "models"


@dataclass(frozen=True, kw_only=True)
class SweepSettings:
    """What every run of a sweep shares; recorded in ``sweep.json``.

    Attributes:
        steps: Optimiser steps instead of the default :class:`~snds.train.TrainConfig`'s.
        rollouts: Random starts of each run's stability check.
        samples: States of each run's decrease-condition check.
        batch_fits: Fit up to this many seeds of one motion and method at once, as one
            stacked model (SNDS and BC; see :func:`snds.batched.fit_many`); 1: one by one.
    """

    steps: int | None = None
    rollouts: int = ROLLOUTS
    samples: int = SAMPLES
    batch_fits: int = 1

    def __post_init__(self) -> None:
        if self.steps is not None and self.steps < 1:
            raise SNDSError(f"steps must be >= 1, got {self.steps}")
        if self.rollouts < 1 or self.samples < 0:
            raise SNDSError(
                f"need rollouts >= 1 and samples >= 0, got {self.rollouts} and {self.samples}"
            )
        if self.batch_fits < 1:
            raise SNDSError(f"batch_fits must be >= 1, got {self.batch_fits}")

    @classmethod
    def quick(cls, *, steps: int | None = None) -> SweepSettings:
        """A smaller stability check (100 rollouts, 5,000 samples) for smoke runs."""
        return cls(steps=steps, rollouts=100, samples=5000)

    def to_dict(self) -> dict:
        """JSON-ready form; ``batch_fits`` only when it is not 1, so that the folders of
        sweeps from before it existed still resume."""
        record = asdict(self)
        if self.batch_fits == 1:
            del record["batch_fits"]
        return record


def _names(spec: str) -> list[str]:
    return [part.strip() for part in spec.split(",") if part.strip()]


def _is_file(motion: str) -> bool:
    """Whether a task's motion is a demonstrations file (by its suffix), not a LASA name."""
    return Path(motion).suffix.lower() in LOADERS


def resolve_motions(spec: str) -> list[str]:
    """Motion names from comma-separated LASA names, :data:`MOTION_GROUPS` keys and paths of
    demonstrations files (``.mat``, ``.csv``, ``.npz``; a pose file makes an SE(3) task).

    Case of names is ignored; duplicates are dropped, the first occurrence keeps its place.

    Raises:
        DataError: For an unknown name or a missing file (the message names it).
    """
    by_lower = {name.lower(): name for name in LASA_NAMES}
    motions: list[str] = []
    for part in _names(spec):
        if part.lower() in MOTION_GROUPS:
            found = MOTION_GROUPS[part.lower()]
        elif part.lower() in by_lower:
            found = (by_lower[part.lower()],)
        elif _is_file(part):
            if not Path(part).is_file():
                raise DataError(f"{part}: no such demonstrations file")
            found = (part,)
        else:
            raise DataError(
                f"unknown motion or group {part!r}; groups: {', '.join(MOTION_GROUPS)}; "
                f"motions: {', '.join(LASA_NAMES)}"
            )
        motions.extend(m for m in found if m not in motions)
    if not motions:
        raise DataError(f"no motions in {spec!r}")
    return motions


def resolve_methods(spec: str) -> list[str]:
    """Method names from a comma-separated list of :data:`~snds.methods.METHODS` keys.

    Raises:
        SNDSError: For an unknown name (the message names it).
    """
    methods: list[str] = []
    for part in _names(spec):
        name = get_method(part).name
        if name not in methods:
            methods.append(name)
    if not methods:
        raise SNDSError(f"no methods in {spec!r}; choose from {', '.join(METHODS)}")
    return methods


@dataclass(frozen=True)
class Task:
    """One run of a sweep: a method trained on a motion with a seed.

    Attributes:
        motion: A LASA motion name, or the path of a demonstrations file.
        method: A key of :data:`~snds.methods.METHODS`.
        seed: Seed of the weights, the mini-batches, the split, the synthetic orientations
            of an SE(3) task and the stability check.
        demos: Train on the first this many demonstrations (None: all).
        se3: Learn a pose policy: position data lifted with synthetic orientations (as
            ``snds train --se3``); set by itself for a pose file.
    """

    motion: str
    method: str
    seed: int
    demos: int | None = None
    se3: bool = False

    def __post_init__(self) -> None:
        if not self.se3 and is_pose_file(self.motion):
            object.__setattr__(self, "se3", True)

    @property
    def key(self) -> str:
        """A stable identifier, the same in every process and run (resume matches on it)."""
        demos = "all" if self.demos is None else str(self.demos)
        space = "/se3" if self.se3 else ""
        return f"{self.motion}/{self.method}/seed={self.seed}/demos={demos}{space}"

    @property
    def label(self) -> str:
        """The task's data in tables and figures: the motion or file name, "-se3" for poses."""
        name = Path(self.motion).stem if _is_file(self.motion) else self.motion
        return name + ("-se3" if self.se3 else "")

    @property
    def space(self) -> type[Space]:
        """The state space the task's policy lives in."""
        return SE3 if self.se3 else Euclidean

    @property
    def model_dir(self) -> Path:
        """Where the run's model goes, relative to the sweep's folder."""
        demos = "all" if self.demos is None else str(self.demos)
        return Path(MODELS_DIR, self.label, self.method, f"seed={self.seed}-demos={demos}")

    def source(self) -> DataSource:
        """Where the task's demonstrations come from."""
        file = _is_file(self.motion)
        return DataSource(
            motion=None if file else self.motion,
            file=Path(self.motion) if file else None,
            demos=self.demos,
            poses=self.se3,
            orientation_seed=self.seed,
        )

    @classmethod
    def from_row(cls, row: dict) -> Task:
        """The task a result row came from."""
        demos = row.get("demos")
        return cls(
            row["motion"],
            row["method"],
            int(row["seed"]),
            None if demos is None else int(demos),
            bool(row.get("se3", False)),
        )


def make_tasks(
    motions: Sequence[str],
    methods: Sequence[str],
    *,
    seeds: int,
    demos: int | None = None,
    se3: bool = False,
) -> list[Task]:
    """Every (motion, method, seed) with seeds 0 .. seeds-1, motion-major; with ``se3`` as
    pose tasks.

    Raises:
        SNDSError: If ``seeds`` < 1, or a method cannot fit a task's state space (the
            baselines fit positions only).
    """
    if seeds < 1:
        raise SNDSError(f"seeds must be >= 1, got {seeds}")
    tasks = [
        Task(motion, method, seed, demos, se3)
        for motion in motions
        for method in methods
        for seed in range(seeds)
    ]
    for task in tasks:
        check_task(task)
    return tasks


def check_task(task: Task) -> None:
    """Refuses a task whose method does not fit its state space, before any work."""
    method = get_method(task.method)
    if task.space not in method.spaces:
        names = ", ".join(name for name, m in METHODS.items() if task.space in m.spaces)
        raise SNDSError(
            f"{task.method} does not fit {task.space.__name__} tasks ({task.label}); "
            f"methods that do: {names}"
        )
