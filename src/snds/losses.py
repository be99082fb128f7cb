r"""The imitation loss: velocity matching plus a short multi-step Euler window (paper eq. 5),
the alignment of V's descent with the direction of travel, and the penalties on V's shape
and warp, assembled into one step's loss by :func:`step_loss`."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from snds.batches import StepInputs, smooth_draws, uniform_states, warp_draws, warp_of
from snds.data.demonstrations import Demonstrations, Normalization, Split
from snds.errors import DataError
from snds.nn.flow import EuclideanizingFlow
from snds.policy import Policy

if TYPE_CHECKING:
    from snds.train import TrainConfig

__all__ = [
    "AT_TARGET",
    "NEAREST_REFERENCES",
    "PULL_REFERENCES",
    "VELOCITY_SHAPES",
    "Samples",
    "align_loss",
    "make_samples",
    "shape_penalty",
    "smooth_penalty",
    "smooth_penalty_at",
    "shape_penalty_at",
    "srvf",
    "step_loss",
    "velocity_loss",
    "warp_penalty",
    "warp_penalty_at",
    "window_loss",
]


@dataclass(frozen=True)
class Samples:
    """Training samples in model coordinates, as tensors.

    Attributes:
        positions: States x_s, shape (N, n).
        velocities: Demonstrated velocities at x_s, shape (N, n).
        window_starts: States x_s that start a window of training samples, shape (M, n).
        window_targets: The demonstrated x_{s+1}, ..., x_{s+Nw}, shape (M, Nw, n).
        window_steps: The demonstration's own time steps, shape (M, Nw).
        tracked: The leading state coordinates that tracking moves (``TrainConfig.
            tracking_gain``): the positions where a phase is in the state (not a pose's
            rotation), 0 without a phase.
    """

    positions: Tensor
    velocities: Tensor
    window_starts: Tensor
    window_targets: Tensor
    window_steps: Tensor
    tracked: int = 0

    def off_target(self, *, positions: bool = True) -> Samples:
        r"""The same samples without the states at the target (within :data:`AT_TARGET` of
        model coordinates 0): the window starts there, and with ``positions`` the velocity
        samples there too.

        At the target :math:`\pi = 0` for any weights, so such a state adds nothing to the
        loss, but its gradient is a 0/0: the projection divides by
        :math:`\|\nabla V\|^2`, which is 0 up to rounding there, and its derivative
        overflows float32. A velocity sample that position noise moves off the target is kept
        (``positions=False``): there it does carry information.
        """
        keep = self.window_starts.norm(dim=-1) > AT_TARGET
        at = self.positions.norm(dim=-1) > AT_TARGET if positions else slice(None)
        return Samples(
            positions=self.positions[at],
            velocities=self.velocities[at],
            window_starts=self.window_starts[keep],
            window_targets=self.window_targets[keep],
            window_steps=self.window_steps[keep],
            tracked=self.tracked,
        )

    def to(self, dtype: torch.dtype, device: torch.device | str = "cpu") -> Samples:
        """The same samples with another dtype / device."""
        moved = {name: t.to(device=device, dtype=dtype) for name, t in self.tensors().items()}
        return Samples(**moved, tracked=self.tracked)

    def tensors(self) -> dict[str, Tensor]:
        """The sample tensors by field name (every field but ``tracked``)."""
        return {
            field.name: getattr(self, field.name)
            for field in dataclasses.fields(self)
            if field.name != "tracked"
        }

    def nearest(self, states: Tensor) -> Tensor:
        """The index of the training sample nearest to each state (B, n), shape (B,).

        The search runs over at most :data:`NEAREST_REFERENCES` samples, evenly spaced in
        the samples' order (all of them when there are fewer), through a k-d tree built on
        the first call: a query costs O(B log N), not O(B N). Euclidean distance in model
        coordinates; the tree lives on the CPU, so states on another device are copied.
        """
        tree, stride = self._reference_tree
        query = states.detach().to(device="cpu", dtype=torch.float64).numpy()
        _, index = tree.query(query, k=1)
        return torch.as_tensor(index * stride, device=states.device)

    def pull(self, states: Tensor, width: float, heading: Tensor) -> Tensor:
        r"""The offsets of states (B, n) from the demonstrated paths that travel their way,
        across the direction of travel and averaged over the nearby training samples, shape
        (B, n):

        .. math:: p(\tilde x) = \sum_j w_j \, (\tilde x - x_j)_{\perp v_j},
            \qquad w_j \propto \exp\big(-\|\tilde x - x_j\|^2 / (2 \sigma^2)\big)
            \max(\cos(h, v_j), 10^{-6}),

        with :math:`\perp v_j` the part across :math:`v_j` (all of it where :math:`v_j = 0`),
        :math:`\sigma` = ``width`` and h the state's ``heading``. Where demonstrations run
        side by side closer than a few :math:`\sigma` the pull is towards their weighted
        middle, not onto whichever one is nearest; where they cross, the paths heading
        elsewhere hardly count; far from the others it is the offset from the nearest path.

        Over at most :data:`PULL_REFERENCES` training samples, evenly spaced in the samples'
        order (their spacing along a path stays well under a sigma of a few hundredths), in
        closed form: with :math:`u_j = v_j / |v_j|`,
        :math:`p = \tilde x - \sum_j w_j x_j - (\sum_j w_j u_j u_j^\top) \tilde x
        + \sum_j w_j (x_j \cdot u_j) u_j`, one matrix product of the weights, O(B N n^2).

        Arguments:
            states: The moved states, shape (B, n).
            width: sigma > 0, in the samples' coordinates.
            heading: Each state's direction of travel, shape (B, n) (any length; a zero
                heading weighs every direction alike).
        """
        positions, directions, moments = (t.to(states) for t in self._pull_references)
        # -|x - x_j|^2 / (2 sigma^2) up to -|x|^2 / (2 sigma^2), which the normalisation
        # cancels, plus the log of the direction factor; exponents below -50 are clamped so
        # that no weight is a (slow) denormal.
        scale = 1.0 / width**2
        bias = (-0.5 * scale) * positions.square().sum(-1)
        logits = torch.addmm(bias, states, positions.T, alpha=scale)
        length = heading.norm(dim=-1, keepdim=True)
        cosines = (heading / torch.where(length > 0, length, 1.0)) @ directions.T
        logits = logits + cosines.clamp_min(1e-6).log()
        weights = (logits - logits.amax(-1, keepdim=True)).clamp_min_(-50.0).exp_()
        weights = weights / weights.sum(-1, keepdim=True)  # (B, N)
        n = states.shape[-1]
        # One product for sum_j w_j x_j, sum_j w_j u_j u_j^T and sum_j w_j (x_j . u_j) u_j.
        mean, spread, along = (weights @ moments).split([n, n * n, n], dim=-1)
        return states - mean - (spread.view(-1, n, n) @ states.unsqueeze(-1)).squeeze(-1) + along

    @functools.cached_property
    def _pull_references(self) -> tuple[Tensor, Tensor, Tensor]:
        """The reference samples of :meth:`pull`: positions x_j (N, n), unit directions of
        travel u_j (N, n; 0 where the velocity is 0), and [x_j, u_j u_j^T flattened,
        (x_j . u_j) u_j], shape (N, n + n^2 + n)."""
        stride = max(1, -(-len(self.positions) // PULL_REFERENCES))
        positions = self.positions[::stride].detach().contiguous()
        velocities = self.velocities[::stride].detach()
        speed = velocities.norm(dim=-1, keepdim=True)
        u = velocities / torch.where(speed > 0, speed, 1.0)
        outer = (u.unsqueeze(-1) * u.unsqueeze(-2)).flatten(1)
        along = (positions * u).sum(-1, keepdim=True) * u
        return positions, u, torch.cat([positions, outer, along], dim=-1)

    @functools.cached_property
    def _reference_tree(self) -> tuple[cKDTree, int]:
        stride = max(1, -(-len(self.positions) // NEAREST_REFERENCES))
        references = self.positions[::stride].detach().to(device="cpu", dtype=torch.float64)
        return cKDTree(references.numpy()), stride


#: States closer than this to the target (model coordinates, where the data span about 1) are
#: the target as float32 resolves it: within a few units of its rounding of a unit length.
AT_TARGET = 1e-6

#: The most training samples :meth:`Samples.nearest` searches (evenly spaced in the samples'
#: order), so the cost of building its tree does not grow with the data.
NEAREST_REFERENCES = 8192
#: The most training samples :meth:`Samples.pull` averages over (evenly spaced in the samples'
#: order): its cost grows with their number, once per training step.
PULL_REFERENCES = 1024


def make_samples(
    demos: Demonstrations,
    normalization: Normalization,
    split: Split,
    *,
    window: int,
    tracked: int = 0,
) -> Samples:
    """Collects the training samples and the multi-step windows that lie wholly in training.

    A window starting at s is used only if s, ..., s + Nw are all training samples, so no
    test sample leaks into training through a window's targets.

    Arguments:
        demos: The demonstrations (user units).
        normalization: Their affine map to model coordinates.
        split: Which samples are for training.
        window: Nw >= 0, the number of Euler steps in a window.
        tracked: :attr:`Samples.tracked`, the leading state coordinates that tracking moves.
    """
    xs, vs, starts, targets, steps = [], [], [], [], []
    for demo, mask in zip(demos, split.train):
        x = normalization.positions_to_model(demo.positions)
        v = normalization.velocities_to_model(demo.velocities)
        t = demo.times / normalization.time
        xs.append(x[mask])
        vs.append(v[mask])
        length = len(x)
        if window == 0 or length <= window:
            continue
        index = np.arange(length - window)
        offsets = np.arange(window + 1)
        ok = mask[index[:, None] + offsets].all(axis=1)
        index = index[ok]
        starts.append(x[index])
        targets.append(x[index[:, None] + offsets[1:]])
        steps.append(t[index[:, None] + offsets[1:]] - t[index[:, None] + offsets[:-1]])
    positions = np.concatenate(xs)
    if len(positions) == 0:
        raise DataError("no training samples left after the split")
    n = demos.dim
    as_tensor = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
    return Samples(
        positions=as_tensor(positions),
        velocities=as_tensor(np.concatenate(vs)),
        window_starts=as_tensor(np.concatenate(starts) if starts else np.zeros((0, n))),
        window_targets=as_tensor(np.concatenate(targets) if targets else np.zeros((0, window, n))),
        window_steps=as_tensor(np.concatenate(steps) if steps else np.zeros((0, window))),
        tracked=tracked,
    )


def srvf(v: Tensor, eps: float = 1e-3) -> Tensor:
    r"""The square-root velocity function :math:`q(v) = v / \sqrt{\|v\| + \epsilon}`."""
    return v / torch.sqrt(v.norm(dim=-1, keepdim=True) + eps)


#: Velocity shapings applied to both prediction and label before the squared error.
VELOCITY_SHAPES: dict[str, Callable[[Tensor], Tensor]] = {"mse": lambda v: v, "srvf": srvf}


def velocity_loss(pred: Tensor, true: Tensor, shape: str = "mse") -> Tensor:
    r""":math:`\mathbb{E} \|q(\pi(x_s)) - q(\dot x_s)\|^2` over samples (*, n)."""
    q = VELOCITY_SHAPES[shape]
    return ((q(pred) - q(true)) ** 2).sum(-1).mean()


def window_loss(
    field: Callable[[Tensor], Tensor], starts: Tensor, targets: Tensor, steps: Tensor
) -> Tensor:
    r"""Multi-step Euler window: :math:`\sum_i 2^{-i} \mathbb{E}\|\hat x_{s+i} - x_{s+i}\|^2`.

    :math:`\hat x` is the Euler rollout of the policy from the demonstrated :math:`x_s` with
    the demonstration's own steps. Each error is divided by the elapsed time squared, making
    it a mean-velocity error of the same scale as the velocity term; without that, the
    position errors of a 1 ms step are a million times smaller than the velocity term and the
    window has no effect.

    Arguments:
        field: The policy in model coordinates, (*, n) -> (*, n).
        starts: Window starts x_s, shape (M, n).
        targets: Demonstrated x_{s+1..s+Nw}, shape (M, Nw, n).
        steps: The time steps, shape (M, Nw).
    """
    x = starts
    elapsed = torch.zeros_like(steps[:, 0])
    total = starts.new_zeros(())
    for i in range(targets.shape[1]):
        x = x + steps[:, i : i + 1] * field(x)
        elapsed = elapsed + steps[:, i]
        error = ((x - targets[:, i]) ** 2).sum(-1) / elapsed**2
        total = total + 2.0 ** -(i + 1) * error.mean()
    return total


def align_loss(grad: Tensor, velocity: Tensor, cosine: float) -> Tensor:
    r"""Speed-weighted hinge on V's descent direction against the direction of travel:
    :math:`\mathbb{E}\, w_s (c - \cos(-\nabla V(x_s), \dot x_s))_+` with
    :math:`w_s = |\dot x_s| / \max |\dot x|` over the batch.

    Where the demonstrations travel down V within the angle :math:`\arccos c`, the decrease
    margin that the projection enforces pushes a state along the demonstrated path, not
    across it, and a slow (resting) stretch of a demonstration neither drifts nor stalls.

    Arguments:
        grad: :math:`\nabla V` at the samples, shape (B, n).
        velocity: The demonstrated velocities, shape (B, n).
        cosine: c in [-1, 1].
    """
    speed = velocity.norm(dim=-1)
    # Through squared norms, clamped: grad V is 0 at the target, where a norm's derivative
    # would be 0 / 0.
    squared = ((grad * grad).sum(-1) * speed**2).clamp_min(1e-24)
    cos = -(grad * velocity).sum(-1) / torch.sqrt(squared)
    weight = speed / speed.max().clamp_min(1e-12)
    return (weight * torch.relu(cosine - cos)).mean()


def step_loss(policy: Policy, config: TrainConfig, inputs: StepInputs) -> torch.Tensor:
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
        shape = shape_penalty_at(policy, inputs.shape_states)
        loss = loss + every * config.shape_weight * shape
    if inputs.warp_draws is not None:
        warp = warp_penalty_at(warp_of(policy), *inputs.warp_draws)
        loss = loss + every * config.warp_weight * warp
    if inputs.smooth_draws is not None:
        smooth = smooth_penalty_at(policy, *inputs.smooth_draws)
        loss = loss + every * config.smooth_weight * smooth
    return loss


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
    return shape_penalty_at(
        policy, uniform_states(dim, generator, next(policy.parameters()), count)
    )


def shape_penalty_at(policy: Policy, x: torch.Tensor) -> torch.Tensor:
    """:func:`shape_penalty` at given states x, shape (count, n)."""
    ratio = policy.lyapunov(x) / (x * x).sum(-1)
    return torch.log(ratio).var()


def smooth_penalty(
    policy: Policy,
    samples: Samples,
    generator: torch.Generator,
    step: float,
    radius: float,
    count: int = 256,
) -> torch.Tensor:
    r""":math:`\operatorname{E}\, w(x) |f_p(x + e) - 2 f_p(x) + f_p(x - e)|^2 / h^4` over random
    states x off the data (:func:`snds.batches.smooth_draws`, model coordinates) and steps e of
    length h in a uniformly random direction of the positions: the squared second difference
    of the positions' part :math:`f_p` of the nominal field, an estimate of its mean squared
    curvature (:math:`|D^2 f_p(x)[e, e]|^2 / h^4`) for ripples longer than h. A phase and a
    pose's rotation are left alone: the streamlines are the positions'.

    It is 0 for a field that is affine along every such step, is hardly changed by one that
    bends over the demonstrations' scale, and is large for the short waves random Fourier
    features leave where no data constrain f: what shows as wavy streamlines and rollouts
    from new starts. The guarantee does not depend on it.

    Arguments:
        policy: The policy (its :meth:`~snds.policy.Policy.nominal` field).
        samples: The training samples (the phase of states in a phased space).
        generator: Source of the random states and steps (the training's).
        step: h, model coordinates.
        radius: r of the weight :math:`w(x) = 1 - \exp(-d(x)^2 / (2 r^2))`, d(x) the
            distance from x to the nearest training sample: the penalty fades on the data,
            where the demonstrations may ask for sharp turns.
        count: Number of states.
    """
    p = policy.space.position_dim
    draws = smooth_draws(samples, p, generator, next(policy.parameters()), step, radius, count)
    return smooth_penalty_at(policy, *draws)


def smooth_penalty_at(
    policy: Policy, x: torch.Tensor, e: torch.Tensor, weight: torch.Tensor
) -> torch.Tensor:
    """:func:`smooth_penalty` at given states x and steps e, each (count, n), with weights
    (count,)."""
    f = policy.nominal(torch.cat([x - e, x, x + e]))[:, : policy.space.position_dim]
    below, at, above = f.chunk(3)
    h2 = (e * e).sum(-1)
    return (weight * ((above - 2 * at + below) ** 2).sum(-1) / (h2 * h2)).mean()


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
    return warp_penalty_at(warp, *warp_draws(dim, generator, next(warp.parameters()), count))


def warp_penalty_at(warp: EuclideanizingFlow, x: torch.Tensor, probe: torch.Tensor) -> torch.Tensor:
    """:func:`warp_penalty` at given states and probes, each (count, n)."""
    _, caches = warp.forward_with_caches(x)
    return ((warp.jvp(caches, probe) - probe) ** 2).sum(-1).mean()
