"""How the cost of the default `snds train` grows: demonstrations, samples per demonstration,
and state dimension.

Each configuration runs in its own process (one torch thread): the default policy and
training on synthetic demonstrations of a stable spiral ``x' = A x`` (random unit starts,
10 s each), then the default evaluation and stability check, as ``snds train`` does. It
records the training and check times (wall and CPU) and the process's peak resident memory.

    python benchmarks/scaling.py            # the 7 configurations, table into README

Writes ``benchmarks/results/scaling.json`` and ``.csv``, and (without ``--no-readme``) the
table between the ``scaling`` markers of ``benchmarks/README.md``.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

from _readme import write_readme_section

HERE = Path(__file__).resolve().parent
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


def run_one(count: int, samples: int, dim: int) -> dict:
    """Trains and evaluates one configuration in this process; returns its row."""
    import torch

    torch.set_num_threads(1)
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


def summarise(rows: list[dict]) -> str:
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--one", nargs=3, type=int, help=argparse.SUPPRESS)
    parser.add_argument("--no-readme", action="store_true")
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_one(*args.one)))
        return
    rows = []
    for count, samples, dim in CONFIGURATIONS:
        command = [sys.executable, __file__, "--one", str(count), str(samples), str(dim)]
        output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
        rows.append(json.loads(output.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), flush=True)
    out = HERE / "results"
    out.mkdir(exist_ok=True)
    meta = {
        "date": datetime.date.today().isoformat(),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.platform()}",
    }
    (out / "scaling.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    with open(out / "scaling.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    table = summarise(rows)
    print(table)
    if not args.no_readme:
        header = (
            f"Measured {meta['date']} on {meta['machine']}; one configuration at a time, one "
            "torch thread, default policy, training and check."
        )
        write_readme_section("scaling", header + "\n\n" + table)


if __name__ == "__main__":
    main()
