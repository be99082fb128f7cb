"""Training: one frozen :class:`TrainConfig` and one :func:`fit`."""

from __future__ import annotations

import copy
import math
import sys
import time
from dataclasses import asdict, dataclass, field

import torch
from tqdm.auto import tqdm

from snds.data.demonstrations import Demonstrations, Split
from snds.errors import ConfigError, SNDSError
from snds.losses import VELOCITY_SHAPES, make_samples, velocity_loss, window_loss
from snds.policy import StablePolicy

DTYPES = {"float32": torch.float32, "float64": torch.float64}


class TrainingError(SNDSError, RuntimeError):
    """Training diverged even after restarting from its last good state."""


@dataclass(frozen=True, kw_only=True)
class TrainConfig:
    """How to fit a policy; saved beside the model.

    Attributes:
        steps: Maximum number of optimiser steps.
        max_seconds: Stop after this wall time (None: no limit).
        lr: Peak learning rate of Adam.
        warmup: Fraction of the steps with a linear learning-rate warm-up.
        final_lr_fraction: The cosine schedule decays to lr x this.
        batch_size: Samples per step for the velocity term (0: full batch).
        window_batch_size: Windows per step for the multi-step term (0: all); smaller than
            `batch_size` since each window costs Nw evaluations of the policy.
        grad_clip: Maximum gradient norm.
        velocity_shape: "mse" (the authors' code) or "srvf" (the paper).
        window: Nw, the Euler steps of the multi-step term (0: velocity term only).
        velocity_weight: gamma_0; the window terms have gamma_i = 2^-i.
        patience: Stop when the smoothed loss has not improved by `min_improvement` (relative)
            for this many steps (0: never stop early).
        min_improvement: Relative improvement that resets the patience counter.
        max_restarts: Restarts from the last good state after a NaN or diverging loss.
        seed: Seed of the initial weights and the mini-batches.
        dtype: "float32" (fast) or "float64".
        device: A torch device ("cpu", "cuda", ...).
    """

    steps: int = 3000
    max_seconds: float | None = None
    lr: float = 1e-2
    warmup: float = 0.02
    final_lr_fraction: float = 0.01
    batch_size: int = 512
    window_batch_size: int = 128
    grad_clip: float = 1.0
    velocity_shape: str = "mse"
    window: int = 0
    velocity_weight: float = 1.0
    patience: int = 0
    min_improvement: float = 1e-3
    max_restarts: int = 5
    seed: int = 0
    dtype: str = "float32"
    device: str = "cpu"

    def __post_init__(self) -> None:
        if self.steps < 1:
            raise ConfigError(f"steps must be >= 1, got {self.steps}")
        if self.velocity_shape not in VELOCITY_SHAPES:
            raise ConfigError(
                f"unknown velocity_shape {self.velocity_shape!r}; choose from "
                f"{list(VELOCITY_SHAPES)}"
            )
        if self.dtype not in DTYPES:
            raise ConfigError(f"unknown dtype {self.dtype!r}; choose from {list(DTYPES)}")
        if self.window < 0 or self.batch_size < 0 or self.window_batch_size < 0:
            raise ConfigError(
                f"window and batch sizes must be >= 0, got window {self.window}, batch_size "
                f"{self.batch_size}, window_batch_size {self.window_batch_size}"
            )
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ConfigError(f"lr must be a positive number, got {self.lr}")
        try:
            device = torch.device(self.device)
        except RuntimeError:
            raise ConfigError(f"unknown device {self.device!r} (e.g. cpu, cuda, cuda:1)") from None
        # Checked here, not at the first tensor op: a missing GPU must fail before any work.
        if device.type == "cuda" and not torch.cuda.is_available():
            raise ConfigError(f"device {self.device!r}: no CUDA device is available")

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return asdict(self)


@dataclass
class TrainResult:
    """What :func:`fit` did.

    Attributes:
        history: The loss at every step.
        seconds: Wall time of the optimisation.
        steps: Steps taken.
        restarts: Restarts after a NaN or diverging loss.
        stopped: Why training ended ("steps", "plateau" or "time").
    """

    history: list[float] = field(default_factory=list)
    seconds: float = 0.0
    steps: int = 0
    restarts: int = 0
    stopped: str = "steps"


def _learning_rate(step: int, config: TrainConfig) -> float:
    warm = max(1, int(config.warmup * config.steps))
    if step < warm:
        return config.lr * (step + 1) / warm
    progress = (step - warm) / max(1, config.steps - warm)
    low = config.lr * config.final_lr_fraction
    return low + 0.5 * (config.lr - low) * (1 + math.cos(math.pi * progress))


def _batch(size: int, total: int, generator: torch.Generator, device: str) -> torch.Tensor | None:
    if size == 0 or size >= total:
        return None
    return torch.randint(total, (size,), generator=generator).to(device)


def fit(
    policy: StablePolicy,
    demos: Demonstrations,
    split: Split,
    config: TrainConfig,
    *,
    progress: bool = True,
) -> TrainResult:
    """Fits a policy to demonstrations (in place) by minimising the loss of paper eq. (5).

    Adam with a warm-up and cosine schedule and gradient clipping. A NaN or a loss that
    jumps far above its best restores the last good weights, halves the learning rate and
    goes on, so a bad step never needs a manual rerun.

    Arguments:
        policy: The policy to train; moved to ``config.dtype`` and ``config.device``.
        demos: The demonstrations, in user units.
        split: Which samples train (the rest are ignored here).
        config: The optimisation settings.
        progress: Show a progress bar (only on a terminal).

    Returns:
        The loss history and timing.
    """
    dtype = DTYPES[config.dtype]
    policy.to(device=config.device, dtype=dtype)
    samples = make_samples(demos, policy.normalization, split, window=config.window).to(
        dtype, config.device
    )
    generator = torch.Generator().manual_seed(config.seed)
    optimizer = torch.optim.Adam(policy.parameters(), lr=config.lr)
    result = TrainResult()
    good_state = copy.deepcopy(policy.state_dict())
    best = smoothed = math.inf
    since_best, lr_scale = 0, 1.0
    show = progress and sys.stderr.isatty()
    start = time.perf_counter()
    bar = tqdm(range(config.steps), disable=not show, desc="train", leave=False)
    for step in bar:
        loss = _loss(policy, samples, config, generator)
        value = float(loss.detach())
        if not math.isfinite(value) or value > 1e3 * max(best, 1e-8):
            result.restarts += 1
            if result.restarts > config.max_restarts:
                raise TrainingError(
                    f"loss diverged {result.restarts} times (last {value:.3g}); try a lower lr"
                )
            policy.load_state_dict(good_state)
            optimizer = torch.optim.Adam(policy.parameters(), lr=config.lr)
            lr_scale *= 0.5
            continue
        for group in optimizer.param_groups:
            group["lr"] = lr_scale * _learning_rate(step, config)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), config.grad_clip)
        optimizer.step()
        result.history.append(value)
        smoothed = value if smoothed == math.inf else 0.95 * smoothed + 0.05 * value
        if smoothed < best * (1 - config.min_improvement):
            best, since_best = smoothed, 0
            if step % 50 == 0:
                good_state = copy.deepcopy(policy.state_dict())
        else:
            since_best += 1
        if step % 20 == 0:
            bar.set_postfix(loss=f"{smoothed:.2e}")
        if config.patience and since_best >= config.patience:
            result.stopped = "plateau"
            break
        if config.max_seconds is not None and time.perf_counter() - start > config.max_seconds:
            result.stopped = "time"
            break
    bar.close()
    result.seconds = time.perf_counter() - start
    result.steps = len(result.history)
    return result


def _loss(
    policy: StablePolicy, samples, config: TrainConfig, generator: torch.Generator
) -> torch.Tensor:
    index = _batch(config.batch_size, len(samples.positions), generator, config.device)
    x, v = samples.positions, samples.velocities
    if index is not None:
        x, v = x[index], v[index]
    loss = config.velocity_weight * velocity_loss(policy.field(x), v, config.velocity_shape)
    if config.window and len(samples.window_starts):
        index = _batch(
            config.window_batch_size, len(samples.window_starts), generator, config.device
        )
        starts, targets, steps = (
            samples.window_starts,
            samples.window_targets,
            samples.window_steps,
        )
        if index is not None:
            starts, targets, steps = starts[index], targets[index], steps[index]
        loss = loss + window_loss(policy.field, starts, targets, steps)
    return loss
