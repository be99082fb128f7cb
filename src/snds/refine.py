r"""Refinement: a trained policy taught more demonstrations, in about a second.

A refinement is :func:`snds.train.fit` started from the trained policy's weights instead of
fresh ones, on the old demonstrations and the new, with a short schedule
(:class:`RefineConfig`). Nothing else changes:

- The guarantee is structural (the projection of :func:`snds.policy.project`), so it holds
  for the refined policy as for any weights: :math:`\nabla V^\top \pi \le -a(x)` everywhere.
- The policy keeps its normalisation (target, length and time scales), because its weights
  are functions of model coordinates; demonstrations beyond the trained extent reach model
  coordinates :math:`|\tilde x| > 1`, where the policy's ``decay_far`` asks a faster
  decrease (:attr:`Refinement.reach` says how far they go). The target stays the model's:
  :func:`added_demonstrations` moves each new demonstration's end onto it.
- A phase (:mod:`snds.phase`) gives the new demonstrations the next codes of the same
  codebook, scaled by the extent the model was trained with, so the old demonstrations keep
  the phases the model learnt.
- The old demonstrations stay in the samples, so the policy does not forget them.

    refined = refine(policy, demos, split, train=recorded_train_config)    # in place

:func:`snds.refine_run.refine_run` is the run of ``snds train --init``: a model folder
refined with the demonstrations of a file, saved and evaluated. The schedule's measured
reasons are in docs/design.md ("Refinement").
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from snds.callbacks import Callback
from snds.data.demonstrations import Demonstrations, Split
from snds.data.targets import MAX_END_SPREAD, end_at
from snds.errors import ConfigError, DataError
from snds.phase import Phase
from snds.policy import Policy
from snds.train import TrainConfig, TrainResult, fit

__all__ = [
    "RefineConfig",
    "Refinement",
    "added_demonstrations",
    "kept_phase",
    "refine",
    "refine_settings",
]


@dataclass(frozen=True, kw_only=True)
class RefineConfig:
    """The schedule of a refinement; the rest of the training settings are the model's own.

    Attributes:
        steps: Optimiser steps.
        lr: Peak learning rate of Adam (after a warm-up of a fifth of the steps, a cosine
            decay to ``final_lr_fraction`` of it, as in :func:`snds.train.fit`).
        final_lr_fraction: The cosine schedule decays to lr x this.
        new_weight: How many times each new demonstration's samples count among the
            training samples (1: as often as an old demonstration's).
        batch_size: Samples per step for the velocity term (None: the model's own).
        fit_lyapunov: Train V too (False: V stays as the model learnt it and only the
            nominal field f moves, which makes a step cheaper; the guarantee holds either
            way, see :attr:`snds.train.TrainConfig.fit_lyapunov`).
        max_seconds: Stop after this wall time (None: no limit).
    """

    steps: int = 130
    lr: float = 5e-3
    final_lr_fraction: float = 0.1
    new_weight: int = 1
    batch_size: int | None = 256
    fit_lyapunov: bool = False
    max_seconds: float | None = None

    def __post_init__(self) -> None:
        if type(self.steps) is not int or self.steps < 1:
            raise ConfigError(f"refinement steps must be an integer >= 1, got {self.steps!r}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ConfigError(f"refinement lr must be a positive number, got {self.lr}")
        if not 0 < self.final_lr_fraction <= 1:
            raise ConfigError(f"final_lr_fraction must be in (0, 1], got {self.final_lr_fraction}")
        if type(self.new_weight) is not int or self.new_weight < 1:
            raise ConfigError(f"new_weight must be an integer >= 1, got {self.new_weight!r}")
        batch = self.batch_size
        if batch is not None and (type(batch) is not int or batch < 0):
            raise ConfigError(
                f"refinement batch_size must be an integer >= 0 or None, got {self.batch_size!r}"
            )

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return dataclasses.asdict(self)


def refine_settings(config: RefineConfig, train: TrainConfig) -> TrainConfig:
    """The training settings of a refinement: the model's ``train`` with the refinement's
    steps, learning rate, final fraction, batch size, whether V trains and time limit (no
    early stop by plateau, whose smoothed loss would start from the trained model's)."""
    return dataclasses.replace(
        train,
        steps=config.steps,
        lr=config.lr,
        final_lr_fraction=config.final_lr_fraction,
        batch_size=train.batch_size if config.batch_size is None else config.batch_size,
        fit_lyapunov=config.fit_lyapunov,
        max_seconds=config.max_seconds,
        patience=0,
    )


@dataclass(frozen=True)
class Refinement:
    """What :func:`refine` did.

    Attributes:
        result: The fit's loss history and timing (:class:`snds.train.TrainResult`).
        train: The settings it ran with (:func:`refine_settings`), saved beside the model.
        reach: The largest distance of a training state from the target, in model
            coordinates (1: the trained extent; more: the demonstrations reach beyond it,
            where ``decay_far`` applies).
    """

    result: TrainResult
    train: TrainConfig
    reach: float


def refine(
    policy: Policy,
    demos: Demonstrations,
    split: Split,
    *,
    config: RefineConfig = RefineConfig(),
    train: TrainConfig = TrainConfig(),
    new: Sequence[int] = (),
    callbacks: Sequence[Callback] = (),
    progress: bool = False,
    checkpoint: Path | None = None,
    checkpoint_every: int = 200,
    threads: int | None = None,
) -> Refinement:
    """Refines a trained policy (in place) on old and new demonstrations.

    The same as ``fit(policy, demos', split', refine_settings(config, train))`` with each
    demonstration of ``new`` repeated ``config.new_weight`` times in ``demos'`` and
    ``split'``: a fit that starts from the policy's weights, bit for bit, so a checkpoint of
    a refinement resumes as any fit's does.

    Arguments:
        policy: The trained policy; its weights are the start, its normalisation stays.
        demos: All demonstrations, old and new, in the policy's space and coordinates (a
            phase as :func:`added_demonstrations` appends it).
        split: Which samples train, over ``demos``.
        config: The refinement's schedule.
        train: The model's training settings (its recorded ``train`` config: the loss, the
            noise, the seed); :func:`refine_settings` gives the schedule.
        new: Indices of the new demonstrations in ``demos`` (weighted by
            ``config.new_weight``).
        callbacks: The fit's hooks (:class:`snds.callbacks.Callback`).
        progress: Show a progress bar (only on a terminal).
        checkpoint: A ``.safetensors`` file to resume from if it exists, and to write.
        checkpoint_every: Steps between checkpoints.
        threads: Torch CPU threads (None: the library's choice).

    Raises:
        DataError: If an index of ``new`` is out of range.
    """
    for index in new:
        if not 0 <= index < len(demos):
            raise DataError(f"new demonstration {index} out of range 0..{len(demos) - 1}")
    order = [i for i in range(len(demos)) for _ in range(config.new_weight if i in new else 1)]
    if len(order) != len(demos):
        demos = demos.select(order)
        split = Split(tuple(split.train[i] for i in order))
    settings = refine_settings(config, train)
    result = fit(
        policy,
        demos,
        split,
        settings,
        callbacks=callbacks,
        progress=progress,
        checkpoint=checkpoint,
        checkpoint_every=checkpoint_every,
        threads=threads,
    )
    return Refinement(result=result, train=settings, reach=_reach(policy, demos, split))


def _reach(policy: Policy, demos: Demonstrations, split: Split) -> float:
    """The largest model-coordinate norm of the training states."""
    chart = policy.training_demonstrations(demos)
    states = np.concatenate([demo.states[mask] for demo, mask in zip(chart, split.train)])
    return float(np.linalg.norm(policy.normalization.positions_to_model(states), axis=-1).max())


def added_demonstrations(
    old: Demonstrations,
    new: Demonstrations,
    *,
    phase: Phase | None = None,
    max_end_spread: float = MAX_END_SPREAD,
) -> Demonstrations:
    """The old demonstrations followed by the new, in the trained model's terms: each new
    end moved onto the old target (:func:`snds.data.targets.end_at`, the linear-in-time
    offset of :func:`snds.data.common_target`), and the model's phase appended with the
    extent it was trained with (:func:`kept_phase`).

    Arguments:
        old: The demonstrations the model was trained on, without a phase.
        new: The demonstrations to add, without a phase, of the same dimension.
        phase: The model's phase (None: none).
        max_end_spread: Largest accepted distance of a new end from the old target, in
            extents of the old demonstrations.

    Raises:
        DataError: If the dimensions differ or a new demonstration ends too far from the
            target.
    """
    if old.phase_dim or new.phase_dim:
        raise DataError("give the demonstrations without a phase; the model's is appended")
    if new.dim != old.dim:
        raise DataError(f"the new demonstrations have dimension {new.dim}, the model's {old.dim}")
    extent = old.extent()
    moved = []
    for number, demo in enumerate(new):
        gap = float(np.linalg.norm(demo.positions[-1] - old.target))
        if gap > max_end_spread * extent:
            raise DataError(
                f"new demonstration {number} ends {gap:.4g} from the model's target "
                f"{np.round(old.target, 4).tolist()}, {gap / extent:.0%} of its extent "
                f"{extent:.4g}, more than max_end_spread={max_end_spread:g} allows"
            )
        moved.append(end_at(demo, old.target))
    joined = Demonstrations(old.demos + tuple(moved), old.target, old.name)
    return joined if phase is None else kept_phase(phase, old).apply(joined)


def kept_phase(phase: Phase, old: Demonstrations) -> Phase:
    """The model's phase with its extent fixed: the one it records, else the extent of the
    demonstrations it was trained on (``old``, without a phase)."""
    return phase if phase.extent is not None else dataclasses.replace(phase, extent=old.extent())
