"""Latency of a policy: eager PyTorch, the ONNX export in onnxruntime, torch.export, and the
C export (``snds export --format c``, built with gcc -O2, called through ctypes).

Two cases: one state per call (the control-loop case; one thread) and batches of 10,000
states (one thread, and all cores). Each call is timed on its own with ``perf_counter_ns``;
the table gives the median and the 99th percentile. The C rows are one state per call only
(a batch through ctypes would time Python's loop), and include ctypes' call (about 1 us).
Inputs are prepared before the clock starts, in each backend's own type (a torch tensor, a
NumPy array).

    snds train --motion Sine --out runs/Sine          # the model (about a minute)
    python benchmarks/latency.py --model runs/Sine    # table into benchmarks/README.md

Writes ``benchmarks/results/latency.json`` (with the exported files' equality checks) and
``.csv``, and (without ``--no-readme``) the table between the ``latency`` markers of
``benchmarks/README.md``. The exported files go to a temporary folder.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import onnxruntime
import torch
from _runner import machine, machine_line, parser, write_readme_section, write_results

from snds import export
from snds.export import c as c_export
from snds.export import c_check
from snds.export.graph import policy_copy
from snds.models import load_model

BATCH = 10_000


def _time(call: Callable[[], object], *, calls: int, warmup: int) -> tuple[np.ndarray, np.ndarray]:
    """Wall and CPU seconds of each of ``calls`` timed calls, after ``warmup`` untimed ones.

    CPU time is the process's (``process_time_ns``): on a shared machine a one-thread call's
    CPU time is what it would take on a free core, while its wall time includes the time the
    scheduler gave to other work. With more threads it also counts their spinning.
    """
    for _ in range(warmup):
        call()
    seconds, cpu = np.empty(calls), np.empty(calls)
    for i in range(calls):
        begin, begin_cpu = time.perf_counter_ns(), time.process_time_ns()
        call()
        cpu[i] = (time.process_time_ns() - begin_cpu) * 1e-9
        seconds[i] = (time.perf_counter_ns() - begin) * 1e-9
    return seconds, cpu


def _backends(policy, files: dict[str, Path], threads: int) -> dict[str, Callable]:
    """Functions from a prepared input to velocities, one per (backend, precision)."""
    torch.set_num_threads(threads)
    eager32 = policy_copy(policy, torch.float32)
    eager64 = policy_copy(policy, torch.float64)
    program = torch.export.load(str(files["pt2"])).module()

    def eager(module):
        def run(x):
            with torch.inference_mode():
                return module(x)

        return run

    def onnx(path):
        # What a user gets from snds.export.load_onnx: one state through bound buffers, a
        # batch split across the threads.
        return export.load_onnx(path, threads=threads)

    def exported(x):
        with torch.inference_mode():
            return program(x)

    backends = {
        "eager PyTorch float32": eager(eager32),
        "eager PyTorch float64": eager(eager64),
        "ONNX Runtime float32": onnx(files["onnx32"]),
        "ONNX Runtime float64": onnx(files["onnx64"]),
        "torch.export float32": exported,
    }
    if "c" in files:
        backends.update(_c_backends(policy, files["c"]))
    return backends


def _c_backends(policy, library: Path) -> dict[str, Callable]:
    """One state through the compiled C export's ``snds_policy`` / ``snds_policy_f``."""
    import ctypes

    out = {}
    for suffix, real, dtype in (
        ("", ctypes.c_double, "float64"),
        ("_f", ctypes.c_float, "float32"),
    ):
        function = getattr(ctypes.CDLL(str(library)), f"snds_policy{suffix}")
        pointer = ctypes.POINTER(real)
        function.argtypes, function.restype = [pointer, pointer], ctypes.c_int
        result = np.zeros(policy.space.tangent_dim, dtype=dtype)
        result_pointer = result.ctypes.data_as(pointer)

        def run(x, function=function, pointer=pointer, result_pointer=result_pointer):
            # x: one prepared state (1, n), contiguous, in the build's precision
            function(x.ctypes.data_as(pointer), result_pointer)

        out[f"C {dtype}"] = run
    return out


def _input(name: str, x: np.ndarray):
    dtype = np.float64 if "float64" in name else np.float32
    array = np.ascontiguousarray(x, dtype=dtype)
    return array if name.startswith(("ONNX", "C ")) else torch.from_numpy(array)


def measure(
    policy,
    files: dict[str, Path],
    *,
    calls: int,
    seed: int,
    rounds: int = 3,
    batch_calls: int = 50,
) -> list[dict]:
    """All rows: each backend, one state (1 thread) and a batch (1 thread, all cores).

    The machine is shared: each configuration is measured in ``rounds`` rounds, the backends
    taking turns, and the round with the lowest median is kept (with its own p99), so a
    burst of someone else's work inflates at most the rounds it overlaps.
    """
    states = export.random_states(policy, BATCH, seed=seed)
    # The control-loop case: a state inside the demonstrations' box, away from the target.
    single = (policy.normalization.center + 0.5 * policy.normalization.length)[None]
    cores = os.cpu_count() or 1
    rows = []
    plan = [("single", single, 1, calls), ("batch", states, 1, batch_calls)]
    if cores > 1:
        plan.append(("batch", states, cores, batch_calls))
    for case, x, threads, count in plan:
        backends = _backends(policy, files, threads)
        best: dict[str, np.ndarray] = {}
        best_cpu: dict[str, np.ndarray] = {}
        for _ in range(rounds):
            for name, run in backends.items():
                if name.startswith("C ") and case != "single":
                    continue
                prepared = _input(name, x)
                seconds, cpu = _time(
                    lambda run=run, p=prepared: run(p), calls=count, warmup=max(count // 10, 2)
                )
                if name not in best or np.median(seconds) < np.median(best[name]):
                    best[name] = seconds
                if name not in best_cpu or np.median(cpu) < np.median(best_cpu[name]):
                    best_cpu[name] = cpu
        for name, seconds in best.items():
            rows.append(
                {
                    "backend": name,
                    "case": case,
                    "states_per_call": len(x),
                    "threads": threads,
                    "calls": count,
                    "rounds": rounds,
                    "median_us": round(float(np.median(seconds)) * 1e6, 2),
                    "p99_us": round(float(np.percentile(seconds, 99)) * 1e6, 2),
                    "cpu_median_us": round(float(np.median(best_cpu[name])) * 1e6, 2),
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    return rows


def table(rows: list[dict], checks: dict[str, dict]) -> str:
    """Markdown: one line per backend; single state in us, batches in ms."""
    names = list(dict.fromkeys(r["backend"] for r in rows))
    multi = sorted({r["threads"] for r in rows if r["case"] == "batch" and r["threads"] > 1})
    header = "| backend | 1 state: median / p99 (us) | 10,000 states, 1 thread: median / p99 (ms)"
    header += "".join(f" | 10,000 states, {t} threads: median / p99 (ms)" for t in multi)
    header += " | 10,000 states, 1 thread: CPU time (ms)"
    header += " | difference from the library: same precision / float64 |"
    lines = [header, "|---" * (5 + len(multi)) + "|"]
    for name in names:
        mine = {(r["case"], r["threads"]): r for r in rows if r["backend"] == name}
        one = mine[("single", 1)]
        cells = [f"{one['median_us']:.1f} / {one['p99_us']:.1f} (CPU {one['cpu_median_us']:.1f})"]
        for threads in [1, *multi]:
            batch = mine.get(("batch", threads))
            cells.append(
                "-"
                if batch is None
                else f"{batch['median_us'] / 1e3:.2f} / {batch['p99_us'] / 1e3:.2f}"
            )
        batch = mine.get(("batch", 1))
        cells.append("-" if batch is None else f"{batch['cpu_median_us'] / 1e3:.2f}")
        check = checks.get(name)
        cells.append(
            "(reference)"
            if check is None
            else f"{check['max_error']:.1e} / {check['max_error_float64']:.1e}"
        )
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _run(
    policy, folder: Path, *, calls: int, seed: int, rounds: int, batch_calls: int
) -> tuple[list[dict], dict]:
    files = {
        "onnx32": export.export_onnx(policy, folder / "policy-float32.onnx"),
        "onnx64": export.export_onnx(policy, folder / "policy-float64.onnx", dtype=torch.float64),
        "pt2": export.export_pt2(policy, folder / "policy-float32.pt2"),
    }
    if c_check.compiler() is not None:
        header = c_export.export_c(policy, folder / "policy.h")
        files["c"] = c_check.compile_shared(header, folder / "policy.so")
    checks = {
        "ONNX Runtime float32": export.verify(files["onnx32"], policy).to_dict(),
        "ONNX Runtime float64": export.verify(files["onnx64"], policy).to_dict(),
        "torch.export float32": export.verify(files["pt2"], policy).to_dict(),
    }
    if "c" in files:
        double, single = c_check.verify_c(folder / "policy.h", policy)
        checks["C float64"], checks["C float32"] = double.to_dict(), single.to_dict()
    rows = measure(policy, files, calls=calls, seed=seed, rounds=rounds, batch_calls=batch_calls)
    return rows, checks


def main() -> None:
    options = parser(__doc__, threads=False, tag=True)
    options.add_argument("--model", type=Path, default=Path("runs/Sine"), help="model directory")
    options.add_argument("--calls", type=int, default=10_000, help="timed single-state calls")
    options.add_argument("--rounds", type=int, default=3, help="rounds; the best one is kept")
    options.add_argument("--batch-calls", type=int, default=50, help="timed batch calls")
    options.add_argument("--seed", type=int, default=0, help="seed of the batch states")
    args = options.parse_args()
    if not (args.model / "model.json").is_file():
        raise SystemExit(
            f"{args.model}: no model; train one with `snds train --motion Sine --out {args.model}`"
        )
    policy, description = load_model(args.model)
    with tempfile.TemporaryDirectory(prefix="snds-latency-") as folder:
        rows, checks = _run(
            policy,
            Path(folder),
            calls=args.calls,
            seed=args.seed,
            rounds=args.rounds,
            batch_calls=args.batch_calls,
        )
    meta = machine() | {
        "onnxruntime": onnxruntime.__version__,
        "model": str(args.model),
        "motion": description.get("data", {}).get("motion"),
        "architecture": description.get("policy"),
        "checks": checks,
    }
    name = "latency" + (f"-{args.tag}" if args.tag else "")
    write_results(name, rows, meta)
    body = table(rows, checks)
    print(body)
    if not args.no_readme:
        sizes = meta["architecture"] or {}
        header = (
            f"{machine_line(meta)} On a machine shared with other work wall times grow; the "
            "CPU time of a one-thread call is what it takes on a free core. "
            f"`python benchmarks/latency.py --model {args.model}`: best of {args.rounds} "
            "rounds per row; "
            f"torch {meta['torch']}, onnxruntime {meta['onnxruntime']}; model `{args.model}` "
            f"({meta['motion'] or 'custom data'}; hidden {sizes.get('hidden')}, "
            f"{sizes.get('fourier_features')} Fourier features). The differences are the "
            "largest over 10,000 random states (up to 1000x the extent) of "
            "|exported - library| / max(|library|, top speed), the library in the export's "
            "precision and in float64. ONNX rows run `snds.export.load_onnx`: one state "
            "through buffers bound to the session, a batch split across the threads."
        )
        write_readme_section(name, header + "\n\n" + body)


if __name__ == "__main__":
    main()
