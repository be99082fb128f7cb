"""Core benchmark: the default SNDS configuration on the paper's 8 LASA motions.

Runs every (motion, seed) as ``snds train --phase-codes 0 --plot`` does
(:func:`snds.run.train_run` into a temporary folder): all 7 demonstrations, a random 0.8 / 0.2
split of the samples, the evaluation on the test samples with the library's default check
(random starts from a box 3x the extent, decrease-condition samples in a box 10x the extent)
and the plots, each part timed from the run's callbacks. Each run has one torch thread;
``--jobs`` runs run side by side in worker processes (default: all cores; ``--jobs 1`` runs
them one after the other in this process).

    python benchmarks/core.py --jobs 1              # 8 motions x 3 seeds, table into README
    python benchmarks/core.py --motions Sine --seeds 1 --quick --set window=0 --tag no-window
    python benchmarks/core.py --summarise benchmarks/results/core.json   # table from a file

The policy is the paper's first-order x' = f(x) (no phase in the state), as ``snds
benchmark`` compares it with the baselines; ``--set KEY=VALUE`` replaces a field of
``PolicyConfig`` or ``TrainConfig``.

Writes ``benchmarks/results/core[-TAG].json`` and ``.csv``, and (without ``--no-readme``)
the table between the ``core`` markers of ``benchmarks/README.md``.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

from _runner import (
    machine,
    machine_line,
    parse_pairs,
    parser,
    split_overrides,
    write_readme_section,
    write_results,
)

from snds.benchmark import MOTION_GROUPS, PAPER_SNDS_MSE
from snds.callbacks import Callback
from snds.parallel import starmap_unordered

PAPER8 = MOTION_GROUPS["paper8"]
PAPER_MSE = PAPER_SNDS_MSE
#: DTW (paper scale, mean of 3 seeds) of the default before training was made fast (3,000
#: steps at lr 0.01); issue 18's bar is at most 1.1x these.
DTW_BEFORE = {
    "Sine": 0.614,
    "PShape": 0.815,
    "Worm": 0.386,
    "GShape": 4.20,
    "NShape": 1.04,
    "DoubleBendedLine": 2.29,
    "CShape": 1.98,
    "Angle": 1.36,
}


class _Clock(Callback):
    """Wall and CPU time at a run's marks: start, model saved, metrics written, return."""

    def __init__(self) -> None:
        self.marks = [(time.perf_counter(), time.process_time())]

    def mark(self, *_: object) -> None:
        self.marks.append((time.perf_counter(), time.process_time()))

    on_saved = on_evaluated = mark

    def parts(self) -> list[tuple[float, float]]:
        """(wall, CPU) seconds of each part: training, the check, the plots."""
        return [(b[0] - a[0], b[1] - a[1]) for a, b in zip(self.marks, self.marks[1:])]


def run_one(
    motion: str, seed: int, overrides: dict[str, object], quick: bool, threads: int = 1
) -> dict:
    """Trains and evaluates one (motion, seed) in this process through the run API (as
    ``snds train --motion M --seed S --phase-codes 0 --plot``); returns one result row."""
    import torch

    torch.set_num_threads(threads)
    from snds import DataSource, SplitConfig, train_run
    from snds.policy import PolicyConfig
    from snds.recipes import Recipe
    from snds.stability import CheckConfig
    from snds.train import TrainConfig

    policy_overrides, train_overrides = split_overrides(overrides)
    # The paper's policy x' = f(x), no phase: as snds benchmark compares it with the baselines.
    recipe = Recipe(
        policy=PolicyConfig(**policy_overrides), train=TrainConfig(**train_overrides), phase=None
    )
    sizes = {"rollouts": 200, "samples": 10_000} if quick else {}
    clock = _Clock()
    with tempfile.TemporaryDirectory() as folder:
        run = train_run(
            DataSource(motion=motion),
            folder,
            recipe=recipe,
            seed=seed,
            split=SplitConfig(test_fraction=0.2),
            check=CheckConfig(seed=seed, **sizes),
            plots=True,
            callbacks=[clock],
            threads=threads,
        )
        clock.mark()
    (_, train_cpu), (check_seconds, check_cpu), (plot_seconds, plot_cpu) = clock.parts()
    metrics = run.metrics.to_dict()
    stability = metrics.pop("stability")
    return {
        "motion": motion,
        "seed": seed,
        "train_seconds": round(run.result.seconds, 2),
        "train_cpu_seconds": round(train_cpu, 2),
        "check_seconds": round(check_seconds, 2),
        "check_cpu_seconds": round(check_cpu, 2),
        "plot_seconds": round(plot_seconds, 2),
        "plot_cpu_seconds": round(plot_cpu, 2),
        "steps": run.result.steps,
        "restarts": run.result.restarts,
        **{k: v for k, v in metrics.items() if isinstance(v, float)},
        "converged_fraction": stability["converged_fraction"],
        "rollouts": stability["rollouts"],
        "median_time_to_converge": stability["median_time_to_converge"],
        "decrease_violations": stability["decrease_violations"],
        "samples_checked": stability["samples_checked"],
    }


def summarise(rows: list[dict], motions: list[str]) -> str:
    """A Markdown table of mean +- std per motion."""
    import numpy as np

    lines = [
        "| motion | train s (CPU s) | check s | plots s | velocity MSE (paper scale, test) "
        "| paper SNDS MSE | DTW (paper scale) | DTW bar (1.1x before) | converged "
        "| decrease violations |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for motion in motions:
        mine = [r for r in rows if r["motion"] == motion]
        if not mine:
            continue

        def stat(key: str, fmt: str, mine: list[dict] = mine) -> str:
            values = np.array([r[key] for r in mine], dtype=float)
            return f"{values.mean():{fmt}} ± {values.std():{fmt}}"

        # Rows of results files from before the plots were timed have none.
        plots = stat("plot_seconds", ".1f") if all("plot_seconds" in r for r in mine) else "-"
        lines.append(
            f"| {motion} | {stat('train_seconds', '.1f')} ({stat('train_cpu_seconds', '.1f')}) "
            f"| {stat('check_seconds', '.1f')} | {plots} | {stat('velocity_mse_paper', '.5f')} "
            f"| {PAPER_MSE.get(motion, float('nan')):.4f} | {stat('dtw_paper', '.3f')} "
            f"| {1.1 * DTW_BEFORE.get(motion, float('nan')):.3f} "
            f"| {min(r['converged_fraction'] for r in mine):.3f} (min) "
            f"| {sum(r['decrease_violations'] for r in mine)} |"
        )
    return "\n".join(lines)


def main() -> None:
    options = parser(__doc__, seeds=3, jobs=True, overrides=True, tag=True)
    options.add_argument("--motions", nargs="+", default=list(PAPER8))
    options.add_argument("--quick", action="store_true", help="smaller stability check")
    options.add_argument(
        "--summarise",
        metavar="JSON",
        default=None,
        help="rebuild the table (and README section 'core') from a results file; no runs",
    )
    args = options.parse_args()
    if args.summarise:
        record = json.loads(Path(args.summarise).read_text())
        meta, rows = record["meta"], record["rows"]
        motions = [m for m in PAPER8 if any(r["motion"] == m for r in rows)]
        motions += sorted({r["motion"] for r in rows} - set(motions))
        table = summarise(rows, motions)
        print(table)
        if not args.no_readme:
            write_readme_section("core", header_line(meta, rows) + "\n\n" + table)
        return
    overrides = parse_pairs(args.set)
    calls = [
        (m, s, overrides, args.quick, args.threads) for m in args.motions for s in range(args.seeds)
    ]
    finished = {}
    for index, row in starmap_unordered(run_one, calls, jobs=args.jobs):
        finished[index] = row
        print(json.dumps(row), flush=True)
    # The files keep the order of the runs (motion-major), whichever finished first.
    rows = [finished[index] for index in range(len(calls))]
    name = "core" + (f"-{args.tag}" if args.tag else "")
    meta = machine(threads=args.threads, jobs=args.jobs)
    meta |= {"seeds": args.seeds, "quick": args.quick, "overrides": overrides}
    write_results(name, rows, meta)
    table = summarise(rows, args.motions)
    print(table)
    if not args.no_readme:
        write_readme_section(name, header_line(meta, rows) + "\n\n" + table)


def header_line(meta: dict, rows: list[dict]) -> str:
    """The sentence above the table: where, how, and the training and check seconds."""
    import numpy as np

    def spread(*keys: str) -> str:
        values = np.array([sum(r[key] for key in keys) for r in rows], dtype=float)
        return f"median {np.median(values):.1f} s (max {values.max():.1f})"

    after = ""
    if all("plot_seconds" in r for r in rows):
        after = f"; the check and the plots together wall {spread('check_seconds', 'plot_seconds')}"

    return (
        f"{machine_line(meta)} Overrides {meta['overrides'] or 'none'}"
        f"{'; quick check' if meta.get('quick') else ''}. Training wall {spread('train_seconds')}, "
        f"CPU {spread('train_cpu_seconds')}; check wall {spread('check_seconds')}, CPU "
        f"{spread('check_cpu_seconds')}{after}."
    )


if __name__ == "__main__":
    main()
