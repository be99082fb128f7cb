"""Real recordings: does the default `snds train` retrace every real file of ../shared/data,
drawn shapes that cross and the paper's 8 LASA motions, and reach the target from new starts
and after pushes?

Each task is trained with the default ``snds train`` and only the data options its file
needs (a rate, a quaternion order, a length unit), one run per seed, then measured:

* ``frechet``: the worst discrete Fréchet distance between a demonstration and the rollout
  from its start over 1.5x its duration, in extents (``retrace_frechet_max`` of
  metrics.json); ``final``: the worst distance of such a rollout's end from the target;
* ``angle_along`` / ``angle_end``: a pose model's mean orientation error along the path and
  at the end, radians (metrics.json);
* ``converged``, ``violations``: the stability check; ``safe_dt`` beside ``data_dt``, the
  demonstrations' mean step;
* ``check_cpu`` beside ``train_cpu``: the check's CPU seconds, measured again here, against
  the fit's;
* ``ratio`` / ``arrived``: from 40 random positions in the demonstrations' box enlarged
  1.5x (a pose start takes the nearest sample's orientation; a phase comes from
  :func:`snds.phase.start_state`), the median path length over the straight distance, and
  the share arriving within 1 % of the extent within 3x the longest demonstration's duration;
* ``push``: after a push sideways of 10 % of the extent at 30 % of each demonstration's
  duration (the phase kept), the worst Fréchet distance between the rest of the rollout
  and the rest of the demonstration, in extents. The pushed state is the first point of the
  rest, 0.10 from the demonstration's point: 0.10 is the floor, met by a rollout that never
  goes further from the demonstration than the push took it;
* ``safe_dt_rollouts``: the largest safe Euler step over the states the check's rollouts
  visit only (``safe_dt`` adds the 50,000 decrease samples of the 10x box);
* ``rough``: :func:`snds.metrics.field_roughness`, the median angle in degrees between the
  velocities of neighbouring points of a 101 x 101 grid over the 3x box (the plane of the
  first two coordinates through the target, at phase 0): ripples off the data.

    python benchmarks/real_recordings.py --seeds 3 --jobs 2   # train, measure, write
    python benchmarks/real_recordings.py --seeds 3 --done-only  # measure runs already trained
    python benchmarks/real_recordings.py --shapes OUT_DIR       # only write the drawn shapes

The drawn shapes ("e", loop, alpha, phi) are drawn as a person draws on the page: several
demonstrations each with its own pace, a small affine jitter and hand tremor (seeded), written
as ``snds train --data`` CSV files.

Writes runs under ``runs/real-recordings/`` (the drawn shapes' CSV files in its ``drawn/``),
``benchmarks/results/real-recordings.json`` and the ``real-recordings`` table of
``benchmarks/README.md``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path

import numpy as np
from _runner import (
    DATA,
    RESULTS,
    children_cpu,
    machine,
    machine_line,
    parser,
    set_threads,
    write_readme_section,
    write_results,
)

from snds.data import DataSource
from snds.metrics import field_roughness, frechet
from snds.models import load_model
from snds.phase import start_state
from snds.policy import float64_copy
from snds.rollout import rollout_numpy
from snds.stability import CheckConfig, check_stability


def _e(s: np.ndarray) -> np.ndarray:
    # The bar from left to right, then counter-clockwise around, crossing the bar's start.
    bar = s < 0.3
    angle = np.where(bar, 0.0, (s - 0.3) / 0.7) * 1.75 * np.pi
    x = np.where(bar, -1.0 + 2.0 * s / 0.3, np.cos(angle))
    y = np.where(bar, 0.0, np.sin(angle))
    return np.stack([x, y], -1)


def _loop(s: np.ndarray) -> np.ndarray:
    # A trochoid: left to right with one loop in the middle.
    turn = 2.0 * np.pi * s
    return np.stack([3.0 * s + 1.2 * np.sin(turn), 1.2 * (1.0 - np.cos(turn))], -1)


def _alpha(s: np.ndarray) -> np.ndarray:
    angle = np.pi * (0.15 + 1.7 * s)
    return np.stack([0.6 * np.sin(2.0 * angle) + 0.5 * (s - 0.5), np.sin(angle)], -1)


def _phi(s: np.ndarray) -> np.ndarray:
    # A circle from the top, then a stroke down through it, crossing it twice.
    circle = s < 0.6
    angle = np.pi / 2 + 2.0 * np.pi * s / 0.6
    x = np.where(circle, np.cos(angle), 0.0)
    y = np.where(circle, np.sin(angle), 1.0 - 2.6 * (s - 0.6) / 0.4)
    return np.stack([x, y], -1)


#: The shapes by name, each a curve over s in [0, 1].
SHAPES: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "e": _e,
    "loop": _loop,
    "alpha": _alpha,
    "phi": _phi,
}


def draw(
    name: str,
    *,
    demos: int = 7,
    samples: int = 400,
    seed: int = 0,
    scale: float = 100.0,
    rate: float = 100.0,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Demonstrations of one shape: (positions (T, 2), times (T,)) each, sampled at ``rate``
    Hz, with a slow start and end, a random pace, affine jitter and tremor."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(demos):
        count = samples + int(rng.integers(-samples // 5, samples // 5))
        t = np.linspace(0.0, 1.0, count)
        s = (1.0 - np.cos(np.pi * t ** rng.uniform(0.7, 1.3))) / 2.0
        warp = np.eye(2) + rng.normal(0.0, 0.06, (2, 2))
        points = SHAPES[name](s) @ warp.T + rng.normal(0.0, 0.05, 2)
        points = points + 0.3 * rng.normal(0.0, 0.004, points.shape).cumsum(0)
        out.append((scale * points, np.arange(count) / rate))
    return out


def write_csv(name: str, path: Path, **options: float) -> Path:
    """Writes the demonstrations of ``name`` as ``demo,t,x1,x2`` rows; returns ``path``."""
    rows = ["demo,t,x1,x2"]
    for d, (points, times) in enumerate(draw(name, **options)):
        rows += [f"{d},{t:.4f},{x:.4f},{y:.4f}" for t, (x, y) in zip(times, points)]
    path.write_text("\n".join(rows) + "\n")
    return path


#: The paper's 8 LASA motions (``snds train --motion NAME``).
PAPER8 = ["Sine", "PShape", "Worm", "GShape", "NShape", "DoubleBendedLine", "CShape", "Angle"]

#: What the RoboTasks9 files need (../shared/data/README.md): no time stamps (60 Hz), the
#: quaternion scalar first, centimetres.
CLFD = ["--rate", "60", "--quaternion-order", "wxyz", "--length-unit", "cm"]

#: Each task: its data file (relative to ../shared/data, or a drawn shape) and the options
#: its file needs.
TASKS: dict[str, list[str]] = {
    "Messy_snake": ["Messy_snake.mat"],
    "3D_Cshape_top": ["3D_Cshape_top.mat"],
    "3D_viapoint_1": ["3D_viapoint_1.mat"],
    "3D-pick-box_0-2": ["3D-pick-box.mat", "--demos", "0,2"],
    "3D-pick-box_1-3": ["3D-pick-box.mat", "--demos", "1,3"],
    "3D_sink": ["3D_sink.mat"],
    "pouring": ["clfd/pouring.npy", *CLFD],
    "bottle2shelf": ["clfd/bottle2shelf.npy", *CLFD],
    "panda_pose": ["panda_kinesthetic_pose.mat", "--quaternion-order", "wxyz"],
    **{f"drawn_{name}": [f"drawn:{name}"] for name in SHAPES},
    **{f"lasa_{name}": [f"motion:{name}"] for name in PAPER8},
}

BARS = {"frechet": 0.05, "final": 0.01, "angle_along": 0.1, "angle_end": 0.05, "push": 0.10}


def train(task: str, seed: int, out: Path, drawn: Path, threads: int = 1) -> float:
    """Trains one task with the default `snds train`; returns its CPU seconds."""
    file, *options = TASKS[task]
    if file.startswith("motion:"):
        source = ["--motion", file[7:]]
    else:
        source = [
            "--data",
            str(drawn / f"{file[6:]}.csv" if file.startswith("drawn:") else DATA / file),
        ]
    argv = ["--threads", str(threads), "--quiet", "train", *source, "--seed", str(seed)]
    start = time.process_time()
    before = children_cpu()
    subprocess.run([sys.executable, "-m", "snds", *argv, *options, "--out", str(out)], check=True)
    return children_cpu() - before + time.process_time() - start


def measure(run: Path, seed: int) -> dict:
    """The figures of one trained run (see the module docstring)."""
    metrics = json.loads((run / "metrics.json").read_text())
    policy, description = load_model(run)
    demos = DataSource.from_record(description["data"], poses=description["kind"] == "se3").load()
    policy = float64_copy(policy)
    stability = metrics["stability"]
    start = time.process_time()
    check_stability(policy, demos, config=CheckConfig(seed=seed))
    check_cpu = time.process_time() - start
    row = {
        "frechet": metrics["retrace_frechet_max"],
        "final": metrics["retrace_final_max"],
        "angle_along": metrics.get("angle_error_along"),
        "angle_end": metrics.get("final_angle_error"),
        "converged": stability["converged_fraction"],
        "violations": stability["decrease_violations"],
        "safe_dt": stability["largest_safe_dt"],
        "safe_dt_rollouts": stability["largest_safe_dt_on_rollouts"],
        "data_dt": demos.mean_dt(),
        "train_cpu": metrics["train_seconds"],
        "check_cpu": check_cpu,
        "phase_dim": demos.phase_dim,
        "rough": field_roughness(policy, demos).median,
    }
    return row | new_starts(policy, demos, seed) | {"push": pushed(policy, demos)}


def _base_states(demos, positions: np.ndarray) -> np.ndarray:
    """Base states (no phase) at ``positions``: a pose takes the nearest sample's orientation."""
    p = demos.position_dim
    b = len(demos.target) - demos.phase_dim
    if b == p:
        return positions
    samples = np.concatenate([demo.states for demo in demos])
    nearest = np.argmin(np.linalg.norm(samples[None, :, :p] - positions[:, None], axis=-1), axis=1)
    return np.concatenate([positions, samples[nearest, p:b]], axis=1)


def _start(demos, base: np.ndarray) -> np.ndarray:
    return start_state(demos, base) if demos.phase_dim else base


def new_starts(policy, demos, seed: int, count: int = 40) -> dict:
    """Median path ratio and arrival share from random starts in the 1.5x box."""
    p = demos.position_dim
    positions = demos.positions()
    low, high = positions.min(0), positions.max(0)
    rng = np.random.default_rng(seed)
    chosen = (low + high) / 2 + rng.uniform(-1, 1, (count, p)) * (high - low) / 2 * 1.5
    starts = np.stack([_start(demos, b) for b in _base_states(demos, chosen)])
    duration = demos.max_duration()
    dt = demos.mean_dt()
    paths = rollout_numpy(policy, starts, dt=dt, steps=int(np.ceil(3 * duration / dt)))[..., :p]
    target = demos.target[:p]
    lengths = np.linalg.norm(np.diff(paths, axis=1), axis=-1).sum(1)
    ratios = lengths / np.linalg.norm(paths[:, 0] - target, axis=-1)
    arrived = np.linalg.norm(paths[:, -1] - target, axis=-1) <= 0.01 * demos.extent()
    return {"ratio": float(np.median(ratios)), "arrived": float(arrived.mean())}


def pushed(policy, demos, at: float = 0.3, size: float = 0.1) -> float:
    """Worst Fréchet distance (extents) of the rest of a pushed rollout from the rest of its
    demonstration (see the module docstring)."""
    p = demos.position_dim
    extent = demos.extent()
    worst = 0.0
    for demo in demos:
        dt = demo.duration / (len(demo.times) - 1)
        k = int(at * (len(demo.times) - 1))
        before = rollout_numpy(policy, demo.states[:1], dt=dt, steps=k)[0, -1]
        velocity = demo.velocities[k, :p]
        sideways = np.zeros(p)
        sideways[:2] = [-velocity[1], velocity[0]]
        if np.linalg.norm(sideways) == 0:
            sideways[0] = 1.0
        before[:p] += size * extent * sideways / np.linalg.norm(sideways)
        rest = rollout_numpy(policy, before[None], dt=dt, steps=int(1.5 * (len(demo.times) - k)))
        gap = frechet(rest[0, :, :p], demo.positions[k:, :p]) / extent
        worst = max(worst, gap)
    return worst


def meets(row: dict, bars: tuple[str, ...] = tuple(BARS)) -> bool:
    ok = all(row[k] is None or row[k] <= BARS[k] for k in bars)
    return (
        ok
        and row["converged"] == 1.0
        and row["violations"] == 0
        and row["safe_dt"] >= row["data_dt"]
        and row["check_cpu"] <= row["train_cpu"]
        and row["ratio"] <= 2.0
        and row["arrived"] == 1.0
    )


def _cell(value) -> str:
    return "-" if value is None else f"{value:.3g}"


def _commits(rows: list[dict]) -> str:
    """Which commit measured which tasks, where the rows come from more than one (--merge)."""
    tasks: dict[str, list[str]] = {}
    for row in rows:
        names = tasks.setdefault(row.get("commit", "?"), [])
        if row["task"] not in names:
            names.append(row["task"])
    if len(tasks) < 2:
        return ""
    return " Rows by commit: " + "; ".join(f"{c}: {', '.join(t)}" for c, t in tasks.items()) + "."


def table(rows: list[dict], meta: dict) -> str:
    columns = ["frechet", "final", "angle_along", "angle_end", "push", "ratio", "arrived", "rough"]
    seeds = max((r["seed"] for r in rows), default=-1) + 1
    lines = [
        f"{machine_line(meta)} `python benchmarks/real_recordings.py --seeds {seeds} "
        f"--jobs {meta['jobs']}`; worst "
        "over the seeds; bars: Fréchet <= 0.05, final "
        "<= 0.01, angle along <= 0.1 rad, at the end <= 0.05, push <= 0.10 (extents), ratio "
        "<= 2, arrived 1.0, converged 1.0, 0 violations, safe step >= data step, check CPU <= "
        "fit CPU; rough: the field's median turn between neighbouring grid points, degrees "
        "(no bar)." + _commits(rows),
        "",
        "| task | seeds | " + " | ".join(columns) + " | safe step / data step (on rollouts) "
        "| check / fit CPU "
        "| meets every bar | every bar but the push |",
        "|---" * (len(columns) + 6) + "|",
    ]
    for task in TASKS:
        mine = [r for r in rows if r["task"] == task]
        if not mine:
            continue
        worst = {
            c: None if mine[0].get(c) is None else max(r[c] for r in mine)
            for c in columns
            if c != "arrived"
        }
        worst["arrived"] = min(r["arrived"] for r in mine)
        safe = min(r["safe_dt"] / r["data_dt"] for r in mine)
        visited = min(r["safe_dt_rollouts"] / r["data_dt"] for r in mine)
        check = max(r["check_cpu"] / r["train_cpu"] for r in mine)
        passed = sum(meets(r) for r in mine)
        unpushed = sum(meets(r, tuple(k for k in BARS if k != "push")) for r in mine)
        lines.append(
            f"| {task} | {len(mine)} | "
            + " | ".join(_cell(worst[c]) for c in columns)
            + f" | {safe:.3g} ({visited:.3g}) | {check:.2f} "
            + f"| {passed} of {len(mine)} | {unpushed} of {len(mine)} |"
        )
    return "\n".join(lines)


def one(
    task: str, seed: int, runs: Path, drawn: Path, threads: int, done_only: bool
) -> dict | None:
    """Trains (unless done or ``done_only``) and measures one task at one seed."""
    set_threads(threads)
    run = runs / f"{task}-{seed}"
    if not done_only and not (run / "metrics.json").is_file():
        train(task, seed, run, drawn, threads)
    if not (run / "metrics.json").is_file():
        return None
    row = {"task": task, "seed": seed, **measure(run, seed)}
    print(json.dumps(row), flush=True)
    return row


def main() -> None:
    options = parser(__doc__, seeds=3, jobs=True)
    options.add_argument("--tasks", default=",".join(TASKS))
    options.add_argument("--runs", type=Path, default=Path("runs/real-recordings"))
    options.add_argument("--done-only", action="store_true", help="measure trained runs only")
    options.add_argument("--out", type=Path, default=RESULTS / "real-recordings.json")
    options.add_argument("--shapes", type=Path, metavar="DIR", help="only write the drawn shapes")
    options.add_argument(
        "--merge",
        action="store_true",
        help="keep the rows of the other tasks from --out (each row records its commit)",
    )
    args = options.parse_args()
    if args.shapes:
        args.shapes.mkdir(parents=True, exist_ok=True)
        for name in SHAPES:
            print(write_csv(name, args.shapes / f"{name}.csv"))
        return
    if not DATA.is_dir():
        raise SystemExit(f"no data folder at {DATA}")
    set_threads(args.threads)
    meta = machine(threads=args.threads, jobs=args.jobs)
    # Beside the runs, not in a temporary folder: a run's model.json names its data file, so
    # `--done-only` and `snds plot` of a drawn run read it again later.
    drawn = args.runs / "drawn"
    drawn.mkdir(parents=True, exist_ok=True)
    for name in SHAPES:
        write_csv(name, drawn / f"{name}.csv")
    tasks, seeds = zip(*[(t, s) for t in args.tasks.split(",") for s in range(args.seeds)])
    task_run = partial(
        one, runs=args.runs, drawn=drawn, threads=args.threads, done_only=args.done_only
    )
    with ProcessPoolExecutor(args.jobs) as pool:
        done = pool.map(task_run, tasks, seeds)
        rows = [row | {"commit": meta["commit"]} for row in done if row is not None]
    if args.merge and args.out.is_file():
        earlier = json.loads(args.out.read_text())
        commit = earlier["meta"]["commit"]
        ran = {row["task"] for row in rows}
        kept = [r for r in earlier["rows"] if r["task"] not in ran]
        rows = [{"commit": commit} | r for r in kept] + rows
        rows.sort(key=lambda r: (list(TASKS).index(r["task"]), r["seed"]))
    write_results(args.out.stem, rows, meta, folder=args.out.parent, with_csv=False)
    if not args.no_readme:
        write_readme_section("real-recordings", table(rows, meta))


if __name__ == "__main__":
    main()
