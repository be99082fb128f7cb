"""The paper's Section IV as `snds benchmark` sweeps: SNDS against the published baselines.

Three sweeps, each resumable (a rerun skips the runs already in its folder):

* ``paper8``: the paper's 8 LASA motions, all 7 demonstrations (its Fig. 4, 5);
* ``paper8-demos1``: the same from one demonstration (sample efficiency);
* ``multi``: Multi_Models_1-4, motions made of several distinct shapes (its Fig. 6).

    python benchmarks/sweeps.py                    # all five methods x 10 seeds, into README
    python benchmarks/sweeps.py --methods snds,bc,lpvds --seeds 3 --only paper8

Runs go to ``runs/sweeps/<name>/`` (models included); each sweep's ``results.csv``,
``results.jsonl``, ``sweep.json``, ``summary.md`` and figures are copied to
``benchmarks/results/sweeps/<name>/``. The README gets, per sweep, SNDS against the best
published baseline (SDS-EF, LPV-DS, SEDS) per motion, BC beside them as the unconstrained
control (block ``snds-vs-baselines`` for paper8; the other sweeps' go to the top of their
``summary.md``). ``--tables`` rebuilds those from the committed results without running
anything, and prints the sweeps' wall time on N Dask workers. A sweep whose ``runs/`` folder
is gone (a fresh clone, another machine) starts from the committed ``results.jsonl``: its
finished rows are not run again, though their models are not there for the figures.

A sweep's rows come from one commit: ``provenance.json`` beside them records it (with its
``src/`` tree, the wall time and where the runs ran), and resuming with another ``src/``, or
with uncommitted changes there, is refused. ``--scheduler`` runs on a Dask cluster, and keeps
each run's start and stop from its task stream (``tasks.jsonl``)::

    dask scheduler --host 127.0.0.1 --port 8786 &
    dask worker tcp://127.0.0.1:8786 --nworkers 2 --nthreads 1 &
    python benchmarks/sweeps.py --scheduler tcp://127.0.0.1:8786
    python benchmarks/sweeps.py --tables      # the README blocks from results/sweeps

The wall time on N workers is the makespan of a greedy list schedule of the measured run
durations (the runs in the sweep's order, each to the first free worker, as Dask hands them
out), checked against the measured wall time of the cluster that ran the sweep. The durations
were measured with every core busy; a cluster with a core per worker runs each at least as
fast.
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import shutil
import statistics
import subprocess
import time
from collections import defaultdict
from pathlib import Path

from _runner import RESULTS, machine, machine_line, parser, write_readme_section

from snds.benchmark import (
    MOTION_GROUPS,
    SweepSettings,
    finished_rows,
    make_tasks,
    plot_benchmark,
    resolve_methods,
    resolve_motions,
    run_sweep,
)
from snds.io import write_json

HERE = Path(__file__).resolve().parent
SWEEPS_RESULTS = RESULTS / "sweeps"
#: name -> (motions, demonstrations per task; None: all 7)
SWEEPS: dict[str, tuple[str, int | None]] = {
    "paper8": ("paper8", None),
    "paper8-demos1": ("paper8", 1),
    "multi": ("multi", None),
}
#: name -> the README block of its comparison with the baselines (the others: in its summary)
BLOCKS = {"paper8": "snds-vs-baselines"}
PROVENANCE = "provenance.json"
TASKS = "tasks.jsonl"
#: What a sweep keeps under results/sweeps/<name>/ (the figures stay in runs/).
COPIED = ("results.jsonl", "sweep.json", PROVENANCE, TASKS, "summary.md")
#: The published stable methods a user would pick instead of SNDS.
BASELINES = ("sdsef", "lpvds", "seds")
#: SNDS's network without the projection: the unconstrained control.
CONTROL = "bc"
WORKERS = (1, 2, 4, 8, 16, 32, 64, 128)


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
        machine=machine(jobs=args.jobs or os.cpu_count() or 1),
    )
    return record


def run(name: str, args: argparse.Namespace, settings: SweepSettings) -> str:
    """Runs (or resumes) one sweep and copies its results to ``results/sweeps/<name>/``."""
    motions, demos = SWEEPS[name]
    tasks = make_tasks(
        resolve_motions(motions), resolve_methods(args.methods), seeds=args.seeds, demos=demos
    )
    out = args.runs / name
    copy = SWEEPS_RESULTS / name
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
    plot_benchmark(rows, out)  # the figures, in runs/
    copy.mkdir(parents=True, exist_ok=True)
    for file in COPIED:
        if (out / file).exists():
            shutil.copyfile(out / file, copy / file)
    _summary_header(copy, name, args, settings, record)


def _summary_header(
    copy: Path, name: str, args: argparse.Namespace, settings: SweepSettings, record: dict
) -> None:
    """Heads the copied ``summary.md`` with how the sweep was run and how to rerun it."""
    motions, demos = SWEEPS[name]
    wall = record.get("wall_seconds")
    header = (
        f"# {name}: {motions}, "
        + ("all 7 demonstrations" if demos is None else f"{demos} demonstration(s)")
        + f", {args.seeds} seeds\n\nCommit `{record['commit'][:10]}`, {record['where']}"
        + (f", {wall / 60:.0f} min wall time" if wall else "")
        + f". {machine_line(machine(jobs=args.jobs or os.cpu_count() or 1))} "
        f"Each run's check: {settings.rollouts} rollouts from the 3x box, {settings.samples} "
        f"decrease samples in the 10x box (float64). `python benchmarks/sweeps.py --only {name}` "
        f"(or `snds benchmark --methods {args.methods} --motions {motions}"
        + (f" --demos {demos}" if demos else "")
        + f" --seeds {args.seeds} --rollouts {settings.rollouts} --samples {settings.samples}`)."
        "\n\n"
    )
    path = copy / "summary.md"
    if path.exists():
        path.write_text(header + path.read_text())


def _rows(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _mean(rows: list[dict], key: str) -> float:
    return statistics.fmean(row[key] for row in rows)


def _sd(rows: list[dict], key: str) -> float:
    """The sample standard deviation over seeds (0 for a single run)."""
    return statistics.stdev(row[key] for row in rows) if len(rows) > 1 else 0.0


def _order(motion: str) -> tuple[int, str]:
    """The paper's order of its motions (its Fig. 4), then the rest by name."""
    paper = MOTION_GROUPS["paper8"] + MOTION_GROUPS["multi"]
    return (paper.index(motion), "") if motion in paper else (len(paper), motion)


def compare(rows: list[dict]) -> list[dict]:
    """Per motion, in the paper's order: SNDS's means over its seeds against the best mean of
    the published baselines, and BC's beside them."""
    by: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for row in rows:
        by[(row["motion"], row["method"])].append(row)
    records = []
    for motion in sorted({m for m, method in by if method == "snds"}, key=_order):
        ours = by[(motion, "snds")]
        methods = [m for m in BASELINES if by[(motion, m)]]
        if not methods:
            continue  # no baseline has run on this motion yet
        dtw = {m: _mean(by[(motion, m)], "dtw_paper") for m in methods}
        mse = {m: _mean(by[(motion, m)], "velocity_mse_paper") for m in methods}
        best_dtw, best_mse = min(dtw, key=dtw.get), min(mse, key=mse.get)
        control = by[(motion, CONTROL)]
        records.append(
            {
                "motion": motion,
                "runs": len(ours),
                "dtw": _mean(ours, "dtw_paper"),
                "dtw_sd": _sd(ours, "dtw_paper"),
                "best_baseline_dtw": dtw[best_dtw],
                "best_baseline_dtw_sd": _sd(by[(motion, best_dtw)], "dtw_paper"),
                "best_dtw_method": best_dtw,
                "mse": _mean(ours, "velocity_mse_paper"),
                "best_baseline_mse": mse[best_mse],
                "best_mse_method": best_mse,
                "control_dtw": _mean(control, "dtw_paper") if control else None,
                "control_mse": _mean(control, "velocity_mse_paper") if control else None,
                "control_converged": (
                    min(row["converged_fraction"] for row in control) if control else None
                ),
                "min_converged": min(row["converged_fraction"] for row in ours),
                "violations": sum(row["decrease_violations"] for row in ours),
            }
        )
    return records


def _cell(value: float | None, spec: str) -> str:
    return "n/a" if value is None else format(value, spec)


def comparison_table(records: list[dict], name: str) -> str:
    """The README block of one sweep: SNDS against the baselines, BC beside them."""
    lines = [
        f"`{name}` (means over seeds, paper scale; DTW's standard deviation over seeds in "
        "brackets; **bold**: SNDS below every baseline). Rows: "
        f"`results/sweeps/{name}/results.jsonl`; every method's table: "
        f"`results/sweeps/{name}/summary.md`.",
        "",
        "| motion | runs | SNDS DTW | best baseline DTW | SNDS MSE | best baseline MSE "
        "| SNDS converged (min) | violations | BC DTW | BC MSE | BC converged (min) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        dtw = f"{r['dtw']:.3f}"
        mse = f"{r['mse']:.3g}"
        lines.append(
            f"| {r['motion']} | {r['runs']} "
            f"| {f'**{dtw}**' if r['dtw'] < r['best_baseline_dtw'] else dtw} ({r['dtw_sd']:.3f}) "
            f"| {r['best_dtw_method']} {r['best_baseline_dtw']:.3f} "
            f"({r['best_baseline_dtw_sd']:.3f}) "
            f"| {f'**{mse}**' if r['mse'] < r['best_baseline_mse'] else mse} "
            f"| {r['best_mse_method']} {r['best_baseline_mse']:.3g} "
            f"| {r['min_converged']:.3f} | {r['violations']} "
            f"| {_cell(r['control_dtw'], '.3f')} | {_cell(r['control_mse'], '.3g')} "
            f"| {_cell(r['control_converged'], '.3f')} |"
        )
    dtw_ahead = sum(r["dtw"] < r["best_baseline_dtw"] for r in records)
    mse_ahead = sum(r["mse"] < r["best_baseline_mse"] for r in records)
    lines += ["", f"DTW ahead on {dtw_ahead} of {len(records)}, MSE on {mse_ahead}."]
    return "\n".join(lines)


def _with_comparison(summary: Path, body: str) -> None:
    """Puts the comparison with the baselines at the top of a sweep's ``summary.md``."""
    if not summary.exists():
        return
    marker = "<!-- against-baselines -->"
    text = summary.read_text().split(marker)[-1].lstrip()
    summary.write_text(f"{body}\n\n{marker}\n\n{text}")


def task_stream(scheduler: str) -> list[dict]:
    """The finished tasks the scheduler remembers: key, worker, start and stop (epoch s).

    The scheduler records its task stream once a client has asked for it, which
    :func:`main` does when it starts.
    """
    from dask.distributed import Client

    with Client(scheduler) as client:
        stream = client.get_task_stream(start=0)
    events = []
    for task in stream:
        compute = [s for s in task.get("startstops", ()) if s["action"] == "compute"]
        if compute:
            events.append(
                {
                    "key": str(task["key"]),
                    "worker": str(task["worker"]),
                    "start": compute[0]["start"],
                    "stop": compute[-1]["stop"],
                }
            )
    return events


def collect(events: list[dict], folder: Path) -> int:
    """Adds the events of the runs whose rows are in ``folder`` to its ``tasks.jsonl``
    (a run already there keeps its first record); returns how many it holds."""
    rows = finished_rows(folder)
    path = folder / TASKS
    held = {}
    if path.exists():
        held = {e["key"]: e for e in map(json.loads, path.read_text().splitlines()) if e}
    for event in events:
        if event["key"] in rows and event["key"] not in held:
            held[event["key"]] = event | {"method": rows[event["key"]]["method"]}
    ordered = sorted(held.values(), key=lambda e: e["start"])
    tmp = path.with_suffix(".tmp")
    tmp.write_text("".join(json.dumps(e) + "\n" for e in ordered))
    tmp.replace(path)
    return len(ordered)


def makespan(durations: list[float], workers: int) -> float:
    """The wall time of running ``durations`` in order, each on the first free worker."""
    free = [0.0] * workers
    for duration in durations:
        heapq.heapreplace(free, free[0] + duration)
    return max(free)


def scaling(events: list[dict]) -> dict:
    """The measured wall time and workers of ``events``, and the makespan on more workers."""
    events = sorted(events, key=lambda e: e["start"])
    durations = [e["stop"] - e["start"] for e in events]
    by_method: dict[str, list[float]] = defaultdict(list)
    for event, duration in zip(events, durations, strict=True):
        by_method[event["method"]].append(duration)
    workers = len({e["worker"] for e in events})
    return {
        "runs": len(events),
        "workers": workers,
        "run_seconds": sum(durations),
        "measured_wall": max(e["stop"] for e in events) - min(e["start"] for e in events),
        "schedule_wall": makespan(durations, workers),
        "longest_run": max(durations),
        "mean_run_by_method": {m: statistics.fmean(d) for m, d in by_method.items()},
        "makespan": {n: makespan(durations, n) for n in WORKERS},
    }


def scaling_table(results: dict[str, dict]) -> str:
    """The README block ``cluster-scaling``."""
    shown = (2, 8, 16, 64)
    lines = [
        "| sweep | runs timed | run time (worker-min) | measured wall on 2 workers (min) "
        "| schedule's wall (min) | longest run (s) | "
        + " | ".join(f"{n} workers (min)" for n in shown)
        + " |",
        "|---|---|---|---|---|---|" + "---|" * len(shown),
    ]
    for name, r in results.items():
        lines.append(
            f"| {name} | {r['runs']} | {r['run_seconds'] / 60:.0f} "
            f"| {r['measured_wall'] / 60:.1f} | {r['schedule_wall'] / 60:.1f} "
            f"| {r['longest_run']:.0f} | "
            + " | ".join(f"{r['makespan'][n] / 60:.1f}" for n in shown)
            + " |"
        )
    return "\n".join(lines)


def tables(names: list[str], *, readme: bool) -> None:
    """Writes the README blocks from ``results/sweeps`` (no runs)."""
    timed = {}
    for name in names:
        folder = SWEEPS_RESULTS / name
        if not (folder / "results.jsonl").exists():
            continue
        records = compare(_rows(folder / "results.jsonl"))
        body = comparison_table(records, name)
        print(body)
        if name not in BLOCKS:
            _with_comparison(folder / "summary.md", body)
        elif readme:
            write_readme_section(BLOCKS[name], body)
        if (folder / TASKS).exists():
            timed[name] = scaling(_rows(folder / TASKS))
    if timed:  # printed only: the README quotes it in a sentence
        print(scaling_table(timed))


def main() -> None:
    options = parser(__doc__, seeds=10, threads=False)
    options.add_argument("--methods", default="snds,bc,sdsef,lpvds,seds")
    options.add_argument("--only", nargs="+", choices=list(SWEEPS), default=list(SWEEPS))
    options.add_argument("--rollouts", type=int, default=300, help="per run's stability check")
    options.add_argument("--samples", type=int, default=20_000, help="per run's decrease check")
    options.add_argument("--jobs", type=int, default=None, help="local processes (all cores)")
    options.add_argument("--scheduler", default=None, help="Dask scheduler, e.g. tcp://host:8786")
    options.add_argument("--runs", type=Path, default=Path("runs/sweeps"))
    options.add_argument("--tables", action="store_true", help="only the README blocks, no runs")
    options.add_argument(
        "--done-only",
        action="store_true",
        help="run nothing: summarise the runs of these methods and seeds already finished",
    )
    args = options.parse_args()
    if not args.tables:
        settings = SweepSettings(rollouts=args.rollouts, samples=args.samples)
        if args.scheduler and not args.done_only:
            task_stream(args.scheduler)  # the scheduler records its task stream from now on
        for name in args.only:
            run(name, args, settings)
    tables(args.only, readme=not args.no_readme)


if __name__ == "__main__":
    main()
