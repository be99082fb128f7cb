"""Noise correction: fits of the default policy at several (offset noise, gain, share) settings.

Each fit is the library's default (``RECIPES["default"]``, the 0.8 / 0.2 split of ``snds
train``) with ``correction_noise``, ``noise_correction`` and ``correction_share`` replaced;
only the accuracy is evaluated (velocity MSE on the test samples and DTW of the rollouts from
the demonstrations' starts, paper scale), no stability check. One row per fit, appended to
the output file (so several invocations build one table); ``--jobs`` fits side by side, one
torch thread each.

    python benchmarks/noise_correction.py --seeds 3 --settings 0:0:0 0.005:10:0.25
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import torch

from snds import make_policy
from snds.benchmark import MOTION_GROUPS
from snds.data import load_lasa, split_samples
from snds.evaluate import accuracy
from snds.policy import float64_copy
from snds.recipes import RECIPES
from snds.train import fit

HERE = Path(__file__).resolve().parent


def run(motion: str, seed: int, setting: str) -> dict:
    """One fit and its accuracy; ``setting`` is ``NOISE:GAIN:SHARE``."""
    torch.set_num_threads(1)
    noise, gain, share = map(float, setting.split(":"))
    recipe = RECIPES["default"]
    demos = load_lasa(motion)
    split = split_samples(demos, test_fraction=0.2, seed=seed)
    policy = make_policy(demos, config=recipe.policy, seed=seed)
    config = dataclasses.replace(
        recipe.train,
        correction_noise=noise,
        noise_correction=gain,
        correction_share=share,
        seed=seed,
    )
    cpu = time.process_time()
    fit(policy, demos, split, config, progress=False)
    seconds = time.process_time() - cpu
    metrics = accuracy(float64_copy(policy), demos, split)
    return {
        "motion": motion,
        "seed": seed,
        "correction_noise": noise,
        "noise_correction": gain,
        "correction_share": share,
        "velocity_mse_paper": metrics["velocity_mse_paper"],
        "dtw_paper": metrics["dtw_paper"],
        "frechet_paper": metrics["frechet_paper"],
        "train_cpu_seconds": round(seconds, 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--motions", nargs="+", default=list(MOTION_GROUPS["paper8"]))
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument(
        "--settings",
        nargs="+",
        default=["0:0:0", "0.005:10:0.25"],
        help="NOISE:GAIN:SHARE triples",
    )
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument(
        "--out", type=Path, default=HERE / "results" / "noise-correction" / "rows.jsonl"
    )
    args = parser.parse_args()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    jobs = [
        (motion, seed, setting)
        for setting in args.settings
        for seed in range(args.seeds)
        for motion in args.motions
    ]
    with ProcessPoolExecutor(args.jobs) as pool, open(args.out, "a") as out:
        for row in pool.map(run, *zip(*jobs)):
            print(json.dumps(row), flush=True)
            out.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
