"""The cost of ``snds plot --obstacle`` against ``snds plot`` on one model, side by side.

Both commands run as subprocesses with one torch thread on the same saved model (a position
model without a phase: obstacles take those), ``--repeat`` times each, alternating; the
figures are each command's wall time and the CPU time of its process (user + system), the
median over the repeats. The obstacle is the one ``benchmarks/obstacles.py`` places on the
motion's demonstrated path (one sphere of radius 0.08 extent, margin 0.02 extent, at half
of demonstration 0's arc length).

Usage::

    snds --threads 1 train --motion Sine --seed 0 --phase-codes 0 --out runs/Sine0
    python benchmarks/plot_cost.py --model runs/Sine0 --motion Sine

Writes ``benchmarks/results/plot_cost.json`` (with the CPU model and the machine's load).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from obstacles import spheres_on_path

from snds.data import load_lasa

OUT = Path(__file__).resolve().parent / "results" / "plot_cost.json"


def cpu_model() -> str:
    """The CPU's model name (lscpu's), or the platform's processor string."""
    try:
        text = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return platform.processor()
    for line in text.splitlines():
        if line.startswith("Model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor()


def timed(command: list[str]) -> tuple[float, float]:
    """Wall and CPU seconds (user + system of the child) of one command."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True, help="a position model folder")
    parser.add_argument("--motion", default="Sine", help="its LASA motion")
    parser.add_argument("--repeat", type=int, default=1, help="runs of each command")
    args = parser.parse_args()
    obstacle = spheres_on_path(load_lasa(args.motion), 1).obstacles[0]
    spec = "sphere:{},{},margin={}".format(
        ",".join(f"{c:.9g}" for c in obstacle.center), f"{obstacle.radius:.9g}", obstacle.margin
    )
    snds = [sys.executable, "-m", "snds", "--quiet", "--threads", "1", "plot", str(args.model)]
    runs: dict[str, list[tuple[float, float]]] = {"plot": [], "plot --obstacle": []}
    with tempfile.TemporaryDirectory() as out:
        for _ in range(args.repeat):
            runs["plot"].append(timed([*snds, "--out", out]))
            runs["plot --obstacle"].append(timed([*snds, "--out", out, "--obstacle", spec]))
    figures = {
        name: {
            "wall_s": statistics.median(w for w, _ in times),
            "cpu_s": statistics.median(c for _, c in times),
            "runs": [{"wall_s": w, "cpu_s": c} for w, c in times],
        }
        for name, times in runs.items()
    }
    record = {
        "model": str(args.model),
        "motion": args.motion,
        "obstacle": spec,
        "cpu": cpu_model(),
        "load_average": os.getloadavg(),
        "threads": 1,
        **figures,
        "ratio_wall": figures["plot --obstacle"]["wall_s"] / figures["plot"]["wall_s"],
        "ratio_cpu": figures["plot --obstacle"]["cpu_s"] / figures["plot"]["cpu_s"],
    }
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(record, indent=1))
    print(json.dumps({k: v for k, v in record.items() if k not in ("plot", "plot --obstacle")}))
    for name in runs:
        print(f"{name}: wall {figures[name]['wall_s']:.1f} s, CPU {figures[name]['cpu_s']:.1f} s")


if __name__ == "__main__":
    main()
