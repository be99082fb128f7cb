"""One training step's inputs: its mini-batches and the penalties' random states.

:func:`draw_step` is the one place that draws from a fit's generator, in a fixed order, so a
batched fit (:mod:`snds.batched`) draws exactly what a single one (:func:`snds.train.fit`)
draws; the loss (:func:`snds.losses.step_loss`) then has no randomness of its own.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch

from snds.nn.flow import EuclideanizingFlow
from snds.policy import Policy

if TYPE_CHECKING:
    from snds.losses import Samples
    from snds.train import TrainConfig

__all__ = [
    "StepInputs",
    "across",
    "corrected_batch",
    "draw_step",
    "smooth_draws",
    "tracked_batch",
    "uniform_states",
    "warp_draws",
    "warp_of",
]


@dataclass(frozen=True)
class StepInputs:
    """What one step's loss is evaluated on: its mini-batches and the penalties' random
    states, drawn by :func:`draw_step` (model coordinates; None where the term is off).

    Attributes:
        positions: The velocity term's states, position noise added, shape (B, n).
        velocities: Their demonstrated velocities, shape (B, n).
        windows: The window term's starts (M, n), targets (M, Nw, n) and steps (M, Nw).
        shape_states: The shape penalty's states, shape (256, n).
        warp_draws: The warp penalty's random inputs (see :func:`warp_draws`).
        smooth_draws: The smoothness penalty's states and steps (see :func:`smooth_draws`).
    """

    positions: torch.Tensor
    velocities: torch.Tensor
    windows: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
    shape_states: torch.Tensor | None = None
    warp_draws: tuple[torch.Tensor, ...] | None = None
    smooth_draws: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None


def warp_of(policy: Policy) -> EuclideanizingFlow | None:
    """The diffeomorphism inside a policy's V, if it has one."""
    return getattr(getattr(policy, "lyapunov", None), "warp", None)


def _indices(size: int, total: int, generator: torch.Generator, device: str) -> torch.Tensor | None:
    if size == 0 or size >= total:
        return None
    return torch.randint(total, (size,), generator=generator).to(device)


def draw_step(
    policy: Policy,
    samples: Samples,
    config: TrainConfig,
    generator: torch.Generator,
    step: int = 0,
) -> StepInputs:
    """Draws one step's random inputs from the fit's generator: the one place that does, in
    a fixed order (batch, noise, windows, shape states, warp draws), so a batched fit
    (:mod:`snds.batched`) draws exactly what :func:`snds.train.fit` draws."""
    index = _indices(config.batch_size, len(samples.positions), generator, config.device)
    x, v = samples.positions, samples.velocities
    if index is not None:
        x, v = x[index], v[index]
    if config.position_noise:
        x = x + config.position_noise * torch.randn(x.shape, generator=generator).to(x)
    if config.noise_correction and config.correction_share:
        x, v = corrected_batch(x, v, samples, config, generator)
    if config.tracking_gain and config.tracking_share and samples.tracked:
        x, v = tracked_batch(x, v, samples.tracked, config, generator)
    inputs = StepInputs(positions=x, velocities=v)
    if config.window and len(samples.window_starts):
        index = _indices(
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
        inputs = replace(inputs, shape_states=uniform_states(x.shape[-1], generator, param))
    if config.warp_weight and warp_of(policy) is not None and policy.stable:
        inputs = replace(inputs, warp_draws=warp_draws(x.shape[-1], generator, param))
    if config.smooth_weight:
        p = policy.space.position_dim
        draws = smooth_draws(samples, p, generator, param, config.smooth_step, config.smooth_radius)
        inputs = replace(inputs, smooth_draws=draws)
    return inputs


def corrected_batch(
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
        offset = across(moved - anchor, velocity)
    target = velocity - config.noise_correction * offset
    x, v = x.clone(), v.clone()
    x[chosen], v[chosen] = moved, target
    return x, v


def tracked_batch(
    x: torch.Tensor,
    v: torch.Tensor,
    tracked: int,
    config: TrainConfig,
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor]:
    r"""A batch (B, n) with a share of its states moved in their first ``tracked``
    coordinates (the positions; the phase kept) and trained back towards where they were:
    :math:`(x + \delta, v - k \delta)` (see ``TrainConfig.tracking_gain``)."""
    chosen = torch.rand(len(x), generator=generator).to(x.device) < config.tracking_share
    offsets = config.tracking_noise * torch.randn(x.shape, generator=generator).to(x)
    offsets[:, tracked:] = 0.0
    offsets[~chosen] = 0.0
    return x + offsets, v - config.tracking_gain * offsets


def across(offset: torch.Tensor, velocity: torch.Tensor) -> torch.Tensor:
    """The part of offsets (B, n) across the directions of travel (B, n); all of an offset
    where the velocity is 0."""
    speed = velocity.norm(dim=-1, keepdim=True)
    direction = velocity / torch.where(speed > 0, speed, 1.0)
    return offset - (offset * direction).sum(-1, keepdim=True) * direction


def uniform_states(
    dim: int, generator: torch.Generator, like: torch.Tensor, count: int = 256
) -> torch.Tensor:
    """``count`` states uniform in [-2, 2]^n (model coordinates), dtype and device of ``like``."""
    return torch.rand(count, dim, generator=generator).to(like) * 4.0 - 2.0


def warp_draws(
    dim: int, generator: torch.Generator, like: torch.Tensor, count: int = 256
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`snds.losses.warp_penalty`'s random inputs: states uniform in [-2, 2]^n and one
    Gaussian probe each, both (count, n)."""
    x = uniform_states(dim, generator, like, count)
    return x, torch.randn(count, dim, generator=generator).to(like)


def smooth_draws(
    samples: Samples,
    position_dim: int,
    generator: torch.Generator,
    like: torch.Tensor,
    step: float,
    radius: float,
    count: int = 256,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    r""":func:`snds.losses.smooth_penalty`'s random inputs: states (count, n), one step each
    of length ``step`` in a uniformly random direction of the positions (count, n; 0 in the
    other coordinates), and each state's weight :math:`1 - \exp(-d^2 / (2 r^2))` (count,),
    with d its distance from the nearest training sample and r ``radius``, so that the penalty
    leaves the fit on the data alone.

    The positions (the first ``position_dim`` coordinates) are uniform in [-2, 2]. The other
    coordinates, if any (a phase, a pose's rotation), are a random training sample's for half
    of the states and 0 for the other half: the slices a rollout visits
    (:func:`snds.phase.start_state` gives a start beside the data its nearest sample's phase,
    and one away from them phase 0), which uniform states of the whole box would almost never
    reach.
    """
    n = samples.positions.shape[-1]
    x = uniform_states(position_dim, generator, like, count)
    if n > position_dim:
        index = torch.randint(len(samples.positions), (count,), generator=generator)
        rest = samples.positions[index.to(samples.positions.device), position_dim:].clone()
        rest[count // 2 :] = 0.0
        x = torch.cat([x, rest.to(x)], dim=-1)
    direction = torch.randn(count, position_dim, generator=generator).to(like)
    e = torch.zeros_like(x)
    e[:, :position_dim] = step * direction / direction.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    gap = x - samples.positions[samples.nearest(x)].to(x)
    weight = 1.0 - torch.exp(-(gap * gap).sum(-1) / (2 * radius**2))
    return x, e, weight
