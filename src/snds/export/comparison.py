"""The check that an export computes what the library computes (:func:`verify`).

:func:`verify` runs an exported file on random states (:func:`snds.export.random_states`,
from near the target to 1000x the demonstrations' extent; for poses with orientations
uniform on SO(3)) and compares it with the library evaluated in the same precision.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from snds.export.graph import NUMPY_DTYPES, random_states, signature, top_speed
from snds.export.runtime import load_onnx, load_pt2
from snds.policy import Policy

__all__ = [
    "DATA_BOX",
    "ROUNDING_SLACK",
    "TOLERANCE",
    "Check",
    "compare",
    "relative_error",
    "verify",
]

#: Largest accepted difference from the library evaluated in the export's precision,
#: relative to max(|velocity|, top speed) of each state. float64 graphs agree to rounding
#: (about 1e-13). float32 cannot promise 1e-5: next to the target V and its gradient are small
#: differences of order-1 numbers and the projection divides by |grad V|, so rounding is
#: amplified there, and two float32 implementations that order the sums differently
#: (onnxruntime's kernels, torch's) differ by about as much as each differs from float64
#: (measured figures: docs/design.md, "Export accuracy").
TOLERANCE = {torch.float64: 1e-5, torch.float32: 3e-4}
#: A float32 export also passes when it is no farther from the exact (float64) policy than
#: this many times the float32 library itself: next to the target two float32
#: implementations may each be far from the exact policy and differ from each other by as
#: much (docs/design.md, "Export accuracy").
ROUNDING_SLACK = 2.0


DATA_BOX = 1.0


@dataclass(frozen=True)
class Check:
    """The comparison of an exported model with the library.

    Attributes:
        path: The exported file.
        dtype: Its precision.
        samples: Number of random states.
        seed: Their seed.
        max_error: Largest difference relative to max(|library velocity|, top speed), over
            the states, the library in the export's precision: the criterion.
        max_error_float64: The same against the library in float64 (equal to ``max_error``
            for a float64 export): how far the export is from the exact policy.
        library_error: The library in the export's precision against itself in float64, on
            the same scale: the rounding that precision costs the library itself.
        max_abs_diff: Largest absolute difference of a velocity component, user units (of a
            twist's component for a pose policy: user units/s or rad/s).
        max_error_near: ``max_error`` over the states in the data's box (:data:`DATA_BOX`
            extents around the target; a pose policy: whose position is).
        max_abs_diff_near: ``max_abs_diff`` over those states.
        max_error_far: ``max_error`` over the states beyond the data's box (out to
            1000 extents).
        max_abs_diff_far: ``max_abs_diff`` over those states.
        max_speed_far: The largest velocity component there (what ``max_abs_diff_far`` is a
            difference of).
        tolerance: The accepted ``max_error``.
        passed: Whether ``max_error <= tolerance``, or, for a float32 export, whether
            ``max_error_float64 <= max(tolerance, ROUNDING_SLACK * library_error)``: the
            export is as close to the exact policy as the library in float32 is.
    """

    path: str
    dtype: str
    samples: int
    seed: int
    max_error: float
    max_error_float64: float
    library_error: float
    max_abs_diff: float
    max_error_near: float
    max_abs_diff_near: float
    max_error_far: float
    max_abs_diff_far: float
    max_speed_far: float
    tolerance: float
    passed: bool

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return asdict(self)

    def summary(self) -> str:
        """The differences in words, the data's box and far out apart."""
        return (
            f"largest difference from the library ({self.dtype}, {self.samples} random states): "
            f"in the data's box {self.max_error_near:.2e} relative, {self.max_abs_diff_near:.2e} "
            f"absolute; beyond it, out to 1000x the extent, {self.max_error_far:.2e} relative, "
            f"{self.max_abs_diff_far:.2e} absolute (of velocities up to {self.max_speed_far:.2e})"
        )


def verify(
    path: str | Path,
    policy: Policy,
    *,
    samples: int = 10_000,
    seed: int = 0,
    tolerance: float | None = None,
) -> Check:
    """Runs an exported model on random states and compares it with the library.

    The library is evaluated in the exported file's precision, on the same inputs: a pose
    policy's export on random poses (orientations uniform on SO(3)) against its
    :meth:`~snds.se3.PosePolicy.forward`.

    Arguments:
        path: An ``.onnx`` or ``.pt2`` file written by this module.
        policy: The policy it was exported from.
        samples: Number of states (see :func:`random_states`).
        seed: Seed of the states.
        tolerance: Accepted relative difference; :data:`TOLERANCE` of the dtype by default.

    Returns:
        The comparison.
    """
    path = Path(path)
    run = load_onnx(path) if path.suffix == ".onnx" else load_pt2(path)
    probe = np.asarray(run(random_states(policy, 1, seed=seed)))
    dtype = torch.float64 if probe.dtype == np.float64 else torch.float32
    return compare(
        run, policy, path=path, dtype=dtype, samples=samples, seed=seed, tolerance=tolerance
    )


def compare(
    run: Callable[[np.ndarray], np.ndarray],
    policy: Policy,
    *,
    path: str | Path,
    dtype: torch.dtype,
    samples: int = 10_000,
    seed: int = 0,
    tolerance: float | None = None,
) -> Check:
    """Compares a function of states (B, space.dim) -> velocities, in ``dtype``, with the
    library in the same precision on :func:`random_states` (see :func:`verify`).

    Arguments:
        run: The exported policy.
        policy: The policy it was exported from.
        path: The file it came from (recorded).
        dtype: Its precision.
        samples: Number of states.
        seed: Their seed.
        tolerance: Accepted relative difference; :data:`TOLERANCE` of the dtype by default.
    """
    kind = signature(policy)
    states = random_states(policy, samples, seed=seed).astype(NUMPY_DTYPES[dtype])
    exported = np.asarray(run(states), dtype=np.float64)
    with torch.no_grad():
        reference = kind.library(torch.as_tensor(states)).double().numpy()
        exact = kind.library(torch.as_tensor(states).double()).numpy()
    difference = np.abs(exported - reference)
    near = kind.extents(states) <= DATA_BOX
    max_error = relative_error(exported, reference, policy)
    if not np.all(np.isfinite(exported)):
        max_error = math.inf
    limit = TOLERANCE[dtype] if tolerance is None else tolerance
    max_error_float64 = relative_error(exported, exact, policy)
    library_error = relative_error(reference, exact, policy)
    passed = max_error <= limit or (
        dtype == torch.float32 and max_error_float64 <= max(limit, ROUNDING_SLACK * library_error)
    )

    def largest(values: np.ndarray) -> float:
        return float(values.max()) if values.size else 0.0

    return Check(
        path=str(path),
        dtype=str(dtype).removeprefix("torch."),
        samples=int(samples),
        seed=int(seed),
        max_error=max_error,
        max_error_float64=max_error_float64,
        library_error=library_error,
        max_abs_diff=largest(difference),
        max_error_near=relative_error(exported[near], reference[near], policy),
        max_abs_diff_near=largest(difference[near]),
        max_error_far=relative_error(exported[~near], reference[~near], policy),
        max_abs_diff_far=largest(difference[~near]),
        max_speed_far=largest(np.abs(reference[~near])),
        tolerance=float(limit),
        passed=bool(passed),
    )


def relative_error(values: np.ndarray, reference: np.ndarray, policy: Policy) -> float:
    """Largest |values - reference| / max(|reference|, top speed) over states (B, m), the
    outputs divided by :meth:`Signature.output_scale` first."""
    if not values.size:
        return 0.0
    divisors = signature(policy).output_scale()
    values, reference = values / divisors, reference / divisors
    # The floor at the top speed: next to the target velocities vanish, and a difference of
    # rounding size relative to a vanishing velocity would say nothing about the model.
    scale = np.maximum(np.linalg.norm(reference, axis=-1), top_speed(policy))
    return float(np.max(np.linalg.norm(values - reference, axis=-1) / scale))
