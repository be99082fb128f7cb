"""Does calling ``torch._fused_adam_`` directly earn its place against the public
``torch.optim.Adam(fused=True).step()``?

Both update the default policy's parameters (the default recipe's networks on Sine, with
gradients from one real training step) by the same kernel, bit for bit; the direct call
(as ``snds.optim.adam_step`` made it up to 0.1.0, kept here as the measured alternative)
skips the optimiser's per-call bookkeeping. Measured: about 65 us saved of a 10 ms step, so
the library calls the public step. This
times ``--calls`` updates of each, alternately, ``--rounds`` times, and a whole training step
(loss, backward, clipping, update) with each, in wall and CPU seconds, one thread.

    python benchmarks/adam_step.py

Writes ``benchmarks/results/adam_step.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import torch

import snds
from snds.batches import draw_step
from snds.losses import step_loss
from snds.optim import adam, clip_gradients
from snds.train import training_samples

HERE = Path(__file__).resolve().parent


def _direct_step(optimizer: torch.optim.Adam, lr: float) -> None:
    """The fused kernel that ``optimizer.step()`` calls, called directly (from the second
    step on, one parameter group, no AMSGrad, maximisation or weight decay)."""
    group = optimizer.param_groups[0]
    group["lr"] = lr
    params = [p for p in group["params"] if p.grad is not None]
    states = [optimizer.state[p] for p in params]
    beta1, beta2 = group["betas"]
    steps = [state["step"] for state in states]
    with torch.no_grad():
        torch._foreach_add_(steps, 1)
        torch._fused_adam_(
            params,
            [p.grad for p in params],
            [state["exp_avg"] for state in states],
            [state["exp_avg_sq"] for state in states],
            [],
            steps,
            amsgrad=False,
            lr=lr,
            beta1=beta1,
            beta2=beta2,
            weight_decay=0.0,
            eps=group["eps"],
            maximize=False,
            grad_scale=None,
            found_inf=None,
        )


def _public_step(optimizer: torch.optim.Adam, lr: float) -> None:
    for group in optimizer.param_groups:
        group["lr"] = lr
    optimizer.step()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--calls", type=int, default=2000, help="updates per timing")
    parser.add_argument("--steps", type=int, default=100, help="training steps per timing")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", type=Path, default=HERE / "results" / "adam_step.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    demos = snds.RECIPES["default"].phase.apply(snds.load_lasa("Sine"))
    split = snds.split_samples(demos, test_fraction=0.2, seed=0)
    config = snds.TrainConfig(seed=0)
    policy = snds.make_policy(demos, config=snds.PolicyConfig())
    samples = training_samples(demos, policy, split, config)
    policy.set_anchors(samples.positions)
    generator = torch.Generator().manual_seed(0)
    parameters = list(policy.parameters())

    def train_step(optimizer: torch.optim.Adam, update, step: int) -> None:
        loss = step_loss(policy, config, draw_step(policy, samples, config, generator, step))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        clip_gradients(parameters, config.grad_clip)
        update(optimizer, 1e-6)

    rows = []
    for round_ in range(args.rounds):
        for name, update in (("direct", _direct_step), ("public", _public_step)):
            optimizer = adam(policy.parameters(), config.lr)
            train_step(optimizer, _public_step, 0)  # Adam's state exists from here on
            wall, cpu = time.perf_counter(), time.process_time()
            for _ in range(args.calls):
                update(optimizer, 1e-9)
            update_wall = (time.perf_counter() - wall) / args.calls
            update_cpu = (time.process_time() - cpu) / args.calls
            wall, cpu = time.perf_counter(), time.process_time()
            for step in range(args.steps):
                train_step(optimizer, update, step)
            rows.append(
                {
                    "round": round_,
                    "update": name,
                    "update_us_wall": 1e6 * update_wall,
                    "update_us_cpu": 1e6 * update_cpu,
                    "train_step_ms_wall": 1e3 * (time.perf_counter() - wall) / args.steps,
                    "train_step_ms_cpu": 1e3 * (time.process_time() - cpu) / args.steps,
                    "load": os.getloadavg(),
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    record = {
        "torch": torch.__version__,
        "parameters": sum(p.numel() for p in parameters),
        "tensors": len(parameters),
        "note": "shared 2-core machine, one thread; see load of each row",
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
