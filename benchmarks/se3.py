"""Higher dimensions and SE(3): the real 3-D arm demonstrations and the paper's SE(3) tasks.

Two parts, each a table in benchmarks/README.md:

* ``arm3d``: SNDS on the four real 3-D files of ``../shared/data`` (positions in metres), the
  paper's protocol (random 0.8 / 0.2 split of the samples, seed 0): DTW of rollouts from the
  demonstrations' starts and their final distance to the target, in metres; the stability
  report (1,000 random starts in a box 3x the extent, 100,000 decrease checks); train time.
  3D-pick-box's demonstrations end at two places 0.26 m apart, so its two pairs (demos 0,2 and
  1,3) are two tasks. Each file with the MLP's Fourier scale 5 (the default) and 2.
* ``se3``: pose policies on Messy Snake (one demonstration), LASA Sine and GShape, lifted to
  SE(3) with synthetic orientations (slerp to the target along the path), SNDS and BC:
  position DTW, orientation error along the path and at the end, the SE(3) stability report
  (1,000 random poses, all orientations), train time.

    python benchmarks/se3.py --part arm3d
    python benchmarks/se3.py --part se3

Writes ``benchmarks/results/{arm3d,se3}.json`` and ``.csv`` after every run (so a partial
run shows what finished) and the table between the part's markers in ``benchmarks/README.md``.
One torch thread.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import platform
import time
from dataclasses import replace
from pathlib import Path

import torch
from _readme import write_readme_section

from snds.data import Normalization, load_demonstrations, load_lasa, split_samples
from snds.data.poses import with_synthetic_orientations
from snds.evaluate import evaluate
from snds.policy import PolicyConfig, StablePolicy
from snds.recipes import RECIPES
from snds.se3 import make_pose_policy
from snds.stability import CheckConfig
from snds.train import TrainConfig, fit

HERE = Path(__file__).resolve().parent
SHARED = HERE.parent.parent / "shared" / "data"

ARM_TASKS = {
    "3D_Cshape_top": ("3D_Cshape_top.mat", None),
    "3D_viapoint_1": ("3D_viapoint_1.mat", None),
    "3D-pick-box (0,2)": ("3D-pick-box.mat", [0, 2]),
    "3D-pick-box (1,3)": ("3D-pick-box.mat", [1, 3]),
    "3D_sink": ("3D_sink.mat", None),
}
SE3_TASKS = ("Messy_snake", "Sine", "GShape")


def machine() -> str:
    return f"{platform.machine()} {platform.processor() or ''} {os.cpu_count()} cores".strip()


def _write(part: str, row: dict | None, header: str, columns: list[tuple[str, str]]) -> None:
    """Saves one run's row (if given) and rebuilds the part's JSON, CSV and README table from
    every row saved so far (runs of one part may go in parallel processes, one task each)."""
    folder = HERE / "results" / part
    folder.mkdir(parents=True, exist_ok=True)
    if row is not None:
        key = "-".join(str(row[k]) for k in ("task", "method", "fourier_scale") if k in row)
        (folder / f"{key.replace(' ', '_')}.json").write_text(json.dumps(row, indent=2) + "\n")
    rows = [json.loads(path.read_text()) for path in folder.glob("*.json")]
    # arm3d rows are all SNDS and carry no method.
    rows.sort(
        key=lambda r: (
            r["order"],
            -r.get("fourier_scale", 0),
            r.get("method") == "bc",
            r.get("method", "snds"),
        )
    )
    out = HERE / "results"
    (out / f"{part}.json").write_text(json.dumps(rows, indent=2) + "\n")
    with (out / f"{part}.csv").open("w", newline="") as file:
        flat = [{k: v for k, v in r.items() if not isinstance(v, dict | list)} for r in rows]
        # Rows of later variants may carry more fields; the header is their union.
        fields = list(dict.fromkeys(k for r in flat for k in r))
        writer = csv.DictWriter(file, fieldnames=fields)
        writer.writeheader()
        writer.writerows(flat)
    lines = [header, "", "| " + " | ".join(name for name, _ in columns) + " |"]
    lines.append("|" + "---|" * len(columns))
    for r in rows:
        lines.append("| " + " | ".join(fmt.format(**r) for _, fmt in columns) + " |")
    write_readme_section(part, "\n".join(lines))


def arm3d(args: argparse.Namespace) -> None:
    for scale in args.fourier_scales:
        for task, (name, select) in ARM_TASKS.items():
            if args.tasks and task not in args.tasks:
                continue
            demos = load_demonstrations(SHARED / name, select=select)
            split = split_samples(demos, test_fraction=0.2, seed=args.seed)
            config = PolicyConfig(fourier_scale=scale)
            policy = StablePolicy(
                dim=3, normalization=Normalization.fit(demos), config=config, seed=args.seed
            )
            cpu = time.process_time()
            result = fit(policy, demos, split, TrainConfig(steps=args.steps, seed=args.seed))
            cpu = time.process_time() - cpu
            metrics = evaluate(policy, demos, split, check=_check(args))
            stability = metrics.pop("stability")
            row = {
                "task": task,
                "order": list(ARM_TASKS).index(task),
                "demos": len(demos),
                "fourier_scale": scale,
                "extent_m": demos.extent(),
                "train_seconds": result.seconds,
                "train_cpu_seconds": cpu,
                **metrics,
                "converged_fraction": stability["converged_fraction"],
                "decrease_violations": stability["decrease_violations"],
                "stability": stability,
            }
            print(json.dumps(row), flush=True)
            _write("arm3d", row, *_arm_table(args))


def _arm_table(args: argparse.Namespace) -> tuple[str, list[tuple[str, str]]]:
    header = (
        f"Real 3-D arm demonstrations (`python benchmarks/se3.py --part arm3d`, "
        f"{datetime.date.today()}, {machine()}, shared with other jobs, so CPU seconds are the "
        f"steadier figure; seed {args.seed}, {args.steps} steps, {args.rollouts} random starts "
        f"in a box 3x the extent, {args.samples} decrease checks). Rollouts from the "
        "demonstrations' starts (the whole set under the sample split): DTW (paper eq. 7, "
        "q = 2: the root of a sum of squares over about 500 pairs), discrete Frechet distance "
        "and final distance to the target after the demonstration's duration, in metres; "
        "velocity MSE in (m/s)^2 on the test samples."
    )
    columns = [
        ("task", "{task}"),
        ("demos", "{demos}"),
        ("Fourier scale", "{fourier_scale:g}"),
        ("extent [m]", "{extent_m:.3f}"),
        ("DTW [m]", "{dtw:.3f}"),
        ("Frechet [m]", "{frechet:.3f}"),
        ("final error [m]", "{final_distance:.4f}"),
        ("velocity MSE", "{velocity_mse:.2e}"),
        ("converged", "{converged_fraction:.3f}"),
        ("violations", "{decrease_violations}"),
        ("train [s] wall / CPU", "{train_seconds:.0f} / {train_cpu_seconds:.0f}"),
    ]
    return header, columns


def se3_demos(task: str, seed: int):
    if task == "Messy_snake":
        # The paper trains on one of its three demonstrations.
        positions = load_demonstrations(SHARED / "Messy_snake.mat", select=[0])
    else:
        positions = load_lasa(task)
    return with_synthetic_orientations(positions, seed=seed)


def _check(args: argparse.Namespace) -> CheckConfig:
    return CheckConfig(rollouts=args.rollouts, samples=args.samples, seed=args.seed)


def se3(args: argparse.Namespace) -> None:
    for task in SE3_TASKS:
        if args.tasks and task not in args.tasks:
            continue
        demos = se3_demos(task, args.seed)
        for method, stable in (("snds", True), ("bc", False)):
            if method not in args.methods:
                continue
            policy = make_pose_policy(demos, config=PolicyConfig(stable=stable), seed=args.seed)
            split = split_samples(demos, test_fraction=0.2, seed=args.seed)
            cpu = time.process_time()
            shape = args.shape_weight if stable else 0.0
            # The settings of `snds train --se3`, with this run's shape penalty.
            config = replace(
                RECIPES["pose"].train, steps=args.steps, seed=args.seed, shape_weight=shape
            )
            result = fit(policy, demos, split, config)
            cpu = time.process_time() - cpu
            metrics = evaluate(policy, demos, split, check=_check(args))
            stability = metrics.pop("stability")
            row = {
                "task": task,
                "order": SE3_TASKS.index(task),
                # A non-default shape penalty is a variant of its own, with its own row.
                "method": f"{method}, shape {shape:g}" if shape else method,
                "shape_weight": shape,
                "demos": len(demos),
                "extent": demos.extent(),
                "train_seconds": result.seconds,
                "train_cpu_seconds": cpu,
                **metrics,
                "converged_fraction": stability["converged_fraction"],
                "decrease_violations": stability["decrease_violations"],
                "v_rises": stability["v_rises"],
                "samples_checked": stability["samples_checked"],
                "stability": stability,
            }
            print(json.dumps(row), flush=True)
            _write("se3", row, *_se3_table(args))


def _se3_table(args: argparse.Namespace) -> tuple[str, list[tuple[str, str]]]:
    header = (
        f"SE(3) pose policies (`python benchmarks/se3.py --part se3`, "
        f"{datetime.date.today()}, {machine()}, shared with other jobs, so CPU seconds are the "
        f"steadier figure; seed {args.seed}, {args.steps} steps). Synthetic orientations: a "
        "slerp from about 89 degrees (plus 0.1 rad of variation per demonstration) to the "
        "target along the path. Position DTW and final error (after the demonstration's "
        "duration) in the data's units (Messy Snake: m, LASA: mm); orientation errors in "
        f"radians; converged: of N random poses (positions in a box 3x the "
        "extent, orientations uniform on SO(3)), SNDS with the guarded step; violations of the "
        "decrease condition at the random poses counted (BC has no V to check)."
    )
    columns = [
        ("task", "{task}"),
        ("method", "{method}"),
        ("position DTW", "{dtw:.3g}"),
        ("DTW (paper scale)", "{dtw_paper:.3f}"),
        ("final position error", "{final_distance:.3g}"),
        ("orientation error along [rad]", "{angle_error_along:.4f}"),
        ("final orientation error [rad]", "{final_angle_error:.4f}"),
        ("converged", "{converged_fraction:.3f} of {stability[rollouts]}"),
        ("violations", "{decrease_violations} of {samples_checked}"),
        ("largest safe step [s]", "{stability[largest_safe_dt]:.2g}"),
        ("train [s] wall / CPU", "{train_seconds:.0f} / {train_cpu_seconds:.0f}"),
    ]
    return header, columns


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=["arm3d", "se3"], required=True)
    parser.add_argument("--steps", type=int, default=TrainConfig.steps)
    parser.add_argument("--rollouts", type=int, default=1000)
    parser.add_argument("--samples", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--tasks", nargs="+", default=None, help="only these tasks (run parts in parallel)"
    )
    parser.add_argument(
        "--methods", nargs="+", default=["snds", "bc"], help="se3 part: snds and/or bc"
    )
    parser.add_argument("--fourier-scales", type=float, nargs="+", default=[5.0, 2.0])
    parser.add_argument(
        "--shape-weight",
        type=float,
        default=0.0,
        help="se3 part: TrainConfig.shape_weight of the SNDS runs (a row of its own if > 0)",
    )
    parser.add_argument(
        "--collect", action="store_true", help="only rebuild the tables from saved runs"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.collect:
        _write(args.part, None, *{"arm3d": _arm_table, "se3": _se3_table}[args.part](args))
        return
    {"arm3d": arm3d, "se3": se3}[args.part](args)


if __name__ == "__main__":
    main()
