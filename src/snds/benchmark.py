"""Benchmark sweeps: methods x motions x seeds, resumable, on local cores or a Dask cluster.

A sweep is a list of :class:`Task`. Each task trains and evaluates one policy in one process
with one torch thread (:func:`run_task`) and gives one flat row. :func:`run_sweep` appends
every finished row to ``results.jsonl`` at once (flushed and fsynced), so an interrupted
sweep loses at most the tasks that were running; rerunning it into the same folder skips
the tasks already there. At the end it writes ``results.csv`` and ``summary.md``, and
:func:`plot_benchmark` draws the figures.

    rows = run_sweep(make_tasks(["Sine"], ["snds", "bc"], seeds=3), out=Path("runs/b"))
    plot_benchmark(rows, Path("runs/b"))
"""

from __future__ import annotations

import csv
import json
import os
import resource
import sys
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from snds.data import LASA_NAMES, DataSource, split_samples
from snds.data.files import LOADERS
from snds.data.poses import is_pose_file
from snds.errors import DataError, SNDSError
from snds.evaluate import evaluate
from snds.io import atomic_write
from snds.method import Fitted
from snds.methods import METHODS, get_method
from snds.models import load_model
from snds.parallel import starmap_unordered, torch_threads
from snds.plotting import Panel, figure_legend, plot_panels
from snds.policy import float64_copy
from snds.runs import RunFolder
from snds.spaces import SE3, Euclidean, Space
from snds.stability import ROLLOUTS, SAMPLES, CheckConfig

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

#: SNDS velocity MSE (paper scale) in the paper's Fig. 4, for comparison in summaries.
PAPER_SNDS_MSE: dict[str, float] = {
    "Sine": 0.0018,
    "PShape": 0.0016,
    "Worm": 0.0031,
    "GShape": 0.0024,
    "NShape": 0.0016,
    "DoubleBendedLine": 0.0028,
    "CShape": 0.0014,
    "Angle": 0.0012,
}

#: The columns of a result row, in the order of ``results.csv``.
ROW_FIELDS: tuple[str, ...] = (
    "motion",
    "method",
    "seed",
    "demos",
    "se3",
    "train_seconds",
    "train_cpu_seconds",
    "velocity_mse",
    "velocity_mse_paper",
    "velocity_error_relative",
    "dtw",
    "dtw_paper",
    "final_distance",
    "angle_error_along",
    "final_angle_error",
    "converged_fraction",
    "decrease_violations",
    "samples_checked",
    "median_time_to_converge",
    "shortened_fraction",
    "largest_safe_dt",
    "peak_memory_mb",
)

#: The sweep settings that change results; a folder holds results of one setting only.
SETTINGS_FILE = "sweep.json"
RESULTS_FILE = "results.jsonl"
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
        _check_task(task)
    return tasks


def _check_task(task: Task) -> None:
    """Refuses a task whose method does not fit its state space, before any work."""
    method = get_method(task.method)
    if task.space not in method.spaces:
        names = ", ".join(name for name, m in METHODS.items() if task.space in m.spaces)
        raise SNDSError(
            f"{task.method} does not fit {task.space.__name__} tasks ({task.label}); "
            f"methods that do: {names}"
        )


class _PeakMemory:
    """Peak resident memory of this process during a block, in MiB.

    On Linux the kernel's high-water mark (``VmHWM``) is reset at the start (writing 5 to
    ``/proc/self/clear_refs``), so the figure is the task's own peak, whatever ran before it
    in the same worker. Elsewhere it falls back to ``ru_maxrss``, which never resets: exact
    only for a worker's first task. Either way it costs nothing, unlike tracemalloc, which
    slows training several times and misses torch's native allocations.
    """

    def __enter__(self) -> _PeakMemory:
        self.resettable = False
        try:
            Path("/proc/self/clear_refs").write_text("5")
            self.resettable = self._hwm() is not None
        except OSError:
            pass
        self.peak = 0.0
        return self

    def __exit__(self, *exc: object) -> None:
        hwm = self._hwm() if self.resettable else None
        if hwm is not None:
            self.peak = hwm
        else:
            # ru_maxrss is in KiB on Linux and in bytes on macOS.
            peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
            self.peak = peak / (2**20 if sys.platform == "darwin" else 2**10)

    @staticmethod
    def _hwm() -> float | None:
        try:
            for line in Path("/proc/self/status").read_text().splitlines():
                if line.startswith("VmHWM:"):
                    return float(line.split()[1]) / 1024
        except OSError:
            pass
        return None


@dataclass(frozen=True)
class TaskOutput:
    """What one run gives back to the sweep.

    Attributes:
        row: The flat result row, keys :data:`ROW_FIELDS`.
        model: The trained model's files by name (``model.safetensors``, ``model.json``);
            returned as bytes so that a run on a remote worker needs no shared disk.
    """

    row: dict
    model: dict[str, bytes]


def run_task(task: Task, settings: SweepSettings) -> TaskOutput:
    """Trains and evaluates one task in this process with one torch thread.

    The paper's protocol: a random 0.8 / 0.2 split of the samples (seeded by the task's
    seed), the default :class:`~snds.train.TrainConfig`, :func:`snds.evaluate.evaluate` on the
    test samples.

    ``peak_memory_mb`` is the process's peak resident memory during the task (see
    :class:`_PeakMemory`), the Python interpreter and torch included. ``train_seconds`` is the
    fit's wall time, ``train_cpu_seconds`` the CPU time of this process during the fit (all
    its threads): on a machine shared with other work the wall time grows, the CPU time
    hardly does.

    Arguments:
        task: The run.
        settings: Training steps and the size of the stability check.

    Returns:
        The result row and the trained model's files.
    """
    return run_batch([task], settings)[0]


def run_batch(tasks: Sequence[Task], settings: SweepSettings) -> list[TaskOutput]:
    """Runs tasks of one method as :func:`run_task` runs each, with their fits as one stacked
    model (:meth:`snds.method.NeuralMethod.fit_many`; a single task is fitted alone).

    The fits equal separate ones up to rounding, which training amplifies (see
    :mod:`snds.batched`). Each row's ``train_seconds`` and ``train_cpu_seconds`` are its
    share of the stacked fit (the total over the number of tasks); ``peak_memory_mb`` is the
    batch's.

    Arguments:
        tasks: Runs of one method (seeds of one motion, typically).
        settings: Training steps and the size of the stability check.

    Returns:
        Each task's result row and trained model's files, in order.
    """
    method = get_method(tasks[0].method)
    if any(task.method != method.name for task in tasks):
        raise SNDSError(f"a batch runs one method, got {sorted({t.method for t in tasks})}")
    # One thread per run: the networks are small, and runs side by side fill the cores.
    with torch_threads(1):
        with _PeakMemory() as memory:
            data = []
            for task in tasks:
                demos = task.source().load()
                data.append((demos, split_samples(demos, test_fraction=0.2, seed=task.seed)))
            cpu = time.process_time()
            if len(tasks) == 1:
                fits = [method.fit(*data[0], seed=tasks[0].seed, steps=settings.steps)]
            else:
                fits = method.fit_many(
                    [demos for demos, _ in data],
                    [split for _, split in data],
                    seeds=[task.seed for task in tasks],
                    steps=settings.steps,
                )
            cpu = (time.process_time() - cpu) / len(tasks)
            metrics = [
                evaluate(
                    fitted.policy,
                    demos,
                    split,
                    check=CheckConfig(
                        seed=task.seed, rollouts=settings.rollouts, samples=settings.samples
                    ),
                    threads=1,
                ).to_dict()
                for task, fitted, (demos, split) in zip(tasks, fits, data)
            ]
    return [
        _output(task, fitted, task_metrics, cpu, memory.peak)
        for task, fitted, task_metrics in zip(tasks, fits, metrics)
    ]


def _output(task: Task, fitted: Fitted, metrics: dict, cpu: float, peak: float) -> TaskOutput:
    """A run's result row and model files from its fit and its evaluation."""
    stability = metrics["stability"]
    # Every row has every column; a metric the task's space does not define is None.
    row = dict.fromkeys(ROW_FIELDS) | {
        "motion": task.motion,
        "method": task.method,
        "seed": task.seed,
        "demos": task.demos,
        "se3": task.se3,
        "train_seconds": fitted.seconds,
        "train_cpu_seconds": cpu,
        **{k: float(metrics[k]) for k in ROW_FIELDS if k in metrics},
        **{k: stability[k] for k in ROW_FIELDS if k in stability},
        "peak_memory_mb": peak,
    }
    # JSON has no NaN (and NaN != NaN breaks resumed-row equality): "not defined" is None.
    row = {k: None if isinstance(v, float) and np.isnan(v) else v for k, v in row.items()}
    extra = {
        "data": task.source().record(),
        "split": {"test_fraction": 0.2, "seed": task.seed, "test_demos": None},
        **fitted.record,
    }
    return TaskOutput(row=row, model=RunFolder.model_files(fitted.policy, extra))


def _units(tasks: Sequence[Task], batch_fits: int) -> list[tuple[Task, ...]]:
    """The tasks grouped into the runs of one worker call: up to ``batch_fits`` tasks of one
    motion, method and number of demonstrations where the method fits several at once
    (SNDS, BC), every other task alone; in the order of ``tasks``."""
    units: list[list[Task]] = []
    filling: dict[tuple, list[Task]] = {}
    for task in tasks:
        if batch_fits == 1 or not hasattr(get_method(task.method), "fit_many"):
            units.append([task])
            continue
        group = (task.motion, task.method, task.demos, task.se3)
        unit = filling.get(group)
        if unit is None or len(unit) == batch_fits:
            unit = filling[group] = []
            units.append(unit)
        unit.append(task)
    return [tuple(unit) for unit in units]


def _run_unit(unit: tuple[Task, ...], settings: SweepSettings) -> list[TaskOutput]:
    return [run_task(unit[0], settings)] if len(unit) == 1 else run_batch(unit, settings)


# ---------------------------------------------------------------------------------------------
# The results folder: append-only JSON lines, then a CSV and a summary.


def _read_results(path: Path) -> dict[str, dict]:
    """Rows of ``results.jsonl`` by task key; drops a torn last line left by a kill."""
    if not path.is_file():
        return {}
    rows: dict[str, dict] = {}
    good: list[str] = []
    text = path.read_text()
    for line in text.splitlines():
        try:
            row = json.loads(line)
            rows[Task.from_row(row).key] = row
            good.append(line)
        except (json.JSONDecodeError, KeyError, TypeError, ValueError):
            continue
    if text and (not text.endswith("\n") or len(good) != len(text.splitlines())):
        # Appending after a torn line would glue the next row to it: rewrite the good ones.
        atomic_write(path, lambda tmp: tmp.write_text("".join(f"{g}\n" for g in good)))
    return rows


def finished_rows(out: Path) -> dict[str, dict]:
    """The result rows already in a sweep folder, by :attr:`Task.key`."""
    return _read_results(Path(out) / RESULTS_FILE)


def _append_row(path: Path, row: dict) -> None:
    with open(path, "a") as handle:
        handle.write(json.dumps(row) + "\n")
        handle.flush()
        os.fsync(handle.fileno())


def _check_settings(out: Path, settings: dict) -> None:
    path = out / SETTINGS_FILE
    if path.is_file():
        previous = json.loads(path.read_text())
        if previous != settings:
            raise SNDSError(
                f"{out} holds results of a sweep with {previous}, this one has {settings}; "
                "use another --out"
            )
    else:
        atomic_write(path, lambda tmp: tmp.write_text(json.dumps(settings) + "\n"))


def write_csv(rows: Sequence[dict], path: Path) -> None:
    """Writes rows as CSV with the columns :data:`ROW_FIELDS`, atomically."""

    def write(tmp: Path) -> None:
        with open(tmp, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(ROW_FIELDS), extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)

    atomic_write(path, write)


def _label(row: dict) -> str:
    """The row's task in tables and figures (:attr:`Task.label`)."""
    return Task.from_row(row).label


def _groups(rows: Sequence[dict]) -> Iterator[tuple[str, str, list[dict]]]:
    """(motion, method, rows) in the order they first appear."""
    keys: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        keys.setdefault((_label(row), row["method"]), []).append(row)
    for (motion, method), group in keys.items():
        yield motion, method, group


def _angle(group: list[dict], stat) -> str:
    if all(r.get("final_angle_error") is None for r in group):
        return "-"
    return stat(group, "final_angle_error", ".3g")


def summarise(rows: Sequence[dict]) -> str:
    """A Markdown table of mean ± std (over seeds) per motion and method.

    Errors are given to 3 significant digits (one-demonstration MSEs are below 1e-4). The
    "shortened" column is the mean fraction of stability rollouts in which the guarded Euler
    step had to shorten a step (where plain Euler at the data's step would not decrease V);
    "n/a" for methods without a Lyapunov function, which take plain steps. Where some rows
    are SE(3) tasks, a last column gives their orientation error at the end of the rollouts
    from the demonstrations' starts (radians; "-" for position tasks).
    """

    def stat(group: list[dict], key: str, fmt: str) -> str:
        values = np.array([r.get(key) for r in group], dtype=float)
        values = values[np.isfinite(values)]
        # Rows of older sweeps may lack a field (train CPU s before it was recorded).
        if len(values) == 0:
            return "n/a"
        more = f" ({len(values)} runs)" if len(values) < len(group) else ""
        if len(values) == 1:
            # One run has no spread to show: "± 0" would claim one.
            return f"{values[0]:{fmt}}{more}"
        return f"{values.mean():{fmt}} ± {values.std():{fmt}}{more}"

    poses = any(r.get("final_angle_error") is not None for r in rows)
    lines = [
        "| motion | method | runs | velocity MSE (paper scale) | paper's SNDS MSE "
        "| DTW (paper scale) | train s | train CPU s | converged | decrease violations "
        "| shortened |" + (" final angle (rad) |" if poses else ""),
        "|---|---|---|---|---|---|---|---|---|---|---|" + ("---|" if poses else ""),
    ]
    total = 0
    for motion, method, group in _groups(rows):
        violations = sum(int(r["decrease_violations"]) for r in group)
        total += violations
        checked = METHODS[method].has_lyapunov if method in METHODS else True
        lines.append(
            f"| {motion} | {method} | {len(group)} | {stat(group, 'velocity_mse_paper', '.3g')} "
            f"| {PAPER_SNDS_MSE[motion] if motion in PAPER_SNDS_MSE and method == 'snds' else '-'} "
            f"| {stat(group, 'dtw_paper', '.3g')} | {stat(group, 'train_seconds', '.1f')} "
            f"| {stat(group, 'train_cpu_seconds', '.1f')} "
            f"| {stat(group, 'converged_fraction', '.3f')} "
            f"(min {min(r['converged_fraction'] for r in group):.3f}) "
            f"| {violations if checked else 'n/a (no V)'} "
            f"| {stat(group, 'shortened_fraction', '.2f') if checked else 'n/a'} |"
            + (f" {_angle(group, stat)} |" if poses else "")
        )
    lines += [
        "",
        f"Total decrease violations: {total}.",
        "",
        "Mean ± standard deviation over the runs (seeds) of each row; one run: its value. "
        "Paper's SNDS MSE: the paper's Fig. 4, on the snds rows. Converged: the fraction of "
        "the stability check's random starts that arrived at the target (worst run in "
        "brackets). Shortened: the fraction of those rollouts in which the guarded Euler step "
        "had to shorten a step, where plain Euler at the data's step would not have decreased "
        "V (n/a: a method without V takes plain steps).",
    ]
    return "\n".join(lines) + "\n"


def _run_units(
    units: Sequence[tuple[Task, ...]], *, jobs: int, scheduler: str | None, settings: SweepSettings
) -> Iterator[TaskOutput]:
    """The outputs of the units' runs as they finish: in this process (``jobs == 1``), on a
    local process pool or on a Dask cluster (:func:`snds.parallel.starmap_unordered`)."""
    calls = [(unit, settings) for unit in units]
    keys = ["+".join(task.key for task in unit) for unit in units]
    for _, outputs in starmap_unordered(
        _run_unit, calls, jobs=jobs, scheduler=scheduler, keys=keys
    ):
        yield from outputs


def _store(out: Path, output: TaskOutput) -> None:
    """Writes a run's model, then appends its row: a row on disk always has its model."""
    RunFolder(out / Task.from_row(output.row).model_dir).write_files(output.model)
    _append_row(out / RESULTS_FILE, output.row)


def run_sweep(
    tasks: Iterable[Task],
    *,
    out: Path,
    settings: SweepSettings | None = None,
    jobs: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
) -> list[dict]:
    """Runs the tasks not yet in ``out`` and writes the results.

    Each finished run's model goes to ``out/models/...`` (see :attr:`Task.model_dir`) and its
    row is appended to ``out/results.jsonl`` at once; tasks whose key is already there are
    skipped, so an interrupted sweep resumes where it stopped. A folder holds the results of
    one :class:`SweepSettings` (recorded in ``sweep.json``); mixing them is refused. At the
    end ``results.csv`` and ``summary.md`` cover the given tasks.

    Arguments:
        tasks: The runs.
        out: The results folder (created if needed).
        settings: What the runs share (default: :class:`SweepSettings` ()).
        jobs: Local worker processes (default: all cores; 1 runs in this process).
        scheduler: A Dask scheduler address such as ``tcp://host:8786``; runs there instead.
        progress: Show a progress bar (only on a terminal).

    Returns:
        One row per task, in the order of ``tasks``.
    """
    from tqdm.auto import tqdm

    settings = settings or SweepSettings()
    tasks = list(dict.fromkeys(tasks))
    jobs = jobs or os.cpu_count() or 1
    if jobs < 1:
        raise SNDSError(f"jobs must be >= 1, got {jobs}")
    for task in tasks:
        _check_task(task)
        resolve_motions(task.motion)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    _check_settings(out, settings.to_dict())
    done = _read_results(out / RESULTS_FILE)
    pending = [task for task in tasks if task.key not in done]
    units = _units(pending, settings.batch_fits)
    outputs = _run_units(units, jobs=jobs, scheduler=scheduler, settings=settings)
    show = progress and sys.stderr.isatty()
    start = time.perf_counter()
    with tqdm(
        total=len(tasks),
        initial=len(tasks) - len(pending),
        disable=not show,
        desc="benchmark",
        unit="run",
    ) as bar:
        for output in outputs:
            _store(out, output)
            row = output.row
            done[Task.from_row(row).key] = row
            bar.set_postfix_str(f"{row['motion']}/{row['method']}", refresh=False)
            bar.update()
    ordered = [done[task.key] for task in tasks]
    write_csv(ordered, out / "results.csv")
    summary = summarise(ordered)
    seconds = time.perf_counter() - start
    header = (
        f"# Benchmark\n\n{len(tasks)} runs ({len(pending)} new, {seconds:.0f} s); "
        f"steps {settings.steps or 'default'}; stability check of {settings.rollouts} "
        f"rollouts and {settings.samples} decrease samples per run.\n\n"
    )
    atomic_write(out / "summary.md", lambda tmp: tmp.write_text(header + summary))
    return ordered


# ---------------------------------------------------------------------------------------------
# Figures.


def _save(fig, path: Path) -> Path:
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=120))
    return path


def plot_benchmark(rows: Sequence[dict], out: Path) -> list[Path]:
    """Writes the sweep's figures (:func:`benchmark_figures`) into ``out``, then
    ``streamlines.png``: one row per method, one column per motion, the lowest seed's model
    (from ``out/models``) with its rollouts; the paper's Fig. 5 and 6. Skipped for runs whose
    model is not there."""
    out = Path(out)
    paths = [_save(fig, out / name) for name, fig in benchmark_figures(rows).items()]
    cells = {(motion, method): group for motion, method, group in _groups(rows)}
    motions = list(dict.fromkeys(motion for motion, _ in cells))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    panels = _panels(cells, out, motions, methods)
    if any(panel is not None for row in panels for panel in row):
        paths.append(plot_panels(panels, out / "streamlines.png"))
    return paths


def benchmark_figures(rows: Sequence[dict]) -> dict[str, Figure]:
    """The sweep's figures by file name, each legend above its axes (it hides no bar or dot):

    * ``mse_violin.png``: log10 of the velocity MSE (paper scale), one violin per method and
      motion, every run a dot (a violin needs two runs or more); the paper's Fig. 4.
    * ``dtw_violin.png``: the same for the DTW of rollouts from the demonstrations' starts.
    * ``train_time.png``: train seconds, mean and std over seeds.
    * ``converged.png``: the fraction of random starts that reached the target, mean over
      seeds with the worst seed marked.
    """
    # The rows of each (motion, method) cell, each row's label read once.
    cells = {(motion, method): group for motion, method, group in _groups(rows)}
    motions = list(dict.fromkeys(motion for motion, _ in cells))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    width = 0.8 / max(1, len(methods))
    size = (max(5.0, 1.2 * len(motions) * max(1, len(methods)) ** 0.5 + 2), 4.0)

    def offsets(i: int) -> np.ndarray:
        return np.arange(len(motions)) + (i - (len(methods) - 1) / 2) * width

    def values(motion: str, method: str, key: str) -> np.ndarray:
        return np.array([r[key] for r in cells.get((motion, method), [])], dtype=float)

    def violins(key: str, label: str) -> Figure:
        fig = Figure(figsize=size, layout="constrained")
        ax = fig.subplots()
        for i, method in enumerate(methods):
            color = f"C{i}"
            for x, motion in zip(offsets(i), motions):
                logs = np.log10(np.clip(values(motion, method, key), 1e-12, None))
                logs = logs[np.isfinite(logs)]
                if len(logs) > 1 and np.ptp(logs) > 0:
                    parts = ax.violinplot(
                        [logs], positions=[x], widths=0.9 * width, showextrema=False
                    )
                    for body in parts["bodies"]:
                        body.set_facecolor(color)
                        body.set_alpha(0.4)
                # One run per cell gives no violin: a larger mark, so it reads as a result.
                mark = 10 if len(logs) > 1 else 36
                ax.scatter(np.full(len(logs), x), logs, s=mark, color=color, zorder=3)
            ax.scatter([], [], color=color, label=method)
        ax.set_xticks(range(len(motions)), motions, rotation=30, ha="right")
        ax.set_xlim(-0.5, len(motions) - 0.5)
        ax.set_ylabel(label)
        if all(len(group) == 1 for group in cells.values()):
            ax.set_title("one run per method and motion (no violins)", fontsize="small")
        _legend_above(fig, ax)
        return fig

    figures = {
        "mse_violin.png": violins("velocity_mse_paper", "log10 velocity MSE (paper scale)"),
        "dtw_violin.png": violins("dtw_paper", "log10 DTW (paper scale)"),
    }

    fig = Figure(figsize=size, layout="constrained")
    ax = fig.subplots()
    for i, method in enumerate(methods):
        seconds = [values(motion, method, "train_seconds") for motion in motions]
        means = [v.mean() if v.size else np.nan for v in seconds]
        stds = [v.std() if v.size else np.nan for v in seconds]
        ax.bar(offsets(i), means, width=width, yerr=stds, label=method, color=f"C{i}")
    ax.set_xticks(range(len(motions)), motions, rotation=30, ha="right")
    ax.set_ylabel("train seconds (mean ± std over seeds)")
    _legend_above(fig, ax)
    figures["train_time.png"] = fig

    fig = Figure(figsize=size, layout="constrained")
    ax = fig.subplots()
    for i, method in enumerate(methods):
        fractions = [values(motion, method, "converged_fraction") for motion in motions]
        means = [v.mean() if v.size else np.nan for v in fractions]
        worst = [v.min() if v.size else np.nan for v in fractions]
        ax.bar(offsets(i), means, width=width, label=method, color=f"C{i}")
        ax.scatter(offsets(i), worst, marker="_", s=120, color="black", zorder=3)
    ax.scatter([], [], marker="_", s=120, color="black", label="worst seed")
    ax.set_xticks(range(len(motions)), motions, rotation=30, ha="right")
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("converged fraction of random starts")
    _legend_above(fig, ax)
    figures["converged.png"] = fig
    return figures


def _legend_above(fig, ax) -> None:
    """The axes' legend above them, in the figure (:func:`snds.plotting.figure_legend`):
    bars that reach 1 and dots anywhere on the scale stay in view."""
    handles, labels = ax.get_legend_handles_labels()
    figure_legend(fig, handles, labels, loc="outside upper center")


def _panels(
    cells: dict[tuple[str, str], list[dict]], out: Path, motions: list[str], methods: list[str]
) -> list:
    """The streamline panels: the lowest seed's saved model per method (row) and motion
    (``cells``: the rows of each (motion label, method))."""
    grid = []
    for method in methods:
        line = []
        for motion in motions:
            runs = cells.get((motion, method), [])
            task = Task.from_row(min(runs, key=lambda r: r["seed"])) if runs else None
            folder = out / task.model_dir if task else None
            if folder is None or not folder.is_dir():
                line.append(None)
                continue
            policy, _ = load_model(folder)
            if policy.space.dim != 2:
                # Streamlines need a plane: 3-D positions and poses have none.
                line.append(None)
                continue
            demos = task.source().load()
            line.append(Panel(float64_copy(policy), demos, f"{motion} — {method}"))
        grid.append(line)
    return grid
