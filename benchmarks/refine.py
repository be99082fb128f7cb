"""Refinement benchmark: fit on 6 demonstrations, refine with the 7th, against a fit from
scratch on all 7 (issue 43's bars).

For every (motion, seed) of the paper's 8 LASA motions: a random 0.8 / 0.2 split of the 7
demonstrations' samples; the default SNDS fitted on the first 6 (the trained model); a fit
from scratch on all 7, timed side by side in the same process; then each schedule refines a
copy of the trained model with the 7th demonstration (:func:`snds.refine.refine`) and is
evaluated on all 7 (velocity MSE on the test samples, DTW, the library's default stability
check) and on the 6 old ones (DTW before and after). One torch thread, runs one after the
other (wall and CPU seconds both recorded, with the load average: the machine may be shared).

    python benchmarks/refine.py                                  # 8 motions x 3 seeds
    python benchmarks/refine.py --motions Sine --seeds 1 --schedule 100:5e-3:1 50:5e-3:1

A schedule is ``steps:lr:new_weight`` (:class:`snds.refine.RefineConfig`); the default is the
library's. Writes ``benchmarks/results/refine[-TAG].json`` and (without ``--no-readme``) the
table between the ``refine`` markers of ``benchmarks/README.md``.
"""

from __future__ import annotations

import argparse
import copy
import datetime
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
from _runner import cpu_name, write_readme_section

from snds.benchmark import MOTION_GROUPS
from snds.data import Split, load_lasa, split_samples
from snds.evaluate import accuracy, evaluate
from snds.methods import make_policy
from snds.phase import Phase
from snds.policy import PolicyConfig, float64_copy
from snds.refine import RefineConfig, added_demonstrations, refine
from snds.stability import CheckConfig
from snds.train import TrainConfig, fit

PAPER8 = MOTION_GROUPS["paper8"]
HERE = Path(__file__).resolve().parent
COMMAND = "python benchmarks/refine.py"


def timed(work):
    """``work()``, its wall and CPU seconds."""
    wall, cpu = time.perf_counter(), time.process_time()
    out = work()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def fitted(demos, split, seed):
    """The default SNDS (as benchmarks/core.py trains it; with the phase ``demos`` carry)
    fitted on ``demos``; wall, CPU s."""
    policy = make_policy(demos, config=PolicyConfig(), seed=seed)
    _, wall, cpu = timed(lambda: fit(policy, demos, split, TrainConfig(seed=seed), progress=False))
    return policy, wall, cpu


def scores(policy, demos, split, old, old_split, seed):
    """Accuracy and stability on all demonstrations, DTW on the old ones (paper scale)."""
    metrics = evaluate(policy, demos, split, check=CheckConfig(seed=seed))
    stability = metrics["stability"]
    return {
        "dtw": metrics["dtw_paper"],
        "mse": metrics["velocity_mse_paper"],
        "converged": stability["converged_fraction"],
        "violations": stability["decrease_violations"],
        "old_dtw": accuracy(float64_copy(policy), old, old_split)["dtw_paper"],
    }


def run_one(
    motion: str, seed: int, schedules: list[RefineConfig], phase: Phase | None = None
) -> list[dict]:
    """One (motion, seed): the trained model, the fit from scratch, each schedule's
    refinement; one row per schedule. With ``phase``, the trained model's phase is scaled by
    the 6 demonstrations' extent (kept by the refinement), the scratch fit's by the 7's."""
    raw = load_lasa(motion)
    old_raw = raw.select(range(6))
    # The refinement's demonstrations: the old ones as the model was trained on them.
    demos = added_demonstrations(old_raw, raw.select([6]), phase=phase)
    scratch_demos = raw if phase is None else phase.apply(raw)
    split = split_samples(demos, test_fraction=0.2, seed=seed)
    old = demos.select(range(6))
    old_split = Split(split.train[:6])
    trained, base_wall, base_cpu = fitted(old, old_split, seed)
    scratch, full_wall, full_cpu = fitted(scratch_demos, split, seed)
    before = accuracy(float64_copy(trained), old, old_split)["dtw_paper"]
    # The fit from scratch is the accuracy bar only: its check is benchmarks/core.py's.
    scratch64 = float64_copy(scratch)
    reference = {
        key: accuracy(scratch64, scratch_demos, split)[f"{name}_paper"]
        for key, name in (("dtw", "dtw"), ("mse", "velocity_mse"))
    }
    rows = []
    for schedule in schedules:
        policy = copy.deepcopy(trained)
        refined, wall, cpu = timed(
            lambda policy=policy, schedule=schedule: refine(
                policy, demos, split, config=schedule, train=TrainConfig(seed=seed), new=[6]
            )
        )
        rows.append(
            {
                "motion": motion,
                "seed": seed,
                "phase_codes": 0 if phase is None else phase.codes,
                "schedule": schedule.to_dict(),
                "refine_seconds": wall,
                "refine_cpu_seconds": cpu,
                "full_seconds": full_wall,
                "full_cpu_seconds": full_cpu,
                "base_seconds": base_wall,
                "base_cpu_seconds": base_cpu,
                "reach": refined.reach,
                "old_dtw_before": before,
                "scratch": reference,
                **scores(policy, demos, split, old, old_split, seed),
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    return rows


def label(schedule: dict) -> str:
    text = f"{schedule['steps']} steps, lr {schedule['lr']:g}, new x{schedule['new_weight']}"
    if schedule.get("batch_size") is not None:
        text += f", batch {schedule['batch_size']}"
    if not schedule.get("fit_lyapunov", True):
        text += ", V kept"
    return text


def summarise(rows: list[dict]) -> str:
    """One line per schedule: medians and the bars of issue 43."""
    lines = [
        "| schedule | refine s (CPU s), median | full fit s (CPU s), median | refine / full "
        "| DTW / scratch (worst motion) | MSE / scratch (worst motion) | old DTW / before "
        "(worst motion) | converged (min) | violations |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for key in dict.fromkeys(json.dumps(r["schedule"], sort_keys=True) for r in rows):
        mine = [r for r in rows if json.dumps(r["schedule"], sort_keys=True) == key]
        motions = list(dict.fromkeys(r["motion"] for r in mine))

        def worst(metric: str, reference, mine=mine, motions=motions) -> str:
            # Per motion, the mean over seeds of each side, then the worst motion's ratio.
            ratios = {
                m: np.mean([r[metric] for r in mine if r["motion"] == m])
                / np.mean([reference(r) for r in mine if r["motion"] == m])
                for m in motions
            }
            name = max(ratios, key=ratios.get)
            return f"{ratios[name]:.2f} ({name})"

        median = lambda k, mine=mine: float(np.median([r[k] for r in mine]))  # noqa: E731
        ratio = np.median([r["refine_seconds"] / r["full_seconds"] for r in mine])
        lines.append(
            f"| {label(mine[0]['schedule'])} | {median('refine_seconds'):.2f} "
            f"({median('refine_cpu_seconds'):.2f}) | {median('full_seconds'):.1f} "
            f"({median('full_cpu_seconds'):.1f}) | {ratio:.1%} "
            f"| {worst('dtw', lambda r: r['scratch']['dtw'])} "
            f"| {worst('mse', lambda r: r['scratch']['mse'])} "
            f"| {worst('old_dtw', lambda r: r['old_dtw_before'])} "
            f"| {min(r['converged'] for r in mine):.3f} | {sum(r['violations'] for r in mine)} |"
        )
    return "\n".join(lines)


def parse_schedule(text: str) -> RefineConfig:
    """``steps:lr:new_weight[:batch_size[:keep]]`` (``keep``: V stays as trained)."""
    fields = text.split(":")
    if not 3 <= len(fields) <= 5:
        raise argparse.ArgumentTypeError(f"{text}: steps:lr:new_weight[:batch_size[:keep]]")
    steps, lr, weight, batch, keep = (fields + ["", ""])[:5]
    if keep not in ("", "keep"):
        raise argparse.ArgumentTypeError(f"{text}: the fifth field is 'keep' or nothing")
    return RefineConfig(
        steps=int(steps),
        lr=float(lr),
        new_weight=int(weight),
        batch_size=int(batch) if batch else None,
        fit_lyapunov=keep != "keep",
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--motions", nargs="+", default=list(PAPER8))
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument(
        "--schedule", nargs="+", type=parse_schedule, default=[RefineConfig()], help="S:LR:W"
    )
    parser.add_argument(
        "--phase-codes",
        type=int,
        default=0,
        help="a phase of this many codes in the state (default 0: none, as benchmarks/core.py)",
    )
    parser.add_argument("--tag", default="", help="suffix of the result file")
    parser.add_argument("--no-readme", action="store_true")
    parser.add_argument(
        "--summarise",
        nargs="+",
        metavar="JSON",
        default=None,
        help="the table (and README section) from results files (e.g. halves run side by "
        "side); no runs",
    )
    args = parser.parse_args()
    if args.summarise:
        records = [json.loads(Path(path).read_text()) for path in args.summarise]
        rows = [row for record in records for row in record["rows"]]
        meta = records[0]["meta"] | {
            "command": " ".join(r["meta"]["command"] for r in records),
            "load_average_before": max(r["meta"]["load_average_before"] for r in records),
            "load_average_after": max(r["meta"]["load_average_after"] for r in records),
        }
        finish(rows, meta, "refine", readme=not args.no_readme)
        return
    torch.set_num_threads(1)
    phase = Phase(codes=args.phase_codes) if args.phase_codes else None
    meta = {
        "date": datetime.date.today().isoformat(),
        "cpu": cpu_name(),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.platform()}",
        "threads": 1,
        "load_average_before": os.getloadavg(),
        "command": " ".join(["python", "benchmarks/refine.py", *sys.argv[1:]]),
    }
    name = "refine" + (f"-{args.tag}" if args.tag else "")
    rows: list[dict] = []
    # Seeds outermost: a sweep cut short has every motion at the seeds it finished.
    for seed in range(args.seeds):
        for motion in args.motions:
            rows += run_one(motion, seed, args.schedule, phase)
            meta["load_average_after"] = os.getloadavg()
            save(rows, meta, name)
    finish(rows, meta, name, readme=not args.no_readme)


def save(rows: list[dict], meta: dict, name: str) -> None:
    """Writes ``results/NAME.json`` (after every run: a sweep cut short keeps its rows)."""
    out = HERE / "results"
    out.mkdir(exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")


def finish(rows: list[dict], meta: dict, name: str, *, readme: bool) -> None:
    """Writes ``results/NAME.json``, prints the table and puts it into the README."""
    save(rows, meta, name)
    table = summarise(rows)
    print(table)
    if readme:
        before, after = meta["load_average_before"][0], meta["load_average_after"][0]
        header = (
            f"`{meta['command']}` ({len(rows)} rows; {meta['cpu']}, one torch thread per run; "
            f"1-minute load average {before:.1f} before and {after:.1f} after on "
            f"{os.cpu_count()} cores: the machine was shared, so wall times run well above "
            "CPU times, and the ratio to a full fit timed beside it is the fairer figure)"
        )
        write_readme_section(name, header + "\n\n" + table)


if __name__ == "__main__":
    main()
