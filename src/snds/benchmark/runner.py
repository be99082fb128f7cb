"""One run of a sweep (or a few fitted together): train, evaluate, and give back the result row
and the model's files, in the process that runs it, with one torch thread.
"""

from __future__ import annotations

import resource
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from snds.benchmark.results import ROW_FIELDS
from snds.benchmark.tasks import SweepSettings, Task
from snds.callbacks import Callback, EndEvent
from snds.errors import SNDSError
from snds.evaluate import evaluate
from snds.fitting import Fitted
from snds.methods import Method, NeuralMethod, get_method
from snds.models import DESCRIPTION, WEIGHTS
from snds.parallel import torch_threads
from snds.run import SplitConfig, split_of, train_run
from snds.runs import RunFolder
from snds.stability import CheckConfig

__all__ = ["SPLIT", "TaskOutput", "run_batch", "run_task"]


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


#: The paper's protocol: a random fifth of the samples held out, seeded by the task's seed.
SPLIT = SplitConfig(test_fraction=0.2)


@dataclass(frozen=True)
class _Trained:
    """A run's fit and evaluation, before the row is made."""

    seconds: float  # wall time of the fit
    cpu: float  # CPU seconds of this process during the fit
    metrics: dict  # the evaluation (Evaluation.to_dict)
    model: dict[str, bytes]  # the model's files


class _FitClock(Callback):
    """The CPU time of this process from the clock's making to the end of the fit."""

    def __init__(self) -> None:
        self.start = time.process_time()
        self.seconds = 0.0

    def on_end(self, event: EndEvent) -> None:
        self.seconds = time.process_time() - self.start


def run_task(task: Task, settings: SweepSettings) -> TaskOutput:
    """Trains and evaluates one task in this process with one torch thread.

    The paper's protocol: a random 0.8 / 0.2 split of the samples (:data:`SPLIT`, seeded by
    the task's seed), the training settings of the method's recipe, :func:`snds.evaluate.evaluate`
    on the test samples. SNDS and BC (:class:`~snds.methods.NeuralMethod`) train as
    ``snds train`` does, through :func:`snds.run.train_run` in a temporary folder; the other
    methods through their :meth:`~snds.methods.Method.fit`.

    ``peak_memory_mb`` is the process's peak resident memory during the task (see
    :class:`_PeakMemory`), the Python interpreter and torch included. ``train_seconds`` is the
    fit's wall time, ``train_cpu_seconds`` the CPU time of this process during the fit (all
    its threads; for SNDS and BC it counts the loading of the data too, a few milliseconds):
    on a machine shared with other work the wall time grows, the CPU time hardly does.

    Arguments:
        task: The run.
        settings: Training steps and the size of the stability check.

    Returns:
        The result row and the trained model's files.
    """
    method = get_method(task.method)
    # One thread per run: the networks are small, and runs side by side fill the cores.
    with torch_threads(1), _PeakMemory() as memory:
        if isinstance(method, NeuralMethod):
            trained = _train_run(task, method, settings)
        else:
            trained = _fit_method(task, method, settings)
    return _output(task, trained, memory.peak)


def _check(task: Task, settings: SweepSettings) -> CheckConfig:
    """The stability check of a task's run (seeded by the task's seed)."""
    return CheckConfig(seed=task.seed, rollouts=settings.rollouts, samples=settings.samples)


def _train_run(task: Task, method: NeuralMethod, settings: SweepSettings) -> _Trained:
    """A network policy's run through :func:`snds.run.train_run`, in a temporary folder of
    which the model's files are kept."""
    clock = _FitClock()
    with tempfile.TemporaryDirectory(prefix="snds-benchmark-") as folder:
        run = train_run(
            task.source(),
            folder,
            recipe=method.recipe(task.space, steps=settings.steps),
            seed=task.seed,
            split=SPLIT,
            check=_check(task, settings),
            callbacks=[clock],
            threads=1,
        )
        model = {name: (run.folder.path / name).read_bytes() for name in (WEIGHTS, DESCRIPTION)}
    return _Trained(run.result.seconds, clock.seconds, run.metrics.to_dict(), model)


def _fit_method(task: Task, method: Method, settings: SweepSettings) -> _Trained:
    """A run of a method that is not trained by :func:`snds.run.train_run` (the baselines):
    its :meth:`~snds.methods.Method.fit`, evaluated and saved as that run would be."""
    demos = task.source().load()
    split_record = SPLIT.record(task.seed)
    split = split_of(demos, split_record)
    cpu = time.process_time()
    fitted = method.fit(demos, split, seed=task.seed, steps=settings.steps)
    cpu = time.process_time() - cpu
    metrics = evaluate(fitted.policy, demos, split, check=_check(task, settings), threads=1)
    return _Trained(fitted.seconds, cpu, metrics.to_dict(), _model_files(task, fitted))


def _model_files(task: Task, fitted: Fitted) -> dict[str, bytes]:
    """The files of a fitted model with the record a run writes beside it."""
    record = {"data": task.source().record(), "split": SPLIT.record(task.seed), **fitted.record}
    return RunFolder.model_files(fitted.policy, record)


def run_batch(tasks: Sequence[Task], settings: SweepSettings) -> list[TaskOutput]:
    """Runs tasks of one method as :func:`run_task` runs each, with their fits as one stacked
    model (:meth:`snds.methods.NeuralMethod.fit_many`; a single task is run alone).

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
    if len(tasks) == 1:
        return [run_task(tasks[0], settings)]
    method = get_method(tasks[0].method)
    if any(task.method != method.name for task in tasks):
        raise SNDSError(f"a batch runs one method, got {sorted({t.method for t in tasks})}")
    with torch_threads(1), _PeakMemory() as memory:
        data = []
        for task in tasks:
            demos = task.source().load()
            data.append((demos, split_of(demos, SPLIT.record(task.seed))))
        cpu = time.process_time()
        fits = method.fit_many(
            [demos for demos, _ in data],
            [split for _, split in data],
            seeds=[task.seed for task in tasks],
            steps=settings.steps,
        )
        cpu = (time.process_time() - cpu) / len(tasks)
        trained = [
            _Trained(
                fitted.seconds,
                cpu,
                evaluate(
                    fitted.policy, demos, split, check=_check(task, settings), threads=1
                ).to_dict(),
                _model_files(task, fitted),
            )
            for task, fitted, (demos, split) in zip(tasks, fits, data)
        ]
    return [_output(task, one, memory.peak) for task, one in zip(tasks, trained)]


def _output(task: Task, trained: _Trained, peak: float) -> TaskOutput:
    """A run's result row from its fit and its evaluation."""
    metrics = trained.metrics
    stability = metrics["stability"]
    # Every row has every column; a metric the task's space does not define is None.
    row = dict.fromkeys(ROW_FIELDS) | {
        "motion": task.motion,
        "method": task.method,
        "seed": task.seed,
        "demos": task.demos,
        "se3": task.se3,
        **{k: float(metrics[k]) for k in ROW_FIELDS if k in metrics},
        **{k: stability[k] for k in ROW_FIELDS if k in stability},
        "train_seconds": trained.seconds,
        "train_cpu_seconds": trained.cpu,
        "peak_memory_mb": peak,
    }
    # JSON has no NaN (and NaN != NaN breaks resumed-row equality): "not defined" is None.
    row = {k: None if isinstance(v, float) and np.isnan(v) else v for k, v in row.items()}
    return TaskOutput(row=row, model=trained.model)
