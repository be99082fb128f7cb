"""Accuracy screen: fits of the default policy with settings replaced, no stability check.

Each fit is the library's default (``RECIPES["default"]``, the 0.8 / 0.2 split of ``snds
train``, the first ``--demos`` demonstrations) with some :class:`~snds.train.TrainConfig` or
:class:`~snds.policy.PolicyConfig` fields replaced; only the accuracy is evaluated (velocity
MSE on the test samples, DTW and Fréchet distance of the rollouts from the demonstrations'
starts, paper scale). A screen ranks variants before the full evaluation (``snds benchmark``,
``core.py``) measures the one kept. One row per fit, appended to the output file (so several
invocations build one table); ``--jobs`` fits side by side, one torch thread each.

    python benchmarks/screen.py --seeds 3 --variant off:noise_correction=0 --variant default:
    python benchmarks/screen.py --demos 1 --motions PShape GShape --variant lr01:lr=0.01
    python benchmarks/screen.py --seeds 5 --motions ../shared/data/Messy_snake.mat

A variant is ``NAME:KEY=VALUE,KEY=VALUE`` (``NAME:`` alone is the default); values are read
as JSON where they parse, else as strings.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import statistics
import time
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import torch
from _overrides import parse_value, split_overrides

from snds import make_policy
from snds.benchmark import MOTION_GROUPS
from snds.data import load_demonstrations, load_lasa, split_samples
from snds.evaluate import accuracy
from snds.policy import float64_copy
from snds.recipes import RECIPES
from snds.train import fit

HERE = Path(__file__).resolve().parent


def parse_variant(text: str) -> tuple[str, dict[str, object]]:
    """``NAME:KEY=VALUE,...`` -> (name, {key: value}); values are JSON where they parse (a
    list such as ``hidden=[64,64]`` keeps its commas)."""
    name, _, pairs = text.partition(":")
    overrides: dict[str, object] = {}
    for match in re.finditer(r"([^,=]*)(=?)(\[[^\]]*\]|[^,]*)", pairs):
        key, sep, value = match.groups()
        if not (key or sep or value):
            continue
        if not sep or not key:
            raise SystemExit(f"screen.py: variant {text!r}: {match.group(0)!r} is not KEY=VALUE")
        overrides[key] = parse_value(value)
    return name, overrides


def _load(task: str):
    """A LASA motion by name, or a demonstrations file by path."""
    return load_demonstrations(task) if Path(task).suffix else load_lasa(task)


def run(motion: str, seed: int, demos: int | None, name: str, overrides: dict) -> dict:
    """One fit and its accuracy (``motion``: a LASA name or a demonstrations file)."""
    torch.set_num_threads(1)
    recipe = RECIPES["default"]
    policy_overrides, train_overrides = split_overrides(overrides)
    data = _load(motion)
    if demos is not None:
        data = data.first(demos)
    split = split_samples(data, test_fraction=0.2, seed=seed)
    policy_config = dataclasses.replace(recipe.policy, **policy_overrides)
    policy = make_policy(data, config=policy_config, seed=seed)
    config = dataclasses.replace(recipe.train, **train_overrides, seed=seed)
    cpu = time.process_time()
    result = fit(policy, data, split, config, progress=False)
    seconds = time.process_time() - cpu
    metrics = accuracy(float64_copy(policy), data, split)
    return {
        "variant": name,
        "overrides": overrides,
        "motion": motion,
        "seed": seed,
        "demos": demos,
        "velocity_mse_paper": metrics["velocity_mse_paper"],
        "velocity_error_relative": metrics["velocity_error_relative"],
        "dtw_paper": metrics["dtw_paper"],
        "frechet_paper": metrics["frechet_paper"],
        "final_loss": statistics.fmean(result.history[-50:]),
        "restarts": result.restarts,
        "train_cpu_seconds": round(seconds, 2),
    }


def summary(rows: list[dict]) -> str:
    """A Markdown table: per variant and motion, the mean and worst DTW and the mean MSE."""
    groups: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for row in rows:
        groups[row["variant"], row["motion"]].append(row)
    lines = [
        "| variant | motion | fits | DTW mean | DTW worst | MSE mean | CPU s |",
        "|---|---|---|---|---|---|---|",
    ]
    for (name, motion), group in groups.items():
        dtw = [row["dtw_paper"] for row in group]
        mse = statistics.fmean(row["velocity_mse_paper"] for row in group)
        cpu = statistics.median(row["train_cpu_seconds"] for row in group)
        lines.append(
            f"| {name} | {motion} | {len(group)} | {statistics.fmean(dtw):.3f} | "
            f"{max(dtw):.3f} | {mse:.3g} | {cpu:.1f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--motions",
        nargs="+",
        default=list(MOTION_GROUPS["paper8"]),
        help="LASA motions, groups of them (paper8, multi, all), or demonstrations files",
    )
    parser.add_argument("--seeds", type=int, default=1, help="seeds 0 .. N-1")
    parser.add_argument("--seed-list", type=int, nargs="+", help="these seeds instead")
    parser.add_argument("--demos", type=int, default=None, help="the first K demonstrations")
    parser.add_argument(
        "--variant", action="append", default=None, help="NAME:KEY=VALUE,... (repeatable)"
    )
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--out", type=Path, default=HERE / "results" / "screen" / "rows.jsonl")
    args = parser.parse_args()
    variants = [parse_variant(text) for text in args.variant or ["default:"]]
    seeds = args.seed_list or list(range(args.seeds))
    motions = [motion for name in args.motions for motion in MOTION_GROUPS.get(name, (name,))]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    jobs = [
        (motion, seed, args.demos, name, overrides)
        for name, overrides in variants
        for seed in seeds
        for motion in motions
    ]
    rows = []
    with ProcessPoolExecutor(args.jobs) as pool, open(args.out, "a") as out:
        for row in pool.map(run, *zip(*jobs)):
            print(json.dumps(row), flush=True)
            out.write(json.dumps(row) + "\n")
            rows.append(row)
    print(summary(rows))


if __name__ == "__main__":
    main()
