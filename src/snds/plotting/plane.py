"""Plots in the plane of x1 and x2: streamlines, panels, the Lyapunov function, obstacles.

States with more than two coordinates are shown in the plane of x1 and x2 through the target,
with x3..xn held at the target's values; rollouts are projected onto that plane.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from matplotlib import colors
from matplotlib.figure import Figure

from snds.data.demonstrations import Demonstrations
from snds.obstacles import ModulatedPolicy
from snds.parallel import torch_threads
from snds.phase import start_states
from snds.plotting.draw import (
    DPI,
    GRID,
    axes_legend,
    draw_demos,
    draw_field,
    draw_paths,
    draw_scene,
    draw_target,
    figure_legend,
    finish_axes,
    lyapunov_values,
    new_figure,
    plane_grid,
    require_stable,
    save_figure,
    title_of,
)
from snds.plotting.rollouts import rollouts_until_arrival
from snds.policy import Policy
from snds.steppers import GuardedEuler

__all__ = [
    "AVOIDING",
    "Panel",
    "plot_lyapunov",
    "plot_obstacles",
    "plot_panels",
    "plot_streamlines",
]


def plot_streamlines(
    policy: Policy,
    demos: Demonstrations,
    path: str | Path,
    *,
    rollouts: np.ndarray | None = None,
    perturbed: np.ndarray | None = None,
    title: str | None = None,
) -> Path:
    """Streamlines of the policy with the demonstrations, rollouts and the target. With a
    phase in the state (:mod:`snds.phase`), the streamlines are those of the velocity a new
    start at each point begins with (:func:`snds.phase.start_states`); the rollouts are the
    whole motions.

    Arguments:
        policy: The policy, float64 and in eval mode.
        demos: The demonstrations, drawn as thin dark lines with a marker at each start.
        path: Where to write the PNG.
        rollouts: Rollouts from the demonstrations' starts, shape (B, T, n); solid lines.
        perturbed: Rollouts from perturbed starts, shape (B, T, n); dashed lines.
        title: Title; the demonstrations' name by default.

    Returns:
        The path written.
    """
    starts = [r[:, :, : demos.position_dim][:, 0] for r in (rollouts, perturbed) if r is not None]
    (x1, x2), points = plane_grid(demos, include=starts)
    if demos.phase_dim:
        # With a phase, the field of the plane is the one a new start there begins with.
        points = start_states(demos, points[:, : len(demos.target) - demos.phase_dim])
    fig, ax = new_figure(x1, x2)
    stream = draw_field(ax, policy, x1, x2, points)
    colorbar = fig.colorbar(
        stream.lines, ax=ax, fraction=0.04, pad=0.02, extend="max", extendfrac=0.03
    )
    colorbar.set_label("speed")
    colorbar.outline.set_visible(False)
    draw_paths(ax, demos, rollouts, perturbed)
    projected = rollouts is not None or perturbed is not None
    title = title if title is not None else title_of(demos, policy)
    if demos.phase_dim:
        finish_axes(ax, x1, x2, 2, f"{title}\nfield at a new start's phase", projected=projected)
    else:
        finish_axes(ax, x1, x2, demos.dim, title, projected=projected)
    axes_legend(fig, ax)
    return save_figure(fig, path)


@dataclass(frozen=True)
class Panel:
    """One panel of :func:`plot_panels`: a policy on its demonstrations.

    Attributes:
        policy: The policy, float64 and in eval mode.
        demos: Its demonstrations.
        title: The panel's title.
    """

    policy: Policy
    demos: Demonstrations
    title: str


@torch_threads(1)
def plot_panels(
    rows: Sequence[Sequence[Panel | None]],
    path: str | Path,
    *,
    random_starts: int = 8,
    seed: int = 0,
) -> Path:
    """A grid of streamline panels (the paper's Fig. 5 and 6): one row per method, say.

    Each panel shows the policy's streamlines, the demonstrations, rollouts from the
    demonstrations' starts (solid) and from ``random_starts`` uniform starts in the view
    (dashed, the same starts for every panel of a column), each until it arrives
    (:func:`rollouts_until_arrival`). A policy that fails shows it: dashed paths that stop
    short of the target.
    The policies are evaluated with one torch thread (:func:`snds.parallel.torch_threads`):
    a rollout calls a small network on a few states thousands of times, which several
    threads slow down many times over on a busy machine.

    Arguments:
        rows: The panels, row by row; None leaves a cell empty.
        path: Where to write the PNG.
        random_starts: Random starts per panel.
        seed: Seed of the random starts.

    Returns:
        The path written.
    """
    nrows = len(rows)
    ncols = max((len(row) for row in rows), default=0)
    if nrows == 0 or ncols == 0:
        raise ValueError("plot_panels needs at least one panel")
    fig = Figure(figsize=(2.9 * ncols, 2.5 * nrows + 0.5), dpi=DPI, layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False)
    column_starts: dict[int, np.ndarray] = {}
    for i, row in enumerate(rows):
        for j in range(ncols):
            ax = axes[i, j]
            panel = row[j] if j < len(row) else None
            if panel is None:
                ax.set_axis_off()
                continue
            demos, policy = panel.demos, panel.policy
            (x1, x2), points = plane_grid(demos)
            if j not in column_starts:
                rng = np.random.default_rng(seed + j)
                starts = np.tile(demos.target, (random_starts, 1))
                starts[:, 0] = rng.uniform(x1[0], x1[-1], random_starts)
                starts[:, 1] = rng.uniform(x2[0], x2[-1], random_starts)
                column_starts[j] = starts
            demo_starts = np.stack([demo.positions[0] for demo in demos])
            # Until arrival, as every plot of a run (rollouts_until_arrival), in one batch.
            both, _ = rollouts_until_arrival(
                policy, demos, np.concatenate([demo_starts, column_starts[j]]), dt=demos.mean_dt()
            )
            rollouts, perturbed = both[: len(demo_starts)], both[len(demo_starts) :]
            draw_field(ax, policy, x1, x2, points, density=0.9)
            draw_paths(ax, demos, rollouts, perturbed, random_label="rollout from random start")
            ax.set_aspect("equal")
            ax.set_xlim(x1[0], x1[-1])
            ax.set_ylim(x2[0], x2[-1])
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(panel.title, fontsize="medium")
    handles, labels = [], []
    for ax in axes.flat:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            if label not in labels:
                handles.append(handle)
                labels.append(label)
    figure_legend(fig, handles, labels, loc="outside lower center")
    return save_figure(fig, path)


def plot_lyapunov(policy: Policy, demos: Demonstrations, path: str | Path) -> Path:
    """Filled contours of the Lyapunov function V with the demonstrations over them.

    Arguments:
        policy: A stable policy, float64 and in eval mode.
        demos: The demonstrations.
        path: Where to write the PNG.

    Returns:
        The path written.

    Raises:
        ValueError: If the policy has no Lyapunov guarantee (``policy.stable`` is False).
    """
    require_stable(policy)
    (x1, x2), points = plane_grid(demos)
    v = lyapunov_values(policy, points).reshape(GRID, GRID)
    # V grows quadratically away from the target: log-spaced levels show the basin's shape
    # near the target as well as far out, where linear levels would put nearly every line.
    positive = v[v > 0]
    low = max(float(np.percentile(positive, 0.5)), float(positive.max()) * 1e-6)
    levels = np.geomspace(low, float(v.max()), 16)

    fig, ax = new_figure(x1, x2)
    filled = ax.contourf(
        x1,
        x2,
        np.clip(v, low, None),
        levels=levels,
        norm=colors.LogNorm(low, float(v.max())),
        cmap="viridis",
        zorder=0,
    )
    ax.contour(x1, x2, v, levels=levels, colors="white", linewidths=0.4, alpha=0.5, zorder=1)
    colorbar = fig.colorbar(filled, ax=ax, fraction=0.04, pad=0.02)
    decades = np.arange(np.ceil(np.log10(low)), np.floor(np.log10(v.max())) + 1)
    colorbar.set_ticks(10.0**decades, labels=[f"$10^{{{int(d)}}}$" for d in decades])
    colorbar.minorticks_off()
    colorbar.set_label("V (model units)")
    colorbar.outline.set_visible(False)
    # White lines read on every colour of the map; no legend, whose white entries would not.
    draw_demos(ax, demos, color="white")
    draw_target(ax, demos.target)
    finish_axes(
        ax, x1, x2, demos.dim, "Lyapunov function V" + (f" — {demos.name}" if demos.name else "")
    )
    return save_figure(fig, path)


#: The guarded step among obstacles: 40 halvings (1e-12 of the period) before holding a state.
AVOIDING = GuardedEuler(max_halvings=40)


def plot_obstacles(
    policy: Policy,
    demos: Demonstrations,
    scene,
    path: str | Path,
    *,
    random_starts: int = 8,
    seed: int = 0,
) -> Path:
    """Streamlines of a policy modulated by obstacles (:mod:`snds.obstacles`), with them.

    The obstacles are filled grey, their margins dashed; rollouts are guarded
    (:class:`~snds.steppers.GuardedEuler` with the scene) until they arrive or are held, for 3x
    the longest demonstration at most (:func:`rollouts_until_arrival`), from the
    demonstrations' starts (solid) and from ``random_starts`` free starts in the view
    (dashed). States with more than two coordinates are shown in the slice through the target.

    Arguments:
        policy: The policy without obstacles, float64 and in eval mode.
        demos: The demonstrations.
        scene: The :class:`~snds.obstacles.Scene`.
        path: Where to write the PNG.
        random_starts: Random free starts.
        seed: Seed of the random starts.

    Returns:
        The path written.
    """

    (x1, x2), points = plane_grid(demos)
    rng = np.random.default_rng(seed)
    candidates = np.tile(demos.target, (50 * random_starts, 1))
    candidates[:, 0] = rng.uniform(x1[0], x1[-1], len(candidates))
    candidates[:, 1] = rng.uniform(x2[0], x2[-1], len(candidates))
    free = scene.free(torch.as_tensor(candidates)).numpy()
    random = candidates[free][:random_starts]
    starts = np.stack([demo.positions[0] for demo in demos])
    starts = starts[scene.free(torch.as_tensor(starts)).numpy()]
    # One batch for both sets of starts: a step costs the same for 8 states as for 15.
    paths, _ = rollouts_until_arrival(
        policy,
        demos,
        np.concatenate([starts, random]),
        dt=demos.mean_dt(),
        durations=3.0,
        stepper=AVOIDING,
        scene=scene,
    )
    rollouts, perturbed = (paths[: len(starts)] if len(starts) else None), paths[len(starts) :]
    fig, ax = new_figure(x1, x2)
    stream = draw_field(ax, ModulatedPolicy(policy, scene), x1, x2, points)
    colorbar = fig.colorbar(
        stream.lines, ax=ax, fraction=0.04, pad=0.02, extend="max", extendfrac=0.03
    )
    colorbar.set_label("speed")
    colorbar.outline.set_visible(False)
    draw_scene(ax, scene, x1, x2, points)
    draw_paths(ax, demos, rollouts, perturbed, random_label="rollout from random start")
    title = f"{title_of(demos, policy)}, {len(scene.bodies)} obstacle" + (
        "s" if len(scene.bodies) != 1 else ""
    )
    finish_axes(ax, x1, x2, demos.dim, title, projected=True)
    axes_legend(fig, ax)
    return save_figure(fig, path)
