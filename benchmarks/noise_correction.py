"""Noise correction: seed-0 fits of the default policy at several (position noise, gain) pairs.

Each fit is the library's default (``RECIPES["default"]``, the 0.8 / 0.2 split of ``snds
train``) with ``position_noise`` and ``noise_correction`` replaced; only the accuracy is
evaluated (velocity MSE on the test samples and DTW of the rollouts from the demonstrations'
starts, paper scale), no stability check. One row per fit, appended to the output file (so
several invocations build one table).

    python benchmarks/noise_correction.py --motions Sine CShape --settings 0.0015:0 0.0015:10
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import torch

from snds import make_policy
from snds.data import load_lasa, split_samples
from snds.evaluate import accuracy
from snds.policy import float64_copy
from snds.recipes import RECIPES
from snds.train import fit

HERE = Path(__file__).resolve().parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--motions", nargs="+", default=["Sine", "CShape", "DoubleBendedLine"])
    parser.add_argument(
        "--settings", nargs="+", default=["0.0015:0", "0.0015:10"], help="NOISE:GAIN pairs"
    )
    parser.add_argument("--out", type=Path, default=HERE / "results" / "noise-correction.jsonl")
    args = parser.parse_args()
    torch.set_num_threads(1)
    recipe = RECIPES["default"]
    with open(args.out, "a") as out:
        for motion in args.motions:
            demos = load_lasa(motion)
            split = split_samples(demos, test_fraction=0.2, seed=0)
            for setting in args.settings:
                noise, gain = map(float, setting.split(":"))
                policy = make_policy(demos, config=recipe.policy, seed=0)
                config = dataclasses.replace(
                    recipe.train, position_noise=noise, noise_correction=gain, seed=0
                )
                cpu = time.process_time()
                fit(policy, demos, split, config, progress=False)
                seconds = time.process_time() - cpu
                metrics = accuracy(float64_copy(policy), demos, split)
                row = {
                    "motion": motion,
                    "position_noise": noise,
                    "noise_correction": gain,
                    "velocity_mse_paper": metrics["velocity_mse_paper"],
                    "dtw_paper": metrics["dtw_paper"],
                    "frechet_paper": metrics["frechet_paper"],
                    "train_cpu_seconds": round(seconds, 2),
                }
                print(json.dumps(row), flush=True)
                out.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
