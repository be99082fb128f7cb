"""Many fits at once on the CPU: K seeds of one motion as one stacked model against K fits.

For K = 1, 3, 10: seeds 0 .. K-1 of a LASA motion (default Sine) with the library's default
architecture and training settings but a short budget (``--steps``, default 200), fitted one
after the other with :func:`snds.train.fit` and then together with
:func:`snds.batched.fit_many` (the same total work). Reported: wall and CPU seconds of both,
the speed-up (separate over batched, both clocks; the fastest of ``--repeats`` alternating runs)
and the held-out velocity MSE of both (equal up to rounding, which a float32 fit amplifies; see
:mod:`snds.batched`).

    python benchmarks/batched.py

Writes ``benchmarks/results/batched.json`` after every K and the table between the
``batched`` markers of ``benchmarks/README.md``. One torch thread.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch
from _readme import write_readme_section

from snds.data import Demonstrations, Split, load_lasa, split_samples
from snds.methods import METHODS
from snds.metrics import velocity_mse
from snds.policy import Policy, float64_copy
from snds.train import TrainConfig

HERE = Path(__file__).resolve().parent


def timed(run, *args, **kwargs) -> tuple[object, float, float]:
    """``run(*args, **kwargs)``'s value, wall seconds and CPU seconds of this process."""
    wall, cpu = time.perf_counter(), time.process_time()
    value = run(*args, **kwargs)
    return value, time.perf_counter() - wall, time.process_time() - cpu


def fit_each(method, demos: Demonstrations, splits: list[Split], seeds: list[int], steps: int):
    """The fits one after the other."""
    return [method.fit(demos, split, seed=seed, steps=steps) for seed, split in zip(seeds, splits)]


def held_out_mse(policy: Policy, demos: Demonstrations, split: Split) -> float:
    """Velocity MSE (user units) on the test samples, in float64."""
    test = split.test()
    positions = np.concatenate([d.positions[m] for d, m in zip(demos, test)])
    velocities = np.concatenate([d.velocities[m] for d, m in zip(demos, test)])
    return float(velocity_mse(float64_copy(policy).predict(positions), velocities))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--motion", default="Sine")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--counts", default="1,3,10", help="comma-separated K")
    parser.add_argument(
        "--repeats", type=int, default=2, help="runs of each; the fastest of each clock counts"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    # As snds benchmark fits SNDS: the default architecture and TrainConfig but the steps.
    method = METHODS["snds"]
    demos = load_lasa(args.motion)
    rows = []
    for count in [int(k) for k in args.counts.split(",")]:
        seeds = list(range(count))
        splits = [split_samples(demos, test_fraction=0.2, seed=seed) for seed in seeds]
        separate, batched = [], []
        # Alternating, so that a busy spell of the shared machine slows both alike.
        for _ in range(args.repeats):
            separate.append(timed(fit_each, method, demos, splits, seeds, args.steps))
            batched.append(
                timed(method.fit_many, [demos] * count, splits, seeds=seeds, steps=args.steps)
            )
        alone, together = separate[0][0], batched[0][0]
        wall_alone, cpu_alone = (min(run[i] for run in separate) for i in (1, 2))
        wall_batch, cpu_batch = (min(run[i] for run in batched) for i in (1, 2))
        mse = [
            [held_out_mse(fitted.policy, demos, split) for fitted, split in zip(fits, splits)]
            for fits in (alone, together)
        ]
        rows.append(
            {
                "fits": count,
                "motion": args.motion,
                "steps": args.steps,
                "dtype": TrainConfig.dtype,
                "separate_wall_seconds": wall_alone,
                "separate_cpu_seconds": cpu_alone,
                "batched_wall_seconds": wall_batch,
                "batched_cpu_seconds": cpu_batch,
                "speedup_wall": wall_alone / wall_batch,
                "speedup_cpu": cpu_alone / cpu_batch,
                "held_out_mse_separate": mse[0],
                "held_out_mse_batched": mse[1],
                "repeats": args.repeats,
                "load_average_1min": os.getloadavg()[0],
            }
        )
        print(json.dumps(rows[-1]), flush=True)
        out = HERE / "results"
        out.mkdir(exist_ok=True)
        (out / "batched.json").write_text(json.dumps(rows, indent=2) + "\n")
        machine = f"{platform.machine()} {platform.processor() or ''} {os.cpu_count()} cores"
        lines = [
            f"K seeds of {args.motion} fitted one after the other (`snds.train.fit`) and as one "
            f"stacked model (`snds.batched.fit_many`): `python benchmarks/batched.py`, "
            f"{datetime.date.today()}, {machine}, shared with other jobs (so CPU seconds are "
            f"the steadier figure); default architecture and training settings "
            f"({TrainConfig.dtype}) but {args.steps} steps, one thread, the fastest of "
            f"{args.repeats} runs of each. Not measured on a GPU.",
            "",
            "| K | separate wall [s] | separate CPU [s] | batched wall [s] | batched CPU [s] "
            "| speed-up wall | speed-up CPU | held-out velocity MSE, separate / batched "
            "(mean of K) |",
            "|---|---|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {r['fits']} | {r['separate_wall_seconds']:.1f} | {r['separate_cpu_seconds']:.1f} "
            f"| {r['batched_wall_seconds']:.1f} | {r['batched_cpu_seconds']:.1f} "
            f"| {r['speedup_wall']:.2f}x | {r['speedup_cpu']:.2f}x "
            f"| {np.mean(r['held_out_mse_separate']):.3g} / "
            f"{np.mean(r['held_out_mse_batched']):.3g} |"
            for r in rows
        ]
        write_readme_section("batched", "\n".join(lines))


if __name__ == "__main__":
    main()
