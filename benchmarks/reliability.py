"""Reliability: default training on every LASA motion and every real file, 5 seeds, no reruns.

Two parts, one table in benchmarks/README.md (``reliability`` markers), every run through
``snds train`` with its defaults and ``--seed S``:

* ``lasa``: ``--motion M`` for the 30 motions (the paper's protocol: a random 0.8 / 0.2 split
  of the samples, the split of ``snds benchmark``);
* ``real``: ``--data FILE`` for each file of ``../shared/data`` (3D-pick-box's demonstrations
  end at two places 0.26 m apart, so its pairs 0,2 and 1,3 are two tasks, as a user would
  select them with ``--demos``).

Every run faces the same bars, set before the sweep: the held-out velocity error at most
:data:`ACCURACY_BAR` of the demonstrated velocities' mean square (``velocity_error_relative``,
scale-free, so one bar fits millimetres and metres), converged fraction 1.0 from the stability
check's random starts, and zero decrease violations. Both parts use the same check: 300
rollouts from the 3x box, 20,000 decrease samples in the 10x box (float64).

    python benchmarks/reliability.py                  # both parts; resumes
    python benchmarks/reliability.py --part real --seeds 2
    python benchmarks/reliability.py --recipe convex  # a convex V (--warp-layers 0 ...)
    python benchmarks/reliability.py --part real --seeds 3 --recipe phase  # --phase-codes 3
    python benchmarks/reliability.py --part real --seeds 3 --recipe plain  # --phase-codes 0

Runs go to ``runs/reliability/{lasa,real}/`` (``runs/reliability-RECIPE`` for a recipe; models
included); rows, a per-task summary and the README table go to
``benchmarks/results/reliability/``. Both parts resume: a finished run is not run again, and a
runs folder made with other library defaults or flags is refused (``settings.json``).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import time
from collections.abc import Sequence
from pathlib import Path

from _runner import DATA, RESULTS, machine, machine_line, parser, write_readme_section

from snds.benchmark import SweepSettings, resolve_motions
from snds.io import atomic_write, write_json
from snds.parallel import starmap_unordered
from snds.policy import PolicyConfig
from snds.train import TrainConfig

SHARED = DATA
#: The largest held-out velocity error, relative to the demonstrated velocities' mean square.
ACCURACY_BAR = 0.05
#: task -> (file in ../shared/data, ``--demos`` selection or None for all)
REAL_TASKS: dict[str, tuple[str, str | None]] = {
    "Messy_snake": ("Messy_snake.mat", None),
    "3D_Cshape_top": ("3D_Cshape_top.mat", None),
    "3D_viapoint_1": ("3D_viapoint_1.mat", None),
    "3D-pick-box (0,2)": ("3D-pick-box.mat", "0,2"),
    "3D-pick-box (1,3)": ("3D-pick-box.mat", "1,3"),
    "3D_sink": ("3D_sink.mat", None),
}


#: ``--recipe`` name -> the ``snds train`` flags it adds. A recipe other than the default has
#: its own runs, results and README block, compared with the default's.
RECIPES: dict[str, list[str]] = {
    "default": [],
    # A convex V trained on the demonstrated states (docs/design.md, "The Lyapunov function").
    "convex": ["--warp-layers", "0", "--warp-weight", "0", "--position-noise", "0"],
    # A phase of 3 numbers in the state (snds.phase), as the default of `snds train` has it.
    "phase": ["--phase-codes", "3"],
    # The positions alone, x' = f(x), as `snds benchmark` (the LASA part) trains them.
    "plain": ["--phase-codes", "0"],
}


def meets_bars(row: dict) -> dict[str, bool]:
    """Which of the three bars a run meets."""
    error = row.get("velocity_error_relative")
    return {
        "accuracy": error is not None and error <= ACCURACY_BAR,
        "converged": row.get("converged_fraction") == 1.0,
        "no_violations": row.get("decrease_violations") == 0,
    }


# ---------------------------------------------------------------------------------------------
# The two parts.


def run_lasa(args: argparse.Namespace, settings: SweepSettings) -> None:
    tasks = {motion: ["--motion", motion] for motion in resolve_motions(args.motions)}
    _run_cli(args, settings, "lasa", tasks)


def lasa_rows(args: argparse.Namespace) -> list[dict]:
    """The finished LASA runs of these motions and seeds, motion-major."""
    return _cli_rows(args, "lasa", resolve_motions(args.motions))


def sweep_settings(recipe: str, settings: SweepSettings) -> dict:
    """What decides a run's result besides its task and seed: flags, library defaults, check."""
    # Through JSON, so that it compares equal to the record read back (tuples become lists).
    return json.loads(
        json.dumps(
            {
                "flags": RECIPES[recipe],
                "policy_defaults": PolicyConfig().to_dict(),
                "train_defaults": TrainConfig().to_dict(),
                "check": {"rollouts": settings.rollouts, "samples": settings.samples},
            }
        )
    )


def check_runs_folder(runs: Path, expected: dict) -> None:
    """Refuses to resume runs made with other settings; records them in a new folder."""
    record = runs / "settings.json"
    if record.is_file():
        found = json.loads(record.read_text())
        if found != expected:
            keys = sorted(k for k in expected if found.get(k) != expected[k])
            raise SystemExit(
                f"reliability: {runs} holds runs made with other {', '.join(keys)} "
                f"(see {record}); pass a new --runs folder"
            )
    elif any(runs.glob("*/*/seed=*/row.json")):
        raise SystemExit(
            f"reliability: {runs} holds runs of unrecorded settings; pass a new --runs"
        )
    else:
        runs.mkdir(parents=True, exist_ok=True)
        write_json(record, expected)


def _snds_train(argv: list[str]) -> float:
    """Runs ``snds`` with these arguments in this worker; returns its CPU seconds."""
    from snds.cli import main

    cpu = time.process_time()
    code = main(argv)
    if code != 0:
        raise RuntimeError(f"snds {' '.join(argv)} exited with {code}")
    return time.process_time() - cpu


def _cli_row(part: str, task: str, seed: int, directory: Path, cpu: float) -> dict:
    metrics = json.loads((directory / "metrics.json").read_text())
    stability = metrics["stability"]
    return {
        "part": part,
        "task": task,
        "seed": seed,
        "train_seconds": metrics["train_seconds"],
        "train_and_check_cpu_seconds": cpu,
        **{k: metrics[k] for k in ("velocity_mse", "velocity_error_relative", "dtw_paper")},
        **{
            k: stability[k]
            for k in ("converged_fraction", "decrease_violations", "samples_checked")
        },
        "final_distance": metrics["final_distance"],
    }


def _run_dir(args: argparse.Namespace, part: str, task: str, seed: int) -> Path:
    return args.runs / part / task.replace(" ", "_") / f"seed={seed}"


def _run_cli(
    args: argparse.Namespace, settings: SweepSettings, part: str, tasks: dict[str, list[str]]
) -> None:
    """Each (task, seed) through ``snds train`` with the recipe's flags; skips finished runs.

    Arguments:
        tasks: Task name -> the flags that select its data.
    """
    pending = []
    for task, select in tasks.items():
        for seed in range(args.seeds):
            directory = _run_dir(args, part, task, seed)
            if (directory / "row.json").is_file():
                continue
            argv = ["--quiet", "train", *select, "--seed", str(seed), *RECIPES[args.recipe]]
            argv += ["--rollouts", str(settings.rollouts), "--samples", str(settings.samples)]
            pending.append((task, seed, directory, argv + ["--out", str(directory)]))
    # Each row is written as its run finishes: an interrupted sweep keeps every finished run.
    calls = [(argv,) for *_, argv in pending]
    for index, cpu in starmap_unordered(_snds_train, calls, jobs=args.jobs):
        task, seed, directory, _ = pending[index]
        row = _cli_row(part, task, seed, directory, cpu)
        write_json(directory / "row.json", row)
        print(json.dumps(row), flush=True)


def run_real(args: argparse.Namespace, settings: SweepSettings) -> None:
    """Each (file, seed) through ``snds train`` with its defaults; skips finished runs."""
    if not SHARED.is_dir():
        print(f"reliability: {SHARED} is absent; skipping the real files")
        return
    tasks = {
        task: ["--data", str(SHARED / name), *(["--demos", select] if select else [])]
        for task, (name, select) in REAL_TASKS.items()
    }
    _run_cli(args, settings, "real", tasks)


def _cli_rows(args: argparse.Namespace, part: str, tasks: Sequence[str]) -> list[dict]:
    """The finished ``snds train`` runs of these tasks and seeds, task-major."""
    files = [_run_dir(args, part, t, s) / "row.json" for t in tasks for s in range(args.seeds)]
    return [json.loads(file.read_text()) for file in files if file.is_file()]


def real_rows(args: argparse.Namespace) -> list[dict]:
    """The finished real-file runs of these seeds, task-major."""
    return _cli_rows(args, "real", list(REAL_TASKS))


# ---------------------------------------------------------------------------------------------
# Summaries.


def _by_task(rows: Sequence[dict]) -> dict[tuple[str, str], list[dict]]:
    groups: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["part"], row["task"]), []).append(row)
    return groups


def _cpu(row: dict) -> float:
    return row.get("train_cpu_seconds") or row.get("train_and_check_cpu_seconds") or float("nan")


def task_table(rows: Sequence[dict]) -> str:
    """One line per task: its worst seed on each bar, and how far its seeds spread."""
    lines = [
        "| part | task | runs | all bars met | worst velocity error (relative) | worst / median "
        "seed | lowest converged | violations | DTW (paper scale, mean) | CPU s, max (lasa "
        "by snds benchmark: training; by snds train: training and check) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for (part, task), group in _by_task(rows).items():
        errors = [r["velocity_error_relative"] for r in group]
        met = sum(all(meets_bars(r).values()) for r in group)
        lines.append(
            f"| {part} | {task} | {len(group)} | {met} | {max(errors):.4f} | "
            f"{max(errors) / statistics.median(errors):.2f} | "
            f"{min(r['converged_fraction'] for r in group):.3f} | "
            f"{sum(r['decrease_violations'] for r in group)} | "
            f"{statistics.mean(r['dtw_paper'] for r in group):.3f} | "
            f"{max(_cpu(r) for r in group):.1f} |"
        )
    return "\n".join(lines)


def overall_table(rows: Sequence[dict]) -> str:
    """One line per part: how many runs met each bar, and the worst figures."""
    lines = [
        "| part | runs | accuracy met | converged 1.0 | 0 violations | all bars | worst "
        "velocity error (relative) | lowest converged | decrease samples checked |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for part in ("lasa", "real"):
        group = [r for r in rows if r["part"] == part]
        if not group:
            continue
        bars = [meets_bars(r) for r in group]
        worst = max(group, key=lambda r: r["velocity_error_relative"])
        lowest = min(group, key=lambda r: r["converged_fraction"])
        lines.append(
            f"| {part} | {len(group)} | {sum(b['accuracy'] for b in bars)} | "
            f"{sum(b['converged'] for b in bars)} | {sum(b['no_violations'] for b in bars)} | "
            f"{sum(all(b.values()) for b in bars)} | "
            f"{worst['velocity_error_relative']:.4f} ({worst['task']}, seed {worst['seed']}) | "
            f"{lowest['converged_fraction']:.3f} ({lowest['task']}, seed {lowest['seed']}) | "
            f"{sum(r['samples_checked'] for r in group):,} |"
        )
    return "\n".join(lines)


def against(rows: Sequence[dict], other: Sequence[dict], label: str) -> str:
    """How these runs compare with ``other`` recipe's on the same (part, task, seed)."""
    base = {(r["part"], r["task"], r["seed"]): r for r in other}
    pairs = [(r, base[k]) for r in rows if (k := (r["part"], r["task"], r["seed"])) in base]
    lines = [
        f"| part | runs | error lower | median error ratio (these / {label}) | worst ratio | "
        f"DTW lower | mean DTW (these / {label}) | median training-time ratio |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for part in ("lasa", "real"):
        mine = [(r, b) for r, b in pairs if r["part"] == part]
        if not mine:
            continue
        ratios = [r["velocity_error_relative"] / b["velocity_error_relative"] for r, b in mine]
        worst = max(range(len(mine)), key=ratios.__getitem__)
        dtw = [(r["dtw_paper"], b["dtw_paper"]) for r, b in mine]
        # Wall time of the training alone: both recipes record it, two runs side by side.
        wall = [r["train_seconds"] / b["train_seconds"] for r, b in mine]
        lines.append(
            f"| {part} | {len(mine)} | {sum(q < 1 for q in ratios)} | "
            f"{statistics.median(ratios):.2f} | {ratios[worst]:.2f} ({mine[worst][0]['task']}, "
            f"seed {mine[worst][0]['seed']}) | {sum(a < b for a, b in dtw)} | "
            f"{statistics.mean(a for a, _ in dtw):.2f} / {statistics.mean(b for _, b in dtw):.2f}"
            f" | {statistics.median(wall):.1f} |"
        )
    return f"Against the {label} recipe on the same runs (its table below or above):\n\n" + (
        "\n".join(lines)
    )


def _results(recipe: str) -> Path:
    return RESULTS / ("reliability" if recipe == "default" else f"reliability-{recipe}")


def write_results(rows: Sequence[dict], args: argparse.Namespace, settings: SweepSettings) -> None:
    results = _results(args.recipe)
    name = results.name
    results.mkdir(parents=True, exist_ok=True)
    write_json(results / "rows.json", list(rows))
    fields = list(dict.fromkeys(k for r in rows for k in r))

    def write_csv(tmp: Path) -> None:
        with tmp.open("w", newline="") as file:
            writer = csv.DictWriter(file, fieldnames=fields)
            writer.writeheader()
            writer.writerows(rows)

    atomic_write(results / "rows.csv", write_csv)
    recipe = "" if args.recipe == "default" else f" --recipe {args.recipe}"
    jobs = args.jobs or os.cpu_count() or 1
    flags = f"--seeds {args.seeds}{recipe}" + (f" --jobs {args.jobs}" if args.jobs else "")
    header = (
        f"{machine_line(machine(jobs=jobs))} A resumed sweep keeps the rows of its earlier runs. "
        f"`python benchmarks/reliability.py {flags}`. Bars: held-out velocity error at most "
        f"{ACCURACY_BAR:g} of the velocities' mean square, converged 1.0 from "
        f"{settings.rollouts} random starts in the 3x box, 0 violations in {settings.samples:,} "
        f"decrease samples in the 10x box (float64). Per task: `results/{name}/summary.md`; "
        f"rows: `results/{name}/rows.csv`."
    )
    body = f"{header}\n\n{overall_table(rows)}"
    other = "plain" if args.recipe == "default" else "default"
    other_rows = _results(other) / "rows.json"
    if other_rows.is_file():
        body += "\n\n" + against(rows, json.loads(other_rows.read_text()), other)
    (results / "summary.md").write_text(f"{body}\n\n{task_table(rows)}\n")
    if not args.no_readme:
        write_readme_section(name, body)


def main() -> None:
    options = parser(__doc__, seeds=5, threads=False)
    options.add_argument("--part", choices=["lasa", "real", "both"], default="both")
    options.add_argument("--motions", default="all", help="LASA motions or groups")
    options.add_argument("--rollouts", type=int, default=300, help="per run's stability check")
    options.add_argument("--samples", type=int, default=20_000, help="per run's decrease check")
    options.add_argument("--jobs", type=int, default=None, help="local processes (all cores)")
    options.add_argument(
        "--runs", type=Path, default=None, help="runs folder (runs/reliability[-RECIPE])"
    )
    options.add_argument(
        "--recipe",
        choices=list(RECIPES),
        default="default",
        help="training flags to add (default: none); a recipe has its own results and table",
    )
    args = options.parse_args()
    settings = SweepSettings(rollouts=args.rollouts, samples=args.samples)
    if args.runs is None:
        args.runs = Path("runs") / _results(args.recipe).name
    check_runs_folder(args.runs, sweep_settings(args.recipe, settings))
    if args.part in ("real", "both"):
        run_real(args, settings)
    if args.part in ("lasa", "both"):
        run_lasa(args, settings)
    # The table holds every finished run of both parts, whichever part ran now.
    write_results(lasa_rows(args) + real_rows(args), args, settings)


if __name__ == "__main__":
    main()
