"""One run of a sweep (or a few fitted together): train, evaluate, and give back the result row
and the model's files, in the process that runs it, with one torch thread.
"""

from __future__ import annotations

import resource
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from snds.benchmark.results import ROW_FIELDS
from snds.benchmark.tasks import SweepSettings, Task
from snds.data import split_samples
from snds.errors import SNDSError
from snds.evaluate import evaluate
from snds.fitting import Fitted
from snds.methods import get_method
from snds.parallel import torch_threads
from snds.runs import RunFolder
from snds.stability import CheckConfig

__all__ = ["PeakMemory", "TaskOutput", "run_batch", "run_task"]


class PeakMemory:
    """Peak resident memory of this process during a block, in MiB.

    On Linux the kernel's high-water mark (``VmHWM``) is reset at the start (writing 5 to
    ``/proc/self/clear_refs``), so the figure is the task's own peak, whatever ran before it
    in the same worker. Elsewhere it falls back to ``ru_maxrss``, which never resets: exact
    only for a worker's first task. Either way it costs nothing, unlike tracemalloc, which
    slows training several times and misses torch's native allocations.
    """

    def __enter__(self) -> PeakMemory:
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
    :class:`PeakMemory`), the Python interpreter and torch included. ``train_seconds`` is the
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
    model (:meth:`snds.methods.NeuralMethod.fit_many`; a single task is fitted alone).

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
        with PeakMemory() as memory:
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
