"""Plots: streamlines with demonstrations and rollouts, Lyapunov contours, loss, V over time.

Every function draws on its own :class:`~matplotlib.figure.Figure`, never through pyplot, so
it needs no display and leaves the user's backend alone (selecting Agg at import would
silently turn off a notebook's inline plots); it writes the PNG atomically (a reader never
sees half a file) and returns the path it wrote.

States with more than two coordinates are shown in the plane of x1 and x2 through the target,
with x3..xn held at the target's values; rollouts are projected onto that plane.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import torch
from matplotlib import colors
from matplotlib.figure import Figure

from snds.arrival import ARRIVAL_TOLERANCE
from snds.data.demonstrations import Demonstrations
from snds.io import atomic_write
from snds.obstacles import ModulatedPolicy
from snds.parallel import torch_threads
from snds.phase import start_states
from snds.policy import Policy
from snds.rollout import Arrival, rollout, rollout_numpy
from snds.stability import CheckConfig
from snds.steppers import GuardedEuler

FIGSIZE = (6.0, 4.5)  # plots against time or step
AXES_INCHES = 4.6  # longer side of the axes of a plot in the plane
DPI = 150
GRID = 100  # points per side of the evaluation grid
#: Below this V (model units, about 1e-5 of the extent from the target) a rollout has arrived.
V_FLOOR = 1e-10

DEMO_COLOR = "#262626"
ROLLOUT_COLOR = "#d9480f"
PERTURBED_COLOR = "#6741d9"
# The streamlines are the backdrop: a pale slice of a blue map keeps them below the data.
STREAM_CMAP = colors.LinearSegmentedColormap.from_list(
    "snds_stream", matplotlib.colormaps["Blues"](np.linspace(0.25, 0.8, 256))
)


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
    (x1, x2), points = _plane(demos, include=starts)
    if demos.phase_dim:
        # With a phase, the field of the plane is the one a new start there begins with.
        points = start_states(demos, points[:, : len(demos.target) - demos.phase_dim])
    fig, ax = _figure(x1, x2)
    stream = _draw_field(ax, policy, x1, x2, points)
    colorbar = fig.colorbar(
        stream.lines, ax=ax, fraction=0.04, pad=0.02, extend="max", extendfrac=0.03
    )
    colorbar.set_label("speed")
    colorbar.outline.set_visible(False)
    _draw_paths(ax, demos, rollouts, perturbed)
    projected = rollouts is not None or perturbed is not None
    title = title if title is not None else _name(demos, policy)
    if demos.phase_dim:
        _finish(ax, x1, x2, 2, f"{title}\nfield at a new start's phase", projected=projected)
    else:
        _finish(ax, x1, x2, demos.dim, title, projected=projected)
    _legend(fig, ax)
    return _save(fig, path)


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
            (x1, x2), points = _plane(demos)
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
            _draw_field(ax, policy, x1, x2, points, density=0.9)
            _draw_paths(ax, demos, rollouts, perturbed, random_label="rollout from random start")
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
    return _save(fig, path)


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
    _require_stable(policy)
    (x1, x2), points = _plane(demos)
    v = _lyapunov(policy, points).reshape(GRID, GRID)
    # V grows quadratically away from the target: log-spaced levels show the basin's shape
    # near the target as well as far out, where linear levels would put nearly every line.
    positive = v[v > 0]
    low = max(float(np.percentile(positive, 0.5)), float(positive.max()) * 1e-6)
    levels = np.geomspace(low, float(v.max()), 16)

    fig, ax = _figure(x1, x2)
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
    _draw_demos(ax, demos, color="white")
    _draw_target(ax, demos.target)
    _finish(
        ax, x1, x2, demos.dim, "Lyapunov function V" + (f" — {demos.name}" if demos.name else "")
    )
    return _save(fig, path)


def plot_loss(history: list[float], path: str | Path) -> Path:
    """Training loss per step on a log axis, raw and smoothed.

    Arguments:
        history: The loss at every step.
        path: Where to write the PNG.

    Returns:
        The path written.
    """
    loss = np.asarray(history, dtype=np.float64)
    steps = np.arange(1, loss.size + 1)
    fig, ax = _figure()
    ax.plot(steps, loss, color="#74c0fc", linewidth=0.8, alpha=0.8, label="loss")
    if loss.size >= 20:
        ax.plot(steps, _smooth(loss), color="#1864ab", linewidth=1.6, label="smoothed")
        ax.legend(frameon=False, loc="upper right")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    if loss.size:
        ax.set_title(f"Training loss (final {loss[-1]:.3g}, best {np.nanmin(loss):.3g})")
    ax.grid(True, which="major", color="0.9", linewidth=0.6)
    _despine(ax)
    return _save(fig, path)


def plot_rollout_lyapunov(
    policy: Policy,
    rollouts: np.ndarray,
    dt: float,
    path: str | Path,
    *,
    perturbed: np.ndarray | None = None,
    arrived: np.ndarray | None = None,
) -> Path:
    """V along rollouts against time, on a log axis: a stable policy makes each curve fall.

    A curve ends where the rollout arrived (``arrived``, marked with a dot), or where V drops
    below :data:`V_FLOOR`, i.e. where the rollout has reached the target up to rounding;
    below that, V is rounding noise that would only clutter the plot.

    Arguments:
        policy: A stable policy, float64 and in eval mode.
        rollouts: States in user units, shape (B, T, n); solid lines.
        dt: Time step of the rollouts, in seconds.
        path: Where to write the PNG.
        perturbed: Rollouts from perturbed starts, same time step; dashed lines.
        arrived: The step at which each rollout arrived (:func:`rollouts_until_arrival`), those
            of ``rollouts`` then those of ``perturbed``, shape (B,); -1: not arrived.

    Returns:
        The path written.

    Raises:
        ValueError: If the policy has no Lyapunov guarantee.
    """
    _require_stable(policy)
    fig, ax = _figure()
    rises = total = 0
    count = 0 if rollouts is None else len(rollouts)
    ends = {} if arrived is None else {"solid": arrived[:count], "dashed": arrived[count:]}
    for group, color, style, label, key in (
        (rollouts, ROLLOUT_COLOR, "-", "from demo start", "solid"),
        (perturbed, PERTURBED_COLOR, "--", "from perturbed start", "dashed"),
    ):
        if group is None or len(group) == 0:
            continue
        group = np.asarray(group, dtype=np.float64)
        count, length, dim = group.shape
        v = _lyapunov(policy, group.reshape(-1, dim)).reshape(count, length)
        above = v > V_FLOOR
        # Only steps that start above the floor count: below it V is rounding noise.
        steps = above[:, :-1]
        rises += int(((np.diff(v, axis=1) > 0) & steps).sum())
        total += int(steps.sum())
        times = dt * np.arange(length)
        for i, curve in enumerate(v):
            # Keep the first point below the floor so that each curve visibly reaches it.
            floor = np.flatnonzero(~above[i])
            stop = floor[0] + 1 if floor.size else length
            at = ends[key][i] if key in ends else -1
            if at >= 0:
                stop = min(stop, at + 1)
                ax.plot(times[at], max(curve[at], V_FLOOR), "o", color=color, markersize=3)
            ax.plot(
                times[:stop],
                np.maximum(curve[:stop], V_FLOOR),
                style,
                color=color,
                linewidth=1.0,
                alpha=0.75,
                label=label if i == 0 else None,
            )
    ax.axhline(V_FLOOR, color="0.6", linewidth=0.8, linestyle=":", zorder=0)
    ax.annotate(
        "at the target (up to rounding)",
        (0.01, V_FLOOR),
        xycoords=("axes fraction", "data"),
        xytext=(0, 3),
        textcoords="offset points",
        ha="left",
        va="bottom",
        fontsize="x-small",
        color="0.45",
    )
    ax.set_yscale("log")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("V (model units)")
    verdict = "V decreases at every step" if rises == 0 else f"V rises at {rises} of {total} steps"
    until = "" if arrived is None else ", until arrival (dots)"
    ax.set_title(f"V along rollouts{until}: {verdict}", fontsize="medium")
    ax.legend(frameon=False, loc="upper right", fontsize="small")
    ax.grid(True, which="major", color="0.9", linewidth=0.6)
    _despine(ax)
    return _save(fig, path)


def rollouts_until_arrival(
    policy: Policy, demos: Any, starts: np.ndarray, *, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Euler rollouts at the data's step until every one has arrived
    (:func:`snds.arrival.arrival_time`, within :data:`~snds.arrival.ARRIVAL_TOLERANCE` of
    each error scale), in pieces of 1.5 longest-demonstration durations, at most the stability
    check's cap (:attr:`~snds.stability.CheckConfig.horizon_factor` durations): every plot
    of a run shows the same rollouts, to the same end.

    Returns:
        The rollouts, shape (B, T, space.dim), and the step at which each arrived, shape
        (B,) (-1 for one that had not arrived at the cap).
    """
    duration = demos.max_duration()
    piece = max(1, int(1.5 * duration / dt))
    cap = int(CheckConfig().horizon_factor * duration / dt)
    target = torch.tensor(np.asarray(demos.target, dtype=np.float64))
    arrival = Arrival.of(policy.space, target, demos.extent(), tolerance=ARRIVAL_TOLERANCE)
    x0 = torch.tensor(np.asarray(starts, dtype=np.float64))
    # Whole pieces until every rollout has arrived: the first piece that reaches the cap ends it.
    steps = piece * max(1, -(-cap // piece))
    result = rollout(policy, x0, dt=dt, steps=steps, until=arrival, check_every=piece)
    return result.states.transpose(0, 1).cpu().numpy(), arrival.steps(result.states)


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
    low, high = _box(demos.positions(), space.positions(np.asarray(demos.target)), scale=1.5)
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
                demos, rollouts, out / "paths.png", perturbed=perturbed, title=_name(demos, policy)
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
                title=_name(demos, policy),
                **orientations,
            )
        )
    if history:
        paths.append(plot_loss(history, out / "loss.png"))
    return paths


OBSTACLE_COLOR = "#868e96"
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
    (:class:`~snds.steppers.GuardedEuler` with the scene) for 3x the longest demonstration, from the
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

    (x1, x2), points = _plane(demos)
    rng = np.random.default_rng(seed)
    candidates = np.tile(demos.target, (50 * random_starts, 1))
    candidates[:, 0] = rng.uniform(x1[0], x1[-1], len(candidates))
    candidates[:, 1] = rng.uniform(x2[0], x2[-1], len(candidates))
    free = scene.free(torch.as_tensor(candidates)).numpy()
    random = candidates[free][:random_starts]
    starts = np.stack([demo.positions[0] for demo in demos])
    starts = starts[scene.free(torch.as_tensor(starts)).numpy()]
    dt = demos.mean_dt()
    steps = int(3 * demos.max_duration() / dt)
    # One batch for both sets of starts: a step costs the same for 8 states as for 15.
    paths = rollout_numpy(
        policy, np.concatenate([starts, random]), dt=dt, steps=steps, stepper=AVOIDING, scene=scene
    )
    rollouts, perturbed = (paths[: len(starts)] if len(starts) else None), paths[len(starts) :]
    fig, ax = _figure(x1, x2)
    stream = _draw_field(ax, ModulatedPolicy(policy, scene), x1, x2, points)
    colorbar = fig.colorbar(
        stream.lines, ax=ax, fraction=0.04, pad=0.02, extend="max", extendfrac=0.03
    )
    colorbar.set_label("speed")
    colorbar.outline.set_visible(False)
    _draw_scene(ax, scene, x1, x2, points)
    _draw_paths(ax, demos, rollouts, perturbed, random_label="rollout from random start")
    title = f"{_name(demos, policy)}, {len(scene.bodies)} obstacle" + (
        "s" if len(scene.bodies) != 1 else ""
    )
    _finish(ax, x1, x2, demos.dim, title, projected=True)
    _legend(fig, ax)
    return _save(fig, path)


def _draw_scene(ax, scene, x1: np.ndarray, x2: np.ndarray, points: np.ndarray) -> None:
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
    (x1, x2), _ = _plane(demos, include=drawn)
    fig, ax = _figure(x1, x2, colorbar=False)
    _draw_paths(ax, demos, rollouts, perturbed)
    _finish(ax, x1, x2, 2, title)
    _legend(fig, ax)
    return _save(fig, path)


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
    return _save(fig, path)


# --- geometry --------------------------------------------------------------------------------


def _box(points: np.ndarray, target: np.ndarray, *, scale: float) -> tuple[np.ndarray, np.ndarray]:
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


def _plane(
    demos: Demonstrations, *, include: Sequence[np.ndarray] = ()
) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """A GRID x GRID grid over the view of x1, x2; other coordinates at the target's values.

    Returns:
        The axes' ticks (x1, x2), each shape (GRID,), and the grid's points, (GRID * GRID, n),
        row-major with x2 along rows as :meth:`~matplotlib.axes.Axes.streamplot` expects.
    """
    target = demos.target
    low, high = _box(demos.positions()[:, :2], target[:2], scale=1.4)
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
def _lyapunov(policy: Policy, points: np.ndarray) -> np.ndarray:
    """V at user states (N, space.dim), in model units."""
    param = next(policy.parameters())
    x = torch.as_tensor(points, dtype=param.dtype, device=param.device)
    v, _ = policy.lyapunov.value_and_grad(policy.to_model(x))
    return v.cpu().numpy()


def _require_stable(policy: Policy) -> None:
    if not policy.stable:
        raise ValueError(
            "this policy has no Lyapunov function (it was built with stable=False); "
            "V can only be plotted for a stable policy"
        )


def _smooth(values: np.ndarray) -> np.ndarray:
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


def _figure(x1: np.ndarray | None = None, x2: np.ndarray | None = None, *, colorbar: bool = True):
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


def _draw_field(
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


def _draw_paths(
    ax,
    demos: Demonstrations,
    rollouts: np.ndarray | None,
    perturbed: np.ndarray | None,
    *,
    random_label: str = "perturbed rollout",
) -> None:
    """Demonstrations, rollouts from their starts (solid), other rollouts (dashed), target."""
    _draw_demos(ax, demos, color=DEMO_COLOR)
    if rollouts is not None:
        _draw_rollouts(
            ax,
            rollouts,
            color=ROLLOUT_COLOR,
            style="-",
            label="rollout from demo start",
            starts=False,
        )
    if perturbed is not None:
        _draw_rollouts(
            ax, perturbed, color=PERTURBED_COLOR, style="--", label=random_label, starts=True
        )
    _draw_target(ax, demos.target)


def _draw_demos(ax, demos: Demonstrations, *, color: str) -> None:
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


def _draw_rollouts(
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


def _draw_target(ax, target: np.ndarray) -> None:
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


def _finish(
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
    _despine(ax)


def _legend(fig, ax) -> None:
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


def _despine(ax) -> None:
    for side in ("top", "right"):
        ax.spines[side].set_visible(False)


def _name(demos: Demonstrations, policy: Policy) -> str:
    kind = "stable policy" if policy.stable else "unconstrained policy"
    return f"{demos.name} — {kind}" if demos.name else kind


def _save(fig: Figure, path: str | Path) -> Path:
    """Writes ``fig`` as a PNG atomically (see :func:`snds.io.atomic_write`)."""
    path = Path(path)
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=DPI))
    finally:
        fig.clear()
    return path
