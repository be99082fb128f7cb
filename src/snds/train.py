"""Training: one frozen :class:`TrainConfig` and one :func:`fit`."""

from __future__ import annotations

import copy
import hashlib
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file
from tqdm.auto import tqdm

from snds.data.demonstrations import Demonstrations, Split
from snds.errors import CheckpointError, ConfigError, DataError, TrainingError
from snds.io import atomic_write
from snds.losses import (
    VELOCITY_SHAPES,
    Samples,
    align_loss,
    make_samples,
    velocity_loss,
    window_loss,
)
from snds.nn.flow import EuclideanizingFlow
from snds.policy import Policy, StablePolicy

DTYPES = {"float32": torch.float32, "float64": torch.float64}


@dataclass(frozen=True, kw_only=True)
class TrainConfig:
    r"""How to fit a policy; saved beside the model.

    Attributes:
        steps: Maximum number of optimiser steps.
        max_seconds: Stop after this wall time (None: no limit).
        lr: Peak learning rate of Adam.
        warmup: Fraction of the steps with a linear learning-rate warm-up (at least
            :data:`MIN_WARMUP_STEPS` steps, or a fifth of a shorter fit).
        final_lr_fraction: The cosine schedule decays to lr x this.
        batch_size: Samples per step for the velocity term (0: full batch).
        window_batch_size: Windows per step for the multi-step term (0: all); smaller than
            `batch_size` since each window costs Nw evaluations of the policy.
        grad_clip: Maximum gradient norm.
        velocity_shape: "mse" (the authors' code) or "srvf" (the paper).
        window: Nw, the Euler steps of the multi-step term (0: velocity term only).
        velocity_weight: gamma_0; the window terms have gamma_i = 2^-i.
        nominal_weight: beta, the weight of a second velocity term on the nominal field f
            itself. Where the projection is active (ReLU rectifier), pi does not depend on
            f's component along grad V, so the velocity term alone gives that component no
            gradient and a fit can stall; this term keeps f near the data everywhere. The
            guarantee is pi's and does not depend on it (0: off, the paper's loss).
        position_noise: Standard deviation of Gaussian noise added to the training states at
            every step (model coordinates, where the data span about [-1, 1]); the
            velocities stay as demonstrated (``noise_correction`` moves and corrects states
            of its own). It smooths the fit where demonstrations run close together at
            different speeds (0: off; SE(3) pose policies train without it).
        noise_correction: A gain k per unit of model time that pulls states back onto the
            demonstrated paths. A share (``correction_share``) of each batch's states is
            moved by further Gaussian offsets of standard deviation ``correction_noise``
            (on top of the position noise); each moved state :math:`\tilde x` is trained
            towards :math:`v_j - k (\tilde x - x_j)_\perp`, with :math:`x_j` the training
            sample nearest to it (:meth:`Samples.nearest`), :math:`v_j` its velocity and
            :math:`\perp` the part across :math:`v_j` (all of it where :math:`v_j = 0`). The
            nearest sample, not the one the state was moved from: a state that lands on a
            neighbouring demonstration learns that demonstration's velocity, so close
            demonstrations do not contradict each other (0: off).
        correction_noise: The standard deviation of those offsets (model coordinates).
        correction_share: The share of each batch's states that is moved and corrected, in
            [0, 1].
        correction_width: sigma > 0: the offset :math:`(\tilde x - x_j)_\perp` is averaged over
            the training samples near the moved state, with Gaussian weights of width sigma
            (model coordinates) and by how well their direction of travel agrees with the
            nearest sample's (:meth:`snds.losses.Samples.pull`), so that between
            demonstrations running side by side closer than a few sigma the pull points to
            their middle instead of onto whichever is nearest, and a rollout from a start they
            share does not snap onto one of them. The velocity :math:`v_j` stays the nearest
            sample's (0: the offset from the nearest sample alone).
        shape_weight: Weight of the penalty :math:`\operatorname{Var}_x \log(V(x) / |x|^2)`
            over 256 random states, uniform in :math:`[-2, 2]^n` (model coordinates): it
            keeps V's sublevel sets round where the data do not ask otherwise, against stiff
            fields (0: off). The projection is unchanged by scaling V, and so is the penalty.
        warp_weight: Weight of :func:`warp_penalty`, which keeps the Jacobian of a warped V's
            diffeomorphism near the identity off the data, against stiff fields (stable
            policies with a warp only; 0: off).
        align_weight: Weight of :func:`snds.losses.align_loss`, which asks V to descend
            along the demonstrated direction of travel (within ``arccos(align_cosine)``),
            weighted by speed. The decrease margin then pushes a slow or resting stretch of a
            demonstration along its path, not across it towards the target (stable policies
            only; 0: off).
        align_cosine: The cosine c of that hinge, in [-1, 1].
        penalty_every: Evaluate the shape and warp penalties at every k-th step only, with k
            times their weight (1: every step).
        patience: Stop when the smoothed loss has not improved by `min_improvement` (relative)
            for this many steps (0: never stop early).
        min_improvement: Relative improvement that resets the patience counter.
        max_restarts: Restarts from the last good state after a NaN or diverging loss.
        seed: Seed of the initial weights and the mini-batches.
        dtype: "float32" (fast) or "float64".
        device: A torch device ("cpu", "cuda", ...).
    """

    steps: int = 1500
    max_seconds: float | None = None
    lr: float = 2e-2
    warmup: float = 0.02
    final_lr_fraction: float = 0.01
    batch_size: int = 512
    window_batch_size: int = 128
    grad_clip: float = 1.0
    velocity_shape: str = "mse"
    window: int = 0
    velocity_weight: float = 1.0
    nominal_weight: float = 0.01
    position_noise: float = 0.0015
    noise_correction: float = 10.0
    correction_noise: float = 0.005
    correction_share: float = 0.1
    correction_width: float = 0.04
    shape_weight: float = 0.0
    warp_weight: float = 0.001
    align_weight: float = 0.1
    align_cosine: float = 0.5
    penalty_every: int = 4
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
        if self.penalty_every < 1:
            raise ConfigError(f"penalty_every must be >= 1, got {self.penalty_every}")
        if not 0.0 <= self.correction_share <= 1.0:
            raise ConfigError(f"correction_share must be in [0, 1], got {self.correction_share}")
        if not -1.0 <= self.align_cosine <= 1.0:
            raise ConfigError(f"align_cosine must be in [-1, 1], got {self.align_cosine}")
        if self.window < 0 or self.batch_size < 0 or self.window_batch_size < 0:
            raise ConfigError(
                f"window and batch sizes must be >= 0, got window {self.window}, batch_size "
                f"{self.batch_size}, window_batch_size {self.window_batch_size}"
            )
        for name in (
            "nominal_weight",
            "position_noise",
            "noise_correction",
            "correction_noise",
            "correction_width",
            "shape_weight",
            "warp_weight",
            "align_weight",
        ):
            weight = getattr(self, name)
            if not (weight >= 0 and math.isfinite(weight)):
                raise ConfigError(f"{name} must be a number >= 0, got {weight}")
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


def _adam(policy: Policy, config: TrainConfig) -> torch.optim.Adam:
    # The fused implementation updates every parameter in one kernel: the networks are small,
    # so a step's cost is mostly the number of operations, not their size.
    return torch.optim.Adam(policy.parameters(), lr=config.lr, fused=True)


def clip_gradients(parameters: Sequence[torch.Tensor], max_norm: float) -> torch.Tensor:
    """Scales the gradients of ``parameters`` to a total 2-norm of at most ``max_norm``;
    returns the norm before clipping (NaN or inf if a gradient is).

    The same operations, in the same order, as ``torch.nn.utils.clip_grad_norm_(parameters,
    max_norm, foreach=True)`` on parameters of one device and dtype (so the same bits), without
    its per-call grouping work; other parameter sets go through it. Taking the parameters as a
    list (not a module) spares a walk of the module tree on every step.
    """
    grads = [p.grad for p in parameters if p.grad is not None]
    kinds = {(g.device, g.dtype) for g in grads}
    if len(kinds) != 1 or any(g.is_sparse for g in grads):
        return torch.nn.utils.clip_grad_norm_(parameters, max_norm, foreach=True)
    with torch.no_grad():
        total = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads, 2.0)), 2.0)
        torch._foreach_mul_(grads, torch.clamp(max_norm / (total + 1e-6), max=1.0))
    return total


def adam_step(optimizer: torch.optim.Adam, lr: float) -> None:
    """``optimizer.step()`` at learning rate ``lr`` (which it keeps in its parameter groups).

    For a fused Adam of one parameter group, without AMSGrad, maximisation or weight decay,
    whose state exists (from the second step on), this calls the kernel that
    ``optimizer.step()`` calls, with the same arguments, directly: the same update, bit for
    bit, without the optimiser's per-call bookkeeping, which costs more than the kernel on
    these small networks. Otherwise it calls ``optimizer.step()``.
    """
    for group in optimizer.param_groups:
        group["lr"] = lr
    group = optimizer.param_groups[0]
    params = [p for p in group["params"] if p.grad is not None]
    states = [optimizer.state.get(p) for p in params]
    direct = (
        len(optimizer.param_groups) == 1
        and hasattr(torch, "_fused_adam_")
        and group.get("fused")
        and not (group["amsgrad"] or group["maximize"] or group["weight_decay"])
        and not (group.get("differentiable") or group.get("decoupled_weight_decay"))
        and params
        and all(states)
        and len({(p.device, p.dtype) for p in params}) == 1
    )
    if not direct:
        optimizer.step()
        return
    beta1, beta2 = group["betas"]
    steps = [state["step"] for state in states]
    with torch.no_grad():
        torch._foreach_add_(steps, 1)
        torch._fused_adam_(
            params,
            [p.grad for p in params],
            [state["exp_avg"] for state in states],
            [state["exp_avg_sq"] for state in states],
            [],
            steps,
            amsgrad=False,
            lr=lr,
            beta1=beta1,
            beta2=beta2,
            weight_decay=0.0,
            eps=group["eps"],
            maximize=False,
            grad_scale=None,
            found_inf=None,
        )


def _batch(size: int, total: int, generator: torch.Generator, device: str) -> torch.Tensor | None:
    if size == 0 or size >= total:
        return None
    return torch.randint(total, (size,), generator=generator).to(device)


def training_samples(
    demos: Demonstrations, policy: Policy, split: Split, config: TrainConfig
) -> Samples:
    """The samples a fit trains on, in model coordinates, in ``config``'s dtype and device:
    those of ``split`` (:func:`snds.losses.make_samples`) without the states exactly at the
    target that nothing moves off it (:meth:`~snds.losses.Samples.off_target`).

    Arguments:
        demos: The demonstrations in the coordinates the policy's normalisation maps (a pose
            policy's chart: :meth:`~snds.policy.Policy.training_demonstrations`).
        policy: The policy to train.
        split: Which samples train.
        config: The fit's settings.
    """
    samples = make_samples(demos, policy.normalization, split, window=config.window)
    samples = samples.off_target(positions=not config.position_noise)
    if len(samples.positions) == 0:
        raise DataError("no training samples away from the target")
    return samples.to(DTYPES[config.dtype], config.device)


def fit(
    policy: StablePolicy,
    demos: Demonstrations,
    split: Split,
    config: TrainConfig,
    *,
    progress: bool = True,
    checkpoint: Path | None = None,
    checkpoint_every: int = 200,
) -> TrainResult:
    """Fits a policy to demonstrations (in place) by minimising the loss of paper eq. (5).

    Adam with a warm-up and cosine schedule and gradient clipping. A NaN or a loss that
    jumps far above its best restores the last good weights, halves the learning rate and
    goes on, so a bad step never needs a manual rerun.

    With ``checkpoint``, the whole state of the optimisation is written there every
    ``checkpoint_every`` steps and at the end (see :func:`save_checkpoint`), and a fit that
    finds a checkpoint there continues from it: a fit killed midway and started again gives
    the same weights, bit for bit, as one that was never interrupted.

    Arguments:
        policy: The policy to train; moved to ``config.dtype`` and ``config.device``.
        demos: The demonstrations, in user units, in the policy's space (poses for a pose
            policy).
        split: Which samples train (the rest are ignored here).
        config: The optimisation settings.
        progress: Show a progress bar (only on a terminal).
        checkpoint: A ``.safetensors`` file to resume from if it exists, and to write.
        checkpoint_every: Steps between checkpoints.

    Returns:
        The loss history and timing (both counting the steps before a resume).

    Raises:
        CheckpointError: If the checkpoint is corrupted, or was made with other settings, an
            other architecture or other training data.
        TrainingError: If the loss keeps diverging.
    """
    if checkpoint_every < 1:
        raise ConfigError(f"checkpoint_every must be >= 1, got {checkpoint_every}")
    dtype = DTYPES[config.dtype]
    policy.to(device=config.device, dtype=dtype)
    # In the coordinates the normalisation maps to model coordinates (a pose policy's chart).
    chart = policy.training_demonstrations(demos)
    samples = training_samples(chart, policy, split, config)
    policy.set_anchors(samples.positions)
    generator = torch.Generator().manual_seed(config.seed)
    optimizer = _adam(policy, config)
    parameters = list(policy.parameters())  # the same tensors after a restart's reload
    state = _State(good=copy.deepcopy(policy.state_dict()))
    identity = _identity(policy, config, samples)
    if checkpoint is not None and Path(checkpoint).is_file():
        state = _restore(Path(checkpoint), identity, policy, optimizer, generator)
    result = state.result
    show = progress and sys.stderr.isatty()
    start = time.perf_counter() - result.seconds
    bar = tqdm(
        range(state.step, config.steps),
        initial=state.step,
        total=config.steps,
        disable=not show or state.finished,
        desc="train",
        leave=False,
    )
    for step in [] if state.finished else bar:
        state.step = step
        if checkpoint is not None and step > 0 and step % checkpoint_every == 0:
            result.seconds = time.perf_counter() - start
            save_checkpoint(Path(checkpoint), state, identity, policy, optimizer, generator)
        loss = _loss(policy, samples, config, generator, step)
        value = float(loss.detach())
        diverged = _diverged(value, state)
        if not diverged:
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            norm = clip_gradients(parameters, config.grad_clip)
            # A finite loss can still have a NaN gradient (a division that underflows in its
            # backward pass); stepping on it would make every weight NaN, the saved good
            # state included.
            diverged = not bool(torch.isfinite(norm))
        if diverged:
            optimizer = _restart(policy, state, config, value)
            continue
        _step(policy, optimizer, state, config, value)
        if step % 20 == 0:
            bar.set_postfix(loss=f"{state.smoothed:.2e}")
        if config.patience and state.since_best >= config.patience:
            result.stopped = "plateau"
            break
        if config.max_seconds is not None and time.perf_counter() - start > config.max_seconds:
            result.stopped = "time"
            break
    bar.close()
    if not state.finished:
        result.seconds = time.perf_counter() - start
        result.steps = len(result.history)
        state.finished = True
        if checkpoint is not None:
            # A kill after training but before the caller saved the model resumes from here
            # without training again.
            save_checkpoint(Path(checkpoint), state, identity, policy, optimizer, generator)
    return result


def _diverged(value: float, state: _State) -> bool:
    """Whether a step's loss is NaN or jumped far above the best smoothed loss so far."""
    return not math.isfinite(value) or value > 1e3 * max(state.best, 1e-8)


def _restart(policy: Policy, state: _State, config: TrainConfig, value: float) -> torch.optim.Adam:
    """Restores the last good weights after a diverged step; returns a new Adam (the rate is
    halved through ``state.lr_scale``).

    Raises:
        TrainingError: After ``config.max_restarts`` restarts.
    """
    state.result.restarts += 1
    if state.result.restarts > config.max_restarts:
        raise TrainingError(
            f"loss or its gradient diverged {state.result.restarts} times (last loss "
            f"{value:.3g}); try a lower lr"
        )
    policy.load_state_dict(state.good)
    optimizer = _adam(policy, config)
    state.lr_scale *= 0.5
    return optimizer


def _step(
    policy: Policy, optimizer: torch.optim.Adam, state: _State, config: TrainConfig, value: float
) -> None:
    """Steps on the (clipped) gradient at ``state.step`` and books the step's loss: history,
    smoothed loss, best and patience counter, and now and then the good state to restart from."""
    step = state.step
    adam_step(optimizer, state.lr_scale * _learning_rate(step, config))
    state.result.history.append(value)
    state.smoothed = value if state.smoothed == math.inf else 0.95 * state.smoothed + 0.05 * value
    if state.smoothed < state.best * (1 - config.min_improvement):
        state.best, state.since_best = state.smoothed, 0
        if step % 50 == 0:
            state.good = copy.deepcopy(policy.state_dict())
    else:
        state.since_best += 1


# Checkpoints: the whole optimisation state in one safetensors file (tensors), with the
# scalars, settings and identity as JSON in its header, so one atomic rename writes it all.

CHECKPOINT_VERSION = 1
#: The checkpoint's name in a model directory (``snds train --resume`` looks for it there).
CHECKPOINT = "checkpoint.safetensors"
_RECORD = "snds_checkpoint"


@dataclass
class _State:
    """Everything of a fit that changes from step to step, besides weights and optimiser."""

    good: dict[str, torch.Tensor]
    result: TrainResult = field(default_factory=TrainResult)
    step: int = 0
    best: float = math.inf
    smoothed: float = math.inf
    since_best: int = 0
    lr_scale: float = 1.0
    finished: bool = False


def _identity(policy: Policy, config: TrainConfig, samples: Samples) -> dict:
    """What must be the same for a checkpoint to continue a fit: settings, model, data."""
    digest = hashlib.sha256()
    for tensor in vars(samples).values():
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    identity = {
        "train": config.to_dict(),
        "kind": policy.kind,
        "dim": policy.dim,
        "policy": policy.config.to_dict(),
        "normalization": policy.normalization.to_dict(),
        "data_sha256": digest.hexdigest(),
    }
    # As it reads back from the file (tuples become lists), so the two compare equal.
    return json.loads(json.dumps(identity))


def save_checkpoint(
    path: Path,
    state: _State,
    identity: dict,
    policy: Policy,
    optimizer: torch.optim.Optimizer,
    generator: torch.Generator,
) -> None:
    """Writes the state of a fit atomically (see :func:`fit`); safetensors and JSON only."""

    tensors = {f"policy.{k}": v for k, v in policy.state_dict().items()}
    tensors |= {f"good.{k}": v for k, v in state.good.items()}
    optimizer_state = optimizer.state_dict()
    for index, entries in optimizer_state["state"].items():
        tensors |= {f"optimizer.{index}.{k}": v for k, v in entries.items()}
    tensors["generator"] = generator.get_state()
    tensors["history"] = torch.tensor(state.result.history, dtype=torch.float64)
    tensors = {k: v.detach().cpu().contiguous() for k, v in tensors.items()}
    result = {k: v for k, v in asdict(state.result).items() if k != "history"}
    record = {
        "version": CHECKPOINT_VERSION,
        "identity": identity,
        "step": state.step,
        "best": state.best,
        "smoothed": state.smoothed,
        "since_best": state.since_best,
        "lr_scale": state.lr_scale,
        "finished": state.finished,
        "result": result,
        "optimizer_groups": optimizer_state["param_groups"],
    }
    metadata = {_RECORD: json.dumps(record)}
    atomic_write(path, lambda tmp: save_file(tensors, str(tmp), metadata=metadata))


def _restore(
    path: Path,
    identity: dict,
    policy: Policy,
    optimizer: torch.optim.Optimizer,
    generator: torch.Generator,
) -> _State:
    """Loads a checkpoint into ``policy``, ``optimizer`` and ``generator``; the rest returned."""
    try:
        with safe_open(str(path), framework="pt") as file:
            record = json.loads((file.metadata() or {})[_RECORD])
        tensors = load_file(str(path))
        if record.get("version") != CHECKPOINT_VERSION:
            raise CheckpointError(
                f"{path}: checkpoint version {record.get('version')!r}, this snds reads "
                f"{CHECKPOINT_VERSION}"
            )
        if record["identity"] != identity:
            theirs, ours = record["identity"], identity
            differ = [k for k in ours if theirs.get(k) != ours[k]]
            details = [
                f"{k}.{f}: {theirs[k].get(f)!r} -> {ours[k][f]!r}"
                for k in differ
                if isinstance(ours[k], dict) and isinstance(theirs.get(k), dict)
                for f in ours[k]
                if theirs[k].get(f) != ours[k][f]
            ]
            names = {
                "train": "train settings",
                "kind": "method",
                "dim": "dimension",
                "policy": "architecture",
                "normalization": "normalisation",
                "data_sha256": "training data",
            }
            raise CheckpointError(
                f"{path}: made with other {', '.join(names.get(k, k) for k in differ)} "
                f"({'; '.join(details[:3]) or 'the training data differ'}); "
                "train without resuming, or with the same arguments"
            )

        def part(prefix: str) -> dict[str, torch.Tensor]:
            return {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}

        policy.load_state_dict(part("policy."))
        entries: dict[int, dict[str, torch.Tensor]] = {}
        for key, tensor in part("optimizer.").items():
            index, name = key.split(".", 1)
            entries.setdefault(int(index), {})[name] = tensor
        optimizer.load_state_dict({"state": entries, "param_groups": record["optimizer_groups"]})
        generator.set_state(tensors["generator"])
        history = tensors["history"].tolist()
        state = _State(
            good={k: v.to(policy.center.device) for k, v in part("good.").items()},
            result=TrainResult(history=history, **record["result"]),
            step=int(record["step"]),
            best=float(record["best"]),
            smoothed=float(record["smoothed"]),
            since_best=int(record["since_best"]),
            lr_scale=float(record["lr_scale"]),
            finished=bool(record["finished"]),
        )
    except CheckpointError:
        raise
    # A damaged file can fail in the reader (SafetensorError, OSError), in the JSON, or in a
    # missing or misshapen entry (KeyError, TypeError, ValueError, RuntimeError from torch).
    except (SafetensorError, OSError, KeyError, TypeError, ValueError, RuntimeError) as error:
        raise CheckpointError(f"{path}: corrupted checkpoint ({error})") from error
    return state


@dataclass(frozen=True)
class _StepInputs:
    """What one step's loss is evaluated on: its mini-batches and the penalties' random
    states, drawn by :func:`_draw_step` (model coordinates; None where the term is off).

    Attributes:
        positions: The velocity term's states, position noise added, shape (B, n).
        velocities: Their demonstrated velocities, shape (B, n).
        windows: The window term's starts (M, n), targets (M, Nw, n) and steps (M, Nw).
        shape_states: The shape penalty's states, shape (256, n).
        warp_draws: The warp penalty's random inputs (see :func:`_warp_draws`).
    """

    positions: torch.Tensor
    velocities: torch.Tensor
    windows: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
    shape_states: torch.Tensor | None = None
    warp_draws: tuple[torch.Tensor, ...] | None = None


def _loss(
    policy: StablePolicy,
    samples: Samples,
    config: TrainConfig,
    generator: torch.Generator,
    step: int = 0,
) -> torch.Tensor:
    return _step_loss(policy, config, _draw_step(policy, samples, config, generator, step))


def _warp_of(policy: Policy) -> EuclideanizingFlow | None:
    """The diffeomorphism inside a policy's V, if it has one."""
    return getattr(getattr(policy, "lyapunov", None), "warp", None)


def _draw_step(
    policy: StablePolicy,
    samples: Samples,
    config: TrainConfig,
    generator: torch.Generator,
    step: int = 0,
) -> _StepInputs:
    """Draws one step's random inputs from the fit's generator: the one place that does, in
    a fixed order (batch, noise, windows, shape states, warp draws), so a batched fit
    (:mod:`snds.batched`) draws exactly what :func:`fit` draws."""
    index = _batch(config.batch_size, len(samples.positions), generator, config.device)
    x, v = samples.positions, samples.velocities
    if index is not None:
        x, v = x[index], v[index]
    if config.position_noise:
        x = x + config.position_noise * torch.randn(x.shape, generator=generator).to(x)
    if config.noise_correction and config.correction_share:
        x, v = _corrected(x, v, samples, config, generator)
    inputs = _StepInputs(positions=x, velocities=v)
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
        inputs = replace(inputs, windows=(starts, targets, steps))
    param = next(policy.parameters())
    if step % config.penalty_every:
        return inputs
    if config.shape_weight and policy.stable:
        inputs = replace(inputs, shape_states=_uniform_states(x.shape[-1], generator, param))
    if config.warp_weight and _warp_of(policy) is not None and policy.stable:
        inputs = replace(inputs, warp_draws=_warp_draws(x.shape[-1], generator, param))
    return inputs


def _corrected(
    x: torch.Tensor,
    v: torch.Tensor,
    samples: Samples,
    config: TrainConfig,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor]:
    """A batch (B, n) with a share of its states moved off the data and their velocities
    corrected towards the nearest training sample (see ``TrainConfig.noise_correction``)."""
    chosen = torch.rand(len(x), generator=generator).to(x.device) < config.correction_share
    offsets = config.correction_noise * torch.randn(x.shape, generator=generator).to(x)
    moved = x[chosen] + offsets[chosen]
    nearest = samples.nearest(moved)
    anchor, velocity = samples.positions[nearest], samples.velocities[nearest]
    if config.correction_width:
        offset = samples.pull(moved, config.correction_width, velocity)
    else:
        offset = _across(moved - anchor, velocity)
    target = velocity - config.noise_correction * offset
    x, v = x.clone(), v.clone()
    x[chosen], v[chosen] = moved, target
    return x, v


def _across(offset: torch.Tensor, velocity: torch.Tensor) -> torch.Tensor:
    """The part of offsets (B, n) across the directions of travel (B, n); all of an offset
    where the velocity is 0."""
    speed = velocity.norm(dim=-1, keepdim=True)
    direction = velocity / torch.where(speed > 0, speed, 1.0)
    return offset - (offset * direction).sum(-1, keepdim=True) * direction


def _step_loss(policy: StablePolicy, config: TrainConfig, inputs: _StepInputs) -> torch.Tensor:
    """The loss of paper eq. (5) with the penalties, on one step's drawn inputs; no
    randomness of its own (so it can run under ``torch.func.vmap``)."""
    v = inputs.velocities
    terms = policy.field_terms(inputs.positions)
    pi, f = terms.field, terms.nominal
    loss = config.velocity_weight * velocity_loss(pi, v, config.velocity_shape)
    if config.align_weight and terms.grad is not None:
        loss = loss + config.align_weight * align_loss(terms.grad, v, config.align_cosine)
    if config.nominal_weight and f is not None:
        loss = loss + config.nominal_weight * velocity_loss(f, v, config.velocity_shape)
    if inputs.windows is not None:
        loss = loss + window_loss(policy.field, *inputs.windows)
    # The penalties come at every k-th step only, with k times their weight: the same expected
    # gradient at a fraction of the cost (each is a pass over V or its warp at random states).
    every = config.penalty_every
    if inputs.shape_states is not None:
        shape = _shape_penalty_at(policy, inputs.shape_states)
        loss = loss + every * config.shape_weight * shape
    if inputs.warp_draws is not None:
        warp = _warp_penalty_at(_warp_of(policy), *inputs.warp_draws)
        loss = loss + every * config.warp_weight * warp
    return loss


def _uniform_states(
    dim: int, generator: torch.Generator, like: torch.Tensor, count: int = 256
) -> torch.Tensor:
    """``count`` states uniform in [-2, 2]^n (model coordinates), dtype and device of ``like``."""
    return torch.rand(count, dim, generator=generator).to(like) * 4.0 - 2.0


def shape_penalty(
    policy: Policy, dim: int, generator: torch.Generator, count: int = 256
) -> torch.Tensor:
    r""":math:`\operatorname{Var}_x \log(V(x) / |x|^2)` at ``count`` random states, uniform in
    :math:`[-2, 2]^n` (model coordinates); 0 exactly when V is a multiple of :math:`|x|^2` there.

    Arguments:
        policy: A policy with a Lyapunov function.
        dim: The state dimension n.
        generator: Source of the random states (the training's, so runs stay reproducible).
        count: Number of states.
    """
    return _shape_penalty_at(
        policy, _uniform_states(dim, generator, next(policy.parameters()), count)
    )


def _shape_penalty_at(policy: Policy, x: torch.Tensor) -> torch.Tensor:
    """:func:`shape_penalty` at given states x, shape (count, n)."""
    ratio = policy.lyapunov(x) / (x * x).sum(-1)
    return torch.log(ratio).var()


def warp_penalty(
    warp: EuclideanizingFlow, dim: int, generator: torch.Generator, count: int = 256
) -> torch.Tensor:
    r"""An unbiased estimate of :math:`\operatorname{E}_x \|J_\phi(x) - I\|_F^2` over
    :math:`[-2, 2]^n` (model coordinates): :math:`\frac{1}{K} \sum_k |(J_\phi(x_k) - I)
    u_k|^2` at ``count`` uniform random states :math:`x_k` with one Gaussian probe
    :math:`u_k \sim N(0, I)` each (Hutchinson's estimator: :math:`\operatorname{E}_u |A u|^2
    = \|A\|_F^2`), so it costs one Jacobian-vector product, not n. It is 0 exactly when the
    warp is a translation there.

    A warp whose Jacobian strays far from the identity makes the projected field stiff: the
    correction :math:`a / |\nabla V|` is bounded by :math:`\rho |z| \|J_\phi^{-1}\|`, and
    bent sublevel sets shorten the Euler steps that still decrease V.

    Arguments:
        warp: The diffeomorphism inside V.
        dim: The state dimension n.
        generator: Source of the random states and probes (the training's, so runs stay
            reproducible).
        count: Number of states.
    """
    return _warp_penalty_at(warp, *_warp_draws(dim, generator, next(warp.parameters()), count))


def _warp_draws(
    dim: int, generator: torch.Generator, like: torch.Tensor, count: int = 256
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`warp_penalty`'s random inputs: states uniform in [-2, 2]^n and one Gaussian
    probe each, both (count, n)."""
    x = _uniform_states(dim, generator, like, count)
    return x, torch.randn(count, dim, generator=generator).to(like)


def _warp_penalty_at(
    warp: EuclideanizingFlow, x: torch.Tensor, probe: torch.Tensor
) -> torch.Tensor:
    """:func:`warp_penalty` at given states and probes, each (count, n)."""
    _, caches = warp.forward_with_caches(x)
    return ((warp.jvp(caches, probe) - probe) ** 2).sum(-1).mean()
