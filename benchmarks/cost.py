"""Cost and scaling: how the cost of the default `snds train` grows with the data, and many
fits at once as one stacked model.

Two parts:

* ``growth``: each configuration in its own process (``--threads`` torch threads): the
  default policy and training on synthetic demonstrations of a stable spiral ``x' = A x``
  (random unit starts, 10 s each), then the default evaluation and stability check, as
  ``snds train`` does: training and check times (wall and CPU) and the process's peak resident
  memory, for the number of demonstrations, samples per demonstration and dimension.
* ``batched``: K seeds of a LASA motion fitted one after the other (``snds.fit``) and as one
  stacked model (``snds.fit_many``) with the default architecture and training settings but
  ``--steps``; wall and CPU seconds of both (the fastest of ``--repeats`` alternating runs),
  their ratio, and the held-out velocity MSE of both.

    python benchmarks/cost.py                          # both parts, tables into README
    python benchmarks/cost.py --part growth --configs 7,1000,2
    python benchmarks/cost.py --part batched --counts 1 --steps 20 --repeats 1 --no-readme

Writes ``benchmarks/results/scaling.json`` / ``.csv`` and ``batched.json`` / ``.csv``, and the
``scaling`` and ``batched`` blocks of ``benchmarks/README.md``.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import numpy as np
from _runner import (
    machine,
    machine_line,
    parser,
    set_threads,
    write_readme_section,
    write_results,
)

from snds.data import Demonstrations, Split, load_lasa, split_samples
from snds.methods import METHODS
from snds.metrics import velocity_mse
from snds.policy import Policy, float64_copy
from snds.train import TrainConfig

#: (demonstrations, samples per demonstration, dimension): each axis varied from (7, 1000, 2).
CONFIGURATIONS = [
    (1, 1000, 2),
    (7, 1000, 2),
    (70, 1000, 2),
    (7, 10_000, 2),
    (7, 100_000, 2),
    (7, 1000, 3),
    (7, 1000, 6),
    (70, 100_000, 3),
]


def spiral(count: int, samples: int, dim: int, seed: int = 0):
    """``count`` demonstrations of ``x' = A x`` (a decaying rotation in the first two
    coordinates, decay in the others), ``samples`` each over 10 s, ending at the origin."""
    import numpy as np
    from scipy.linalg import expm

    from snds.data import Demonstration, Demonstrations

    a = -0.6 * np.eye(dim)
    a[0, 1], a[1, 0] = 1.2, -1.2
    rng = np.random.default_rng(seed)
    times = np.linspace(0.0, 10.0, samples)
    flows = expm(a * (times[1] - times[0]))
    demos = []
    for _ in range(count):
        x = rng.normal(size=dim)
        path = np.empty((samples, dim))
        path[0] = x / np.linalg.norm(x)
        for k in range(1, samples):
            path[k] = flows @ path[k - 1]
        path -= path[-1]
        demos.append(Demonstration(positions=path, velocities=path @ a.T, times=times))
    return Demonstrations(tuple(demos), np.zeros(dim), f"spiral{dim}d")


def run_one(count: int, samples: int, dim: int, threads: int = 1) -> dict:
    """Trains and evaluates one configuration in this process; returns its row."""
    set_threads(threads)
    from snds.data import Normalization, split_samples
    from snds.evaluate import evaluate
    from snds.policy import PolicyConfig, StablePolicy
    from snds.train import TrainConfig, fit

    begin = time.perf_counter()
    demos = spiral(count, samples, dim)
    split = split_samples(demos, test_fraction=0.2, seed=0)
    data_seconds = time.perf_counter() - begin
    policy = StablePolicy(
        dim=dim, normalization=Normalization.fit(demos), config=PolicyConfig(), seed=0
    )
    wall, cpu = time.perf_counter(), time.process_time()
    result = fit(policy, demos, split, TrainConfig(), progress=False)
    train_wall, train_cpu = time.perf_counter() - wall, time.process_time() - cpu
    wall, cpu = time.perf_counter(), time.process_time()
    metrics = evaluate(policy, demos, split)
    check_wall, check_cpu = time.perf_counter() - wall, time.process_time() - cpu
    stability = metrics["stability"]
    return {
        "demos": count,
        "samples_per_demo": samples,
        "dim": dim,
        "data_seconds": round(data_seconds, 2),
        "train_seconds": round(train_wall, 2),
        "train_cpu_seconds": round(train_cpu, 2),
        "steps": result.steps,
        "check_seconds": round(check_wall, 2),
        "check_cpu_seconds": round(check_cpu, 2),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "converged_fraction": stability["converged_fraction"],
        "decrease_violations": stability["decrease_violations"],
        "velocity_error_relative": round(metrics["velocity_error_relative"], 5),
    }


def growth_table(rows: list[dict]) -> str:
    lines = [
        "| demos | samples / demo | dim | train s (CPU s) | check s (CPU s) | peak memory MB "
        "| converged | violations |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['demos']} | {r['samples_per_demo']:,} | {r['dim']} "
            f"| {r['train_seconds']:.1f} ({r['train_cpu_seconds']:.1f}) "
            f"| {r['check_seconds']:.1f} ({r['check_cpu_seconds']:.1f}) "
            f"| {r['peak_rss_mb']:.0f} | {r['converged_fraction']:.3f} "
            f"| {r['decrease_violations']} |"
        )
    return "\n".join(lines)


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


def growth(args: argparse.Namespace) -> None:
    """The ``growth`` part: each configuration in its own process."""
    configs = [tuple(int(v) for v in c.split(",")) for c in args.configs] or CONFIGURATIONS
    rows = []
    for count, samples, dim in configs:
        command = [sys.executable, __file__, "--one", str(count), str(samples), str(dim)]
        command += ["--threads", str(args.threads)]
        output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
        rows.append(json.loads(output.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), flush=True)
    meta = machine(threads=args.threads)
    write_results("scaling", rows, meta)
    table = growth_table(rows)
    print(table)
    if not args.no_readme:
        header = (
            f"{machine_line(meta)} `python benchmarks/cost.py --part growth`: one "
            "configuration at a time, default policy, training and check."
        )
        write_readme_section("scaling", header + "\n\n" + table)


def batched(args: argparse.Namespace) -> None:
    """The ``batched`` part: K separate fits against one stacked fit of K seeds."""
    set_threads(args.threads)
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
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    meta = machine(threads=args.threads)
    write_results("batched", rows, meta)
    lines = [
        f"{machine_line(meta)} `python benchmarks/cost.py --part batched`: K seeds of "
        f"{args.motion}, default architecture and training settings ({TrainConfig.dtype}) but "
        f"{args.steps} steps, the fastest of {args.repeats} runs of each. Not measured on a GPU.",
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
    print("\n".join(lines))
    if not args.no_readme:
        write_readme_section("batched", "\n".join(lines))


def main() -> None:
    options = parser(__doc__)
    options.add_argument("--part", choices=["growth", "batched", "both"], default="both")
    options.add_argument(
        "--configs",
        nargs="*",
        default=[],
        metavar="D,S,N",
        help="growth: demonstrations, samples each, dimension (default: the 8 of the table)",
    )
    options.add_argument("--motion", default="Sine", help="batched: the LASA motion")
    options.add_argument("--steps", type=int, default=200, help="batched: steps per fit")
    options.add_argument("--counts", default="1,3,10", help="batched: comma-separated K")
    options.add_argument("--repeats", type=int, default=2, help="batched: runs of each")
    options.add_argument("--one", nargs=3, type=int, help=argparse.SUPPRESS)
    args = options.parse_args()
    if args.one:
        print(json.dumps(run_one(*args.one, threads=args.threads)))
        return
    if args.part in ("growth", "both"):
        growth(args)
    if args.part in ("batched", "both"):
        batched(args)


if __name__ == "__main__":
    main()
