"""The paper's Section IV experiments as `snds benchmark` sweeps, summarised into the README.

Three sweeps, each resumable (a rerun skips the runs already in its folder):

* ``paper8``: the paper's 8 LASA motions, all 7 demonstrations (its Fig. 4, 5);
* ``paper8-demos1``: the same from one demonstration (sample efficiency);
* ``multi``: Multi_Models_1-4, motions made of several distinct shapes (its Fig. 6).

    python benchmarks/sweeps.py                           # snds,bc x 10 seeds, into README
    python benchmarks/sweeps.py --methods snds,bc,lpvds --seeds 3 --only paper8

Runs go to ``runs/sweeps/<name>/`` (models included); each sweep's ``results.csv``,
``results.jsonl``, ``sweep.json``, ``summary.md`` and figures are copied to
``benchmarks/results/sweeps/<name>/``, and its summary goes between the ``sweep-<name>``
markers of ``benchmarks/README.md``. A sweep whose ``runs/`` folder is gone (a fresh clone,
another machine) starts from the committed ``results.jsonl``: its finished rows are not run
again, though their models are not there for the streamline figure.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shutil
from pathlib import Path

from _readme import write_readme_section

from snds.benchmark import (
    SweepSettings,
    finished_rows,
    make_tasks,
    plot_benchmark,
    resolve_methods,
    resolve_motions,
    run_sweep,
    summarise,
)

HERE = Path(__file__).resolve().parent
#: name -> (motions, demonstrations per task; None: all 7)
SWEEPS: dict[str, tuple[str, int | None]] = {
    "paper8": ("paper8", None),
    "paper8-demos1": ("paper8", 1),
    "multi": ("multi", None),
}
COPIED = (
    "results.csv",
    "results.jsonl",
    "sweep.json",
    "summary.md",
    "mse_violin.png",
    "dtw_violin.png",
    "train_time.png",
    "converged.png",
)


def run(name: str, args: argparse.Namespace, settings: SweepSettings) -> str:
    """Runs (or resumes) one sweep, copies its results, returns its README paragraph."""
    motions, demos = SWEEPS[name]
    tasks = make_tasks(
        resolve_motions(motions), resolve_methods(args.methods), seeds=args.seeds, demos=demos
    )
    out = args.runs / name
    copy = HERE / "results" / "sweeps" / name
    if not (out / "results.jsonl").exists() and (copy / "results.jsonl").exists():
        out.mkdir(parents=True, exist_ok=True)
        for file in ("results.jsonl", "sweep.json"):
            shutil.copyfile(copy / file, out / file)
    if args.done_only:
        done = finished_rows(out)
        tasks = [task for task in tasks if task.key in done]
    rows = run_sweep(tasks, out=out, settings=settings, jobs=args.jobs)
    plot_benchmark(rows, out)
    copy.mkdir(parents=True, exist_ok=True)
    files = COPIED + (("streamlines.png",) if args.streamlines else ())
    for file in files:
        if (out / file).exists():
            shutil.copyfile(out / file, copy / file)
    figures = " ".join(
        f"![{file}](results/sweeps/{name}/{file})" for file in files if file.endswith(".png")
    )
    demos_text = "all 7 demonstrations" if demos is None else f"{demos} demonstration(s)"
    seeds = (
        f"up to {args.seeds} seeds (the runs finished so far)"
        if args.done_only
        else (f"{args.seeds} seeds")
    )
    return (
        f"#### {name}: {motions}, {demos_text}, {seeds}\n\n"
        f"`python benchmarks/sweeps.py --only {name}` (or `snds benchmark --methods "
        f"{args.methods} --motions {motions}"
        + (f" --demos {demos}" if demos else "")
        + f" --seeds {args.seeds} --rollouts {settings.rollouts} --samples "
        f"{settings.samples} --out {out}`). Raw: `results/sweeps/{name}/results.csv`.\n\n"
        f"{summarise(rows)}\n{figures}\n"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", default="snds,bc")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--only", nargs="+", choices=list(SWEEPS), default=list(SWEEPS))
    parser.add_argument("--rollouts", type=int, default=300, help="per run's stability check")
    parser.add_argument("--samples", type=int, default=20_000, help="per run's decrease check")
    parser.add_argument("--jobs", type=int, default=None, help="local processes (all cores)")
    parser.add_argument("--runs", type=Path, default=Path("runs/sweeps"))
    parser.add_argument("--streamlines", action="store_true", help="also copy streamlines.png")
    parser.add_argument("--no-readme", action="store_true")
    parser.add_argument(
        "--done-only",
        action="store_true",
        help="run nothing: summarise the runs of these methods and seeds already finished",
    )
    args = parser.parse_args()
    settings = SweepSettings(rollouts=args.rollouts, samples=args.samples)
    machine = f"{platform.machine()}, {os.cpu_count()} cores, {platform.platform()}"
    for name in args.only:
        paragraph = run(name, args, settings)
        if not args.no_readme:
            header = (
                f"Measured {datetime.date.today().isoformat()} on {machine}; runs side by "
                "side on all cores, one torch thread each; each run's stability check: "
                f"{settings.rollouts} rollouts from the 3x box, {settings.samples} decrease "
                "samples in the 10x box (float64)."
            )
            write_readme_section(f"sweep-{name}", paragraph + "\n" + header)


if __name__ == "__main__":
    main()
