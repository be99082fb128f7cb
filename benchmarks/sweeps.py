"""The paper's Section IV experiments as `snds benchmark` sweeps, summarised into the README.

Three sweeps, each resumable (a rerun skips the runs already in its folder):

* ``paper8``: the paper's 8 LASA motions, all 7 demonstrations (its Fig. 4, 5);
* ``paper8-demos1``: the same from one demonstration (sample efficiency);
* ``multi``: Multi_Models_1-4, motions made of several distinct shapes (its Fig. 6).

    python benchmarks/sweeps.py                    # all five methods x 10 seeds, into README
    python benchmarks/sweeps.py --methods snds,bc,lpvds --seeds 3 --only paper8

Runs go to ``runs/sweeps/<name>/`` (models included); each sweep's ``results.csv``,
``results.jsonl``, ``sweep.json``, ``summary.md`` and figures are copied to
``benchmarks/results/sweeps/<name>/``, and its summary goes between the ``sweep-<name>``
markers of ``benchmarks/README.md``. A sweep whose ``runs/`` folder is gone (a fresh clone,
another machine) starts from the committed ``results.jsonl``: its finished rows are not run
again, though their models are not there for the streamline figure.

A sweep's rows come from one commit: ``provenance.json`` beside them records it (with its
``src/`` tree, the wall time and where the runs ran), and resuming with another ``src/``, or
with uncommitted changes there, is refused. ``--scheduler`` runs on a Dask cluster, and keeps
each run's start and stop from its task stream (``tasks.jsonl``, read by
``cluster_scaling.py``)::

    dask scheduler --host 127.0.0.1 --port 8786 &
    dask worker tcp://127.0.0.1:8786 --nworkers 2 --nthreads 1 &
    python benchmarks/sweeps.py --methods snds,bc,sdsef,lpvds,seds --scheduler tcp://127.0.0.1:8786
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import subprocess
import time
from pathlib import Path

from _readme import shrink_png, write_readme_section
from cluster_scaling import TASKS, collect, task_stream

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
from snds.io import write_json

HERE = Path(__file__).resolve().parent
#: name -> (motions, demonstrations per task; None: all 7)
SWEEPS: dict[str, tuple[str, int | None]] = {
    "paper8": ("paper8", None),
    "paper8-demos1": ("paper8", 1),
    "multi": ("multi", None),
}
PROVENANCE = "provenance.json"
COPIED = (
    "results.csv",
    "results.jsonl",
    "sweep.json",
    PROVENANCE,
    TASKS,
    "summary.md",
    "mse_violin.png",
    "dtw_violin.png",
    "train_time.png",
    "converged.png",
)


def commit() -> tuple[str, str]:
    """The checked-out commit and its ``src/`` tree; refuses uncommitted changes there."""
    root = HERE.parent

    def git(*argv: str) -> str:
        return subprocess.run(
            ["git", *argv], cwd=root, check=True, capture_output=True, text=True
        ).stdout.strip()

    if git("status", "--porcelain", "--", "src"):
        raise SystemExit("src/ has uncommitted changes: a sweep's rows must come from one commit")
    return git("rev-parse", "HEAD"), git("rev-parse", "HEAD:src")


def provenance(out: Path, args: argparse.Namespace) -> dict:
    """The sweep's record in ``out``: the commit its runs started from and that commit's
    ``src/`` tree; resuming with another ``src/``, or rows without a record, is refused.

    The record is written before any run starts, with the time it started; a sweep that was
    stopped before it could add its wall time gets the part up to its last finished row (the
    time ``results.jsonl`` was last written) when it resumes.
    """
    path = out / PROVENANCE
    results = out / "results.jsonl"
    record = json.loads(path.read_text()) if path.is_file() else {}
    if not record and results.exists():
        raise SystemExit(
            f"{out} holds rows but no {PROVENANCE}, so their commit is unknown: delete the "
            "folder to rerun, or write the record of the commit they come from"
        )
    head, tree = commit()
    if record.get("src_tree", tree) != tree:
        raise SystemExit(
            f"{out} holds rows from commit {record['commit'][:10]}, whose src/ differs from "
            "this one's: delete the folder (and its copy under benchmarks/results/sweeps) "
            "to rerun"
        )
    started = record.pop("part_started", None)
    if started is not None:
        last = results.stat().st_mtime if results.exists() else started
        record["wall_seconds"] = record.get("wall_seconds", 0.0) + max(0.0, last - started)
        record["interrupted"] = record.get("interrupted", 0) + 1
    record.setdefault("commit", head)
    record.update(
        src_tree=tree,
        where=f"Dask at {args.scheduler}"
        if args.scheduler
        else f"{args.jobs or os.cpu_count()} local processes",
        machine=f"{platform.machine()}, {os.cpu_count()} cores, {platform.platform()}",
    )
    return record


def run(name: str, args: argparse.Namespace, settings: SweepSettings) -> str:
    """Runs (or resumes) one sweep, copies its results, returns its README paragraph."""
    motions, demos = SWEEPS[name]
    tasks = make_tasks(
        resolve_motions(motions), resolve_methods(args.methods), seeds=args.seeds, demos=demos
    )
    out = args.runs / name
    copy = HERE / "results" / "sweeps" / name
    # Committed rows are resumed only with the record of the commit they come from.
    if not (out / "results.jsonl").exists() and (copy / PROVENANCE).exists():
        out.mkdir(parents=True, exist_ok=True)
        for file in ("results.jsonl", "sweep.json", PROVENANCE):
            shutil.copyfile(copy / file, out / file)
    out.mkdir(parents=True, exist_ok=True)
    record = provenance(out, args)
    if args.done_only:
        done = finished_rows(out)
        tasks = [task for task in tasks if task.key in done]
    pending = len(tasks) - len(finished_rows(out).keys() & {task.key for task in tasks})
    if pending:
        record["part_started"] = time.time()
    write_json(out / PROVENANCE, record)
    rows = run_sweep(tasks, out=out, settings=settings, jobs=args.jobs, scheduler=args.scheduler)
    if args.scheduler and pending:
        collect(task_stream(args.scheduler), out)  # each run's start and stop, for scaling
    if pending:
        started = record.pop("part_started")
        record["wall_seconds"] = record.get("wall_seconds", 0.0) + time.time() - started
        record["runs"] = len(rows)
    write_json(out / PROVENANCE, record)
    plot_benchmark(rows, out)
    copy.mkdir(parents=True, exist_ok=True)
    files = COPIED + (("streamlines.png",) if args.streamlines else ())
    for file in files:
        if (out / file).exists():
            shutil.copyfile(out / file, copy / file)
            if file == "streamlines.png":
                shrink_png(copy / file)
    figures = " ".join(
        f"![{file}](results/sweeps/{name}/{file})" for file in files if file.endswith(".png")
    )
    demos_text = "all 7 demonstrations" if demos is None else f"{demos} demonstration(s)"
    seeds = (
        f"up to {args.seeds} seeds (the runs finished so far)"
        if args.done_only
        else (f"{args.seeds} seeds")
    )
    wall = record.get("wall_seconds")
    where = (
        f"Commit `{record['commit'][:10]}`; {len(rows)} runs on {record['where']}"
        + (f" in {wall / 60:.0f} min wall time" if wall else "")
        + (
            f" (resumed {record['interrupted']} time(s); a stopped part counts up to its last "
            "finished run)"
            if record.get("interrupted")
            else ""
        )
        + ".\n\n"
    )
    return (
        f"#### {name}: {motions}, {demos_text}, {seeds}\n\n{where}"
        f"`python benchmarks/sweeps.py --only {name}` (or `snds benchmark --methods "
        f"{args.methods} --motions {motions}"
        + (f" --demos {demos}" if demos else "")
        + f" --seeds {args.seeds} --rollouts {settings.rollouts} --samples "
        f"{settings.samples} --out {out}`). Raw: `results/sweeps/{name}/results.csv`.\n\n"
        f"{summarise(rows)}\n{figures}\n"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", default="snds,bc,sdsef,lpvds,seds")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--only", nargs="+", choices=list(SWEEPS), default=list(SWEEPS))
    parser.add_argument("--rollouts", type=int, default=300, help="per run's stability check")
    parser.add_argument("--samples", type=int, default=20_000, help="per run's decrease check")
    parser.add_argument("--jobs", type=int, default=None, help="local processes (all cores)")
    parser.add_argument("--scheduler", default=None, help="Dask scheduler, e.g. tcp://host:8786")
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
    if args.scheduler and not args.done_only:
        task_stream(args.scheduler)  # the scheduler records its task stream from now on
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
