"""Evaluation of a trained policy on its demonstrations: accuracy and stability in one record."""

from __future__ import annotations

import numpy as np
import torch

from snds.data.demonstrations import Demonstration, Demonstrations, Split
from snds.metrics import dtw, final_distance, frechet, swept_error_area, velocity_mse
from snds.policy import Policy, float64_copy
from snds.stability import ROLLOUTS, SAMPLES, check_stability


def evaluation_demos(split: Split) -> list[int]:
    """Demonstrations to roll out for DTW: the held-out ones, or all under a sample split."""
    held_out = [i for i, mask in enumerate(split.train) if not mask.any()]
    return held_out or list(range(len(split.train)))


#: Longest reproduction compared with a demonstration: a longer demonstration is resampled to
#: this many samples, uniform in time, for the rollout and the path metrics (DTW and the
#: discrete Frechet distance cost O(T^2)). LASA (1,000) and the files of ../shared/data stay
#: as they are.
MAX_PATH_SAMPLES = 5000


def path_reference(demo: Demonstration, max_samples: int = MAX_PATH_SAMPLES) -> np.ndarray:
    """A demonstration's positions as the reproduction metrics see them, shape (T, n): the
    samples themselves, or ``max_samples`` of them at uniform times (linear interpolation)
    when the demonstration is longer."""
    if len(demo.times) <= max_samples:
        return demo.positions
    times = np.linspace(demo.times[0], demo.times[-1], max_samples)
    return np.stack(
        [np.interp(times, demo.times, demo.positions[:, k]) for k in range(demo.dim)], axis=-1
    )


def reproduce(policy: Policy, demos: Demonstrations, indices: list[int]) -> list[np.ndarray]:
    """Euler rollouts from the starts of demonstrations, each as long as its
    :func:`path_reference` with its mean step.

    All starts are integrated as one batch (each row with its own step, and frozen once it has
    taken its demonstration's number of steps), so the cost is that of the longest one.

    Returns:
        One rollout per index, shape (T_d, n).
    """
    if not indices:
        return []
    device = getattr(policy, "center", torch.empty(0)).device
    # The length of each path_reference, without resampling the demonstration to find it.
    steps = [min(len(demos[i].times), MAX_PATH_SAMPLES) - 1 for i in indices]
    durations = [demos[i].duration / k for i, k in zip(indices, steps)]
    dt = torch.tensor(durations, dtype=torch.float64, device=device)
    starts = np.stack([demos[i].positions[0] for i in indices])
    x = torch.tensor(starts, dtype=torch.float64, device=device)
    remaining = torch.tensor(steps, device=device)
    states = [x]
    with torch.no_grad():
        for _ in range(max(steps)):
            moving = (remaining > 0).unsqueeze(-1)
            x = torch.where(moving, x + dt.unsqueeze(-1) * policy(x), x)
            remaining = remaining - 1
            states.append(x)
    paths = torch.stack(states, dim=1).cpu().numpy()
    return [paths[row, : k + 1] for row, k in enumerate(steps)]


def accuracy(policy: Policy, demos: Demonstrations, split: Split) -> dict[str, float]:
    """Velocity MSE on the test samples (also relative to their mean squared speed); DTW,
    Frechet distance, swept error area (2-D only) and final distance of the reproductions from
    the demonstrations' starts.

    Both in user units and in the paper's scale (positions relative to the target divided by
    the largest distance of a demonstrated position from the target, velocities by the
    largest demonstrated speed), which makes them comparable with the paper's Fig. 4.

    Arguments:
        policy: The policy, in float64.
        demos: All demonstrations of the task.
        split: The train / test split (test samples for MSE; held-out demos for DTW).
    """
    test = split.test()
    has_test = any(mask.any() for mask in test)
    masks = test if has_test else split.train
    positions = np.concatenate([d.positions[m] for d, m in zip(demos, masks)])
    velocities = np.concatenate([d.velocities[m] for d, m in zip(demos, masks)])
    predicted = policy.predict(positions)
    mse = velocity_mse(predicted, velocities)
    speed, extent = demos.max_speed(), demos.extent()
    indices = evaluation_demos(split)
    paths = reproduce(policy, demos, indices)
    references = [path_reference(demos[i]) for i in indices]
    dtws = [dtw(p, r) for p, r in zip(paths, references)]
    frechets = [frechet(p, r) for p, r in zip(paths, references)]
    # The swept error area is defined for planar motions only.
    areas = (
        [swept_error_area(p, r) for p, r in zip(paths, references)]
        if demos.dim == 2
        else [float("nan")]
    )
    return {
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
        "final_distance": float(max(final_distance(p, demos.target) for p in paths)),
    }


def evaluate(
    policy: Policy,
    demos: Demonstrations,
    split: Split,
    *,
    seed: int = 0,
    rollouts: int = ROLLOUTS,
    samples: int = SAMPLES,
    grid: bool = False,
) -> dict:
    """Accuracy and the stability report, as one JSON-ready record.

    Arguments:
        policy: The policy (not modified; evaluated in float64).
        demos: All demonstrations of the task.
        split: The train / test split.
        seed: Seed of the stability check's random starts and samples.
        rollouts: Random starts of the stability check.
        samples: States of the decrease-condition check.
        grid: Start the stability rollouts from a regular grid instead of random states.
    """
    policy64 = float64_copy(policy)
    record = accuracy(policy64, demos, split)
    report = check_stability(
        policy64, demos, rollouts=rollouts, samples=samples, seed=seed, grid=grid
    )
    record["stability"] = report.to_dict()
    return record
