"""A screen, not a library feature: a phase coordinate appended to the real files' state.

Each demonstration gets phi(t) = alpha * E * (1 - t / T_d) (E: the positions' extent), so the
state is (x, phi) in R^{n+1}, ending at (x*, 0); SNDS is trained on it unchanged (its guarantee
then holds in the joint space). Rollouts start at (x_0, alpha E); the bars read the position part
(as ``benchmarks/arm_bars.py``: worst demonstration, Fréchet over the extent at 1.0x and 1.5x the
duration, end distance after 1.5x). ``--alpha 0``: the plain state, for comparison.

    python benchmarks/arm_phase.py --alpha 1 --codes 3 --check > codes3-default.jsonl
    python benchmarks/arm_phase.py --alpha 1 --check --train correction_width=0.01 \
        noise_correction=30 > phase-cw01nc30.jsonl   # --alpha 0: the plain state
    python benchmarks/arm_phase.py --alpha 1 --nominal nearest --gain 10 --check \
        --train correction_width=0.01 noise_correction=30 > phase-nearest10.jsonl
    python benchmarks/arm_phase.py --table results/arm-phase/{plain-cw01nc30,codes3-default}.jsonl

``--nominal nearest`` swaps the trained f for the data's own field after training: the
velocity of the nearest training sample, pulled back across its direction of travel at
``--gain`` per second (its value at the target removed near the target). V and the
projection are kept, so the decrease condition holds for it as for any f (``--check``
measures it).

``--codes M`` appends phi(t) c_d instead, c_d a random unit vector of M numbers per
demonstration (it says which demonstration is followed); ``--start-offset R`` moves each start
by R extents; ``--hold F`` holds the positions still for F durations 30 % of the way (the
phase running on); ``--phase-stop SIGMA`` slows the phase's part of f off the data
(:class:`PhaseGate`); LASA motion names are tasks too.

Rows (each records its options): ``results/arm-phase/``; the seed-0 screen of variants in
``screen-seed0.jsonl``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import types
from pathlib import Path

import numpy as np
import torch
from arm_floor import DATA, TASKS

import snds
from snds.data import DataSource
from snds.data.demonstrations import Demonstration, Demonstrations
from snds.evaluate import evaluate, path_reference
from snds.metrics import dtw, frechet
from snds.policy import float64_copy
from snds.rollout import rollout_numpy


def load(task):
    if task not in TASKS:  # a LASA motion
        return DataSource(motion=task).load()
    file, select = TASKS[task]
    return DataSource(file=DATA / file, demos=select).load()


def with_phase(demos: Demonstrations, alpha: float, kind: str, codes: int = 1) -> Demonstrations:
    """The demonstrations with the phase appended; ``codes`` > 1 appends phi(t) c_d instead, with
    c_d a random unit vector of that many numbers per demonstration (seed 0), so that
    demonstrations are apart in the joint space wherever their phases are not 0."""
    extent = demos.extent()
    rng = np.random.default_rng(0)
    out = []
    for d in demos:
        code = np.ones(1) if codes == 1 else rng.normal(size=codes)
        code /= np.linalg.norm(code)
        s = (d.times - d.times[0]) / d.duration
        if kind == "linear":
            phi = alpha * extent * (1.0 - s)
            dphi = np.full_like(phi, -alpha * extent / d.duration)
        else:  # exponential, 5 time constants over the demonstration
            phi = alpha * extent * np.exp(-5.0 * s)
            dphi = -5.0 / d.duration * phi
        out.append(
            Demonstration(
                np.column_stack([d.positions, phi[:, None] * code]),
                np.column_stack([d.velocities, dphi[:, None] * code]),
                d.times,
            )
        )
    return Demonstrations(tuple(out), np.append(demos.target, np.zeros(codes)), demos.name)


def held_rollout(policy, start, dt, steps, n, held):
    """Positions (steps + held + 1, n) of a rollout whose positions are held still for ``held``
    steps from 30 % of the way (the rest of the state moving on), as a person holding the arm."""
    if not held:
        return rollout_numpy(policy, start, dt=dt, steps=steps)[0][:, :n]
    before = int(0.3 * steps)
    parts = [rollout_numpy(policy, start, dt=dt, steps=before)[0]]
    state = parts[0][-1:].copy()
    for _ in range(held):
        state = rollout_numpy(policy, state, dt=dt, steps=1)[0][-1:].copy()
        state[0, :n] = parts[0][-1, :n]
        parts.append(state.copy())
    parts.append(rollout_numpy(policy, state, dt=dt, steps=steps - before)[0][1:])
    return np.concatenate(parts)[:, :n]


def bars(policy, demos, base, offset=0.0, seed=0, hold=0.0):
    """Worst Fréchet / extent (1.0x, 1.5x the duration) and end distance of rollouts from each
    demonstration's start, moved by ``offset`` times the extent in a random direction, with the
    positions held for ``hold`` times the duration (see :func:`held_rollout`)."""
    p64 = float64_copy(policy)
    n = base.dim
    extent = base.extent()
    rng = np.random.default_rng(seed)
    fr, fr15, ends, dtws = [], [], [], []
    for d, b in zip(demos, base, strict=True):
        dt = d.duration / (len(d.times) - 1)
        steps = int(np.ceil(1.5 * d.duration / dt))
        start = d.states[:1].copy()
        direction = rng.normal(size=n)
        start[0, :n] += offset * extent * direction / np.linalg.norm(direction)
        path = held_rollout(p64, start, dt, steps, n, int(hold * len(d.times)))
        ref = path_reference(b)
        fr.append(frechet(path[: len(d.times)], ref) / extent)
        dtws.append(dtw(path[: len(d.times)], ref))
        fr15.append(frechet(path, ref) / extent)
        ends.append(float(np.linalg.norm(path[-1] - base.target)))
    return max(fr), max(fr15), max(ends), float(np.mean(dtws))


class NearestSample(torch.nn.Module):
    """g(z) = u_j - k (z - z_j)_perp: the nearest training sample's velocity u_j with a pull of
    gain k (per unit of model time) across its direction of travel d_j; f(z) = g(z) - g(0) w(z)
    with w(z) = exp(-|z|^2 / 0.05^2), so that the target is an equilibrium while the field 5%
    of the length away from it stays the data's (the phase velocity never vanishes in the data)."""

    def __init__(self, states, velocities, gain):
        super().__init__()
        directions = velocities / velocities.norm(dim=1, keepdim=True).clamp_min(1e-12)
        self.register_buffer("states", states)
        self.register_buffer("velocities", velocities)
        self.register_buffer("directions", directions)
        self.gain = gain

    width = 0.0

    def _raw(self, z):
        if self.width:
            return torch.cat([self._smooth(c) for c in z.split(1024)])
        j = torch.cat([torch.cdist(c, self.states).argmin(1) for c in z.split(4096)])
        offset = z - self.states[j]
        d = self.directions[j]
        across = offset - (offset * d).sum(1, keepdim=True) * d
        return self.velocities[j] - self.gain * across

    def _smooth(self, z):
        # Gaussian weights of width sigma over every sample: sum_j w_j (u_j - k (z - z_j)_perp).
        sq = torch.cdist(z, self.states, compute_mode="donot_use_mm_for_euclid_dist") ** 2
        w = torch.softmax(-sq / (2 * self.width**2), dim=1)
        offset = z[:, None, :] - self.states[None]
        along = (offset * self.directions[None]).sum(-1, keepdim=True) * self.directions[None]
        return w @ self.velocities - self.gain * (w[..., None] * (offset - along)).sum(1)

    def forward(self, z):
        flat = z.reshape(-1, z.shape[-1])
        out = self._raw(torch.cat([flat, flat.new_zeros(1, flat.shape[1])]))
        weight = torch.exp(-((flat.norm(dim=1, keepdim=True) / 0.05) ** 2))
        return (out[:-1] - weight * out[-1]).reshape(z.shape)


def use_nearest(policy, demos, gain, width=0.0):
    """Replace the policy's nominal by :class:`NearestSample` over all demonstrated samples
    (gain in 1/s)."""
    states = torch.tensor(np.concatenate([d.states for d in demos]), dtype=torch.float32)
    velocities = torch.tensor(np.concatenate([d.velocities for d in demos]), dtype=torch.float32)
    with torch.no_grad():
        z = policy.to_model(states)
        u = velocities / (policy.length / policy.time)
    policy.nearest = NearestSample(z, u, gain * float(policy.time))
    policy.nearest.width = width
    policy.nominal = types.MethodType(lambda self, x: self.nearest(x), policy)


class PhaseGate(torch.nn.Module):
    """g(z) = exp(-(d(z) / sigma)^2), d the distance to the nearest training state: 1 on the
    data, towards 0 where the phase has run on without the positions (an arm held)."""

    def __init__(self, states, width):
        super().__init__()
        self.register_buffer("states", states)
        self.width = width

    def forward(self, z):
        flat = z.reshape(-1, z.shape[-1])
        d = torch.cat([torch.cdist(c, self.states).amin(1) for c in flat.split(4096)])
        return torch.exp(-((d / self.width) ** 2)).reshape(*z.shape[:-1], 1)


def use_phase_stop(policy, demos, n, width):
    """Scale the phase's part of the nominal f by :class:`PhaseGate` (V's projection follows,
    so the decrease condition still holds)."""
    states = torch.tensor(np.concatenate([d.states for d in demos]), dtype=torch.float32)
    with torch.no_grad():
        policy.phase_gate = PhaseGate(policy.to_model(states), width)

    def nominal(self, x):
        f = type(self).nominal(self, x)
        return torch.cat([f[..., :n], self.phase_gate(x) * f[..., n:]], dim=-1)

    policy.nominal = types.MethodType(nominal, policy)


def overrides(pairs: list[str]) -> dict:
    """``key=value`` pairs, the values read as JSON (numbers, lists) or else kept as text."""
    out = {}
    for pair in pairs:
        key, value = pair.split("=", 1)
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


def table(files: list[str]) -> str:
    """A markdown table of rows files (one column per file): worst seed's Fréchet / extent at
    1.0x and 1.5x the duration, end distance, and the runs meeting every bar over 1.5x."""
    columns = {}
    for file in files:
        for line in Path(file).read_text().splitlines():
            row = json.loads(line)
            columns.setdefault(Path(file).stem, {}).setdefault(row["task"], []).append(row)
    head = "| task | " + " | ".join(columns) + " |"
    lines = [head, "|---" * (len(columns) + 1) + "|"]
    for task in TASKS:
        cells = []
        for rows in columns.values():
            rows = rows.get(task, [])
            if not rows:
                cells.append("-")
                continue
            ok = sum(
                r["frechet15"] <= 0.05
                and r["end_m"] <= 0.01
                and r.get("converged") == 1.0
                and r.get("violations") == 0
                for r in rows
            )
            f1 = max(r["frechet"] for r in rows)
            f15 = max(r["frechet15"] for r in rows)
            end = max(r["end_m"] for r in rows)
            cells.append(f"{f1:.3f} / {f15:.3f}, {100 * end:.2f} cm, {ok}/{len(rows)}")
        lines.append(f"| {task} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--table", nargs="*", help="print the table of these rows files and stop")
    p.add_argument("--tasks", nargs="*", default=list(TASKS), help="tasks or LASA motions")
    p.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2])
    p.add_argument("--alpha", type=float, default=1.0)
    p.add_argument("--kind", default="linear")
    p.add_argument("--codes", type=int, default=1, help="numbers of the phase (see with_phase)")
    p.add_argument("--check", action="store_true")
    p.add_argument("--tag", default="")
    p.add_argument("--phase-stop", type=float, default=0.0, help="PhaseGate width, model units")
    p.add_argument("--hold", type=float, default=0.0, help="positions held, x duration")
    p.add_argument("--start-offset", type=float, default=0.0, help="starts moved, x extent")
    p.add_argument("--nominal", choices=["trained", "nearest"], default="trained")
    p.add_argument("--gain", type=float, default=10.0, help="pull of --nominal nearest, 1/s")
    p.add_argument("--width", type=float, default=0.0, help="kernel width of --nominal nearest")
    p.add_argument("--policy", nargs="*", default=[], help="PolicyConfig overrides, key=value")
    p.add_argument("--train", nargs="*", default=[], help="TrainConfig overrides, key=value")
    args = p.parse_args()
    if args.table:
        print(table(args.table))
        return
    torch.set_num_threads(1)
    for task in args.tasks:
        base = load(task)
        demos = with_phase(base, args.alpha, args.kind, args.codes) if args.alpha > 0 else base
        for seed in args.seeds:
            split = snds.split_samples(demos, test_fraction=0.2, seed=seed)
            policy = snds.make_policy(demos, config=snds.PolicyConfig(**overrides(args.policy)))
            t0 = time.process_time()
            snds.fit(policy, demos, split, snds.TrainConfig(seed=seed, **overrides(args.train)))
            cpu = time.process_time() - t0
            if args.phase_stop:
                use_phase_stop(policy, demos, base.dim, args.phase_stop)
            if args.nominal == "nearest":
                use_nearest(policy, demos, args.gain, args.width)
            f1, f15, end, mean_dtw = bars(policy, demos, base, args.start_offset, seed, args.hold)
            row = dict(
                task=task,
                seed=seed,
                alpha=args.alpha,
                kind=args.kind,
                codes=args.codes,
                tag=args.tag,
                policy=args.policy,
                train=args.train,
                start_offset=args.start_offset,
                hold=args.hold,
                phase_stop=args.phase_stop,
                nominal=args.nominal
                if args.nominal == "trained"
                else f"nearest{args.gain:g}" + (f"-w{args.width:g}" if args.width else ""),
                frechet=f1,
                frechet15=f15,
                end_m=end,
                dtw=mean_dtw,
                train_cpu=cpu,
            )
            if args.check:
                m = evaluate(
                    policy, demos, split, check=snds.CheckConfig(rollouts=300, samples=20000)
                )
                row["converged"] = m["stability"]["converged_fraction"]
                row["violations"] = m["stability"]["decrease_violations"]
                row["mse"] = m.get("velocity_mse")
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    sys.exit(main())
