r"""Many fits at once: K policies of one architecture trained as one stacked model.

:func:`fit_many` gives what K calls of :func:`snds.train.fit` give (several seeds of one
motion, or several motions of one dimension), with one forward and one backward pass per step
for all K: each policy's parameters and buffers are stacked along a new leading axis and the
loss :func:`snds.train._step_loss` runs under :func:`torch.func.vmap`. Only the networks are
shared work; everything that makes a fit what it is stays per fit:

* its random inputs (mini-batches, position noise, the penalties' states), drawn by
  :func:`snds.train._draw_step` from its own generator seeded as :func:`~snds.train.fit`
  seeds it, in the same order, outside vmap;
* its Adam (the policy's own, stepped on the policy's own parameters), gradient clipping by
  its own norm, learning-rate schedule, restarts after a diverged step and early stop.

So a fit's weights and loss history equal a separate fit's up to the rounding of batched
against single matrix products, an ulp here and there, which training then amplifies as it
amplifies any rounding difference (a separate fit with its first layer scaled by 1 + 1 ulp
moves as far): in float64, 30 steps on small networks agree to 1e-9 (tests/test_batched.py);
in float32 the loss histories part by 1e-2 within about 10 steps at lr 1e-2, so long float32
fits are alike in distribution (the same data, noise and schedule), not in their digits.
"""

from __future__ import annotations

import copy
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace

import torch
from torch import Tensor, nn
from torch.func import functional_call, vmap
from tqdm.auto import tqdm

from snds.data.demonstrations import Demonstrations, Split
from snds.errors import ConfigError
from snds.losses import Samples
from snds.policy import Policy
from snds.train import (
    DTYPES,
    TrainConfig,
    TrainingError,
    TrainResult,
    _adam,
    _diverged,
    _draw_step,
    _restart,
    _State,
    _step,
    _step_loss,
    _StepInputs,
    clip_gradients,
    training_samples,
)

__all__ = ["fit_many"]


@dataclass(eq=False)
class _Fit:
    """One fit of a batch: what :func:`snds.train.fit` keeps in its locals."""

    index: int
    policy: Policy
    config: TrainConfig
    samples: Samples
    generator: torch.Generator
    optimizer: torch.optim.Adam
    state: _State
    parameters: list[torch.Tensor] = field(init=False)

    def __post_init__(self) -> None:
        # The same tensors for the whole fit: a restart reloads the state dict in place.
        self.parameters = list(self.policy.parameters())


def fit_many(
    policies: Sequence[Policy],
    demos: Sequence[Demonstrations],
    splits: Sequence[Split],
    configs: Sequence[TrainConfig],
    *,
    progress: bool = True,
) -> list[TrainResult]:
    """Fits K policies (in place) as one stacked model; the same as K calls of
    :func:`snds.train.fit`, up to rounding.

    The policies must share one class and one architecture (config and parameter shapes),
    the configs must be equal but for their seed, and the demonstrations may differ
    (other motions of the same dimension, other numbers of samples). Fits whose steps draw
    tensors of other shapes (a full batch of another size) are stacked in separate groups,
    one group after the other.

    A fit that diverges restarts from its last good state exactly as in :func:`fit`, while
    the others go on; one that stops early (``patience``) leaves the stack. Checkpoints are
    not written: a killed batch starts again.

    Arguments:
        policies: K policies to train; each is moved to its config's dtype and device.
        demos: The demonstrations of each fit, in user units.
        splits: Which samples of each fit train.
        configs: The optimisation settings of each fit, equal but for ``seed``.
        progress: Show a progress bar (only on a terminal).

    Returns:
        One result per fit, in order. ``seconds`` is the wall time of the fit's group up to
        the fit's end (shared by all of its group, not divided among them).

    Raises:
        ConfigError: If the lengths, architectures or settings do not match.
        TrainingError: If a fit's loss keeps diverging (the message names the fit).
    """
    count = len(policies)
    if not count or not len(demos) == len(splits) == len(configs) == count:
        raise ConfigError(
            f"need as many demonstrations, splits and configs as policies (at least one), got "
            f"{count} policies, {len(demos)} demonstrations, {len(splits)} splits and "
            f"{len(configs)} configs"
        )
    _check_stackable(policies, configs)
    fits = []
    for index, (policy, demo, split, config) in enumerate(zip(policies, demos, splits, configs)):
        # As fit sets itself up, so that each fit starts from what a separate one would.
        dtype = DTYPES[config.dtype]
        policy.to(device=config.device, dtype=dtype)
        samples = training_samples(demo, policy, split, config)
        policy.set_anchors(samples.positions)
        generator = torch.Generator().manual_seed(config.seed)
        state = _State(good=copy.deepcopy(policy.state_dict()))
        fits.append(_Fit(index, policy, config, samples, generator, _adam(policy, config), state))
    groups: dict[tuple, list[_Fit]] = {}
    for one in fits:
        groups.setdefault(_signature(one), []).append(one)
    for group in groups.values():
        _fit_group(group, progress=progress)
    return [one.state.result for one in fits]


def _check_stackable(policies: Sequence[Policy], configs: Sequence[TrainConfig]) -> None:
    """Raises a ConfigError unless the policies can share one stacked model."""
    if len({id(policy) for policy in policies}) != len(policies):
        raise ConfigError("a policy appears twice; each fit needs its own")
    settings = {replace(config, seed=0) for config in configs}
    if len(settings) > 1:
        first, other = sorted(settings, key=repr)[:2]
        differ = [f.name for f in fields(first) if getattr(first, f.name) != getattr(other, f.name)]
        raise ConfigError(f"the configs differ in {', '.join(differ)}; only the seed may differ")

    def layout(policy: Policy) -> tuple:
        tensors = [*policy.named_parameters(), *policy.named_buffers()]
        return type(policy), policy.config, tuple((k, tuple(v.shape)) for k, v in tensors)

    if len({layout(policy) for policy in policies}) > 1:
        raise ConfigError(
            "the policies differ in class, architecture or tensor shapes; only weights may differ"
        )


def _signature(one: _Fit) -> tuple:
    """The shapes of the tensors a fit's steps draw, from a copy of its generator."""
    probe = torch.Generator().manual_seed(0)
    probe.set_state(one.generator.get_state())
    inputs = _draw_step(one.policy, one.samples, one.config, probe, 0)
    return tuple(None if v is None else _shapes(v) for v in _fields(inputs).values())


def _shapes(value: Tensor | tuple[Tensor, ...]) -> tuple:
    return tuple(t.shape for t in value) if isinstance(value, tuple) else tuple(value.shape)


def _fields(inputs: _StepInputs) -> dict[str, Tensor | tuple[Tensor, ...] | None]:
    # A dict, not dataclasses.asdict (which deep-copies tensors), for vmap's pytrees.
    return {f.name: getattr(inputs, f.name) for f in fields(inputs)}


def _stack(draws: list[_StepInputs]) -> dict[str, Tensor | tuple[Tensor, ...]]:
    """The K fits' step inputs as one dict of tensors with a leading axis of K; the terms
    that are off (None) are left out, since vmap maps tensors only."""
    stacked: dict[str, Tensor | tuple[Tensor, ...]] = {}
    for name, first in _fields(draws[0]).items():
        values = [getattr(inputs, name) for inputs in draws]
        if first is None:
            continue
        if isinstance(first, tuple):
            stacked[name] = tuple(torch.stack(parts) for parts in zip(*values))
        else:
            stacked[name] = torch.stack(values)
    return stacked


class _Loss(nn.Module):
    """The step's loss of one fit as a module's forward, for :func:`functional_call`."""

    def __init__(self, policy: Policy, config: TrainConfig) -> None:
        super().__init__()
        self.policy = policy
        self.config = config

    def forward(self, inputs: dict) -> Tensor:
        return _step_loss(self.policy, self.config, _StepInputs(**inputs))


def _stacked(fits: list[_Fit], which: str) -> dict[str, Tensor]:
    """Each named parameter or buffer of the fits' policies stacked, (K, *shape)."""
    named = [dict(getattr(one.policy, f"named_{which}")()) for one in fits]
    return {f"policy.{name}": torch.stack([n[name] for n in named]) for name in named[0]}


def _fit_group(fits: list[_Fit], *, progress: bool) -> None:
    """Trains fits whose steps draw tensors of the same shapes as one stacked model."""
    config = fits[0].config
    # The shapes and code of the loss, without weights of its own: functional_call gives it
    # the stacked ones, and a meta copy cannot be used by mistake.
    template = _Loss(copy.deepcopy(fits[0].policy).to("meta"), config)

    def loss(tensors: dict[str, Tensor], inputs: dict) -> Tensor:
        return functional_call(template, tensors, (inputs,), strict=True)

    losses_of = vmap(loss)
    show = progress and sys.stderr.isatty()
    start = time.perf_counter()
    active, buffers = list(fits), _stacked(fits, "buffers")
    bar = tqdm(range(config.steps), disable=not show, desc=f"train x{len(fits)}", leave=False)
    for step in bar:
        inputs = []
        for one in active:
            one.state.step = step
            inputs.append(_draw_step(one.policy, one.samples, one.config, one.generator, step))
        losses = losses_of(_stacked(active, "parameters") | buffers, _stack(inputs))
        values = losses.detach().tolist()
        diverged = [_diverged(value, one.state) for value, one in zip(values, active)]
        healthy = [i for i, bad in enumerate(diverged) if not bad]
        for i in healthy:
            active[i].optimizer.zero_grad(set_to_none=True)
        if healthy:
            # The fits share no weights, so the sum's gradient is each fit's own; a diverged
            # fit is left out, as fit skips its backward pass.
            (losses if len(healthy) == len(active) else losses[healthy]).sum().backward()
        for i in healthy:
            norm = clip_gradients(active[i].parameters, config.grad_clip)
            # As in fit: a NaN gradient is a diverged step too.
            diverged[i] = not bool(torch.isfinite(norm))
        stopped = []
        for value, bad, one in zip(values, diverged, active):
            if bad:
                try:
                    one.optimizer = _restart(one.policy, one.state, config, value)
                except TrainingError as error:
                    message = f"fit {one.index} (seed {one.config.seed}): {error}"
                    raise TrainingError(message) from error
                continue
            _step(one.policy, one.optimizer, one.state, config, value)
            if config.patience and one.state.since_best >= config.patience:
                stopped.append(one)
                _finish(one, "plateau", start)
        if config.max_seconds is not None and time.perf_counter() - start > config.max_seconds:
            for one in active:
                if one not in stopped:
                    _finish(one, "time", start)
            break
        if stopped:
            active = [one for one in active if one not in stopped]
            if not active:
                break
            buffers = _stacked(active, "buffers")
        if step % 20 == 0:
            bar.set_postfix(loss=f"{min(one.state.smoothed for one in active):.2e}")
    bar.close()
    for one in fits:
        if not one.state.finished:
            _finish(one, "steps", start)


def _finish(one: _Fit, why: str, start: float) -> None:
    result = one.state.result
    result.stopped = why
    result.seconds = time.perf_counter() - start
    result.steps = len(result.history)
    one.state.finished = True
