"""How smooth is each method's field away from the demonstrations? Issue 21's smoothness.

SNDS, BC and the baselines LPV-DS, SEDS and SDS-EF on Sine, GShape and DoubleBendedLine
(seed 0, all 7 demonstrations), trained and evaluated as ``snds benchmark`` does
(:func:`snds.benchmark.run_sweep`, here with the quick stability check), then scored by
:func:`snds.metrics.field_roughness`: the angles between the velocities of neighbouring
points of a 101 x 101 grid over the stability check's box (3 extents around the target).

    python benchmarks/smoothness.py [--motions Sine GShape] [--methods snds bc] [--no-readme]

The models go to ``runs/smoothness/`` (a rerun loads the ones there instead of training
again). Writes ``benchmarks/results/smoothness.json`` and ``.csv``, the streamline figure
``benchmarks/results/smoothness.png`` (rows: methods, columns: motions; each panel's title
gives its median angle) and the table between the ``smoothness`` markers of
``benchmarks/README.md``.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

from _readme import cpu_name, shrink_png, write_readme_section

from snds.benchmark import SweepSettings, Task, finished_rows, make_tasks, run_sweep
from snds.io import atomic_write
from snds.metrics import ROUGHNESS_GRID, field_roughness
from snds.models import load_model
from snds.parallel import torch_threads
from snds.plotting import Panel, plot_panels
from snds.policy import float64_copy

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
MOTIONS = ("Sine", "GShape", "DoubleBendedLine")
METHODS = ("snds", "bc", "lpvds", "seds", "sdsef")
#: The columns of ``smoothness.csv``.
FIELDS = (
    "motion",
    "method",
    "seed",
    "median_deg",
    "p90_deg",
    "mean_deg",
    "max_deg",
    "pairs",
    "skipped",
    "velocity_mse_paper",
    "dtw_paper",
    "converged_fraction",
    "train_cpu_seconds",
)


def score(rows: list[dict], out: Path) -> tuple[list[dict], list[list[Panel | None]]]:
    """Each run's roughness from its saved model, and the streamline panels (method rows)."""
    scored, panels = [], {}
    for row in rows:
        task = Task.from_row(row)
        policy, _ = load_model(out / task.model_dir)
        policy = float64_copy(policy)
        demos = task.source().load()
        with torch_threads(1):
            roughness = field_roughness(policy, demos)
        scored.append(
            {
                "motion": task.motion,
                "method": task.method,
                "seed": task.seed,
                "median_deg": roughness.median,
                "p90_deg": roughness.p90,
                "mean_deg": roughness.mean,
                "max_deg": roughness.max,
                "pairs": roughness.pairs,
                "skipped": roughness.skipped,
                "spacing": roughness.spacing,
                **{k: row[k] for k in ("velocity_mse_paper", "dtw_paper", "converged_fraction")},
                "train_cpu_seconds": row["train_cpu_seconds"],
            }
        )
        title = f"{task.label} — {task.method}: {roughness.median:.1f}° ({roughness.p90:.0f}°)"
        panels[task.method, task.motion] = Panel(policy, demos, title)
    methods = list(dict.fromkeys(r["method"] for r in scored))
    motions = list(dict.fromkeys(r["motion"] for r in scored))
    grid = [[panels.get((method, motion)) for motion in motions] for method in methods]
    return scored, grid


def table(rows: list[dict], header: str) -> str:
    """The README block: one line per method, median (90th percentile) per motion."""
    motions = list(dict.fromkeys(r["motion"] for r in rows))
    by = {(r["method"], r["motion"]): r for r in rows}
    lines = [
        header,
        "",
        "Median angle between neighbouring velocities, degrees (90th percentile in brackets); "
        "lower is smoother. Then the velocity MSE (paper scale, test samples) of the same run.",
        "",
        "| method | "
        + " | ".join(motions)
        + " | "
        + " | ".join(f"{m} MSE" for m in motions)
        + " |",
        "|---|" + "---|" * (2 * len(motions)),
    ]
    for method in dict.fromkeys(r["method"] for r in rows):
        cells = [by.get((method, m)) for m in motions]
        angles = [f"{c['median_deg']:.2f} ({c['p90_deg']:.1f})" if c else "-" for c in cells]
        mses = [f"{c['velocity_mse_paper']:.4f}" if c else "-" for c in cells]
        lines.append(f"| {method} | " + " | ".join(angles + mses) + " |")
    snds = {r["motion"]: r for r in rows if r["method"] == "snds"}
    if snds:
        lines += [
            "",
            "SNDS's median over each other method's, per motion (below 1: SNDS smoother):",
            "",
        ]
        for method in dict.fromkeys(r["method"] for r in rows):
            if method == "snds":
                continue
            ratios = [
                f"{m} {snds[m]['median_deg'] / by[method, m]['median_deg']:.2f}"
                for m in motions
                if m in snds and (method, m) in by and by[method, m]["median_deg"] > 0
            ]
            lines.append(f"- against {method}: " + ", ".join(ratios))
    lines += [
        "",
        "![Streamlines of each method (rows) on each motion (columns)](results/smoothness.png)",
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--motions", nargs="+", default=list(MOTIONS))
    parser.add_argument("--methods", nargs="+", default=list(METHODS))
    parser.add_argument("--runs", type=Path, default=Path("runs/smoothness"))
    parser.add_argument("--no-readme", action="store_true")
    args = parser.parse_args()
    wall, cpu = time.perf_counter(), time.process_time()
    tasks = make_tasks(args.motions, args.methods, seeds=1)  # seed 0
    # The quick check (100 rollouts, 5,000 decrease samples): this script is about the field.
    settings = SweepSettings.quick()
    new = [task for task in tasks if task.key not in finished_rows(args.runs)]
    rows = run_sweep(tasks, out=args.runs, settings=settings, jobs=1, progress=False)
    scored, grid = score(rows, args.runs)
    figure = plot_panels(grid, RESULTS / "smoothness.png")
    shrink_png(figure)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=HERE
    ).stdout.strip()
    command = "python benchmarks/smoothness.py " + " ".join(sys.argv[1:])
    record = {
        "date": datetime.date.today().isoformat(),
        "commit": commit,
        "command": command.strip(),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.platform()}",
        "cpu": cpu_name(),
        "config": {
            "motions": args.motions,
            "methods": args.methods,
            "seed": 0,
            "demos": "all",
            "sweep": settings.to_dict(),
            "grid": ROUGHNESS_GRID,
            "box": "stability check's: target +- CheckConfig.box_factor (3) extents",
            "runs": str(args.runs),
        },
        "trained": len(new),
        "wall_seconds": wall,
        "cpu_seconds": cpu,
        "load_average": os.getloadavg()[0],
        "rows": scored,
        "figure": str(figure.relative_to(HERE.parent)),
    }
    atomic_write(RESULTS / "smoothness.json", lambda t: t.write_text(json.dumps(record, indent=1)))

    def write_csv(tmp: Path) -> None:
        with open(tmp, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(FIELDS), extrasaction="ignore")
            writer.writeheader()
            writer.writerows(scored)

    atomic_write(RESULTS / "smoothness.csv", write_csv)
    trained = sum(r["train_cpu_seconds"] or 0 for r in rows)
    header = (
        f"Measured {record['date']} at {commit} (`{record['command']}`) on {record['machine']}, "
        f"{record['cpu']}; one process, one torch thread. This run: {wall:.0f} s wall, "
        f"{cpu:.0f} s CPU ({len(new)} of the {len(rows)} models trained, the others loaded "
        f"from `{args.runs}`; the {len(rows)} fits took {trained:.0f} CPU s in all). Seed 0, "
        "all 7 demonstrations, the default of every method; grid "
        f"{ROUGHNESS_GRID} x {ROUGHNESS_GRID} over the target +- 3 extents (spacing 0.06 "
        "extents). Rows: `results/smoothness.csv`."
    )
    text = table(scored, header)
    if not args.no_readme:
        write_readme_section("smoothness", text)
    print(text)


if __name__ == "__main__":
    main()
