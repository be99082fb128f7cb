"""Evaluation of a trained policy on its demonstrations: accuracy and stability in one record."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch
from dtaidistance import dtw_ndim

from snds.arrival import ARRIVAL_TOLERANCE
from snds.data.demonstrations import Split
from snds.metrics import dtw, final_distance, frechet, swept_error_area, velocity_mse
from snds.parallel import torch_threads
from snds.policy import Policy, float64_copy
from snds.spaces import Phased, Space
from snds.stability import CheckConfig, StabilityReport, check_stability
from snds.threads import fastest_threads

__all__ = [
    "MAX_PATH_SAMPLES",
    "RETRACE_DURATIONS",
    "RETRACE_SAMPLES",
    "RETRACE_WARNING",
    "Evaluation",
    "accuracy",
    "evaluate",
    "evaluation_demos",
    "path_reference",
    "reproduce",
    "retrace",
    "warnings",
]

#: Rollouts from the demonstrations' starts for :func:`retrace` run this many times each
#: demonstration's duration: time for one that lags to finish, as a controller would let it.
RETRACE_DURATIONS = 1.5
#: Fewest samples of a demonstration and of the rollout's time steps in :func:`retrace`: a
#: stroke of a few points is compared as the line through them, not with Euler steps as long
#: as its samples' spacing.
RETRACE_SAMPLES = 200
#: A rollout that strays further than this from its demonstration (discrete Frechet distance,
#: in extents) does not retrace it: :func:`warnings` says so.
RETRACE_WARNING = 0.05


def evaluation_demos(split: Split) -> list[int]:
    """Demonstrations to roll out for DTW: the held-out ones, or all under a sample split."""
    held_out = [i for i, mask in enumerate(split.train) if not mask.any()]
    return held_out or list(range(len(split.train)))


#: Longest reproduction compared with a demonstration: a longer demonstration is resampled to
#: this many samples, uniform in time, for the rollout and the path metrics (DTW and the
#: discrete Frechet distance cost O(T^2)). LASA (1,000) and the files of ../shared/data stay
#: as they are.
MAX_PATH_SAMPLES = 5000


def _samples(demo: Any, min_samples: int) -> int:
    """How many samples :func:`path_reference` gives a demonstration."""
    return min(max(len(demo.times), min_samples), MAX_PATH_SAMPLES)


def path_reference(
    demo: Any, max_samples: int = MAX_PATH_SAMPLES, *, min_samples: int = 0
) -> np.ndarray:
    """A demonstration's states as the reproduction metrics see them, shape (T, dim): the
    samples themselves, or ``max_samples`` of them at uniform times when the demonstration is
    longer, ``min_samples`` when it is shorter (positions interpolated linearly, further
    coordinates such as a pose's orientation taken from the sample at or just after each
    time)."""
    states = demo.states
    count = min(max(len(demo.times), min_samples), max_samples)
    if count == len(demo.times):
        return states
    times = np.linspace(demo.times[0], demo.times[-1], count)
    dim = demo.positions.shape[1]
    columns = [np.interp(times, demo.times, demo.positions[:, k]) for k in range(dim)]
    nearest = np.searchsorted(demo.times, times).clip(0, len(demo.times) - 1)
    return np.concatenate([np.stack(columns, axis=-1), states[nearest, dim:]], axis=1)


def reproduce(
    policy: Policy, demos: Any, indices: list[int], *, durations: float = 1.0, min_samples: int = 0
) -> list[np.ndarray]:
    """Euler rollouts along the policy's space from the starts of demonstrations, each with
    the mean step of its :func:`path_reference` (of ``min_samples``) and ``durations`` times
    as long.

    All starts are integrated as one batch (each row with its own step, and frozen once it has
    taken its demonstration's number of steps), so the cost is that of the longest one.

    Returns:
        One rollout per index, shape (T_d, space.dim): T_d - 1 = ``durations`` x the steps of
        its path_reference, rounded up.
    """
    if not indices:
        return []
    device = getattr(policy, "center", torch.empty(0)).device
    advance = policy.space.advance
    # The length of each path_reference, without resampling the demonstration to find it.
    samples = [_samples(demos[i], min_samples) - 1 for i in indices]
    periods = [demos[i].duration / k for i, k in zip(indices, samples)]
    steps = [int(np.ceil(durations * k - 1e-9)) for k in samples]
    dt = torch.tensor(periods, dtype=torch.float64, device=device)
    starts = np.stack([demos[i].states[0] for i in indices])
    x = torch.tensor(starts, dtype=torch.float64, device=device)
    remaining = torch.tensor(steps, device=device)
    states = [x]
    with torch.no_grad():
        for _ in range(max(steps)):
            moving = (remaining > 0).unsqueeze(-1)
            x = torch.where(moving, advance(x, dt, policy(x)), x)
            remaining = remaining - 1
            states.append(x)
    paths = torch.stack(states, dim=1).cpu().numpy()
    return [paths[row, : k + 1] for row, k in enumerate(steps)]


def _errors_along(space: Space, path: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Mean error of each component of ``space`` between the samples of a path (T, dim) and
    a reference (S, dim) that the DTW alignment of their positions pairs, shape (k,)."""
    alignment = dtw_ndim.warping_path(
        np.ascontiguousarray(space.positions(path), dtype=np.float64),
        np.ascontiguousarray(space.positions(reference), dtype=np.float64),
    )
    i, j = np.asarray(alignment).T
    errors = space.errors(torch.as_tensor(path[i]), torch.as_tensor(reference[j]))
    return errors.mean(dim=0).numpy()


def accuracy(
    policy: Policy, demos: Any, split: Split, *, paths: dict[int, np.ndarray] | None = None
) -> dict[str, float]:
    """Velocity MSE on the test samples (also relative to their mean squared speed); DTW,
    Frechet distance, swept error area (2-D only) and final distance of the reproductions from
    the demonstrations' starts.

    Both in user units and in the paper's scale (positions relative to the target divided by
    the largest distance of a demonstrated position from the target, velocities by the
    largest demonstrated speed), which makes them comparable with the paper's Fig. 4. The
    path metrics compare positions; in a space with further error components (a pose's
    angle, radians) each also gets its mean error along the DTW-aligned path
    (``angle_error_along``) and its largest error at the end (``final_angle_error``), and
    each further velocity block its MSE (``angular_velocity_mse``).

    Arguments:
        policy: The policy, in float64.
        demos: All demonstrations of the task (poses for a pose policy).
        split: The train / test split (test samples for MSE; held-out demos for DTW).
        paths: Reproductions already rolled out (:func:`reproduce`), by demonstration index;
            the others are rolled out here.
    """
    space = policy.space
    test = split.test()
    has_test = any(mask.any() for mask in test)
    masks = test if has_test else split.train
    states = np.concatenate([d.states[m] for d, m in zip(demos, masks)])
    demonstrated = np.concatenate([d.velocities[m] for d, m in zip(demos, masks)])
    predicted = policy.predict(states)
    blocks = np.cumsum(space.velocity_sizes)[:-1]
    predicted_blocks = np.split(predicted, blocks, axis=1)
    demonstrated_blocks = np.split(demonstrated, blocks, axis=1)
    predicted, velocities = predicted_blocks[0], demonstrated_blocks[0]
    mse = velocity_mse(predicted, velocities)
    speed, extent = demos.max_speed(), demos.extent()
    target = np.asarray(demos.target)
    indices = evaluation_demos(split)
    known = paths or {}
    missing = [i for i in indices if i not in known]
    rolled = dict(zip(missing, reproduce(policy, demos, missing)))
    paths = [known[i] if i in known else rolled[i] for i in indices]
    references = [path_reference(demos[i]) for i in indices]
    positions = [space.positions(p) for p in paths]
    reference_positions = [space.positions(r) for r in references]
    pairs = list(zip(positions, reference_positions))
    dtws = [dtw(p, r) for p, r in pairs]
    frechets = [frechet(p, r) for p, r in pairs]
    # The swept error area is defined for planar motions only.
    areas = [swept_error_area(p, r) for p, r in pairs] if space.position_dim == 2 else [np.nan]
    record = {
        "frechet": float(np.mean(frechets)),
        "frechet_paper": float(np.mean(frechets) / extent),
        "swept_area": float(np.mean(areas)),
        "swept_area_paper": float(np.mean(areas) / extent**2),
        "velocity_mse": mse,
        "velocity_mse_paper": velocity_mse(predicted / speed, velocities / speed),
        # The share of the demonstrated velocities' energy the policy misses: scale-free, so
        # one bar fits every motion and unit (0: exact; 1: as bad as standing still).
        "velocity_error_relative": mse / velocity_mse(np.zeros_like(velocities), velocities),
        "velocity_mse_on": "test samples" if has_test else "training samples (no test split)",
        "dtw": float(np.mean(dtws)),
        "dtw_paper": float(np.mean(dtws) / extent),
        "final_distance": float(max(final_distance(p, space.positions(target)) for p in positions)),
    }
    for name, got, wanted in zip(
        space.velocity_names[1:], predicted_blocks[1:], demonstrated_blocks[1:]
    ):
        record[f"{name}_mse"] = velocity_mse(got, wanted)
    if len(space.error_names) > 1:
        along = np.mean([_errors_along(space, p, r) for p, r in zip(paths, references)], axis=0)
        ends = space.errors(torch.as_tensor(np.stack([p[-1] for p in paths])), torch.tensor(target))
        worst = ends.max(dim=0).values.numpy()
        for k, name in enumerate(space.error_names[1:], start=1):
            record[f"{name}_error_along"] = float(along[k])
            record[f"final_{name}_error"] = float(worst[k])
    return record


def retrace(
    policy: Policy, demos: Any, *, durations: float = RETRACE_DURATIONS
) -> tuple[dict, dict[int, np.ndarray]]:
    """How far rollouts from every demonstration's start stay from that demonstration.

    Each rollout (:func:`reproduce`, with steps of its demonstration's period or shorter:
    :data:`RETRACE_SAMPLES`) runs ``durations`` x its demonstration's duration; its
    positions are compared with the demonstration's by the discrete Frechet distance
    (:func:`snds.metrics.frechet`: the leash that walks both paths forward), in extents.

    Returns:
        The record: ``retrace_frechet_max`` and ``retrace_frechet_median`` over the
        demonstrations, ``retrace_final_max`` (the largest distance of a rollout's end from
        the target), all in extents, and ``retrace_durations``; and, by index, the first
        duration of each rollout whose steps are :func:`accuracy`'s own (a demonstration of
        :data:`RETRACE_SAMPLES` samples or more), which it then need not roll out again.
    """
    space, extent = policy.space, demos.extent()
    indices = list(range(len(demos)))
    paths = reproduce(policy, demos, indices, durations=durations, min_samples=RETRACE_SAMPLES)
    target = space.positions(np.asarray(demos.target))
    references = [path_reference(demos[i], min_samples=RETRACE_SAMPLES) for i in indices]
    gaps = [frechet(space.positions(p), space.positions(r)) for p, r in zip(paths, references)]
    ends = [final_distance(space.positions(p), target) for p in paths]
    record = {
        "retrace_frechet_max": float(np.max(gaps) / extent),
        "retrace_frechet_median": float(np.median(gaps) / extent),
        "retrace_final_max": float(np.max(ends) / extent),
        "retrace_durations": durations,
    }
    # The same steps as accuracy's reproductions: their first duration is one.
    prefixes = {
        i: p[: _samples(demos[i], 0)]
        for i, p in zip(indices, paths)
        if _samples(demos[i], RETRACE_SAMPLES) == _samples(demos[i], 0)
    }
    return record, prefixes


def warnings(record: dict, *, hint: bool = True) -> list[str]:
    """What a user must know before trusting a model, one sentence each, from an
    :func:`evaluate` record: rollouts that do not retrace the demonstrations, a stiff field,
    starts that do not arrive, and decrease violations.

    Arguments:
        record: The record (its ``retrace_*`` figures and ``stability`` report).
        hint: Whether to suggest a phase for rollouts that do not retrace (not for a policy
            that has one, nor for behavioural cloning, whose rollouts stray for want of V).
    """
    said = []
    worst = record.get("retrace_frechet_max")
    if worst is not None and not worst <= RETRACE_WARNING:
        advice = " (for paths that cross or wind, a phase helps: --phase-codes 3)" if hint else ""
        said.append(
            f"rollouts from the demonstrations' starts do not retrace them: Frechet distance "
            f"up to {100 * worst:.3g} % of the extent (over {100 * RETRACE_WARNING:g} %){advice}"
        )
    end = record.get("retrace_final_max")
    if end is not None and not end <= ARRIVAL_TOLERANCE:
        said.append(
            f"rollouts from the demonstrations' starts end up to {100 * end:.3g} % of the "
            f"extent from the target after {record['retrace_durations']:g}x their duration"
        )
    stability = record.get("stability", {})
    safe, dt = stability.get("largest_safe_dt"), stability.get("dt")
    if safe is not None and dt is not None and safe == safe and safe < dt:
        said.append(
            f"stiff field: the largest safe Euler step {safe:.3g} s is below the data's step "
            f"{dt:.3g} s (a controller at the data's rate needs the guarded step)"
        )
    rollouts, fraction = stability.get("rollouts"), stability.get("converged_fraction")
    if rollouts and fraction is not None and fraction < 1:
        missed = rollouts - round(fraction * rollouts)
        stuck = stability.get("out_of_steps", 0)
        said.append(
            f"{missed} of {rollouts} random starts had not arrived after "
            f"{stability['horizon']:.3g} s"
            + (f" ({stuck} of them out of steps: the guard kept shortening them)" if stuck else "")
        )
    if stability.get("decrease_violations"):
        said.append(f"V fails to decrease at {stability['decrease_violations']} sampled states")
    return said


@dataclass(frozen=True)
class Evaluation:
    """What :func:`evaluate` found: accuracy, retracing and the stability report.

    Attributes:
        accuracy: :func:`accuracy`'s record (velocity MSE, DTW, Frechet, ..., user units and
            the paper's scale).
        retrace: :func:`retrace`'s record (rollouts from every demonstration's start).
        stability: The stability check's report (:func:`snds.stability.check_stability`).
        warnings: What a user must know before trusting the model (:func:`warnings`).
        train_seconds: The fit's wall time, when the evaluation belongs to a training run.
    """

    accuracy: Mapping[str, Any]
    retrace: Mapping[str, float]
    stability: StabilityReport
    warnings: tuple[str, ...] = ()
    train_seconds: float | None = None

    @property
    def velocity_mse_paper(self) -> float:
        """Velocity MSE on the test samples, in the paper's scale."""
        return float(self.accuracy["velocity_mse_paper"])

    @property
    def dtw_paper(self) -> float:
        """Mean DTW distance of the reproductions, in the paper's scale."""
        return float(self.accuracy["dtw_paper"])

    def with_train_seconds(self, seconds: float) -> Evaluation:
        """The same evaluation, with the wall time of the fit it evaluates."""
        return replace(self, train_seconds=seconds)

    # Read-only access by key to the metrics.json record, for code written when evaluate
    # returned that dict (``metrics["stability"]["converged_fraction"]``, ``{**metrics}``).
    def __getitem__(self, key: str) -> Any:
        return self.to_dict()[key]

    def __contains__(self, key: object) -> bool:
        return key in self.to_dict()

    def keys(self) -> Any:
        """The keys of :meth:`to_dict`."""
        return self.to_dict().keys()

    def get(self, key: str, default: Any = None) -> Any:
        """``to_dict().get(key, default)``."""
        return self.to_dict().get(key, default)

    def to_dict(self) -> dict:
        """The JSON-ready record ``metrics.json`` holds: the accuracy and retrace figures,
        ``stability``, ``warnings`` and, in a training run, ``train_seconds``."""
        record = {**self.accuracy, **self.retrace, "stability": self.stability.to_dict()}
        record["warnings"] = list(self.warnings)
        if self.train_seconds is not None:
            record["train_seconds"] = self.train_seconds
        return record


def evaluate(
    policy: Policy,
    demos: Any,
    split: Split,
    *,
    check: CheckConfig = CheckConfig(),
    threads: int | None = None,
) -> Evaluation:
    """Accuracy, retracing and the stability report of a policy on its demonstrations.

    Arguments:
        policy: The policy (not modified; evaluated in float64).
        demos: All demonstrations of the task, in the policy's space.
        split: The train / test split.
        check: The stability check's settings (its seed, sizes, grid starts).
        threads: Torch CPU threads during the evaluation, restored after it (None:
            :func:`snds.threads.fastest_threads` for the check's size).
    """
    with torch_threads(fastest_threads(check) if threads is None else threads):
        policy64 = float64_copy(policy)
        retraced, paths = retrace(policy64, demos)
        record = accuracy(policy64, demos, split, paths=paths)
        stability = check_stability(policy64, demos, check)
    phased = isinstance(policy64.space, Phased)
    said = warnings(
        {**record, **retraced, "stability": stability.to_dict()},
        hint=policy64.stable and not phased,
    )
    return Evaluation(accuracy=record, retrace=retraced, stability=stability, warnings=tuple(said))
