"""Real pose models on the simulated arms: does `snds simulate` take each to its target?

For every pose run of ``real_recordings.py`` (``runs/real-recordings/``: the RoboTasks9
pouring and bottle2shelf files and the Panda kinesthetic poses, one run per seed), runs the
default ``snds simulate RUN --robot ROBOT`` from the first demonstration's first pose on each
arm and reads its ``sim.json``: whether it reached the target (1 mm and 0.02 rad, the
defaults) and whether it ended within 1 cm and 0.05 rad, the final errors, the error of the
arm's start against the demonstration's start (the inverse kinematics from rest), how
close the joints came to their limits, and how far the simulator turned the task's
orientations to fit the arm (``snds.sim.orient``).

    python benchmarks/real_recordings.py --seeds 3 --jobs 2   # trains the runs
    python benchmarks/sim_poses.py                            # then this

Writes ``benchmarks/results/sim-poses.json`` and the ``sim-poses`` table of
``benchmarks/README.md``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from _runner import RESULTS, machine, machine_line, parser, write_readme_section, write_results

#: The pose tasks of real_recordings.py.
POSE_TASKS = ("pouring", "bottle2shelf", "panda_pose")

ROBOTS = ("iiwa", "panda")


def simulate(run: Path, robot: str) -> dict:
    """One default `snds simulate` of a run on a robot; the figures of its sim.json."""
    out = run / f"sim-{robot}"
    argv = ["--quiet", "simulate", str(run), "--robot", robot, "--out", str(out), "--frames", "0"]
    subprocess.run([sys.executable, "-m", "snds", *argv], check=True)
    record = json.loads((out / "sim.json").read_text())
    joints = np.asarray(record["joint_path"])
    margin = np.minimum(
        joints - np.asarray(record["joint_lower"]), np.asarray(record["joint_upper"]) - joints
    )
    return {
        "reached": record["reached"],
        "seconds": record["duration_s"],
        "final_mm": 1000.0 * record["final_error_m"],
        "final_rad": record["final_orientation_error_rad"],
        "start_mm": 1000.0 * record["start_error_m"],
        "start_rad": record["start_orientation_error_rad"],
        "joint_margin_rad": float(margin.min()),
        "tightest_joint": int(np.argmin(margin.min(axis=0))) + 1,
        "turn_rad": float(np.linalg.norm(record["placement"]["orientation_turn_rad"])),
    }


def _cell(mine: list[dict]) -> str:
    worst = max(mine, key=lambda r: (not r["reached"], r["final_mm"]))
    near = sum(r["final_mm"] <= 10.0 and r["final_rad"] <= 0.05 for r in mine)
    return (
        f"{sum(r['reached'] for r in mine)} / {near} of {len(mine)} | {worst['final_mm']:.1f} / "
        f"{worst['final_rad']:.3f} | {max(r['start_mm'] for r in mine):.0f} / "
        f"{max(r['start_rad'] for r in mine):.2f} | {worst['joint_margin_rad']:.2f} "
        f"({worst['tightest_joint']}) | {sum(r['turn_rad'] > 0 for r in mine)}"
    )


def table(rows: list[dict], meta: dict) -> str:
    head = " | ".join(
        f"{robot}: reached / within 1 cm, 0.05 rad | final mm / rad | start mm / rad "
        "| joint margin rad (joint) | turned"
        for robot in ROBOTS
    )
    lines = [
        f"{machine_line(meta)} `python benchmarks/sim_poses.py`: default `snds simulate` (30 s, "
        "1 mm and 0.02 rad) of the pose runs above from their first demonstration's start; the "
        "worst run; turned: runs whose orientations the simulator turned to fit the arm's "
        "joint limits (`--keep-orientation` not given).",
        "",
        f"| task | {head} |",
        "|---" * (1 + 5 * len(ROBOTS)) + "|",
    ]
    for task in POSE_TASKS:
        cells = [_cell(m) for robot in ROBOTS if (m := _of(rows, task, robot))]
        if cells:
            lines.append(f"| {task} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _of(rows: list[dict], task: str, robot: str) -> list[dict]:
    return [r for r in rows if r["task"] == task and r["robot"] == robot]


def main() -> None:
    options = parser(__doc__, threads=False)
    options.add_argument("--runs", type=Path, default=Path("runs/real-recordings"))
    options.add_argument("--out", type=Path, default=RESULTS / "sim-poses.json")
    args = options.parse_args()
    meta = machine()
    rows = []
    for task in POSE_TASKS:
        for run in sorted(args.runs.glob(f"{task}-*")):
            for robot in ROBOTS:
                row = {"task": task, "run": run.name, "robot": robot, **simulate(run, robot)}
                print(json.dumps(row), flush=True)
                rows.append(row)
    if not rows:
        raise SystemExit(f"no pose runs under {args.runs}: run real_recordings.py first")
    write_results(args.out.stem, rows, meta, folder=args.out.parent, with_csv=False)
    if not args.no_readme:
        write_readme_section("sim-poses", table(rows, meta))


if __name__ == "__main__":
    main()
