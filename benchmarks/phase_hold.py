"""Does a policy still retrace its demonstration after the arm was held still for a while?

For every model of the given runs folders (``benchmarks/reliability.py --part real`` left them:
one per file and seed), from each demonstration's start: Euler steps at the demonstration's
mean sample step, the positions held still for ``--hold`` times the duration once 30 % of
the duration has gone by, then released; the run lasts 1.5x the duration plus the hold.
Each step goes through :func:`snds.phase.phase_step` with the positions the "arm" made, so a
model with a phase (:mod:`snds.phase`) keeps its phase waiting while held (``stop``); the
same model with the phase running on while held (``run on``: the state as a plain ODE would
integrate it) is measured beside it. A model without a phase is the plain field, held.

Figures per run, worst demonstration: the discrete Fréchet distance of the positions' path
to the demonstration over the task's extent, and the end distance to the target.

    python benchmarks/reliability.py --part real --seeds 3                  # plain models
    python benchmarks/reliability.py --part real --seeds 3 --recipe phase   # with a phase
    python benchmarks/phase_hold.py runs/reliability/real runs/reliability-phase/real

Writes ``benchmarks/results/phase-hold.json`` and the ``phase-hold`` block of
``benchmarks/README.md`` (``--no-readme``: not).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from _readme import write_readme_section

from snds.data import DataSource
from snds.evaluate import path_reference
from snds.metrics import frechet
from snds.models import load_model
from snds.phase import phase_step
from snds.policy import float64_copy

HERE = Path(__file__).resolve().parent


def held_paths(policy, demos, hold: float, stop: bool) -> list[np.ndarray]:
    """Position paths (T, n) of rollouts from every demonstration's start (one batch), held
    still for ``hold`` durations from 30 % of the way; ``stop``: the phase waits while held."""
    p = policy.space.position_dim
    dt = np.array([d.duration / (len(d.times) - 1) for d in demos])
    begin = np.array([int(0.3 * len(d.times)) for d in demos])
    held = np.array([int(round(hold * len(d.times))) for d in demos])
    steps = np.ceil(1.5 * np.array([d.duration for d in demos]) / dt).astype(int) + held
    state = np.stack([d.states[0] for d in demos])
    path = [state[:, :p].copy()]
    for k in range(int(steps.max())):
        displacement = dt[:, None] * policy.predict(state)
        holding = ((begin <= k) & (k < begin + held))[:, None]
        measured = np.where(holding, state[:, :p], state[:, :p] + displacement[:, :p])
        stepped = phase_step(state, displacement, 1.0, measured, position_dim=p)
        if not stop:  # the phase runs on while held, as an ODE of the whole state would
            stepped[:, p:] = state[:, p:] + displacement[:, p:]
        state = stepped
        path.append(state[:, :p].copy())
    path = np.stack(path, axis=1)
    return [path[b, : steps[b] + 1] for b in range(len(demos))]


def measure(run: Path, hold: float) -> list[dict]:
    """The figures of one run folder: one row per way of holding (plain; stop, run on)."""
    policy, description = load_model(run)
    policy = float64_copy(policy)
    demos = DataSource.from_record(description["data"]).load()
    extent, target = demos.extent(), policy.space.positions(np.asarray(demos.target))
    p = policy.space.position_dim
    phased = p < policy.space.dim
    rows = []
    for stop in (True, False) if phased else (True,):
        paths = held_paths(policy, demos, hold, stop)
        refs = [path_reference(d)[:, :p] for d in demos]
        rows.append(
            {
                "task": run.parent.name,
                "seed": int(run.name.split("=")[1]),
                "model": ("phase, " + ("stop" if stop else "run on")) if phased else "plain",
                "hold": hold,
                "frechet_over_extent": max(
                    frechet(q, r) / extent for q, r in zip(paths, refs, strict=True)
                ),
                "end_distance": max(float(np.linalg.norm(q[-1] - target)) for q in paths),
            }
        )
    return rows


def table(rows: list[dict], folders: list[Path]) -> str:
    """The README block: one line per task and way of holding, worst over seeds."""
    holds = sorted({r["hold"] for r in rows})
    models = list(dict.fromkeys(r["model"] for r in rows))
    head = " | ".join(f"{m} ({h:.0%} held)" for h in holds for m in models)
    lines = [
        "Rollouts from the demonstrations' starts, the positions held still from 30 % of the "
        "way for a share of the duration and released (`python benchmarks/phase_hold.py "
        + " ".join(str(f) for f in folders)
        + "`): the worst demonstration's Fréchet distance over the extent, worst seed. "
        "`stop`: the phase waits while held (`snds.phase.phase_step`, what `snds simulate` "
        "does); `run on`: it runs on.",
        "",
        f"| task | {head} |",
        "|---|" + "---|" * (len(holds) * len(models)),
    ]
    for task in dict.fromkeys(r["task"] for r in rows):
        cells = []
        for h in holds:
            for m in models:
                group = [
                    r for r in rows if r["task"] == task and r["model"] == m and r["hold"] == h
                ]
                worst = max((r["frechet_over_extent"] for r in group), default=None)
                cells.append("" if worst is None else f"{worst:.3f}")
        lines.append(f"| {task} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+", help="reliability runs' real/ folders")
    parser.add_argument("--seeds", type=int, default=3, help="the first N seeds of each task")
    parser.add_argument("--hold", type=float, nargs="+", default=[0.1, 0.3])
    parser.add_argument("--no-readme", action="store_true")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "phase-hold.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rows = []
    for folder in args.runs:
        for task in sorted(p for p in folder.iterdir() if p.is_dir()):
            for run in sorted(task.glob("seed=*"))[: args.seeds]:
                if not (run / "model.json").is_file():
                    continue
                for hold in args.hold:
                    for row in measure(run, hold):
                        rows.append(row)
                        print(json.dumps(row), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"runs": [str(f) for f in args.runs], "rows": rows}) + "\n")
    if not args.no_readme:
        write_readme_section("phase-hold", table(rows, args.runs))


if __name__ == "__main__":
    main()
