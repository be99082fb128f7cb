"""Hooks into a fit and a run: :class:`Callback`, the events it receives, and the progress bar.

A callback overrides the methods it cares about; the others do nothing (the pattern of
Lightning's ``Callback`` and imitation's ``on_batch_end``). :func:`snds.train.fit` and
:func:`snds.batched.fit_many` call the training hooks; :func:`snds.run.train_run` adds the
hooks of a run (the model saved, the evaluation done). Each hook receives one frozen event.

A callback stops a fit by returning True from :meth:`Callback.on_step` (as XGBoost's
``TrainingCallback.after_iteration`` does); the fit then ends as if its steps had run out,
with ``stopped == "callback"``, and is saved and evaluated like any other.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm.auto import tqdm

__all__ = [
    "Callback",
    "CheckpointEvent",
    "EndEvent",
    "EvaluatedEvent",
    "ProgressBar",
    "RestartEvent",
    "SavedEvent",
    "StepEvent",
    "notify",
]


@dataclass(frozen=True)
class StepEvent:
    """One optimiser step taken.

    Attributes:
        fit: Index of the fit (0 for :func:`~snds.train.fit`; its position for
            :func:`~snds.batched.fit_many`).
        step: Index of the step just taken, from 0.
        total: Steps planned (``TrainConfig.steps``).
        loss: The step's loss.
        smoothed: The exponentially smoothed loss (weight 0.05 on each new step).
        lr: The learning rate the step used.
        policy: The policy being trained, live (its weights after this step): read it
            (e.g. ``copy.deepcopy`` or ``state_dict`` to show the field while training),
            never modify it, or the fit is no longer reproducible.
    """

    fit: int
    step: int
    total: int
    loss: float
    smoothed: float
    lr: float
    policy: Any = field(repr=False, compare=False)


@dataclass(frozen=True)
class RestartEvent:
    """A diverged step (NaN, or a loss 1,000 times the best): the fit went back to its last
    good weights with half the learning rate.

    Attributes:
        fit: Index of the fit.
        step: The step that diverged (it is taken again).
        restarts: Restarts so far, this one included.
        loss: The diverged step's loss (NaN or inf possibly).
    """

    fit: int
    step: int
    restarts: int
    loss: float


@dataclass(frozen=True)
class CheckpointEvent:
    """A checkpoint was written (:mod:`snds.checkpoint`).

    Attributes:
        fit: Index of the fit.
        steps: Steps taken before it (a resume continues after them).
        path: The checkpoint file.
    """

    fit: int
    steps: int
    path: Path


@dataclass(frozen=True)
class EndEvent:
    """A fit ended.

    Attributes:
        fit: Index of the fit.
        steps: Steps taken (counting those before a resume).
        stopped: Why: "steps", "plateau", "time" or "callback".
        seconds: Wall time of the optimisation.
        restarts: Restarts after diverged steps.
    """

    fit: int
    steps: int
    stopped: str
    seconds: float
    restarts: int


@dataclass(frozen=True)
class SavedEvent:
    """A run's model is written (:func:`snds.run.train_run`); its evaluation starts next.

    Attributes:
        folder: The run folder, with ``model.safetensors`` and ``model.json``.
    """

    folder: Path


@dataclass(frozen=True)
class EvaluatedEvent:
    """A run's evaluation is written (``metrics.json``).

    Attributes:
        folder: The run folder.
        metrics: The record written (:meth:`snds.evaluate.Evaluation.to_dict`).
    """

    folder: Path
    metrics: dict


class Callback:
    """Base class of the hooks; every method does nothing unless overridden."""

    def on_step(self, event: StepEvent) -> bool | None:
        """After each optimiser step; return True to stop the fit there."""
        return None

    def on_restart(self, event: RestartEvent) -> None:
        """After a diverged step, when the fit has gone back to its last good weights."""

    def on_checkpoint(self, event: CheckpointEvent) -> None:
        """After a checkpoint is written."""

    def on_end(self, event: EndEvent) -> None:
        """When a fit ends (also one resumed from a finished checkpoint)."""

    def on_saved(self, event: SavedEvent) -> None:
        """When a run's model is written, before its evaluation."""

    def on_evaluated(self, event: EvaluatedEvent) -> None:
        """When a run's evaluation is written."""


def notify(callbacks: Sequence[Callback], hook: str, event: Any) -> bool:
    """Calls ``hook`` of every callback, in order, with ``event``; True if any asked to stop
    (every callback is called all the same)."""
    stop = False
    for callback in callbacks:
        stop = bool(getattr(callback, hook)(event)) or stop
    return stop


class ProgressBar(Callback):
    """A tqdm bar of the steps on standard error (drawn only on a terminal), with the
    smoothed loss every 20 steps; :func:`~snds.train.fit` adds one when ``progress`` is on.

    Arguments:
        total: Steps planned.
        initial: Steps already taken (a resumed fit).
        desc: The bar's label.
    """

    def __init__(self, total: int, *, initial: int = 0, desc: str = "train") -> None:
        self.bar = tqdm(
            total=total,
            initial=initial,
            disable=not sys.stderr.isatty(),
            desc=desc,
            leave=False,
        )

    def on_step(self, event: StepEvent) -> None:
        # Every fit of a batch reports the same step: the bar shows the step, not the sum.
        if event.step + 1 > self.bar.n:
            self.bar.update(event.step + 1 - self.bar.n)
            if event.step % 20 == 0:
                self.bar.set_postfix(loss=f"{event.smoothed:.2e}")

    def on_end(self, event: EndEvent) -> None:
        self.bar.close()
