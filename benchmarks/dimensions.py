"""Training time as the state dimension grows: LASA motions stacked into 2-, 4-, 6-, 8-D tasks.

Demonstration i of the n-D task is demonstration i of n / 2 LASA motions side by side (Sine,
then GShape, CShape, Angle), on the time stamps of the first; each other motion's velocities
are rescaled by the ratio of the time steps, so that they stay the derivatives of its positions
on those stamps. The same network, loss and budget in every dimension (3,000 steps, seed 0,
sample split 0.8 / 0.2); reported: wall and CPU seconds of the fit, the velocity MSE and DTW in
the paper's scale, and a stability check from ``--rollouts`` random starts (box 3x the extent)
with ``--samples`` decrease checks.

    python benchmarks/dimensions.py

Writes ``benchmarks/results/dimensions.json`` and ``.csv`` after every dimension and the table
between the ``dimensions`` markers of ``benchmarks/README.md``. One torch thread.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch
from _readme import write_readme_section

from snds.data import Demonstration, Demonstrations, Normalization, load_lasa, split_samples
from snds.evaluate import evaluate
from snds.policy import PolicyConfig, StablePolicy
from snds.stability import CheckConfig
from snds.train import TrainConfig, fit

HERE = Path(__file__).resolve().parent
MOTIONS = ("Sine", "GShape", "CShape", "Angle")


def stacked(count: int) -> Demonstrations:
    """The first ``count`` of :data:`MOTIONS` side by side: a (2 count)-D task."""
    sets = [load_lasa(name) for name in MOTIONS[:count]]
    demos = []
    for parts in zip(*sets):
        times = parts[0].times
        length = min(len(part.times) for part in parts)
        # Velocities on the first motion's stamps: scaled by the ratio of the mean steps.
        ratio = [np.mean(np.diff(p.times)) / np.mean(np.diff(times)) for p in parts]
        demos.append(
            Demonstration(
                np.concatenate([p.positions[:length] for p in parts], axis=1),
                np.concatenate([r * p.velocities[:length] for p, r in zip(parts, ratio)], axis=1),
                times[:length],
            )
        )
    target = np.concatenate([s.target for s in sets])
    return Demonstrations(tuple(demos), target, "+".join(MOTIONS[:count]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=TrainConfig.steps)
    parser.add_argument("--rollouts", type=int, default=200)
    parser.add_argument("--samples", type=int, default=20_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = []
    for count in (1, 2, 3, 4):
        demos = stacked(count)
        split = split_samples(demos, test_fraction=0.2, seed=args.seed)
        policy = StablePolicy(
            dim=demos.dim,
            normalization=Normalization.fit(demos),
            config=PolicyConfig(),
            seed=args.seed,
        )
        cpu = time.process_time()
        result = fit(policy, demos, split, TrainConfig(steps=args.steps, seed=args.seed))
        cpu = time.process_time() - cpu
        metrics = evaluate(
            policy,
            demos,
            split,
            check=CheckConfig(seed=args.seed, rollouts=args.rollouts, samples=args.samples),
        )
        stability = metrics["stability"]
        rows.append(
            {
                "dim": demos.dim,
                "motions": demos.name,
                "train_seconds": result.seconds,
                "train_cpu_seconds": cpu,
                "steps": result.steps,
                "velocity_mse_paper": metrics["velocity_mse_paper"],
                "dtw_paper": metrics["dtw_paper"],
                "converged_fraction": stability["converged_fraction"],
                "decrease_violations": stability["decrease_violations"],
                "rollouts": stability["rollouts"],
                "samples_checked": stability["samples_checked"],
            }
        )
        print(json.dumps(rows[-1]), flush=True)
        out = HERE / "results"
        out.mkdir(exist_ok=True)
        (out / "dimensions.json").write_text(json.dumps(rows, indent=2) + "\n")
        with (out / "dimensions.csv").open("w", newline="") as file:
            writer = csv.DictWriter(file, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        machine = f"{platform.machine()} {platform.processor() or ''} {os.cpu_count()} cores"
        lines = [
            f"Training time against dimension (`python benchmarks/dimensions.py`, "
            f"{datetime.date.today()}, {machine}, shared with other jobs, so CPU seconds are "
            f"the steadier figure; {args.steps} steps, one thread).",
            "",
            "| dim | motions | train [s] wall | train [s] CPU | velocity MSE (paper) | DTW "
            "(paper) | converged | violations |",
            "|---|---|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {r['dim']} | {r['motions']} | {r['train_seconds']:.0f} | "
            f"{r['train_cpu_seconds']:.0f} | {r['velocity_mse_paper']:.4f} | "
            f"{r['dtw_paper']:.3f} | {r['converged_fraction']:.3f} of {r['rollouts']} | "
            f"{r['decrease_violations']} of {r['samples_checked']} |"
            for r in rows
        ]
        write_readme_section("dimensions", "\n".join(lines))


if __name__ == "__main__":
    main()
