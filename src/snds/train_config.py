"""The settings of a fit: one frozen :class:`TrainConfig`, saved beside the model."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch

from snds.errors import ConfigError
from snds.losses import VELOCITY_SHAPES

__all__ = ["DTYPES", "TrainConfig"]

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
        tracking_gain: A gain k per unit of model time that pulls a state back to where its
            demonstration was at the same phase (models with a phase in the state only). A
            share (``tracking_share``) of each batch's states is moved in position only (a
            pose's rotation and the phase kept), by Gaussian offsets :math:`\delta` of
            standard deviation ``tracking_noise``, and trained towards :math:`v_j - k \delta`,
            with :math:`v_j` the velocity of the sample the state was moved from. The phase
            names that sample alone, so the targets never contradict each other, and a rollout
            pushed off its path returns onto the rest of its demonstration instead of wandering
            from where it was pushed (0: off).
        tracking_noise: The standard deviation of those offsets (model coordinates).
        tracking_share: The share of each batch's states that is moved and tracked, in [0, 1].
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
        smooth_weight: Weight of :func:`snds.losses.smooth_penalty`, the squared second
            difference of the positions' part of the nominal field f over steps of length
            ``smooth_step`` at random states off the data (model coordinates): it damps the
            ripples of f's Fourier features where nothing else constrains f, and leaves fields
            that bend smoothly alone (0: off, the default; 3e-6 and why it is not the default
            in docs/design.md).
        smooth_step: The length h of those steps (model coordinates); ripples shorter than
            about 4h are damped most.
        smooth_radius: The penalty fades within about this distance of the training samples
            (model coordinates), where the demonstrations may ask for sharp turns.
        fit_lyapunov: Train V's parameters as well as the nominal field's (False: V stays as
            it is and only f learns, which skips V's parameters in the backward pass; the
            guarantee is structural and holds either way). A refinement keeps V
            (:class:`snds.refine.RefineConfig`).
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
    tracking_gain: float = 3.0
    tracking_noise: float = 0.05
    tracking_share: float = 0.2
    shape_weight: float = 0.0
    warp_weight: float = 0.001
    align_weight: float = 0.1
    align_cosine: float = 0.5
    smooth_weight: float = 0.0
    smooth_step: float = 0.1
    smooth_radius: float = 0.1
    penalty_every: int = 4
    fit_lyapunov: bool = True
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
        for name in ("correction_share", "tracking_share"):
            share = getattr(self, name)
            if not 0.0 <= share <= 1.0:
                raise ConfigError(f"{name} must be in [0, 1], got {share}")
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
            "tracking_gain",
            "tracking_noise",
            "shape_weight",
            "warp_weight",
            "align_weight",
            "smooth_weight",
        ):
            weight = getattr(self, name)
            if not (weight >= 0 and math.isfinite(weight)):
                raise ConfigError(f"{name} must be a number >= 0, got {weight}")
        for name in ("smooth_step", "smooth_radius"):
            value = getattr(self, name)
            if not (value > 0 and math.isfinite(value)):
                raise ConfigError(f"{name} must be a positive number, got {value}")
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
