"""Torch threads: one against two for a fit, an evaluation (with the stability check), and
the README's Python example against ``snds train`` for the same work.

The library runs its work on :func:`snds.threads.fastest_threads` threads unless the caller
says otherwise; this measures the choice. Each size runs with 1 and 2 threads alternately,
``--rounds`` times, in this process (wall and CPU seconds, best of the rounds and all of
them). ``--readme`` also times the README's Python block run as a script against ``python
-m snds train --motion Sine`` (the same data, recipe, fit and check), each in a fresh
process, alternately. The load average before and after each part is written beside it: on a
shared machine the figures move with the other work, the ratio of one to two threads far
less than the wall times.

    python benchmarks/threads.py                      # fit and evaluate, 1 vs 2 threads
    python benchmarks/threads.py --readme --rounds 1  # and the README example vs the CLI

Writes ``benchmarks/results/threads.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from _runner import cpu_name

import snds
from snds.parallel import torch_threads

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def _timed(work) -> dict:
    wall, cpu = time.perf_counter(), time.process_time()
    work()
    return {"wall": time.perf_counter() - wall, "cpu": time.process_time() - cpu}


def measure_library(steps: int, rounds: int, rollouts: int, rows: list, save) -> None:
    """A fit of ``steps`` steps (default recipe, Sine) and its evaluation (the default check
    with ``rollouts`` random starts) at 1 and 2 threads, alternately; ``save`` after each."""
    demos = snds.RECIPES["default"].phase.apply(snds.load_lasa("Sine"))
    split = snds.split_samples(demos, test_fraction=0.2, seed=0)
    config = snds.TrainConfig(steps=steps, seed=0)
    for round_ in range(rounds):
        for threads in (1, 2):
            policy = snds.make_policy(demos, config=snds.PolicyConfig())
            before = os.getloadavg()
            fit = _timed(
                lambda p=policy, t=threads: snds.fit(
                    p, demos, split, config=config, progress=False, threads=t
                )
            )
            check = _timed(
                lambda p=policy, t=threads: snds.evaluate.evaluate(
                    p, demos, split, check=snds.CheckConfig(rollouts=rollouts), threads=t
                )
            )
            rows.append(
                {
                    "round": round_,
                    "threads": threads,
                    "fit_steps": steps,
                    "check_rollouts": rollouts,
                    "fit_wall": fit["wall"],
                    "fit_cpu": fit["cpu"],
                    "evaluate_wall": check["wall"],
                    "evaluate_cpu": check["cpu"],
                    "load_before": before,
                    "load_after": os.getloadavg(),
                }
            )
            print(json.dumps(rows[-1]), flush=True)
            save()


def _readme_block() -> str:
    text = (ROOT / "README.md").read_text()
    return text.split("```python\n", 1)[1].split("```", 1)[0]


def _child(argv: list[str], cwd: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    load = os.getloadavg()
    start = time.perf_counter()
    subprocess.run(argv, cwd=cwd, env=env, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall": wall, "cpu": cpu, "load_before": load, "load_after": os.getloadavg()}


def measure_readme(rounds: int, rows: list, save) -> None:
    """The README's Python block as a script against ``snds train --motion Sine`` (the same
    data, recipe, fit and default check), each in a fresh process."""
    with tempfile.TemporaryDirectory() as folder:
        work = Path(folder)
        script = work / "readme_example.py"
        script.write_text(_readme_block())
        cli = [sys.executable, "-m", "snds", "--quiet", "train", "--motion", "Sine"]
        for round_ in range(rounds):
            for name, argv in (
                ("readme", [sys.executable, str(script)]),
                ("cli", [*cli, "--out", str(work / "run")]),
            ):
                rows.append({"round": round_, "what": name, **_child(argv, work)})
                print(json.dumps(rows[-1]), flush=True)
                save()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=100, help="steps of the timed fit")
    parser.add_argument("--rounds", type=int, default=2, help="alternations of 1 and 2")
    parser.add_argument("--rollouts", type=int, default=100, help="random starts of the check")
    parser.add_argument("--readme", action="store_true", help="also the README vs the CLI")
    parser.add_argument("--no-library", action="store_true", help="skip the 1 vs 2 threads part")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "threads.json")
    args = parser.parse_args()
    record = {
        "cpu": cpu_name(),
        "cores": os.cpu_count(),
        "torch": torch.__version__,
        "default_threads": torch.get_num_threads(),
        "library_threads": snds.threads.fastest_threads(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "note": "shared machine: see load_before / load_after of each row",
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)

    def save() -> None:  # after every row: a long run interrupted keeps what it measured
        args.out.write_text(json.dumps(record, indent=1) + "\n")

    if args.readme:
        record["readme_vs_cli"] = []
        measure_readme(args.rounds, record["readme_vs_cli"], save)
    record["library"] = []
    if args.no_library:
        save()
        return
    with torch_threads(torch.get_num_threads()):
        measure_library(args.steps, args.rounds, args.rollouts, record["library"], save)
    save()
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
