"""Does the warped V earn its place on SE(3) pose policies? The pose recipe's convex V
against a V warped by coupling layers (the positions' default), on the pose tasks of
``benchmarks/se3.py``: Messy Snake, Sine and GShape lifted to SE(3) with synthetic
orientations.

Each run is what ``snds train --se3`` does (the ``pose`` recipe, the default check), with the
variant's overrides: held-out velocity errors, DTW of the positions and the orientation
errors along rollouts from the demonstrations' starts, the stability report and the training
CPU time.

    python benchmarks/pose_warp.py [--seeds 0 1] [--jobs 2]

Writes ``benchmarks/results/pose_warp.json`` and the table between the ``pose-warp`` markers
of ``benchmarks/README.md``. One torch thread per run.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import platform
import statistics
import subprocess
import time
from pathlib import Path

import torch
from _readme import write_readme_section

from snds.data import DataSource, split_samples
from snds.evaluate import evaluate
from snds.io import atomic_write
from snds.methods import make_policy
from snds.parallel import starmap_unordered
from snds.policy import float64_copy
from snds.recipes import RECIPES
from snds.stability import CheckConfig
from snds.train import fit

HERE = Path(__file__).resolve().parent
DATA = HERE.parent.parent / "shared" / "data"
RESULTS = HERE / "results" / "pose_warp.json"

#: name -> (PolicyConfig overrides, TrainConfig overrides) of the ``pose`` recipe.
VARIANTS: dict[str, tuple[dict, dict]] = {
    "convex V (pose recipe)": ({}, {}),
    "warped V (6 layers)": ({"warp_layers": 6}, {}),
    "warped V (6 layers), no shape penalty": ({"warp_layers": 6}, {"shape_weight": 0.0}),
}
#: The tasks: name -> DataSource keywords.
TASKS: dict[str, dict] = {
    "Messy_snake": {"file": DATA / "Messy_snake.mat"},
    "Sine": {"motion": "Sine"},
    "GShape": {"motion": "GShape"},
}


def run(task: str, variant: str, seed: int) -> dict:
    """One fit and its evaluation; the result row."""
    torch.set_num_threads(1)
    source = DataSource(**TASKS[task], poses=True, orientation_seed=seed)
    demos = source.load()
    split = split_samples(demos, test_fraction=0.2, seed=seed)
    policy_overrides, train_overrides = VARIANTS[variant]
    recipe = RECIPES["pose"]
    config = dataclasses.replace(recipe.policy, **policy_overrides)
    train = dataclasses.replace(recipe.train, seed=seed, **train_overrides)
    policy = make_policy(demos, config=config, seed=seed)
    cpu = time.process_time()
    result = fit(policy, demos, split, train, progress=False)
    train_cpu = time.process_time() - cpu
    cpu = time.process_time()
    metrics = evaluate(float64_copy(policy), demos, split, check=CheckConfig(seed=seed))
    check_cpu = time.process_time() - cpu
    stability = metrics["stability"]
    return {
        "task": task,
        "variant": variant,
        "seed": seed,
        "warp_layers": policy.config.warp_layers,
        "train_seconds": result.seconds,
        "train_cpu_seconds": train_cpu,
        "check_cpu_seconds": check_cpu,
        "velocity_mse_paper": metrics["velocity_mse_paper"],
        "angular_velocity_mse": metrics["angular_velocity_mse"],
        "dtw_paper": metrics["dtw_paper"],
        "final_distance": metrics["final_distance"],
        "angle_error_along": metrics["angle_error_along"],
        "final_angle_error": metrics["final_angle_error"],
        "converged_fraction": stability["converged_fraction"],
        "rollouts": stability["rollouts"],
        "decrease_violations": stability["decrease_violations"],
        "samples_checked": stability["samples_checked"],
        "largest_safe_dt": stability["largest_safe_dt"],
        "median_time_to_converge": stability["median_time_to_converge"],
    }


def _mean(rows: list[dict], key: str) -> float:
    return statistics.fmean(r[key] for r in rows)


def table(rows: list[dict], header: str) -> str:
    """The README block: one line per task and variant, means over the seeds."""
    lines = [
        header,
        "",
        "| task | variant | seeds | velocity MSE (paper) | DTW (paper) | angle along [rad] "
        "| final angle [rad] | converged (min) | violations | largest safe step [s] (min) "
        "| train CPU [s] | check CPU [s] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for task in TASKS:
        for variant in VARIANTS:
            group = [r for r in rows if r["task"] == task and r["variant"] == variant]
            if not group:
                continue
            lines.append(
                f"| {task} | {variant} | {len(group)} | {_mean(group, 'velocity_mse_paper'):.4f} "
                f"| {_mean(group, 'dtw_paper'):.3f} | {_mean(group, 'angle_error_along'):.4f} "
                f"| {_mean(group, 'final_angle_error'):.4f} "
                f"| {min(r['converged_fraction'] for r in group):.3f} "
                f"| {sum(r['decrease_violations'] for r in group)} "
                f"| {min(r['largest_safe_dt'] for r in group):.2g} "
                f"| {_mean(group, 'train_cpu_seconds'):.1f} "
                f"| {_mean(group, 'check_cpu_seconds'):.1f} |"
            )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=list(TASKS))
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--no-readme", action="store_true")
    args = parser.parse_args()
    if not (DATA / "Messy_snake.mat").is_file() and "Messy_snake" in args.tasks:
        raise SystemExit(f"{DATA}: the shared data folder is missing (Messy_snake.mat)")
    calls = [(t, v, s) for t in args.tasks for v in VARIANTS for s in args.seeds]
    rows = []
    for _, row in starmap_unordered(run, calls, jobs=args.jobs):
        print(json.dumps(row), flush=True)
        rows.append(row)
    rows.sort(
        key=lambda r: (list(TASKS).index(r["task"]), list(VARIANTS).index(r["variant"]), r["seed"])
    )
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=HERE
    ).stdout.strip()
    config = {"seeds": args.seeds, "tasks": args.tasks, "jobs": args.jobs, "check": "CheckConfig()"}
    record = {
        "date": datetime.date.today().isoformat(),
        "commit": commit,
        "machine": f"{platform.machine()}, {platform.system()}",
        "config": config,
        "rows": rows,
    }
    atomic_write(RESULTS, lambda tmp: tmp.write_text(json.dumps(record, indent=1)))
    header = (
        f"Measured {record['date']} at {commit} (`python benchmarks/pose_warp.py --seeds "
        f"{' '.join(map(str, args.seeds))}`), "
        f"{'one run at a time' if args.jobs == 1 else f'{args.jobs} runs side by side'} on 2 "
        "shared cores, "
        "one torch thread each: read CPU seconds. Means over the seeds; converged and the "
        "largest safe step are the worst seed's; the default check (500 random poses, "
        "50,000 decrease samples)."
    )
    if not args.no_readme:
        write_readme_section("pose-warp", table(rows, header))
    print(table(rows, header))


if __name__ == "__main__":
    main()
