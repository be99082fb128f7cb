"""Does a policy trained on a real arm recording retrace it? The bars of the real 3-D files.

For every model that ``benchmarks/reliability.py --part real`` left (one per file and seed),
two figures per demonstration, both from a rollout that starts at the demonstration's start:

* the discrete Fréchet distance between the rollout over the demonstration's own duration
  (:func:`snds.evaluate.reproduce`, the rollout DTW is measured on: Euler at the
  demonstration's mean sample step, as many steps as it has samples) and the demonstration,
  over the task's extent; the bar: at most 5 %. A rollout that lags its demonstration is
  counted as off the path by what it has not yet covered;
* the distance to the target after 1.5x the demonstration's duration (Euler at the
  demonstration's mean sample step); the bar: at most 1 cm.

The issue's Fréchet bar can also be read on that longer rollout, which has the time to
finish the path: a rollout that lags but stays on the path passes. Both readings are
reported (``frechet_over_extent``: over 1.0x the duration; ``frechet_run_out_over_extent``:
over 1.5x), each with its count of runs meeting every bar.

A run meets the bars when its worst demonstration does, with converged fraction 1.0 and no
decrease violations in its stability check (read from the run's ``metrics.json``).

    python benchmarks/reliability.py --part real --seeds 3
    python benchmarks/arm_bars.py runs/reliability/real --seeds 3
    python benchmarks/reliability.py --part real --seeds 3 --recipe phase   # with a phase
    python benchmarks/arm_bars.py runs/reliability-phase/real --section arm-bars-phase \
        --out benchmarks/results/arm-bars-phase.json

Writes ``benchmarks/results/arm-bars.json`` (``--out``: elsewhere) and the ``arm-bars`` table
of ``benchmarks/README.md`` (``--section``: another; ``--no-readme``: none). A model with a
phase (:mod:`snds.phase`) is measured on its positions. The demonstrations are loaded as each model
records (a model trained since gap filling records ``gaps``, see
:func:`snds.data.files.load_mat`; an older one is measured on re-timed gaps, as it was trained).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from _readme import write_readme_section

from snds.data import DataSource
from snds.evaluate import path_reference, reproduce
from snds.metrics import frechet
from snds.models import load_model
from snds.policy import float64_copy
from snds.rollout import rollout_numpy

HERE = Path(__file__).resolve().parent
FRECHET_BAR = 0.05
END_BAR_M = 0.01


def measure(run: Path) -> dict:
    """The bars' figures of one run folder (a model, its ``metrics.json``)."""
    policy, description = load_model(run)
    source = DataSource.from_record(description["data"])
    demos = source.load()
    policy = float64_copy(policy)
    # A model with a phase (snds.phase) is compared on its positions, as its metrics are.
    positions = policy.space.positions
    extent = demos.extent()
    paths = reproduce(policy, demos, list(range(len(demos))))
    frechets = [
        frechet(positions(p), positions(path_reference(d))) / extent
        for p, d in zip(paths, demos, strict=True)
    ]
    ends, run_out = [], []
    target = positions(np.asarray(demos.target))
    for demo in demos:
        dt = demo.duration / (len(demo.times) - 1)
        steps = int(np.ceil(1.5 * demo.duration / dt))
        path = positions(rollout_numpy(policy, demo.states[:1], dt=dt, steps=steps)[0])
        ends.append(float(np.linalg.norm(path[-1] - target)))
        run_out.append(frechet(path, positions(path_reference(demo))) / extent)
    metrics = json.loads((run / "metrics.json").read_text())
    stability = metrics["stability"]
    row = {
        "task": run.parent.name,
        "seed": int(run.name.split("=")[1]),
        "extent_m": extent,
        "frechet_over_extent": max(frechets),
        "frechet_run_out_over_extent": max(run_out),
        "end_distance_m": max(ends),
        "converged_fraction": stability["converged_fraction"],
        "decrease_violations": stability["decrease_violations"],
        "train_seconds": metrics.get("train_seconds"),
        "gaps": source.gaps,
    }
    rest = (
        row["end_distance_m"] <= END_BAR_M
        and row["converged_fraction"] == 1.0
        and row["decrease_violations"] == 0
    )
    row["meets_bars"] = bool(rest and row["frechet_over_extent"] <= FRECHET_BAR)
    row["meets_bars_run_out"] = bool(rest and row["frechet_run_out_over_extent"] <= FRECHET_BAR)
    return row


def trained_with(source: Path) -> str:
    """The training settings of a reliability runs folder, as far as they differ by default."""
    settings = source.parent / "settings.json"
    if not settings.is_file():
        return ""
    record = json.loads(settings.read_text())
    train = record.get("train_defaults", {})
    flags = " ".join(record.get("flags", []))
    return (
        f" (trained with {train.get('steps')} steps, noise correction "
        f"{train.get('noise_correction')}{', flags ' + flags if flags else ''})"
    )


def table(rows: list[dict], source: Path) -> str:
    """The README block: one line per task, worst over its seeds."""
    lines = [
        f"Rollouts from the demonstrations' starts of the models in `{source}`"
        f"{trained_with(source)} "
        f"(`python benchmarks/arm_bars.py {source}`); worst demonstration and worst seed. "
        f"Bars: Fréchet <= {FRECHET_BAR:.0%} of the extent, <= {END_BAR_M * 100:.0f} cm from "
        "the target after 1.5x the demonstration's duration, converged 1.0, 0 violations. "
        "Lengths in the data's units: metres for the 3D files.",
        "",
        "| task | seeds | extent | Fréchet / extent (1.0x) | Fréchet / extent (1.5x) "
        "| end distance | converged | violations | runs meeting every bar (1.0x / 1.5x) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for task in dict.fromkeys(r["task"] for r in rows):
        group = [r for r in rows if r["task"] == task]
        lines.append(
            f"| {task} | {len(group)} | {group[0]['extent_m']:.3f} "
            f"| {max(r['frechet_over_extent'] for r in group):.3f} "
            f"| {max(r['frechet_run_out_over_extent'] for r in group):.3f} "
            f"| {max(r['end_distance_m'] for r in group):.4f} "
            f"| {min(r['converged_fraction'] for r in group):.3f} "
            f"| {sum(r['decrease_violations'] for r in group)} "
            f"| {sum(r['meets_bars'] for r in group)}/{len(group)} "
            f"/ {sum(r['meets_bars_run_out'] for r in group)}/{len(group)} |"
        )
    met = sum(r["meets_bars"] for r in rows), sum(r["meets_bars_run_out"] for r in rows)
    lines += [
        "",
        f"Runs meeting every bar: {met[0]} of {len(rows)} with the Fréchet distance over 1.0x "
        f"the duration, {met[1]} of {len(rows)} over 1.5x.",
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, help="a reliability run's real/ folder")
    parser.add_argument("--seeds", type=int, default=3, help="the first N seeds of each task")
    parser.add_argument("--no-readme", action="store_true")
    parser.add_argument("--section", default="arm-bars", help="the README block to write")
    parser.add_argument(
        "--out", type=Path, default=HERE / "results" / "arm-bars.json", help="the JSON rows"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = []
    for task in sorted(p for p in args.runs.iterdir() if p.is_dir()):
        for run in sorted(task.glob("seed=*"))[: args.seeds]:
            if (run / "metrics.json").is_file():
                rows.append(measure(run))
                print(json.dumps(rows[-1]), flush=True)
    out = args.out
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"runs": str(args.runs), "rows": rows}, indent=1) + "\n")
    if not args.no_readme:
        write_readme_section(args.section, table(rows, args.runs))


if __name__ == "__main__":
    main()
