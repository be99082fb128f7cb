"""What every plot draws with: colours, the plane of a plot, the field, paths, targets, saving."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib
import numpy as np
import torch
from matplotlib import colors
from matplotlib.figure import Figure

from snds.data.demonstrations import Demonstrations
from snds.io import atomic_write
from snds.policy import Policy

__all__ = [
    "AXES_INCHES",
    "DEMO_COLOR",
    "DPI",
    "FIGSIZE",
    "GRID",
    "OBSTACLE_COLOR",
    "PERTURBED_COLOR",
    "ROLLOUT_COLOR",
    "STREAM_CMAP",
    "V_FLOOR",
    "axes_legend",
    "bounding_box",
    "despine",
    "draw_demos",
    "draw_field",
    "draw_paths",
    "draw_rollouts",
    "draw_scene",
    "draw_target",
    "figure_legend",
    "finish_axes",
    "lyapunov_values",
    "new_figure",
    "plane_grid",
    "require_stable",
    "save_figure",
    "smoothed",
    "title_of",
]


FIGSIZE = (6.0, 4.5)  # plots against time or step
AXES_INCHES = 4.6  # longer side of the axes of a plot in the plane
DPI = 150
GRID = 100  # points per side of the evaluation grid
#: Below this V (model units, about 1e-5 of the extent from the target) a rollout has arrived.
V_FLOOR = 1e-10

DEMO_COLOR = "#262626"
ROLLOUT_COLOR = "#d9480f"
PERTURBED_COLOR = "#6741d9"
OBSTACLE_COLOR = "#868e96"
# The streamlines are the backdrop: a pale slice of a blue map keeps them below the data.
STREAM_CMAP = colors.LinearSegmentedColormap.from_list(
    "snds_stream", matplotlib.colormaps["Blues"](np.linspace(0.25, 0.8, 256))
)


def draw_scene(ax, scene, x1: np.ndarray, x2: np.ndarray, points: np.ndarray) -> None:
    """Each body's physical shape filled grey and its margin dashed, over the grid."""
    with torch.no_grad():
        clearance = scene.clearances(torch.as_tensor(points)).numpy()
    for k, body in enumerate(scene.bodies):
        c = clearance[:, k].reshape(len(x2), len(x1))
        if c.min() < 0:
            ax.contourf(x1, x2, c, levels=[c.min() - 1.0, 0.0], colors=[OBSTACLE_COLOR], zorder=2)
        if body.margin > 0 and c.min() < body.margin:
            ax.contour(
                x1,
                x2,
                c,
                levels=[body.margin],
                colors=[OBSTACLE_COLOR],
                linestyles="--",
                linewidths=0.9,
                zorder=2,
            )
    ax.fill([], [], color=OBSTACLE_COLOR, label="obstacle (dashed: margin)")


#: Colours of a frame's x, y and z axes (the usual red, green, blue).


def bounding_box(
    points: np.ndarray, target: np.ndarray, *, scale: float
) -> tuple[np.ndarray, np.ndarray]:
    """The bounding box of ``points`` and ``target`` enlarged ``scale`` times about its centre.

    A side that the data leave (nearly) flat, such as the width of a straight-line motion,
    gets at least a fifth of the longest side, so the view is never a sliver.
    """
    both = np.vstack([points, target[None]])
    low, high = both.min(axis=0), both.max(axis=0)
    centre, half = (low + high) / 2, (high - low) / 2
    half = np.maximum(half, 0.2 * half.max())
    if half.max() == 0:  # every point at the target
        half = np.ones_like(half)
    return centre - scale * half, centre + scale * half


def plane_grid(
    demos: Demonstrations, *, include: Sequence[np.ndarray] = ()
) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """A GRID x GRID grid over the view of x1, x2; other coordinates at the target's values.

    Returns:
        The axes' ticks (x1, x2), each shape (GRID,), and the grid's points, (GRID * GRID, n),
        row-major with x2 along rows as :meth:`~matplotlib.axes.Axes.streamplot` expects.
    """
    target = demos.target
    low, high = bounding_box(demos.positions()[:, :2], target[:2], scale=1.4)
    extra = [np.asarray(s)[:, :2] for s in include if len(s)]
    if extra:
        # Keep every drawn start in view, with a small margin beyond the outermost one.
        starts = np.concatenate(extra)
        margin = 0.05 * (high - low)
        low = np.minimum(low, starts.min(axis=0) - margin)
        high = np.maximum(high, starts.max(axis=0) + margin)
    x1 = np.linspace(low[0], high[0], GRID)
    x2 = np.linspace(low[1], high[1], GRID)
    grid1, grid2 = np.meshgrid(x1, x2)
    points = np.tile(target, (GRID * GRID, 1))
    points[:, 0], points[:, 1] = grid1.ravel(), grid2.ravel()
    return (x1, x2), points


@torch.no_grad()
def lyapunov_values(policy: Policy, points: np.ndarray) -> np.ndarray:
    """V at user states (N, space.dim), in model units."""
    param = next(policy.parameters())
    x = torch.as_tensor(points, dtype=param.dtype, device=param.device)
    v, _ = policy.lyapunov.value_and_grad(policy.to_model(x))
    return v.cpu().numpy()


def require_stable(policy: Policy) -> None:
    if not policy.stable:
        raise ValueError(
            "this policy has no Lyapunov function (it was built with stable=False); "
            "V can only be plotted for a stable policy"
        )


def smoothed(values: np.ndarray) -> np.ndarray:
    """Centred rolling median over about 2 % of the run, taken in log space.

    Centred, unlike a moving average, so the curve does not lag behind a steep early drop;
    the median ignores the odd spike of a mini-batch.
    """
    half = max(2, values.size // 100)
    logs = np.log(np.clip(values, np.finfo(np.float64).tiny, None))
    padded = np.pad(logs, half, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * half + 1)
    return np.exp(np.median(windows, axis=-1))


# --- drawing ---------------------------------------------------------------------------------


def new_figure(
    x1: np.ndarray | None = None, x2: np.ndarray | None = None, *, colorbar: bool = True
):
    """A figure with one axes; given the view's ticks, equal aspect and a size that fits it.

    A fixed figure size would leave wide motions (LASA's Sine is 6:3) floating in white
    space, so the axes box gets up to AXES_INCHES on its longer side and the figure grows
    around it by room for the title, the labels, the colour bar and the legend.
    """
    if x1 is None or x2 is None:
        fig = Figure(figsize=FIGSIZE, dpi=DPI, layout="constrained")
        return fig, fig.add_subplot()
    ratio = (x2[-1] - x2[0]) / (x1[-1] - x1[0])
    width, height = (
        (AXES_INCHES, AXES_INCHES * ratio) if ratio < 1 else (AXES_INCHES / ratio, AXES_INCHES)
    )
    size = (max(width, 2.5) + (1.9 if colorbar else 0.9), max(height, 2.0) + 1.7)
    fig = Figure(figsize=size, dpi=DPI, layout="constrained")
    ax = fig.add_subplot()
    ax.set_aspect("equal")
    return fig, ax


def draw_field(
    ax,
    policy: Policy,
    x1: np.ndarray,
    x2: np.ndarray,
    points: np.ndarray,
    *,
    density: float = 1.3,
):
    """Streamlines of the policy over the grid, coloured by speed; returns the streamplot."""
    velocity = policy.predict(points)[:, :2].reshape(len(x2), len(x1), 2)
    speed = np.linalg.norm(velocity, axis=-1)
    finite = speed[np.isfinite(speed)]
    top = float(np.percentile(finite, 98)) if finite.size else 1.0
    return ax.streamplot(
        x1,
        x2,
        velocity[..., 0],
        velocity[..., 1],
        color=speed,
        cmap=STREAM_CMAP,
        norm=colors.Normalize(0.0, top if top > 0 else 1.0),
        density=density,
        linewidth=0.7,
        arrowsize=0.7,
        zorder=1,
    )


def draw_paths(
    ax,
    demos: Demonstrations,
    rollouts: np.ndarray | None,
    perturbed: np.ndarray | None,
    *,
    random_label: str = "perturbed rollout",
) -> None:
    """Demonstrations, rollouts from their starts (solid), other rollouts (dashed), target."""
    draw_demos(ax, demos, color=DEMO_COLOR)
    if rollouts is not None:
        draw_rollouts(
            ax,
            rollouts,
            color=ROLLOUT_COLOR,
            style="-",
            label="rollout from demo start",
            starts=False,
        )
    if perturbed is not None:
        draw_rollouts(
            ax, perturbed, color=PERTURBED_COLOR, style="--", label=random_label, starts=True
        )
    draw_target(ax, demos.target)


def draw_demos(ax, demos: Demonstrations, *, color: str) -> None:
    for i, demo in enumerate(demos):
        x = demo.positions
        ax.plot(
            x[:, 0],
            x[:, 1],
            color=color,
            linewidth=1.0,
            alpha=0.9,
            zorder=3,
            label="demonstration" if i == 0 else None,
        )
        ax.plot(
            x[0, 0],
            x[0, 1],
            "o",
            color=color,
            markersize=3.5,
            zorder=3,
            label="demo start" if i == 0 else None,
        )


def draw_rollouts(
    ax, rollouts: np.ndarray, *, color: str, style: str, label: str, starts: bool
) -> None:
    for i, path in enumerate(np.asarray(rollouts)):
        ax.plot(
            path[:, 0],
            path[:, 1],
            style,
            color=color,
            linewidth=1.3,
            alpha=0.9,
            zorder=4,
            label=label if i == 0 else None,
        )
        if starts:
            ax.plot(path[0, 0], path[0, 1], "o", mfc="white", mec=color, mew=1.0, ms=4, zorder=4)


def draw_target(ax, target: np.ndarray) -> None:
    ax.plot(
        target[0],
        target[1],
        "*",
        color="#fab005",
        mec="black",
        mew=0.8,
        markersize=15,
        zorder=6,
        label="target",
    )


def finish_axes(
    ax, x1: np.ndarray, x2: np.ndarray, dim: int, title: str, *, projected: bool = False
) -> None:
    ax.set_xlim(x1[0], x1[-1])
    ax.set_ylim(x2[0], x2[-1])
    ax.set_xlabel("x1")
    ax.set_ylabel("x2")
    if dim > 2:
        rest = "x3" if dim == 3 else f"x3..x{dim}"
        title = f"{title}\nslice {rest} = target" + (", paths projected" if projected else "")
    ax.set_title(title)
    despine(ax)


def axes_legend(fig, ax) -> None:
    # Below the axes, so it never hides a streamline, a demonstration or the target.
    handles, labels = ax.get_legend_handles_labels()
    figure_legend(fig, handles, labels, loc="outside lower center", most_columns=3)


def figure_legend(
    fig: Figure, handles: list, labels: list[str], *, loc: str, most_columns: int | None = None
):
    """A legend of the whole figure outside its axes (``loc`` such as "outside lower
    center", under constrained layout), in as many columns as fit the figure's width: it
    hides no data and is not cut off at the figure's sides.

    Returns:
        The legend.
    """
    columns = min(len(labels), most_columns or len(labels))
    width = fig.get_figwidth() * fig.dpi
    while True:
        legend = fig.legend(
            handles, labels, loc=loc, ncol=max(columns, 1), frameon=False, fontsize="small"
        )
        fig.draw_without_rendering()
        if columns <= 1 or legend.get_window_extent().width <= 0.98 * width:
            return legend
        legend.remove()
        columns -= 1


def despine(ax) -> None:
    for side in ("top", "right"):
        ax.spines[side].set_visible(False)


def title_of(demos: Demonstrations, policy: Policy) -> str:
    kind = "stable policy" if policy.stable else "unconstrained policy"
    return f"{demos.name} — {kind}" if demos.name else kind


def save_figure(fig: Figure, path: str | Path) -> Path:
    """Writes ``fig`` as a PNG atomically (see :func:`snds.io.atomic_write`)."""
    path = Path(path)
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=DPI))
    finally:
        fig.clear()
    return path
