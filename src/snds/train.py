"""Training: one frozen :class:`TrainConfig`, :func:`fit`, and the loop behind it.

:func:`train_loop` steps one fit or several (:func:`snds.batched.fit_many`) through the same
code: restarts after a diverged step, early stopping, checkpoints and callbacks. The loss is
:func:`snds.losses.step_loss` on the inputs :func:`snds.batches.draw_step` draws; the
checkpoint's format is :mod:`snds.checkpoint`'s; the optimiser's step :mod:`snds.optim`'s.
"""

from __future__ import annotations

import contextlib
import copy
import math
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch

from snds.batches import StepInputs, draw_step
from snds.callbacks import (
    Callback,
    CheckpointEvent,
    EndEvent,
    ProgressBar,
    RestartEvent,
    StepEvent,
    notify,
)
from snds.checkpoint import (
    CHECKPOINT,
    FitState,
    TrainResult,
    fit_identity,
    restore_checkpoint,
    save_checkpoint,
)
from snds.data.demonstrations import Demonstrations, Split
from snds.errors import ConfigError, DataError, TrainingError
from snds.losses import Samples, make_samples, step_loss
from snds.optim import adam, adam_step, clip_gradients
from snds.parallel import torch_threads
from snds.policy import Policy
from snds.threads import fastest_threads
from snds.train_config import DTYPES, TrainConfig

__all__ = [
    "CHECKPOINT",
    "DTYPES",
    "MIN_WARMUP_STEPS",
    "Fit",
    "Losses",
    "TrainConfig",
    "TrainResult",
    "TrainingError",
    "fit",
    "held_parameters",
    "prepare_fit",
    "single_losses",
    "train_loop",
    "trained_parameters",
    "training_samples",
]


#: The warm-up lasts at least this many steps (or a fifth of a shorter fit): Adam's first
#: steps move every weight by about the learning rate, so a warm-up of a few steps lets a short
#: fit jump to a poor basin.
MIN_WARMUP_STEPS = 30


def _learning_rate(step: int, config: TrainConfig) -> float:
    warm = max(1, int(config.warmup * config.steps), min(MIN_WARMUP_STEPS, config.steps // 5))
    if step < warm:
        return config.lr * (step + 1) / warm
    progress = (step - warm) / max(1, config.steps - warm)
    low = config.lr * config.final_lr_fraction
    return low + 0.5 * (config.lr - low) * (1 + math.cos(math.pi * progress))


def training_samples(
    demos: Demonstrations, policy: Policy, split: Split, config: TrainConfig
) -> Samples:
    """The samples a fit trains on, in model coordinates, in ``config``'s dtype and device:
    those of ``split`` (:func:`snds.losses.make_samples`) without the states exactly at the
    target that nothing moves off it (:meth:`~snds.losses.Samples.off_target`); with a phase in
    the policy's space, tracking moves the positions (``Samples.tracked``).

    Arguments:
        demos: The demonstrations in the coordinates the policy's normalisation maps (a pose
            policy's chart: :meth:`~snds.policy.Policy.training_demonstrations`).
        policy: The policy to train.
        split: Which samples train.
        config: The fit's settings.
    """
    space = policy.space
    tracked = space.position_dim if space.phase_dim else 0
    samples = make_samples(
        demos, policy.normalization, split, window=config.window, tracked=tracked
    )
    samples = samples.off_target(positions=not config.position_noise)
    if len(samples.positions) == 0:
        raise DataError("no training samples away from the target")
    return samples.to(DTYPES[config.dtype], config.device)


def fit(
    policy: Policy,
    demos: Demonstrations,
    split: Split,
    config: TrainConfig = TrainConfig(),
    *,
    callbacks: Sequence[Callback] = (),
    progress: bool = True,
    checkpoint: Path | None = None,
    checkpoint_every: int = 200,
    threads: int | None = None,
) -> TrainResult:
    """Fits a policy to demonstrations (in place) by minimising the loss of paper eq. (5)
    (:func:`snds.losses.step_loss`).

    Adam with a warm-up and cosine schedule and gradient clipping. A NaN or a loss that
    jumps far above its best restores the last good weights, halves the learning rate and
    goes on, so a bad step never needs a manual rerun.

    With ``checkpoint``, the whole state of the optimisation is written there every
    ``checkpoint_every`` steps and at the end (:mod:`snds.checkpoint`), and a fit that finds
    a checkpoint there continues from it: a fit killed midway and started again gives the
    same weights, bit for bit, as one that was never interrupted.

    Arguments:
        policy: The policy to train; moved to ``config.dtype`` and ``config.device``.
        demos: The demonstrations, in user units, in the policy's space (poses for a pose
            policy).
        split: Which samples train (the rest are ignored here).
        config: The optimisation settings (by name; by position as the fourth argument too).
        callbacks: Hooks called at each step, restart, checkpoint and at the end, in order
            (:class:`snds.callbacks.Callback`); one may stop the fit.
        progress: Show a progress bar (only on a terminal).
        checkpoint: A ``.safetensors`` file to resume from if it exists, and to write.
        checkpoint_every: Steps between checkpoints.
        threads: Torch CPU threads during the fit, restored after it (None:
            :func:`snds.threads.fastest_threads` for the fit's size).

    Returns:
        The loss history and timing (both counting the steps before a resume).

    Raises:
        CheckpointError: If the checkpoint is corrupted, or was made with other settings, an
            other architecture or other training data.
        TrainingError: If the loss keeps diverging.
    """
    if checkpoint_every < 1:
        raise ConfigError(f"checkpoint_every must be >= 1, got {checkpoint_every}")
    one = prepare_fit(policy, demos, split, config, checkpoint=checkpoint)
    if progress and not one.state.finished:
        callbacks = [ProgressBar(config.steps, initial=one.state.step), *callbacks]
    with torch_threads(fastest_threads(config) if threads is None else threads):
        train_loop([one], callbacks=callbacks, checkpoint_every=checkpoint_every)
    return one.state.result


@dataclass(eq=False)
class Fit:
    """One fit inside the training loop: what :func:`train_loop` steps and books.

    Attributes:
        index: Its position among the fits of the loop (the events' ``fit``).
        policy: The policy being trained (in place).
        config: Its settings.
        samples: Its training samples (:func:`training_samples`).
        generator: The source of its mini-batches and noise.
        optimizer: Its Adam (replaced at each restart).
        state: Its step, losses, last good weights and result (:mod:`snds.checkpoint`).
        checkpoint: The file it resumes from and writes (None: none).
        identity: What a checkpoint must match (:func:`snds.checkpoint.fit_identity`).
        label: Its name in an error of a loop of several fits ("" for one).
        parameters: The tensors its first optimiser moves (:func:`trained_parameters`): what
            gradients are clipped over and every restart's Adam is built on.
    """

    index: int
    policy: Policy
    config: TrainConfig
    samples: Samples
    generator: torch.Generator
    optimizer: torch.optim.Adam
    state: FitState
    checkpoint: Path | None = None
    identity: dict = field(default_factory=dict)
    label: str = ""
    parameters: list[torch.Tensor] = field(init=False)

    def __post_init__(self) -> None:
        # The tensors its optimiser moves (trained_parameters), the same for the whole fit: a
        # restart reloads the state dict in place and builds its new Adam over them.
        self.parameters = [p for group in self.optimizer.param_groups for p in group["params"]]


def held_parameters(policy: Policy, config: TrainConfig) -> list[torch.Tensor]:
    """The parameters a fit leaves as they are: V's when ``config.fit_lyapunov`` is False
    (none otherwise, or for a policy without V)."""
    lyapunov = getattr(policy, "lyapunov", None)
    if config.fit_lyapunov or lyapunov is None:
        return []
    return list(lyapunov.parameters())


def trained_parameters(policy: Policy, config: TrainConfig) -> list[torch.Tensor]:
    """The parameters a fit moves: the policy's but :func:`held_parameters`, in the policy's
    order."""
    held = {id(p) for p in held_parameters(policy, config)}
    return [p for p in policy.parameters() if id(p) not in held]


@contextlib.contextmanager
def _holding(fits: Sequence[Fit]) -> Iterator[None]:
    """The fits' held parameters need no gradient while they train (restored after)."""
    held = [p for one in fits for p in held_parameters(one.policy, one.config)]
    before = [p.requires_grad for p in held]
    try:
        for p in held:
            p.requires_grad_(False)
        yield
    finally:
        for p, flag in zip(held, before):
            p.requires_grad_(flag)


def prepare_fit(
    policy: Policy,
    demos: Demonstrations,
    split: Split,
    config: TrainConfig,
    *,
    index: int = 0,
    checkpoint: Path | None = None,
    label: str = "",
) -> Fit:
    """Sets a fit up as :func:`fit` does: the policy in the config's dtype and device, its
    samples, anchors, generator and optimiser, and the state of ``checkpoint`` if that file
    exists.

    Raises:
        CheckpointError: If the checkpoint is corrupted or made for another fit.
    """
    policy.to(device=config.device, dtype=DTYPES[config.dtype])
    # In the coordinates the normalisation maps to model coordinates (a pose policy's chart).
    samples = training_samples(policy.training_demonstrations(demos), policy, split, config)
    policy.set_anchors(samples.positions)
    generator = torch.Generator().manual_seed(config.seed)
    optimizer = adam(trained_parameters(policy, config), config.lr)
    state = FitState(good=copy.deepcopy(policy.state_dict()))
    identity = {}
    if checkpoint is not None:
        checkpoint = Path(checkpoint)
        identity = fit_identity(policy, config, samples)
        if checkpoint.is_file():
            state = restore_checkpoint(checkpoint, identity, policy, optimizer, generator)
    return Fit(
        index, policy, config, samples, generator, optimizer, state, checkpoint, identity, label
    )


#: The losses of the active fits of a step, shape (K,), from their drawn inputs.
Losses = Callable[[list[Fit], list[StepInputs]], torch.Tensor]


def single_losses(active: list[Fit], inputs: list[StepInputs]) -> torch.Tensor:
    """:data:`Losses` fit by fit (:func:`snds.losses.step_loss` on each policy)."""
    return torch.stack([step_loss(one.policy, one.config, x) for one, x in zip(active, inputs)])


def train_loop(
    fits: list[Fit],
    losses_of: Losses = single_losses,
    *,
    callbacks: Sequence[Callback] = (),
    checkpoint_every: int = 200,
) -> None:
    """Trains fits of equal settings (but for their seed) step by step: the one loop behind
    :func:`fit` and :func:`snds.batched.fit_many`.

    At each step it draws every active fit's inputs (:func:`snds.batches.draw_step`), gets
    their losses from ``losses_of``, back-propagates the healthy ones at once (the fits share
    no weights, so the sum's gradient is each fit's own), clips each fit's gradient, and
    steps it, or restarts a fit whose loss or gradient diverged from its last good weights.
    A fit leaves the loop when its steps run out, it plateaus (``patience``), the time is up
    (``max_seconds``, for all) or a callback asks it to stop; each writes its checkpoint
    every ``checkpoint_every`` steps and at its end.

    Raises:
        TrainingError: If a fit's loss keeps diverging (the message names the fit).
    """
    with _holding(fits):
        _train_loop(fits, losses_of, callbacks=callbacks, checkpoint_every=checkpoint_every)


def _train_loop(
    fits: list[Fit],
    losses_of: Losses,
    *,
    callbacks: Sequence[Callback],
    checkpoint_every: int,
) -> None:
    config = fits[0].config
    start = time.perf_counter() - fits[0].state.result.seconds
    for one in fits:
        if one.state.finished:
            _notify_end(one, callbacks)
    active = [one for one in fits if not one.state.finished]
    for step in range(fits[0].state.step, config.steps):
        if not active:
            break
        for one in active:
            one.state.step = step
            if one.checkpoint is not None and step > 0 and step % checkpoint_every == 0:
                one.state.result.seconds = time.perf_counter() - start
                _save(one, callbacks)
        inputs = [
            draw_step(one.policy, one.samples, one.config, one.generator, step) for one in active
        ]
        losses = losses_of(active, inputs)
        values = losses.detach().tolist()
        diverged = [_diverged(value, one.state) for value, one in zip(values, active)]
        healthy = [i for i, bad in enumerate(diverged) if not bad]
        for i in healthy:
            active[i].optimizer.zero_grad(set_to_none=True)
        if healthy:
            (losses if len(healthy) == len(active) else losses[healthy]).sum().backward()
        for i in healthy:
            norm = clip_gradients(active[i].parameters, config.grad_clip)
            # A finite loss can still have a NaN gradient (a division that underflows in its
            # backward pass); stepping on it would make every weight NaN, the saved good
            # state included.
            diverged[i] = not bool(torch.isfinite(norm))
        ended: list[tuple[Fit, str]] = []
        for value, bad, one in zip(values, diverged, active):
            if bad:
                _restart(one, value)
                event = RestartEvent(one.index, step, one.state.result.restarts, value)
                notify(callbacks, "on_restart", event)
                continue
            lr = _step(one, value)
            event = StepEvent(
                one.index, step, config.steps, value, one.state.smoothed, lr, one.policy
            )
            if notify(callbacks, "on_step", event):
                ended.append((one, "callback"))
            elif config.patience and one.state.since_best >= config.patience:
                ended.append((one, "plateau"))
        if config.max_seconds is not None and time.perf_counter() - start > config.max_seconds:
            done = {id(one) for one, _ in ended}
            ended += [(one, "time") for one in active if id(one) not in done]
        for one, why in ended:
            _finish(one, why, start, callbacks)
        active = [one for one in active if not one.state.finished]
    for one in active:
        _finish(one, "steps", start, callbacks)


def _save(one: Fit, callbacks: Sequence[Callback]) -> None:
    save_checkpoint(
        one.checkpoint, one.state, one.identity, one.policy, one.optimizer, one.generator
    )
    steps = len(one.state.result.history)
    notify(callbacks, "on_checkpoint", CheckpointEvent(one.index, steps, one.checkpoint))


def _finish(one: Fit, why: str, start: float, callbacks: Sequence[Callback]) -> None:
    result = one.state.result
    result.stopped = why
    result.seconds = time.perf_counter() - start
    result.steps = len(result.history)
    one.state.finished = True
    if one.checkpoint is not None:
        # A kill after training but before the caller saved the model resumes from here
        # without training again.
        _save(one, callbacks)
    _notify_end(one, callbacks)


def _notify_end(one: Fit, callbacks: Sequence[Callback]) -> None:
    result = one.state.result
    event = EndEvent(one.index, result.steps, result.stopped, result.seconds, result.restarts)
    notify(callbacks, "on_end", event)


def _diverged(value: float, state: FitState) -> bool:
    """Whether a step's loss is NaN or jumped far above the best smoothed loss so far."""
    return not math.isfinite(value) or value > 1e3 * max(state.best, 1e-8)


def _restart(one: Fit, value: float) -> None:
    """Restores the last good weights after a diverged step, with a new Adam at half the
    learning rate (through ``state.lr_scale``).

    Raises:
        TrainingError: After ``config.max_restarts`` restarts.
    """
    state = one.state
    state.result.restarts += 1
    if state.result.restarts > one.config.max_restarts:
        label = f"{one.label}: " if one.label else ""
        raise TrainingError(
            f"{label}loss or its gradient diverged {state.result.restarts} times (last loss "
            f"{value:.3g}); try a lower lr"
        )
    one.policy.load_state_dict(state.good)
    one.optimizer = adam(one.parameters, one.config.lr)
    state.lr_scale *= 0.5


def _step(one: Fit, value: float) -> float:
    """Steps on the (clipped) gradient at ``state.step`` and books the step's loss: history,
    smoothed loss, best and patience counter, and now and then the good state to restart
    from; returns the learning rate used."""
    state, config = one.state, one.config
    step = state.step
    lr = state.lr_scale * _learning_rate(step, config)
    adam_step(one.optimizer, lr)
    state.result.history.append(value)
    state.smoothed = value if state.smoothed == math.inf else 0.95 * state.smoothed + 0.05 * value
    if state.smoothed < state.best * (1 - config.min_improvement):
        state.best, state.since_best = state.smoothed, 0
        if step % 50 == 0:
            state.good = copy.deepcopy(one.policy.state_dict())
    else:
        state.since_best += 1
    return lr
