"""What a phase in the state costs in training: the default fit of each real file with and
without ``--phase-codes 3``, side by side in one process (one torch thread, the same seed).

    python benchmarks/phase_cost.py            # every real task, seed 0

Writes ``benchmarks/results/phase-cost.json`` and the ``phase-cost`` block of
``benchmarks/README.md`` (``--no-readme``: not).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from _readme import cpu_name, write_readme_section
from arm_floor import DATA, TASKS

import snds
from snds.data import DataSource, split_samples
from snds.phase import Phase

HERE = Path(__file__).resolve().parent


def fit_cost(source: DataSource, seed: int) -> dict:
    """Wall and CPU seconds of the default fit (the split of ``snds train``)."""
    demos = source.load()
    split = split_samples(demos, test_fraction=0.2, seed=seed)
    policy = snds.make_policy(demos, config=snds.PolicyConfig(), seed=seed)
    wall, cpu = time.perf_counter(), time.process_time()
    snds.fit(policy, demos, split, snds.TrainConfig(seed=seed))
    return {"wall_s": time.perf_counter() - wall, "cpu_s": time.process_time() - cpu}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-readme", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = []
    for task, (file, used) in TASKS.items():
        for codes in (None, 3):
            phase = None if codes is None else Phase(codes=codes)
            source = DataSource(file=DATA / file, demos=used, phase=phase)
            rows.append({"task": task, "phase_codes": codes, **fit_cost(source, args.seed)})
            print(json.dumps(rows[-1]), flush=True)
    out = HERE / "results" / "phase-cost.json"
    out.write_text(json.dumps({"cpu": cpu_name(), "seed": args.seed, "rows": rows}) + "\n")
    lines = [
        f"Training cost of the default fit, without and with `--phase-codes 3`, side by side in "
        f"one process, one torch thread, seed {args.seed}, on {cpu_name()} "
        "(`python benchmarks/phase_cost.py`); CPU seconds (wall in brackets).",
        "",
        "| task | plain state | with a phase | ratio (CPU) |",
        "|---|---|---|---|",
    ]
    for task in TASKS:
        plain, phased = (r for r in rows if r["task"] == task)
        lines.append(
            f"| {task} | {plain['cpu_s']:.1f} ({plain['wall_s']:.1f}) "
            f"| {phased['cpu_s']:.1f} ({phased['wall_s']:.1f}) "
            f"| {phased['cpu_s'] / plain['cpu_s']:.2f} |"
        )
    if not args.no_readme:
        write_readme_section("phase-cost", "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
