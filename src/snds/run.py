"""A training run: data, recipe, fit, save, evaluation and plots, as ``snds train`` does it.

:func:`train_run` is what the command line (``snds train``) and the page (:mod:`snds.app`)
call; a Python user gets the same run folder, the same numbers and a typed :class:`Run`::

    run = snds.train_run(snds.DataSource(motion="Sine"), "runs/Sine")
    run.metrics.dtw_paper, run.folder.metrics_file

The folder holds ``model.safetensors`` + ``model.json`` (the model and the settings it was
trained with: data, split, training), ``loss.json``, ``metrics.json``, and the plots if asked
(:mod:`snds.runs`). While the fit runs, ``checkpoint.safetensors`` lets ``resume`` continue
a killed run bit for bit; it is removed once the run is complete.
"""

from __future__ import annotations

import copy
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from snds.callbacks import Callback, EvaluatedEvent, SavedEvent, notify
from snds.checkpoint import TrainResult
from snds.data import DataSource, Demonstrations, Split, no_split, split_demos, split_samples
from snds.errors import ConfigError
from snds.evaluate import Evaluation, evaluate
from snds.methods import make_policy
from snds.policy import Policy
from snds.recipes import RECIPES, Recipe
from snds.runs import RunFolder
from snds.stability import CheckConfig
from snds.train import fit

__all__ = [
    "DEFAULT_RUNS",
    "Run",
    "RunWarning",
    "SplitConfig",
    "complete_run",
    "split_of",
    "train_run",
]


class RunWarning(UserWarning):
    """Something about a run the user should know that does not stop it (``resume`` without
    a checkpoint); the CLI prints it as one line."""


#: Where a run without ``out`` goes: ``runs/<name of the data>`` (``-se3`` for poses).
DEFAULT_RUNS = Path("runs")


@dataclass(frozen=True, kw_only=True)
class SplitConfig:
    """Which samples train and which are held out (seeded by the run's seed).

    Attributes:
        test_fraction: The share of samples held out at random (0: none, train on all).
        test_demos: Hold out these whole demonstrations instead (0-based indices).
    """

    test_fraction: float = 0.2
    test_demos: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        if not 0.0 <= self.test_fraction < 1.0:
            raise ConfigError(f"test_fraction must be in [0, 1), got {self.test_fraction}")

    def record(self, seed: int) -> dict:
        """The ``split`` record of ``model.json``, which :func:`split_of` reads back."""
        demos = list(self.test_demos) if self.test_demos is not None else None
        return {"test_fraction": self.test_fraction, "seed": seed, "test_demos": demos}


def split_of(demos: Demonstrations, record: dict) -> Split:
    """The split described by a ``split`` record of ``model.json``."""
    if record.get("test_demos"):
        return split_demos(demos, test_demos=record["test_demos"])
    fraction = float(record.get("test_fraction", 0.0))
    if fraction <= 0:
        return no_split(demos)
    return split_samples(demos, test_fraction=fraction, seed=int(record.get("seed", 0)))


@dataclass(frozen=True)
class Run:
    """A finished training run.

    Attributes:
        model: The trained policy (in the dtype it was trained in).
        metrics: Its evaluation (``metrics.json``: :meth:`Evaluation.to_dict`).
        result: What the fit did (loss history, steps, why it stopped).
        folder: The run folder and its files (:class:`snds.runs.RunFolder`).
        demos: The demonstrations it was trained on, as loaded.
        split: The train / test split.
        config: The record written to ``model.json`` beside the model: ``data``, ``split``
            and ``train``.
        plots: The plots written (empty unless asked).
    """

    model: Policy
    metrics: Evaluation
    result: TrainResult
    folder: RunFolder
    demos: Demonstrations
    split: Split
    config: dict
    plots: tuple[Path, ...] = ()


def _source(source: DataSource | str | Path, recipe: Recipe) -> DataSource:
    if isinstance(source, DataSource):
        return source
    return DataSource(file=Path(source), phase=recipe.phase)


def train_run(
    source: DataSource | str | Path,
    out: str | Path | None = None,
    *,
    recipe: Recipe = RECIPES["default"],
    seed: int = 0,
    split: SplitConfig = SplitConfig(),
    check: CheckConfig = CheckConfig(),
    plots: bool = False,
    resume: bool = False,
    checkpoint_every: int = 200,
    callbacks: Sequence[Callback] = (),
    progress: bool = False,
    threads: int | None = None,
) -> Run:
    """Trains a policy on demonstrations, saves it with its settings, evaluates it.

    The run: load the data; build the policy of ``recipe.policy`` (its weights seeded by
    ``seed``); split the samples; :func:`snds.train.fit` with ``recipe.train`` (its seed set
    to ``seed``); save the model, its record and its loss history; :func:`evaluate` it with
    ``check``; write ``metrics.json`` and, if asked, the plots. Callbacks hear the fit's
    events, then :meth:`~snds.callbacks.Callback.on_saved` once the model is written (the
    evaluation starts) and :meth:`~snds.callbacks.Callback.on_evaluated` once the metrics are.

    Arguments:
        source: The demonstrations: a :class:`snds.data.DataSource`, or a file's path (read
            with the recipe's phase and the library's reading defaults).
        out: The run folder (None: ``runs/<name>``, ``runs/<name>-se3`` for poses).
        recipe: The architecture, training settings and phase (:data:`snds.recipes.RECIPES`);
            the phase applies to a path ``source`` (a DataSource carries its own).
        seed: Seed of the weights, the split and the fit.
        split: Which samples are held out for the evaluation.
        check: The stability check's settings.
        plots: Also write the plots (:func:`snds.plotting.plot_all`).
        resume: Continue from the folder's checkpoint if there is one (same settings).
        checkpoint_every: Steps between checkpoints.
        callbacks: Hooks (:class:`snds.callbacks.Callback`).
        progress: Show a progress bar while fitting (only on a terminal).
        threads: Torch CPU threads for the fit and the evaluation (None: the library's
            choice, :func:`snds.threads.fastest_threads`).

    Raises:
        SNDSError: Bad data, settings or checkpoint (one line naming the cause); nothing of
            an earlier model in ``out`` is left beside a new one.
    """
    source = _source(source, recipe)
    demos = source.load()
    name = demos.name or source.name
    folder = RunFolder(Path(out) if out is not None else DEFAULT_RUNS / _folder_name(name, source))
    policy = make_policy(demos, config=recipe.policy, seed=seed)
    train = replace(recipe.train, seed=seed)
    split_record = split.record(seed)
    data_split = split_of(demos, split_record)
    folder.prepare(resume=resume)
    if resume and not folder.checkpoint.is_file():
        warnings.warn(f"no checkpoint in {folder.path}: training from the start", RunWarning, 2)
    result = fit(
        policy,
        demos,
        data_split,
        config=train,
        callbacks=callbacks,
        progress=progress,
        checkpoint=folder.checkpoint,
        checkpoint_every=checkpoint_every,
        threads=threads,
    )
    record = {"data": source.record(), "split": split_record, "train": train.to_dict()}
    return complete_run(
        folder,
        policy,
        result,
        demos,
        data_split,
        record=record,
        check=check,
        callbacks=callbacks,
        threads=threads,
        plots=plots,
    )


def complete_run(
    folder: RunFolder,
    policy: Policy,
    result: TrainResult,
    demos: Demonstrations,
    split: Split,
    *,
    record: dict,
    check: CheckConfig = CheckConfig(),
    callbacks: Sequence[Callback] = (),
    threads: int | None = None,
    plots: bool = False,
) -> Run:
    """What follows a run's fit (:func:`train_run` and :func:`snds.refine_run.refine_run`):
    saves the model with ``record`` (``model.json``), evaluates it, writes ``metrics.json``,
    draws the plots if asked, and only then removes the checkpoint, so that a kill before
    the end leaves a run to resume."""
    folder.save(policy, result, record=record)
    notify(callbacks, "on_saved", SavedEvent(folder.path))
    metrics = evaluate(policy, demos, split, check=check, threads=threads)
    metrics = metrics.with_train_seconds(result.seconds)
    written = metrics.to_dict()
    folder.write_metrics(written)
    notify(callbacks, "on_evaluated", EvaluatedEvent(folder.path, written))
    drawn: list[Path] = []
    if plots:
        from snds.plotting import plot_all  # matplotlib: only a run that plots imports it

        shown = copy.deepcopy(policy).to(device="cpu", dtype=torch.float64).eval()
        drawn = plot_all(shown, demos, folder.path, history=result.history)
    folder.finish()
    return Run(
        model=policy,
        metrics=metrics,
        result=result,
        folder=folder,
        demos=demos,
        split=split,
        config=record,
        plots=tuple(drawn),
    )


def _folder_name(name: str, source: DataSource) -> str:
    return f"{name}-se3" if source.poses else name
