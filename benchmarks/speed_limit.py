"""The speed limit from far starts: peak commanded speed and arrival, with and without it.

From starts 3x the demonstrations' extent from the target (the corners and edge midpoints
of that box), a controller at ``--rate`` Hz holds the guarded command for each period on an
ideal integrator, with no limit and with limits of 1x and 0.5x the demonstrations' top speed.
The command is the model's C export's ``snds_step`` (what :func:`snds.rollout.safe_velocity`
computes, to rounding: tests/test_c_export.py), 50x faster than the library on one state.
Reported per limit: the peak commanded speed of the positions, how many starts arrive
(within 1 % of the extent), the slowest arrival time, and the shortest guarded step taken on
the way (states farther than 1 % of the extent from the target).

    python benchmarks/speed_limit.py --model tests/fixtures/models-c52752d/sine

Writes ``benchmarks/results/speed_limit.json`` and the table between the ``speed_limit``
markers of ``benchmarks/README.md``.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np
from _runner import RESULTS, machine, machine_line, parser, set_threads, write_readme_section

from snds.export.c import export_c
from snds.export.c_check import load_c
from snds.models import load_model
from snds.policy import float64_copy


def starts(policy, radius: float) -> np.ndarray:
    """The 8 corners and edge midpoints of the square of half-width ``radius`` extents
    around the target (positions of a 2-D model)."""
    extent = float(policy.normalization.length)
    offsets = [(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1) if (i, j) != (0, 0)]
    return policy.target + radius * extent * np.array(offsets, dtype=float)


def run(controller, policy, x0: np.ndarray, *, rate: float, seconds: float, max_speed):
    """Peak speed, arrival times (s; inf: not within 1 % of the extent at the end), and the
    shortest step h taken (s)."""
    dt, extent = 1.0 / rate, float(policy.normalization.length)
    x = np.array(x0, dtype=np.float64)
    peak, shortest = 0.0, dt
    arrived = np.full(len(x0), np.inf)
    for step in range(int(seconds * rate)):
        command, h, _ = controller.step(x, dt, max_speed or 0.0)
        peak = max(peak, float(np.linalg.norm(command, axis=1).max()))
        # Only on the way: at the target V is rounding noise and the guard halves to the end.
        away = np.linalg.norm(x - policy.target, axis=1) > 0.01 * extent
        if away.any():
            shortest = min(shortest, float(h[away].min()))
        x = x + dt * command
        inside = np.linalg.norm(x - policy.target, axis=1) <= 0.01 * extent
        arrived = np.where(inside & np.isinf(arrived), (step + 1) * dt, arrived)
        arrived = np.where(inside, arrived, np.inf)
    worst = float(np.linalg.norm(x - policy.target, axis=1).max() / extent)
    return peak, arrived, shortest, worst


def main() -> None:
    options = parser(__doc__, tag=True)
    options.add_argument("--model", type=Path, default=Path("tests/fixtures/models-c52752d/sine"))
    options.add_argument("--rate", type=float, default=500.0)
    options.add_argument("--seconds", type=float, default=40.0)
    args = options.parse_args()
    set_threads(args.threads)
    policy = float64_copy(load_model(args.model)[0])
    top = float(policy.length / policy.time)
    x0 = starts(policy, 3.0)
    rows = []
    folder = tempfile.TemporaryDirectory(prefix="snds-speed-")
    controller = load_c(
        export_c(policy, Path(folder.name) / "policy.h"), policy, Path(folder.name) / "p.so"
    )
    for factor in (None, 1.0, 0.5):
        limit = None if factor is None else factor * top
        wall, cpu = time.perf_counter(), time.process_time()
        peak, arrivals, shortest, worst = run(
            controller, policy, x0, rate=args.rate, seconds=args.seconds, max_speed=limit
        )
        rows.append(
            {
                "limit_over_top_speed": factor,
                "limit": limit,
                "peak_speed": peak,
                "peak_over_top_speed": peak / top,
                "arrived": int(np.isfinite(arrivals).sum()),
                "starts": len(x0),
                "slowest_arrival_s": float(arrivals.max()),
                "shortest_step_s": shortest,
                "worst_final_distance_over_extent": worst,
                "wall_s": time.perf_counter() - wall,
                "cpu_s": time.process_time() - cpu,
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    meta = machine(threads=args.threads) | {
        "model": str(args.model),
        "rate": args.rate,
        "seconds": args.seconds,
        "top_speed": top,
        "extent": float(policy.normalization.length),
    }
    (RESULTS / f"speed_limit{'-' + args.tag if args.tag else ''}.json").write_text(
        json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n"
    )
    lines = [
        "| limit | peak commanded speed | arrived (1 % of the extent) | slowest arrival (s) "
        "| farthest at the end (extents) | shortest guarded step on the way (s) |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        name = "none" if row["limit"] is None else f"{row['limit_over_top_speed']:g}x top speed"
        lines.append(
            f"| {name} | {row['peak_over_top_speed']:.2f}x top speed | {row['arrived']} of "
            f"{row['starts']} | {row['slowest_arrival_s']:.2f} | "
            f"{row['worst_final_distance_over_extent']:.3f} | {row['shortest_step_s']:.1e} |"
        )
    header = (
        f"{machine_line(meta)} `python benchmarks/speed_limit.py --model {args.model}`: "
        f"(top speed {top:.1f} units/s, extent {meta['extent']:.1f}), 8 starts 3x the extent "
        f"away, the guarded command held for each period at {args.rate:g} Hz on an ideal "
        f"integrator for {args.seconds:g} s."
    )
    print("\n".join(lines))
    if not args.no_readme:
        write_readme_section(
            "speed_limit" + (f"-{args.tag}" if args.tag else ""), header + "\n\n" + "\n".join(lines)
        )


if __name__ == "__main__":
    main()
