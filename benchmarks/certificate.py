"""The step certificate (``snds verify``) on trained models: how much of the 3x box is proven
at the data's rate, what it costs, and whether float32 still decreases V near the target.

    python benchmarks/certificate.py                     # the paper's 8 LASA motions, seed 0
    python benchmarks/certificate.py --full Sine         # also the whole-box search of Sine
    python benchmarks/certificate.py --data /work/shared/data/3D_sink.mat

For every model (trained with ``snds train --seed 0 --threads 1`` into ``--runs`` if absent):

- **sample**: ``--cells`` random cells of the finest starting size (side ``--side`` extents)
  in the 3x box, bounded at the data's step: the fraction proven, CPU seconds per cell, and
  the full box's cell count at that size, hence its CPU cost;
- **full** (``--full NAME``): ``snds.certify.certificate.certify`` over the whole box with
  ``--budget`` cells: status, the proven fraction, the certified step, CPU and wall seconds;
- **float32**: ``--float32`` states at 1e-3 to 1e-1 extents from the target stepped by the
  float32 export at the data's step: how many raise V (V in float64), and the largest
  relative error of the float32 velocity against the float64 one.

Writes ``benchmarks/results/certificate.json`` and the ``certificate`` block of
``benchmarks/README.md`` (``--no-readme``: not).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch
from _runner import (
    RESULTS,
    children_cpu,
    machine,
    machine_line,
    parser,
    set_threads,
    write_readme_section,
)

from snds.certify.bounds import cell_bounds
from snds.certify.certificate import VerifyConfig, certify
from snds.certify.model import PolicyModel
from snds.certify.search import deployed_step
from snds.models import load_model

MOTIONS = ("Sine", "PShape", "Worm", "GShape", "NShape", "DoubleBendedLine", "CShape", "Angle")


def train(name: str, runs: Path, data: str | None) -> tuple[Path, float]:
    """The model of ``name`` (trained now if absent) and the training's CPU seconds."""
    out = runs / name
    if (out / "model.json").is_file():
        return out, float("nan")
    source = ["--data", data] if data else ["--motion", name]
    before = children_cpu()
    # Position policies (no phase in the state): what the certificate covers first.
    command = [sys.executable, "-m", "snds", "--threads", "1", "--quiet", "train", *source]
    subprocess.run([*command, "--phase-codes", "0", "--seed", "0", "--out", str(out)], check=True)
    return out, children_cpu() - before


def sample(policy, dt: float, *, cells: int, side: float, box: float, seed: int) -> dict:
    """Random cells of one size in the box, bounded at one step."""
    model = PolicyModel.from_policy(policy)
    scale = float(policy.normalization.extent) / model.length
    n = model.dim
    rng = np.random.default_rng(seed)
    half_box, half = box * scale, 0.5 * side * scale
    centers = rng.uniform(-half_box + half, half_box - half, (cells, n))
    centers = centers[np.linalg.norm(centers, axis=1) > 4 * half]
    cpu = time.process_time()
    bounds = cell_bounds(model, centers - half, centers + half, step=dt / model.time, eta=1e-6)
    seconds = time.process_time() - cpu
    full = (2 * half_box / (2 * half)) ** n
    return {
        "cells": len(centers),
        "side_extents": side,
        "proven_fraction": float(bounds.proven.mean()),
        "cpu_per_cell": seconds / len(centers),
        "box_cells": full,
        "box_cpu_estimate": full * seconds / len(centers),
        "smallest_cell_step": float(bounds.largest_step.min()) * model.time,
    }


def float32_near_target(policy, dt: float, *, count: int, seed: int) -> dict:
    """float32 steps near the target: V rises and the velocity's relative error."""
    rng = np.random.default_rng(seed)
    n = policy.dim
    radii = 10.0 ** rng.uniform(-3, -1, count) * float(policy.normalization.extent)
    directions = rng.normal(size=(count, n))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    x = policy.target + radii[:, None] * directions
    x32 = x.astype(np.float32).astype(np.float64)
    nxt = deployed_step(policy, x32, dt=dt, dtype=torch.float32)
    exact = deployed_step(policy, x32, dt=dt, dtype=torch.float64)
    p64 = policy.double()
    with torch.no_grad():
        before = p64.lyapunov(p64.to_model(torch.as_tensor(x32)))
        after = p64.lyapunov(p64.to_model(torch.as_tensor(nxt)))
    moved32, moved64 = nxt - x32, exact - x32
    error = np.linalg.norm(moved32 - moved64, axis=1) / np.linalg.norm(moved64, axis=1)
    rises = (after >= before).numpy()
    extent = float(policy.normalization.extent)
    return {
        "states": count,
        "v_rises": int(rises.sum()),
        "farthest_rise_extents": float(radii[rises].max() / extent) if rises.any() else 0.0,
        "largest_relative_error": float(error.max()),
        "median_relative_error": float(np.median(error)),
    }


def main() -> None:
    options = parser(__doc__)
    options.add_argument("--motions", nargs="*", default=list(MOTIONS))
    options.add_argument("--data", action="append", default=[], help="a real file (repeatable)")
    options.add_argument("--runs", type=Path, default=Path("runs/certificate"))
    options.add_argument("--cells", type=int, default=2000)
    options.add_argument("--side", type=float, default=6 / 2**9, help="cell side, extents")
    options.add_argument("--box", type=float, default=3.0)
    options.add_argument("--full", nargs="*", default=[], help="names to search in full")
    options.add_argument("--budget", type=int, default=400_000)
    options.add_argument("--float32", type=int, default=20_000)
    args = options.parse_args()
    set_threads(args.threads)
    tasks = [(m, None) for m in args.motions] + [(Path(d).stem, d) for d in args.data]
    results = []
    for name, data in tasks:
        folder, train_cpu = train(name, args.runs, data)
        policy, _ = load_model(folder)
        stability = json.loads((folder / "metrics.json").read_text())["stability"]
        dt = float(stability["dt"])
        row = {
            "name": name,
            "dim": policy.dim,
            "dt": dt,
            "sampled_largest_safe_dt": stability["largest_safe_dt"],
            "train_cpu_seconds": train_cpu,
            "sample": sample(policy, dt, cells=args.cells, side=args.side, box=args.box, seed=0),
            "float32": float32_near_target(policy, dt, count=args.float32, seed=0),
        }
        if name in args.full:
            wall = time.perf_counter()
            certificate = certify(
                policy, dt=dt, weights_sha256="", config=VerifyConfig(budget=args.budget)
            )
            row["full"] = {
                k: certificate[k]
                for k in (
                    "status",
                    "requested_status",
                    "requested_proven_fraction",
                    "largest_certified_dt",
                    "cells_bounded",
                    "cpu_seconds",
                    "excluded_fraction_of_extent",
                )
            }
            row["full"]["wall_seconds"] = time.perf_counter() - wall
            row["full"]["open_cells"] = len(certificate["open"])
        results.append(row)
        print(json.dumps(row), flush=True)
    out = RESULTS / "certificate.json"
    record = {**machine(threads=args.threads), "box": args.box, "results": results}
    out.write_text(json.dumps(record, indent=1))
    if not args.no_readme:
        write_readme_section("certificate", table(record))


def table(record: dict) -> str:
    """The README block."""
    lines = [
        f"{machine_line(record) if 'date' in record else 'On ' + record['cpu'] + '.'} "
        "`python benchmarks/certificate.py`; CPU seconds are the comparable figure on a shared "
        "machine. Sample: "
        f"{record['results'][0]['sample']['cells']} random cells of side "
        f"{record['results'][0]['sample']['side_extents']:.4g} extents in the "
        f"{record['box']:g}x box, bounded at the data's step.",
        "",
        "| model | n | data step (s) | sampled safe step (s) | cells proven at the data's step "
        "| CPU ms / cell | cells in the box | est. CPU s, whole box | float32 near target: "
        "V rises / states, largest rel. error |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in record["results"]:
        s, f = row["sample"], row["float32"]
        lines.append(
            f"| {row['name']} | {row['dim']} | {row['dt']:.4g} | "
            f"{row['sampled_largest_safe_dt']:.4g} | {100 * s['proven_fraction']:.1f}% | "
            f"{1e3 * s['cpu_per_cell']:.2f} | {s['box_cells']:.3g} | "
            f"{s['box_cpu_estimate']:.0f} | {f['v_rises']} / {f['states']}, "
            f"{f['largest_relative_error']:.1e}, farthest rise {f['farthest_rise_extents']:.2g} |"
        )
    fulls = [r for r in record["results"] if "full" in r]
    if fulls:
        lines += [
            "",
            "Whole-box searches (`certify`, excluded ball 1e-3 of the extent):",
            "",
            "| model | requested step | proven at it | certified step (s) | cells bounded | "
            "open cells | CPU s | wall s |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in fulls:
            g = r["full"]
            lines.append(
                f"| {r['name']} | {r['dt']:.4g} | {100 * g['requested_proven_fraction']:.1f}% "
                f"({g['requested_status']}) | {g['largest_certified_dt']:.4g} | "
                f"{g['cells_bounded']} | {g['open_cells']} | {g['cpu_seconds']:.0f} | "
                f"{g['wall_seconds']:.0f} |"
            )
    return "\n".join(lines)


if __name__ == "__main__":
    main()
