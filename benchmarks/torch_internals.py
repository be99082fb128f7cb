"""Whether skipping ``torch.autograd.Function.apply``'s Python layer earns its place.

``snds.nn.fused.sincos`` (sin and cos of a coupling layer's Fourier angles from one pass)
once called the autograd engine's ``apply`` directly,
``super(torch.autograd.Function, SinCos).apply(angles)``, to skip the argument binding that
``Function.apply`` does in Python on every call. That is a private path, which a torch upgrade
may change. This measures what it saves, on one thread:

1. one call, forward with autograd recording, at the shape of a training step's coupling
   layer (batch 512, 32 features), through ``SinCos.apply``, through the engine's ``apply``,
   and through ``Function.apply`` of the same function in the older ``forward(ctx, ...)``
   form (which binds no arguments, but which torch.func's vmap refuses), alternated over
   ``--rounds`` rounds (median microseconds, wall and CPU);
2. how many calls one training step makes (the ``SinCosBackward`` nodes that torch's profiler
   sees in the default fit's steps);
3. the default fit's time per step (``snds.train.fit`` on one LASA motion for ``--steps``
   steps, per round);

and reports the saving as a share of a step: calls per step x (apply - engine) / step time.

    python benchmarks/torch_internals.py                      # writes results/torch_internals.json
    python benchmarks/torch_internals.py --rounds 9 --steps 80
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch
from _runner import cpu_name

from snds.data import Normalization, load_lasa, split_samples
from snds.nn.fused import SinCos
from snds.policy import StablePolicy
from snds.recipes import RECIPES
from snds.train import fit

RESULTS = Path(__file__).resolve().parent / "results" / "torch_internals.json"


def _engine_apply(angles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    # The path that was dropped: the engine's apply, past Function.apply's binding.
    return super(torch.autograd.Function, SinCos).apply(angles)


class _ContextSinCos(torch.autograd.Function):
    """SinCos in the older form, ``forward(ctx, ...)`` without ``setup_context``:
    ``Function.apply`` binds no arguments for it, but torch.func transforms (vmap) refuse it."""

    @staticmethod
    def forward(ctx, angles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # noqa: ANN001, D102
        sin, cos = torch.sin(angles), torch.cos(angles)
        ctx.save_for_backward(sin, cos)
        return sin, cos

    backward = SinCos.backward


def _per_call(call, angles: torch.Tensor, calls: int) -> tuple[float, float]:
    """The mean over ``calls`` calls: (wall us, CPU us) per call."""
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(calls):
        call(angles)
    return (
        (time.perf_counter() - wall) / calls * 1e6,
        (time.process_time() - cpu) / calls * 1e6,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--motion", default="Sine")
    parser.add_argument("--steps", type=int, default=60, help="steps per timed fit")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--calls", type=int, default=2000, help="calls per round of (1)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    torch.set_num_threads(1)

    # (1) one call each way, alternated.
    angles = torch.randn(512, 32, dtype=torch.float32, requires_grad=True)
    variants = {
        "Function.apply": SinCos.apply,
        "engine apply": _engine_apply,
        "Function.apply, ctx form": _ContextSinCos.apply,
    }
    for call in variants.values():
        _per_call(call, angles, 200)  # warm-up
    per_call: dict[str, list[tuple[float, float]]] = {name: [] for name in variants}
    for _ in range(args.rounds):
        for name, call in variants.items():
            per_call[name].append(_per_call(call, angles, args.calls))
    calls = {
        name: {
            "wall_us": statistics.median(w for w, _ in rows),
            "cpu_us": statistics.median(c for _, c in rows),
        }
        for name, rows in per_call.items()
    }

    # (2) and (3): the default fit.
    demos = load_lasa(args.motion)
    split = split_samples(demos, test_fraction=0.2, seed=0)
    recipe = RECIPES["default"]
    config = replace(recipe.train, steps=args.steps)

    def policy() -> StablePolicy:
        return StablePolicy(
            dim=demos.dim,
            normalization=Normalization.fit(demos),
            config=recipe.policy,
            seed=0,
        )

    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as profile:
        fit(policy(), demos, split, config, progress=False)
    nodes = sum(event.count for event in profile.key_averages() if "SinCosBackward" in event.key)
    calls_per_step = nodes / args.steps
    steps = []
    for _ in range(args.rounds):
        wall, cpu = time.perf_counter(), time.process_time()
        result = fit(policy(), demos, split, config, progress=False)
        steps.append(
            {
                "wall_ms": (time.perf_counter() - wall) / result.steps * 1e3,
                "cpu_ms": (time.process_time() - cpu) / result.steps * 1e3,
            }
        )
    step_ms = statistics.median(s["cpu_ms"] for s in steps)
    saved_us = calls["Function.apply"]["cpu_us"] - calls["engine apply"]["cpu_us"]
    share = calls_per_step * saved_us / (step_ms * 1e3)

    result = {
        "machine": f"{platform.machine()}, {cpu_name()}, {torch.get_num_threads()} thread "
        "(2 cores shared with other work: wall times grow, CPU times less)",
        "torch": torch.__version__,
        "motion": args.motion,
        "rounds": args.rounds,
        "per_call": calls,
        "calls_per_step": calls_per_step,
        "step_ms_median": {
            "wall": statistics.median(s["wall_ms"] for s in steps),
            "cpu": step_ms,
        },
        "saved_us_per_call_cpu": saved_us,
        "saved_share_of_step": share,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    print(
        f"engine apply saves {saved_us:.2f} us CPU per call x {calls_per_step:g} calls per step "
        f"= {100 * share:.2f}% of a {step_ms:.1f} ms step"
    )


if __name__ == "__main__":
    main()
