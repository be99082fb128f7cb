"""Every plot of a run (``snds train --plot``, ``snds plot``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from snds.phase import start_states
from snds.plotting.curves import plot_loss, plot_rollout_lyapunov
from snds.plotting.draw import bounding_box, title_of
from snds.plotting.paths import plot_paths, plot_paths_3d
from snds.plotting.plane import plot_lyapunov, plot_streamlines
from snds.plotting.rollouts import rollouts_until_arrival
from snds.policy import Policy

__all__ = ["plot_all"]


def plot_all(
    policy: Policy,
    demos: Any,
    out_dir: str | Path,
    *,
    history: list[float] | None = None,
    seed: int = 0,
) -> list[Path]:
    """Rolls the policy out along its space from the demonstrations' starts and from perturbed
    starts, and writes every plot that applies into ``out_dir``.

    Perturbed starts are each demonstration's start with its position moved by up to 30 % of
    the extent in every coordinate, plus 6 starts with positions uniform in the
    demonstrations' bounding box enlarged 1.5 times (and, for poses, orientations uniform on
    SO(3)).

    Arguments:
        policy: The policy, float64 and in eval mode.
        demos: The demonstrations (poses for a pose policy).
        out_dir: Folder of the PNGs (created if missing).
        history: Training loss per step; ``loss.png`` is written when given.
        seed: Seed of the perturbations.

    Returns:
        The paths written: for 2-D positions ``streamlines.png`` (with a phase, of the velocity
        a new start takes), then for positions alone ``lyapunov.png``;
        ``rollout_lyapunov.png`` for a stable policy; ``paths.png`` when 2-D positions are
        part of a larger state (a phase); ``paths3d.png`` when positions are 3-D (with
        orientation frames for poses); then ``loss.png``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    space = policy.space
    p = space.position_dim
    rng = np.random.default_rng(seed)
    dt = demos.mean_dt()
    starts = np.stack([demo.states[0] for demo in demos])
    extent = demos.extent()
    low, high = bounding_box(
        demos.positions(), space.positions(np.asarray(demos.target)), scale=1.5
    )
    moved = starts.copy()
    moved[:, :p] += rng.uniform(-0.3, 0.3, size=(len(starts), p)) * extent
    spread = space.uniform(np.asarray(demos.target), 0.0, 6, rng)
    spread[:, :p] = rng.uniform(low, high, size=(6, p))
    perturbed_starts = np.concatenate([moved, spread])
    if demos.phase_dim:
        # A new start takes its phase as a controller gives it one (snds.phase.start_state).
        base = len(demos.target) - demos.phase_dim
        perturbed_starts = start_states(demos, perturbed_starts[:, :base])
    # One batch for both sets of starts: a step costs about the same for 7 states as for 20.
    both, arrived = rollouts_until_arrival(
        policy, demos, np.concatenate([starts, perturbed_starts]), dt=dt
    )
    rollouts, perturbed = both[: len(starts)], both[len(starts) :]

    paths = []
    positions_only = space.dim == p
    if positions_only or p == 2:
        paths.append(
            plot_streamlines(
                policy, demos, out / "streamlines.png", rollouts=rollouts, perturbed=perturbed
            )
        )
    if policy.stable:
        if positions_only:
            paths.append(plot_lyapunov(policy, demos, out / "lyapunov.png"))
        paths.append(
            plot_rollout_lyapunov(
                policy,
                rollouts,
                dt,
                out / "rollout_lyapunov.png",
                perturbed=perturbed,
                arrived=arrived,
            )
        )
    if p == 2 and not positions_only:
        # A field over the plane needs the rest of the state (a phase): paths only.
        paths.append(
            plot_paths(
                demos,
                rollouts,
                out / "paths.png",
                perturbed=perturbed,
                title=title_of(demos, policy),
            )
        )
    if p == 3:
        # Orientation frames where the space has an angle error (poses).
        orientations = (
            {}
            if len(space.error_names) == 1
            else {
                # The quaternion after the position (a phase may follow it).
                "demo_orientations": [demo.states[:, p : p + 4] for demo in demos],
                "rollout_orientations": [r[:, p : p + 4] for r in rollouts],
            }
        )
        paths.append(
            plot_paths_3d(
                [demo.positions[:, :p] for demo in demos],
                [r[:, :p] for r in rollouts],
                space.positions(np.asarray(demos.target)),
                out / "paths3d.png",
                perturbed=[r[:, :p] for r in perturbed],
                title=title_of(demos, policy),
                **orientations,
            )
        )
    if history:
        paths.append(plot_loss(history, out / "loss.png"))
    return paths
