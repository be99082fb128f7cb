"""Paths without a field: in the plane (a state with a phase), in 3-D (frames for poses)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from snds.data.demonstrations import Demonstrations
from snds.plotting.draw import (
    DEMO_COLOR,
    DPI,
    PERTURBED_COLOR,
    ROLLOUT_COLOR,
    axes_legend,
    draw_paths,
    finish_axes,
    new_figure,
    plane_grid,
    save_figure,
)

__all__ = ["FRAME_COLORS", "plot_paths", "plot_paths_3d"]


FRAME_COLORS = ("#e03131", "#2f9e44", "#1971c2")


def plot_paths(
    demos: Demonstrations,
    rollouts: np.ndarray,
    path: str | Path,
    *,
    perturbed: np.ndarray | None = None,
    title: str = "",
) -> Path:
    """Paths in the plane of x1, x2 without a field: demonstrations (dark), rollouts from
    their starts (orange), rollouts from perturbed and random starts (dashed), the target.

    For a state whose velocity at a point of the plane depends on more than the point (a
    phase), where streamlines of the plane would mislead.

    Arguments:
        demos: The demonstrations; their first two columns are drawn.
        rollouts: Rollouts from the demonstrations' starts, shape (B, T, n).
        path: Where to write the PNG.
        perturbed: Rollouts from other starts, shape (B, T, n).
        title: The plot's title.

    Returns:
        The path written.
    """
    # Every drawn point in view: nothing here is clipped to a field's grid.
    drawn = [np.reshape(r, (-1, np.shape(r)[-1])) for r in (rollouts, perturbed) if r is not None]
    (x1, x2), _ = plane_grid(demos, include=drawn)
    fig, ax = new_figure(x1, x2, colorbar=False)
    draw_paths(ax, demos, rollouts, perturbed)
    finish_axes(ax, x1, x2, 2, title)
    axes_legend(fig, ax)
    return save_figure(fig, path)


def plot_paths_3d(
    demos: Sequence[np.ndarray],
    rollouts: Sequence[np.ndarray],
    target: np.ndarray,
    path: str | Path,
    *,
    demo_orientations: Sequence[np.ndarray] | None = None,
    rollout_orientations: Sequence[np.ndarray] | None = None,
    perturbed: Sequence[np.ndarray] = (),
    frames: int = 6,
    title: str = "",
) -> Path:
    """Paths in 3-D: demonstrations (dark), rollouts (orange), rollouts from perturbed starts
    (dashed), and for poses small orientation frames (x red, y green, z blue) along them.

    Arguments:
        demos: Demonstrated positions, each of shape (T, 3).
        rollouts: Rollout positions, each of shape (T, 3).
        target: The target position, shape (3,).
        path: Where to write the PNG.
        demo_orientations: Unit quaternions (x, y, z, w) of the demonstrations, (T, 4) each.
        rollout_orientations: Those of the rollouts (not of the perturbed ones).
        perturbed: Rollouts from perturbed or random starts, each (T, 3).
        frames: Frames drawn along each path with orientations, evenly in time.
        title: The plot's title.

    Returns:
        The path written.
    """
    from scipy.spatial.transform import Rotation

    fig = Figure(figsize=(6.4, 5.6), dpi=DPI, layout="constrained")
    ax = fig.add_subplot(projection="3d")
    everything = np.concatenate([*demos, *rollouts, *perturbed, np.asarray(target)[None]])
    low, high = everything.min(axis=0), everything.max(axis=0)
    size = float((high - low).max()) or 1.0
    groups = (
        (demos, demo_orientations, DEMO_COLOR, "-", "demonstration"),
        (rollouts, rollout_orientations, ROLLOUT_COLOR, "-", "rollout from demo start"),
        (perturbed, None, PERTURBED_COLOR, "--", "rollout from random start"),
    )
    for paths, orientations, color, style, label in groups:
        for i, points in enumerate(paths):
            ax.plot(
                *np.asarray(points).T,
                style,
                color=color,
                linewidth=1.0,
                alpha=0.85,
                label=label if i == 0 else None,
            )
            if orientations is None or frames <= 0:
                continue
            # Frames sized to 6% of the view: visible, yet small against the motion.
            index = np.linspace(0, len(points) - 1, frames).round().astype(int)
            axes = Rotation.from_quat(np.asarray(orientations[i])[index]).as_matrix()
            for k, base in zip(index, axes):
                for column, frame_color in enumerate(FRAME_COLORS):
                    tip = points[k] + 0.06 * size * base[:, column]
                    ax.plot(*np.stack([points[k], tip]).T, color=frame_color, linewidth=1.2)
    ax.scatter(*np.asarray(target)[:, None], marker="*", s=120, color="black", label="target")
    middle = (low + high) / 2
    for setter, centre in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), middle):
        setter(centre - 0.55 * size, centre + 0.55 * size)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    ax.set_title(title, fontsize="medium")
    ax.legend(frameon=False, loc="upper left", fontsize="small")
    return save_figure(fig, path)


# --- geometry --------------------------------------------------------------------------------
