r"""What an export traces and what its inputs are: the module, its signature, its states.

:class:`Exported` is the module that :mod:`snds.export.writers` traces (the fused graph of
:mod:`snds.export.fused` where it applies, else the library's own ``forward``); a policy's
:class:`Signature` says what that graph takes and returns, asked of the policy's space, and
draws the random states (:func:`random_states`) on which :mod:`snds.export.comparison`
checks an export against the library.
"""

from __future__ import annotations

import copy
import json

import numpy as np
import torch

from snds.errors import ExportError
from snds.export.fused import FusedStable, fusable, fused_nominal
from snds.policy import Policy, StablePolicy, project

__all__ = [
    "NUMPY_DTYPES",
    "STATE_RADII",
    "Exported",
    "Signature",
    "check_dtype",
    "policy_copy",
    "random_states",
    "signature",
    "top_speed",
    "trace",
]

#: Spread of the random states of :func:`random_states`, in units of the demonstrations'
#: extent: from near the data out to 1000x.
STATE_RADII = (1.0, 3.0, 10.0, 100.0, 1000.0)
#: The precisions an export is made in, and their NumPy types.
NUMPY_DTYPES = {torch.float32: np.float32, torch.float64: np.float64}


class Exported(torch.nn.Module):
    """The traced module: the policy's ``forward``, in a fixed precision and in eval mode.

    A policy that :class:`~snds.export.fused.FusedStable` computes (the default SNDS policy)
    is traced as that fused graph. For another SNDS policy, f(0), which the library
    evaluates with every batch, is computed once here; the rest is the library's own code.
    g(0) and grad g(0) are not folded: the Bregman difference g(x) - g(0) - grad g(0).x
    cancels O(1) numbers next to the target, and only evaluating g(0) with the same kernels
    as g(x) (the target row in the ICNN's batch, as the library does) keeps the rounding
    errors of the two correlated there. Folded, a float32 export differed from the float32
    library by 2.4e-4 of the top speed next to the target; in the graph, 8e-5.
    :func:`snds.export.verify` compares the export with the library's ``forward``, so a
    change to :meth:`StablePolicy.field` that this misses fails every export.
    """

    def __init__(self, policy: Policy, dtype: torch.dtype) -> None:
        super().__init__()
        self.fused = None
        if fusable(policy):
            self.fused = FusedStable(policy_copy(policy, torch.float64), dtype)
            return
        self.policy = policy_copy(policy, dtype)
        self.folded = type(self.policy) is StablePolicy
        if self.folded:
            with torch.no_grad():
                self.nominal = fused_nominal(self.policy)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.fused is not None:
            return self.fused(x)
        policy = self.policy
        if not self.folded:
            return policy(x)
        z = policy.to_model(x)
        field = self.nominal(z)
        if policy.stable:
            v, grad_v = policy.lyapunov.value_and_grad(z)
            field = project(field, grad_v, policy.decay(v, z), rectifier=policy.config.rectifier)
        return field * (policy.length / policy.time)


def policy_copy(policy: Policy, dtype: torch.dtype) -> Policy:
    """A copy of a policy on the CPU, in ``dtype`` and eval mode; the original is unchanged."""
    return copy.deepcopy(policy).to(device="cpu", dtype=dtype).eval()


def check_dtype(dtype: torch.dtype) -> None:
    """Refuses a precision other than float32 and float64 (:class:`~snds.errors.ExportError`)."""
    if dtype not in NUMPY_DTYPES:
        raise ExportError(f"export is float32 or float64, not {dtype}")


class Signature:
    r"""What the exported graph of a policy computes, asked of its space: states
    (B, space.dim) to velocities (B, space.tangent_dim), user units (a pose policy: poses
    (B, 7) to twists (B, 6)); and the random states that check it.

    A velocity's components are compared in the units of the policy's chart (divided by
    :meth:`~snds.policy.Policy.chart_scales`, one per block: 1 for positions, :math:`L_p`
    and :math:`L_r` for a twist), where the top speed of the normalisation is the floor.

    Arguments:
        policy: The policy.
    """

    def __init__(self, policy: Policy) -> None:
        self.policy = policy
        self.space = policy.space
        #: Width of an input row.
        self.inputs = self.space.dim
        #: The name of the ONNX output: "twist" for a pose (linear and angular velocity),
        #: "velocity" otherwise (a phase model's velocity ends with the phase rate).
        self.output_name = (
            "twist" if "angular_velocity" in self.space.velocity_names else "velocity"
        )
        #: What the graph maps to what, in words.
        self.description = (
            f"(B, {self.space.dim}) {self.space.state_text} -> "
            f"(B, {self.space.tangent_dim}) {self.space.velocity_text}"
        )

    def module(self, dtype: torch.dtype) -> torch.nn.Module:
        """The module to trace, in ``dtype``."""
        return Exported(self.policy, dtype)

    def library(self, x: torch.Tensor) -> torch.Tensor:
        """What the library computes at inputs (B, inputs), in their dtype."""
        return policy_copy(self.policy, x.dtype)(x)

    def random_inputs(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """States (count, space.dim): equal shares with positions uniform in the boxes of
        :data:`STATE_RADII` extents around the target (half-widths), in the order of the
        radii over and over; orientations (poses) uniform on SO(3)."""
        states = np.empty((count, self.inputs))
        extent = float(self.policy.extents()[0])
        for i, radius in enumerate(STATE_RADII):
            rows = slice(i, None, len(STATE_RADII))
            share = len(range(count)[rows])
            states[rows] = self.space.uniform(self.policy.target, radius * extent, share, rng)
        return states

    def extents(self, x: np.ndarray) -> np.ndarray:
        """Each input's largest position offset from the target, in extents, shape (B,)."""
        space, policy = self.space, self.policy
        offset = np.abs(space.positions(x) - space.positions(policy.target)).max(axis=-1)
        return offset / float(policy.extents()[0])

    def output_scale(self) -> np.ndarray:
        """Divisors (outputs,) of the outputs before they are compared with the top speed."""
        blocks = self.policy.chart_scales()[list(self.space.velocity_units)]
        return np.repeat(blocks, self.space.velocity_sizes)

    def metadata(self) -> dict[str, str]:
        """The ONNX file's metadata: what goes in and out, the target, the extents and top
        speeds of each component."""
        space, policy = self.space, self.policy
        speeds = top_speed(policy) * policy.chart_scales()[list(space.velocity_units)]
        return {
            "snds.dim": str(space.tangent_dim),
            "snds.input": space.state_text,
            "snds.output": space.velocity_text,
            "snds.target": json.dumps([float(c) for c in policy.target]),
            **{
                _EXTENT_KEYS[name]: repr(float(value))
                for name, value in zip(space.error_names, policy.extents(), strict=True)
            },
            **{
                _SPEED_KEYS[name]: repr(float(value))
                for name, value in zip(space.velocity_names, speeds, strict=True)
            },
        }


#: The metadata key of each error component's extent (:attr:`~snds.spaces.Space.error_names`).
_EXTENT_KEYS = {"distance": "snds.extent", "angle": "snds.angle_extent"}
#: The metadata key of each velocity block's top speed.
_SPEED_KEYS = {
    "velocity": "snds.top_speed",
    "angular_velocity": "snds.top_angular_speed",
    "phase_rate": "snds.top_phase_rate",
}


def signature(policy: Policy) -> Signature:
    """The :class:`Signature` of a policy's export."""
    return Signature(policy)


def trace(policy: Policy, dtype: torch.dtype) -> torch.export.ExportedProgram:
    """The :class:`Exported` module of a policy traced by ``torch.export``, in ``dtype``, with
    a dynamic batch dimension."""
    kind = signature(policy)
    module = kind.module(dtype)
    example = torch.as_tensor(kind.random_inputs(4, np.random.default_rng(0)), dtype=dtype)
    batch = torch.export.Dim("batch", min=1)
    with torch.no_grad():
        return torch.export.export(module, (example,), dynamic_shapes={"x": {0: batch}})


def random_states(policy: Policy, count: int, *, seed: int = 0) -> np.ndarray:
    """Random inputs of a policy's export, in boxes around the target of 1 to 1000x the extent.

    Equal shares of the positions are drawn uniformly from the boxes of :data:`STATE_RADII`
    (half-widths, in units of the demonstrations' extent), so a check sees the data region,
    the space around it and states far beyond it. A pose policy's inputs are poses: such
    positions with orientations uniform on SO(3).

    Arguments:
        policy: Gives the target and the extent.
        count: Number of states.
        seed: Seed of the draw.

    Returns:
        Positions, shape (count, n), or poses (position, quaternion), shape (count, 7);
        float64.
    """
    return signature(policy).random_inputs(count, np.random.default_rng(seed))


def top_speed(policy: Policy) -> float:
    """The normalisation's unit of speed (the demonstrations' top speed), user units/s (a
    pose policy: of its scaled state)."""
    return float(policy.normalization.length / policy.normalization.time)
