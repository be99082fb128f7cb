"""How a sweep's wall time scales with the workers of a Dask cluster, from its measured runs.

A sweep run with ``--scheduler`` keeps each run's start and stop on its worker
(``tasks.jsonl`` beside its ``results.jsonl``, taken from the scheduler's task stream). The
runs are independent, so the wall time on N single-thread workers is the makespan of a
greedy list schedule of those durations on N machines: the runs in the sweep's order, each
to the first free worker, as Dask's scheduler hands them out. This script checks that the
schedule reproduces the measured wall time on the cluster that ran the sweep, then gives it
for more workers, with the two bounds: the total run time over N, and the longest run.

    python benchmarks/cluster_scaling.py --collect tcp://127.0.0.1:8786   # after a sweep
    python benchmarks/cluster_scaling.py                                  # table into README

The durations were measured with every core busy, so they include the contention of runs side
by side; a cluster with a core per worker and nothing else on it runs each at least as fast.
"""

from __future__ import annotations

import argparse
import heapq
import json
import statistics
from collections import defaultdict
from pathlib import Path

from _readme import write_readme_section

from snds.benchmark import finished_rows
from snds.io import write_json

HERE = Path(__file__).resolve().parent
SWEEPS = HERE / "results" / "sweeps"
TASKS = "tasks.jsonl"
WORKERS = (1, 2, 4, 8, 16, 32, 64, 128)


def task_stream(scheduler: str) -> list[dict]:
    """The finished tasks the scheduler remembers: key, worker, start and stop (epoch s).

    The scheduler records its task stream once a client has asked for it; ``sweeps.py`` asks
    when it starts.
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
    """The measured wall time and worker count of ``events``, and the makespan for more
    workers with its bounds."""
    events = sorted(events, key=lambda e: e["start"])
    durations = [e["stop"] - e["start"] for e in events]
    total = sum(durations)
    workers = len({e["worker"] for e in events})
    measured = max(e["stop"] for e in events) - min(e["start"] for e in events)
    by_method: dict[str, list[float]] = defaultdict(list)
    for event, duration in zip(events, durations, strict=True):
        by_method[event["method"]].append(duration)
    return {
        "runs": len(events),
        "workers": workers,
        "run_seconds": total,
        "measured_wall": measured,
        "schedule_wall": makespan(durations, workers),
        "longest_run": max(durations),
        "mean_run_by_method": {m: statistics.fmean(d) for m, d in by_method.items()},
        "makespan": {n: makespan(durations, n) for n in WORKERS},
    }


def table(results: dict[str, dict]) -> str:
    lines = [
        "| sweep | runs | run time (worker-min) | workers | measured wall (min) "
        "| schedule's wall (min) | longest run (s) | "
        + " | ".join(f"{n} workers (min)" for n in WORKERS)
        + " |",
        "|---|---|---|---|---|---|---|" + "---|" * len(WORKERS),
    ]
    for name, r in results.items():
        lines.append(
            f"| {name} | {r['runs']} | {r['run_seconds'] / 60:.0f} | {r['workers']} "
            f"| {r['measured_wall'] / 60:.1f} | {r['schedule_wall'] / 60:.1f} "
            f"| {r['longest_run']:.0f} | "
            + " | ".join(f"{r['makespan'][n] / 60:.1f}" for n in WORKERS)
            + " |"
        )
    methods = sorted({m for r in results.values() for m in r["mean_run_by_method"]})
    lines += [
        "",
        "Mean run (training and its stability check), seconds: "
        + "; ".join(
            f"{name}: "
            + ", ".join(
                f"{m} {r['mean_run_by_method'][m]:.0f}"
                for m in methods
                if m in r["mean_run_by_method"]
            )
            for name, r in results.items()
        )
        + ".",
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--collect", metavar="SCHEDULER", help="first store the task stream")
    parser.add_argument("--sweeps", nargs="+", default=["paper8", "paper8-demos1", "multi"])
    parser.add_argument("--no-readme", action="store_true")
    args = parser.parse_args()
    events = task_stream(args.collect) if args.collect else []
    results = {}
    for name in args.sweeps:
        folder = SWEEPS / name
        if args.collect:
            print(f"{name}: {collect(events, folder)} runs timed")
        path = folder / TASKS
        if path.exists():
            timed = [json.loads(line) for line in path.read_text().splitlines() if line]
            results[name] = scaling(timed)
    write_json(HERE / "results" / "cluster_scaling.json", results)
    body = table(results)
    print(body)
    if not args.no_readme:
        write_readme_section("cluster-scaling", body)


if __name__ == "__main__":
    main()
