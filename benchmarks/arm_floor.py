"""How close can any field of positions come to the real recordings? Floors from the data.

Issue 21's bar for the real files asks a rollout from each demonstration's start to stay
within a Fréchet distance of 5 % of the extent of that demonstration. A policy of the
position alone, x' = f(x), has one velocity at each point, so where demonstrations cross or
run side by side at different speeds it cannot follow all of them. This script measures how
far the data's own fields get, with no learning in them:

* ``nearest``: the velocity of the nearest demonstrated sample (it returns the demonstrated
  velocity exactly on every sample);
* ``contracting k``: the same plus a pull onto the nearest sample's path,
  v_j - k (x - x_j) across v_j, with gain k per second (what the noise correction at width
  0 trains towards), the pull integrated exactly so that no gain makes the step unstable;

each rolled out from every demonstration's start at the demonstration's mean sample step, as
:mod:`arm_bars` measures the models, the Fréchet distance read over 1.0x and 1.5x the
demonstration's duration. A field that points nowhere at a resting start stays there (a
Fréchet distance near the extent). Beside them, ``crossing``: the demonstrations that come within
1 % of the extent of another one's sample whose direction of travel differs by more than 45
degrees (both moving faster than a tenth of the top speed).

    python benchmarks/arm_floor.py                 # the five real tasks, table into README

Writes ``benchmarks/results/arm-floor.json`` and the ``arm-floor`` block of
``benchmarks/README.md``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
from _readme import write_readme_section
from scipy.spatial import cKDTree

from snds.data import DataSource, DemonstrationSet
from snds.evaluate import path_reference
from snds.io import write_json
from snds.metrics import frechet

HERE = Path(__file__).resolve().parent
DATA = HERE.parent.parent / "shared" / "data"
#: task -> (file, demonstrations used; None: all), as ``benchmarks/reliability.py`` splits them
TASKS: dict[str, tuple[str, tuple[int, ...] | None]] = {
    "3D-pick-box_(0,2)": ("3D-pick-box.mat", (0, 2)),
    "3D-pick-box_(1,3)": ("3D-pick-box.mat", (1, 3)),
    "3D_Cshape_top": ("3D_Cshape_top.mat", None),
    "3D_sink": ("3D_sink.mat", None),
    "3D_viapoint_1": ("3D_viapoint_1.mat", None),
    "Messy_snake": ("Messy_snake.mat", None),
}
GAINS = (2.0, 10.0, 30.0)
BAR = 0.05
Step = Callable[[np.ndarray, float], np.ndarray]


def nearest_field(states: np.ndarray, velocities: np.ndarray, gain: float = 0.0) -> Step:
    """One step of length dt along the nearest sample's velocity, with the offset across it
    shrunk by exp(-gain dt) (the exact flow of the pull, stable at any gain and step)."""
    tree = cKDTree(states)
    directions = velocities / np.maximum(np.linalg.norm(velocities, axis=1, keepdims=True), 1e-12)

    def step(x: np.ndarray, dt: float) -> np.ndarray:
        j = tree.query(x)[1]
        offset = x - states[j]
        across = offset - (offset @ directions[j]) * directions[j]
        return x + dt * velocities[j] - (1.0 - np.exp(-gain * dt)) * across

    return step


def floor(demos: DemonstrationSet, step: Step) -> list[tuple[float, float]]:
    """Per demonstration, the Fréchet distance over the extent of the field's rollout from
    its start over 1.0x and over 1.5x its duration."""
    extent = demos.extent()
    out = []
    for demo in demos:
        samples = len(demo.times)
        dt = demo.duration / (samples - 1)
        x = demo.states[0].astype(float)
        path = [x]
        for _ in range(int(np.ceil(1.5 * (samples - 1)))):
            x = step(x, dt)
            path.append(x)
        path = np.array(path)
        reference = path_reference(demo)
        out.append(
            (
                frechet(path[:samples], reference) / extent,
                frechet(path, reference) / extent,
            )
        )
    return out


def crossing(
    demos: DemonstrationSet, radius: float = 0.01, degrees: float = 45.0, slow: float = 0.1
) -> int:
    """How many demonstrations pass within ``radius`` extents of another's sample whose
    direction of travel differs from theirs by more than ``degrees``; samples slower than
    ``slow`` times the top demonstrated speed (resting starts and ends, where the direction
    is noise) are left out."""
    extent = demos.extent()
    cos = np.cos(np.radians(degrees))
    top = max(float(np.linalg.norm(d.velocities, axis=1).max()) for d in demos)
    moving, units = [], []
    for demo in demos:
        speed = np.linalg.norm(demo.velocities, axis=1)
        keep = speed > slow * top
        moving.append(demo.states[keep])
        units.append(demo.velocities[keep] / speed[keep, None])
    count = 0
    for i in range(len(demos)):
        for j in range(len(demos)):
            if i == j or not len(moving[i]) or not len(moving[j]):
                continue
            hits = cKDTree(moving[j]).query_ball_point(moving[i], radius * extent)
            if any(np.any(units[j][near] @ units[i][k] < cos) for k, near in enumerate(hits)):
                count += 1
                break
    return count


def measure(task: str, file: Path, demos_used: tuple[int, ...] | None) -> dict:
    """The floors of one task."""
    demos = DataSource(file=file, demos=demos_used, gaps="fill").load()
    states = np.concatenate([d.states for d in demos])
    velocities = np.concatenate([d.velocities for d in demos])
    fields = {"nearest": nearest_field(states, velocities)}
    fields |= {f"contracting {k:g}": nearest_field(states, velocities, k) for k in GAINS}
    row = {"task": task, "demonstrations": len(demos), "crossing": crossing(demos)}
    for name, field in fields.items():
        distances = np.array(floor(demos, field))
        row[name] = {
            "worst_1x": float(distances[:, 0].max()),
            "worst_1.5x": float(distances[:, 1].max()),
            "over_bar_1x": int((distances[:, 0] > BAR).sum()),
            "over_bar_1.5x": int((distances[:, 1] > BAR).sum()),
        }
    return row


def table(rows: list[dict]) -> str:
    names = ["nearest"] + [f"contracting {k:g}" for k in GAINS]
    lines = [
        "Worst Fréchet distance over the extent (1.0x / 1.5x the duration) and, in brackets, "
        f"the demonstrations farther than {BAR:.0%} (1.0x / 1.5x), of rollouts of the data's "
        "own fields from every demonstration's start; no learning (`python "
        "benchmarks/arm_floor.py`). Rows: `results/arm-floor.json`.",
        "",
        "| task | demonstrations | crossing another | " + " | ".join(names) + " |",
        "|---|---|---|" + "---|" * len(names),
    ]
    for row in rows:
        cells = [
            f"{row[n]['worst_1x']:.3f} / {row[n]['worst_1.5x']:.3f} "
            f"({row[n]['over_bar_1x']} / {row[n]['over_bar_1.5x']})"
            for n in names
        ]
        lines.append(
            f"| {row['task']} | {row['demonstrations']} | {row['crossing']} | "
            + " | ".join(cells)
            + " |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA, help="the shared data folder")
    parser.add_argument("--no-readme", action="store_true")
    args = parser.parse_args()
    if not args.data.is_dir():
        raise SystemExit(f"{args.data} not found: the real recordings live in ../shared/data")
    rows = []
    for task, (file, used) in TASKS.items():
        rows.append(measure(task, args.data / file, used))
        print(json.dumps(rows[-1]), flush=True)
    write_json(HERE / "results" / "arm-floor.json", {"rows": rows})
    if not args.no_readme:
        write_readme_section("arm-floor", table(rows))


if __name__ == "__main__":
    main()
