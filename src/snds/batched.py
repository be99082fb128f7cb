r"""Many fits at once: K policies of one architecture trained as one stacked model.

:func:`fit_many` gives what K calls of :func:`snds.train.fit` give (several seeds of one
motion, or several motions of one dimension), with one forward and one backward pass per step
for all K: each policy's parameters and buffers are stacked along a new leading axis and the
loss :func:`snds.losses.step_loss` runs under :func:`torch.func.vmap`. Only the networks are
shared work; everything that makes a fit what it is stays per fit:

* its random inputs (mini-batches, position noise, the penalties' states), drawn by
  :func:`snds.batches.draw_step` from its own generator seeded as :func:`~snds.train.fit`
  seeds it, in the same order, outside vmap;
* its Adam (the policy's own, stepped on the policy's own parameters), gradient clipping by
  its own norm, learning-rate schedule, restarts after a diverged step and early stop: the
  loop is :func:`snds.train.train_loop`, the one :func:`~snds.train.fit` runs, with the
  stacked losses of this module in place of one policy's.

So a fit's weights and loss history equal a separate fit's up to the rounding of batched
against single matrix products, an ulp here and there, which training then amplifies as it
amplifies any rounding difference (a separate fit with its first layer scaled by 1 + 1 ulp
moves as far): in float64, 30 steps on small networks agree to 1e-9 (tests/test_batched.py);
in float32 the loss histories part by 1e-2 within about 10 steps at lr 1e-2, so long float32
fits are alike in distribution (the same data, noise and schedule), not in their digits.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import fields, replace

import torch
from torch import Tensor, nn
from torch.func import functional_call, vmap

from snds.batches import StepInputs, draw_step
from snds.callbacks import Callback, ProgressBar
from snds.data.demonstrations import Demonstrations, Split
from snds.errors import ConfigError
from snds.losses import step_loss
from snds.parallel import torch_threads
from snds.policy import Policy
from snds.threads import fastest_threads
from snds.train import Fit, TrainConfig, TrainResult, prepare_fit, train_loop

__all__ = ["StackedLosses", "fit_many"]


def fit_many(
    policies: Sequence[Policy],
    demos: Sequence[Demonstrations],
    splits: Sequence[Split],
    configs: Sequence[TrainConfig],
    *,
    callbacks: Sequence[Callback] = (),
    progress: bool = True,
    threads: int | None = None,
) -> list[TrainResult]:
    """Fits K policies (in place) as one stacked model; the same as K calls of
    :func:`snds.train.fit`, up to rounding.

    The policies must share one class and one architecture (config and parameter shapes),
    the configs must be equal but for their seed, and the demonstrations may differ
    (other motions of the same dimension, other numbers of samples). Fits whose steps draw
    tensors of other shapes (a full batch of another size) are stacked in separate groups,
    one group after the other.

    A fit that diverges restarts from its last good state exactly as in :func:`fit`, while
    the others go on; one that stops early (``patience``, or a callback) leaves the stack.
    Checkpoints are not written: a killed batch starts again.

    Arguments:
        policies: K policies to train; each is moved to its config's dtype and device.
        demos: The demonstrations of each fit, in user units.
        splits: Which samples of each fit train.
        configs: The optimisation settings of each fit, equal but for ``seed``.
        callbacks: Hooks (:class:`snds.callbacks.Callback`); each event's ``fit`` is the
            fit's position in ``policies``.
        progress: Show a progress bar (only on a terminal).
        threads: Torch CPU threads, restored after (None: :func:`snds.threads.fastest_threads`).

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
    fits = [
        prepare_fit(
            policy, demo, split, config, index=index, label=f"fit {index} (seed {config.seed})"
        )
        for index, (policy, demo, split, config) in enumerate(zip(policies, demos, splits, configs))
    ]
    groups: dict[tuple, list[Fit]] = {}
    for one in fits:
        groups.setdefault(_signature(one), []).append(one)
    with torch_threads(fastest_threads(configs[0]) if threads is None else threads):
        for group in groups.values():
            shown = [ProgressBar(configs[0].steps, desc=f"train x{len(group)}")] if progress else []
            train_loop(group, StackedLosses(group), callbacks=[*shown, *callbacks])
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


def _signature(one: Fit) -> tuple:
    """The shapes of the tensors a fit's steps draw, from a copy of its generator."""
    probe = torch.Generator().manual_seed(0)
    probe.set_state(one.generator.get_state())
    inputs = draw_step(one.policy, one.samples, one.config, probe, 0)
    return tuple(None if v is None else _shapes(v) for v in _fields(inputs).values())


def _shapes(value: Tensor | tuple[Tensor, ...]) -> tuple:
    return tuple(t.shape for t in value) if isinstance(value, tuple) else tuple(value.shape)


def _fields(inputs: StepInputs) -> dict[str, Tensor | tuple[Tensor, ...] | None]:
    # A dict, not dataclasses.asdict (which deep-copies tensors), for vmap's pytrees.
    return {f.name: getattr(inputs, f.name) for f in fields(inputs)}


def _stack(draws: list[StepInputs]) -> dict[str, Tensor | tuple[Tensor, ...]]:
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
        return step_loss(self.policy, self.config, StepInputs(**inputs))


def _stacked(fits: list[Fit], which: str) -> dict[str, Tensor]:
    """Each named parameter or buffer of the fits' policies stacked, (K, *shape)."""
    named = [dict(getattr(one.policy, f"named_{which}")()) for one in fits]
    return {f"policy.{name}": torch.stack([n[name] for n in named]) for name in named[0]}


class StackedLosses:
    """The losses of a group's active fits (:data:`snds.train.Losses`) from one stacked model:
    their parameters and buffers stacked along a new leading axis, and the loss of one fit
    run under :func:`torch.func.vmap`.

    Arguments:
        fits: The group; every fit's policy has one architecture.
    """

    def __init__(self, fits: list[Fit]) -> None:
        # The shapes and code of the loss, without weights of its own: functional_call gives
        # it the stacked ones, and a meta copy cannot be used by mistake.
        template = _Loss(copy.deepcopy(fits[0].policy).to("meta"), fits[0].config)

        def loss(tensors: dict[str, Tensor], inputs: dict) -> Tensor:
            return functional_call(template, tensors, (inputs,), strict=True)

        self.losses_of = vmap(loss)
        self.active: list[int] = []
        self.buffers: dict[str, Tensor] = {}

    def __call__(self, active: list[Fit], inputs: list[StepInputs]) -> Tensor:
        ids = [id(one) for one in active]
        if ids != self.active:  # a fit stopped early: the stack shrinks
            self.active, self.buffers = ids, _stacked(active, "buffers")
        return self.losses_of(_stacked(active, "parameters") | self.buffers, _stack(inputs))
