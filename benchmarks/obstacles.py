"""Obstacles across the demonstrated paths: the stability report under obstacles.

For each of the paper's 8 LASA motions (seed 0) and a 3-D real task, a trained model of the
positions alone (``snds train --motion M --seed 0 --phase-codes 0 --out RUNS/M --quiet``;
``--data ../shared/data/3D_Cshape_top.mat --phase-codes 0 --out RUNS/Cshape3D``) gets
obstacles placed by a fixed rule on its demonstrated path, and
:func:`snds.obstacles.check_obstacles` rolls it out from 1,000 random free starts in the
box 3x the extent and from the demonstrations' starts: reached, stalled (clustered, by kind),
penetrated, smallest clearance against the margin, DTW to the demonstrations the obstacles
leave free, and the check's CPU and wall time.

Placement rule (deterministic). Motion i (0-based, in the paper's order) gets K = 1 + i mod 3
spheres of radius 0.08 and margin 0.02 (in units of the motion's extent, the largest
distance of a demonstrated position from the target), with the default influence (the
radius). Their centres are points of demonstration 0 at the fractions of its arc length
(0.5), (0.35, 0.65) or (0.3, 0.5, 0.7); a centre closer than 2 (R + m) + R to an earlier one,
or than R + m + R to the target, moves on along the path by 0.05 of its length until it is
not (and is dropped if that takes it past 0.95: Worm keeps 2 of its 3). The 3-D task gets
one box of half-widths 0.08 extent, turned by 30 degrees about z,
margin 0.02 extent, centred on demonstration 0 at half its arc length.

Usage::

    python benchmarks/obstacles.py --runs runs/obst            # 8 LASA motions + 3-D
    python benchmarks/obstacles.py --runs runs/obst --motions Sine --rollouts 200

Writes ``benchmarks/results/obstacles/{MOTION}.json``, ``summary.csv`` and ``summary.md``, and
the table into benchmarks/README.md (the ``obstacles`` block; not with ``--no-readme``).
"""

from __future__ import annotations

import csv
import json
import time
from pathlib import Path

import numpy as np
from _runner import DATA, RESULTS, machine, machine_line, parser, set_threads, write_readme_section

from snds.benchmark import MOTION_GROUPS
from snds.data import load_demonstrations, load_lasa
from snds.io import to_jsonable
from snds.models import load_model
from snds.obstacles import Box, Scene, Sphere, check_obstacles
from snds.stability import CheckConfig

PAPER8 = list(MOTION_GROUPS["paper8"])
FRACTIONS = {1: (0.5,), 2: (0.35, 0.65), 3: (0.3, 0.5, 0.7)}
RADIUS, MARGIN = 0.08, 0.02
OUT = RESULTS / "obstacles"


def along(path: np.ndarray, fraction: float) -> np.ndarray:
    """The point of a path (T, n) at a fraction of its arc length."""
    lengths = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))]
    return np.array([np.interp(fraction * lengths[-1], lengths, c) for c in path.T])


def spheres_on_path(demos, count: int) -> Scene:
    """The placement rule of the module docstring."""
    extent = demos.extent()
    radius, margin = RADIUS * extent, MARGIN * extent
    path, centres = demos[0].positions, []
    for fraction in FRACTIONS[count]:
        while fraction < 0.95:
            centre = along(path, fraction)
            apart = all(
                np.linalg.norm(centre - c) >= 2 * (radius + margin) + radius for c in centres
            )
            if apart and np.linalg.norm(centre - demos.target) >= 2 * radius + margin:
                centres.append(centre)
                break
            fraction += 0.05
    spheres = tuple(Sphere(center=tuple(c), radius=radius, margin=margin) for c in centres)
    return Scene(obstacles=spheres)


def box_on_path(demos) -> Scene:
    extent = demos.extent()
    centre = along(demos[0].positions, 0.5)
    box = Box(
        center=tuple(centre),
        half_sizes=(RADIUS * extent,) * 3,
        angles=(0.0, 0.0, 30.0),
        margin=MARGIN * extent,
    )
    return Scene(obstacles=(box,))


def run(name: str, model: Path, demos, scene: Scene, rollouts: int) -> dict:
    policy, _ = load_model(model)
    report = check_obstacles(policy, demos, scene, config=CheckConfig(rollouts=rollouts, seed=0))
    record = {"task": name, "model": str(model), **report.to_dict()}
    (OUT / f"{name}.json").write_text(json.dumps(to_jsonable(record), indent=1))
    r, d = report.random, report.demos
    kinds = sorted({s["kind"] for s in r.stall_points})
    return {
        "task": name,
        "obstacles": len(scene.obstacles),
        "random_starts": r.starts,
        "converged": r.converged_fraction,
        "stalled": r.stalled,
        "stall_kinds": "/".join(kinds),
        "penetrated": r.penetrated,
        "min_clearance": r.min_clearance,
        "margin": r.margin,
        "demo_starts": d.starts,
        "demo_reached": d.reached,
        "demo_penetrated": d.penetrated,
        "demo_min_clearance": d.min_clearance,
        "free_demos": len(report.free_demos),
        "dtw_free": report.dtw_free,
        "dtw_free_without": report.dtw_free_without_obstacles,
        "cpu_s": report.cpu_seconds,
        "wall_s": report.wall_seconds,
    }


def markdown(rows: list[dict]) -> str:
    head = (
        "| task | spheres/box | random starts | converged | stalled (kind) | penetrated | "
        "min clearance / margin | demo starts reached | DTW free demos (without obstacles) "
        "| CPU s | wall s |\n|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        dtw = (
            f"{r['dtw_free']:.3g} ({r['dtw_free_without']:.3g}), {r['free_demos']} demos"
            if r["dtw_free"] is not None
            else "none free"
        )
        stalled = f"{r['stalled']}" + (f" ({r['stall_kinds']})" if r["stalled"] else "")
        lines.append(
            f"| {r['task']} | {r['obstacles']} | {r['random_starts']} | {r['converged']:.3f} | "
            f"{stalled} | {r['penetrated']} | {r['min_clearance']:.3g} / {r['margin']:.3g} | "
            f"{r['demo_reached']} of {r['demo_starts']} | {dtw} | {r['cpu_s']:.1f} | "
            f"{r['wall_s']:.1f} |"
        )
    return head + "\n".join(lines) + "\n"


def main() -> None:
    options = parser(__doc__)
    options.add_argument("--runs", type=Path, default=Path("runs/obst"), help="trained models")
    options.add_argument("--motions", default=",".join(PAPER8))
    options.add_argument("--rollouts", type=int, default=1000)
    options.add_argument("--no-3d", action="store_true", help="skip the 3-D task")
    args = options.parse_args()
    set_threads(args.threads)
    meta = machine(threads=args.threads)
    OUT.mkdir(parents=True, exist_ok=True)
    rows = []
    started = time.perf_counter()
    for motion in args.motions.split(","):
        count = 1 + PAPER8.index(motion) % 3 if motion in PAPER8 else 1
        demos = load_lasa(motion)
        rows.append(
            run(motion, args.runs / motion, demos, spheres_on_path(demos, count), args.rollouts)
        )
        print(rows[-1], flush=True)
    if not args.no_3d:
        demos = load_demonstrations(DATA / "3D_Cshape_top.mat")
        rows.append(
            run("3D_Cshape_top", args.runs / "Cshape3D", demos, box_on_path(demos), args.rollouts)
        )
        print(rows[-1], flush=True)
    with open(OUT / "summary.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (OUT / "summary.md").write_text(markdown(rows))
    print(markdown(rows))
    total = time.perf_counter() - started
    print(f"total {total:.0f} s wall")
    if not args.no_readme:
        head = f"{machine_line(meta)} Total {total:.0f} s wall.\n\n"
        write_readme_section("obstacles", head + markdown(rows).rstrip())


if __name__ == "__main__":
    main()
