"""Training speed: variants of the default fit timed side by side in one process.

Each variant trains the default policy on one LASA motion for ``--steps`` steps with
:func:`snds.train.fit` (the schedule is compressed to those steps; the cost of a step does not
depend on it). The variants run in turn, ``--rounds`` times, so that a change in the machine's
load hits all of them alike; the table gives the median ms per step, wall and CPU
(``time.process_time``), and the seconds a full default fit of that variant would take.

    python benchmarks/train_speed.py                          # all variants, Sine
    python benchmarks/train_speed.py --variants default reference --rounds 5
    python benchmarks/train_speed.py --compile                # adds torch.compile (slow)

Variants:

* ``default``: the library as it is.
* ``reference``: the reference path (``snds.nn.fused.ENABLED = False``): the
  same maths in plain operations, as before the fused path.
* ``torch-optimizer``: gradient clipping and the Adam step through torch's own
  ``clip_grad_norm_`` and ``Adam.step`` instead of :func:`snds.train.clip_gradients` and
  :func:`snds.train.adam_step` (the same arithmetic).
* ``before``: both of the above: the training step as it was before these changes.
* ``brute-nearest``: the noise correction's nearest-sample search as all distances
  (``torch.cdist``) instead of the k-d tree of :meth:`snds.losses.Samples.nearest`;
  ``no-correction``: the default with ``noise_correction=0``.
* ``batch16``: a batch of 16: what a step costs that is not proportional to the batch.
* ``batch256``, ``penalty8``: the default with ``batch_size=256`` / ``penalty_every=8``.
* ``warp6-features64`` (the previous default, CHANGELOG), ``warp4-features64``,
  ``warp4-features48``, ``warp3``: other sizes of V's warp than the default's 4 coupling layers
  of 32 random features.
* ``batch256-steps1200``: a combination (its full fit is 1,200 steps).
* ``compiled`` (with ``--compile``): the step's loss under ``torch.compile``; its first
  call's compile time is reported separately (the FX graph cache under
  ``$TORCHINDUCTOR_CACHE_DIR`` makes a second process faster).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import statistics
import time
from collections.abc import Callable, Iterator

import torch

import snds.losses
import snds.nn.fused
import snds.train
from snds.data import Normalization, load_lasa, split_samples
from snds.policy import PolicyConfig, StablePolicy
from snds.train import TrainConfig, fit


@contextlib.contextmanager
def _nothing() -> Iterator[None]:
    yield


@contextlib.contextmanager
def _reference() -> Iterator[None]:
    snds.nn.fused.ENABLED = False
    try:
        yield
    finally:
        snds.nn.fused.ENABLED = True


@contextlib.contextmanager
def _torch_optimizer() -> Iterator[None]:
    clip, step = snds.train.clip_gradients, snds.train.adam_step

    def torch_clip(parameters: list[torch.Tensor], max_norm: float) -> torch.Tensor:
        return torch.nn.utils.clip_grad_norm_(parameters, max_norm, foreach=True)

    def torch_step(optimizer: torch.optim.Adam, lr: float) -> None:
        for group in optimizer.param_groups:
            group["lr"] = lr
        optimizer.step()

    snds.train.clip_gradients, snds.train.adam_step = torch_clip, torch_step
    try:
        yield
    finally:
        snds.train.clip_gradients, snds.train.adam_step = clip, step


@contextlib.contextmanager
def _before() -> Iterator[None]:
    with _reference(), _torch_optimizer():
        yield


@contextlib.contextmanager
def _brute_nearest() -> Iterator[None]:
    original = snds.losses.Samples.nearest

    def nearest(self: snds.losses.Samples, states: torch.Tensor) -> torch.Tensor:
        stride = max(1, -(-len(self.positions) // snds.losses.NEAREST_REFERENCES))
        return torch.cdist(states, self.positions[::stride]).argmin(dim=1) * stride

    snds.losses.Samples.nearest = nearest
    try:
        yield
    finally:
        snds.losses.Samples.nearest = original


_COMPILE_SECONDS: dict[str, float] = {}


@contextlib.contextmanager
def _compiled() -> Iterator[None]:
    original = snds.train._step_loss
    compiled = torch.compile(original, dynamic=False)

    def step_loss(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        if "compile" not in _COMPILE_SECONDS:
            start = time.perf_counter()
            out = compiled(*args, **kwargs)
            _COMPILE_SECONDS["compile"] = time.perf_counter() - start
            return out
        return compiled(*args, **kwargs)

    snds.train._step_loss = step_loss
    try:
        yield
    finally:
        snds.train._step_loss = original


#: name -> (PolicyConfig overrides, TrainConfig overrides, context around the fit)
VARIANTS: dict[str, tuple[dict, dict, Callable[[], contextlib.AbstractContextManager]]] = {
    "default": ({}, {}, _nothing),
    "reference": ({}, {}, _reference),
    "torch-optimizer": ({}, {}, _torch_optimizer),
    "before": ({}, {}, _before),
    "brute-nearest": ({}, {}, _brute_nearest),
    "no-correction": ({}, {"noise_correction": 0.0}, _nothing),
    "batch256": ({}, {"batch_size": 256}, _nothing),
    "batch16": ({}, {"batch_size": 16}, _nothing),
    "penalty8": ({}, {"penalty_every": 8}, _nothing),
    "warp6-features64": ({"warp_layers": 6, "warp_features": 64}, {}, _nothing),
    "warp4-features64": ({"warp_layers": 4, "warp_features": 64}, {}, _nothing),
    "warp4-features48": ({"warp_layers": 4, "warp_features": 48}, {}, _nothing),
    "warp3": ({"warp_layers": 3}, {}, _nothing),
    "batch256-steps1200": ({}, {"batch_size": 256, "steps": 1200}, _nothing),
}


def time_variant(name: str, motion: str, steps: int, seed: int = 0) -> dict:
    """Trains one variant for ``steps`` steps; returns its wall and CPU ms per step."""
    policy_overrides, train_overrides, context = VARIANTS[name]
    demos = load_lasa(motion)
    split = split_samples(demos, test_fraction=0.2, seed=seed)
    policy = StablePolicy(
        dim=demos.dim,
        normalization=Normalization.fit(demos),
        config=PolicyConfig(**policy_overrides),
        seed=seed,
    )
    config = TrainConfig(seed=seed, **{**train_overrides, "steps": steps})
    with context():
        wall, cpu = time.perf_counter(), time.process_time()
        result = fit(policy, demos, split, config, progress=False)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    return {"wall_ms": 1e3 * wall / result.steps, "cpu_ms": 1e3 * cpu / result.steps}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--motion", default="Sine")
    parser.add_argument("--steps", type=int, default=150, help="steps per timed fit")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (the CLI's: 1)")
    parser.add_argument("--variants", nargs="+", default=None)
    parser.add_argument("--compile", action="store_true", help="add the torch.compile variant")
    parser.add_argument("--json", default=None, help="also write the rows to this file")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.compile:
        VARIANTS["compiled"] = ({}, {}, _compiled)
    names = args.variants or list(VARIANTS)
    default_steps = {
        name: dataclasses.replace(TrainConfig(), **VARIANTS[name][1]).steps for name in names
    }
    samples: dict[str, list[dict]] = {name: [] for name in names}
    # One untimed warm-up fit (first-call costs: allocations, lazy imports, compilation).
    for name in names:
        time_variant(name, args.motion, 10)
    for _ in range(args.rounds):
        for name in names:
            samples[name].append(time_variant(name, args.motion, args.steps))
    rows = []
    print(f"{args.motion}, {args.steps} steps per fit, median of {args.rounds} rounds")
    print("| variant | ms/step wall | ms/step CPU | full fit s wall (CPU) |")
    print("|---|---|---|---|")
    for name in names:
        wall = statistics.median(s["wall_ms"] for s in samples[name])
        cpu = statistics.median(s["cpu_ms"] for s in samples[name])
        full = default_steps[name]
        rows.append({"variant": name, "wall_ms": wall, "cpu_ms": cpu, "steps": full})
        seconds = f"{wall * full / 1e3:.1f} ({cpu * full / 1e3:.1f})"
        print(f"| {name} | {wall:.2f} | {cpu:.2f} | {seconds} |")
    if _COMPILE_SECONDS:
        print(f"torch.compile: first call {_COMPILE_SECONDS['compile']:.1f} s wall")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump({"rows": rows, "compile": _COMPILE_SECONDS}, handle, indent=2)


if __name__ == "__main__":
    main()
