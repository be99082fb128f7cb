"""Pictures of a simulated run: a strip of rendered frames, and the path against the demos.

Like :mod:`snds.plotting`, every function draws on its own :class:`~matplotlib.figure.Figure`
(never pyplot) and writes the PNG atomically. Frames come from PyBullet's TinyRenderer,
which needs no display: the arm is put back at recorded joint positions and photographed,
with the demonstrations (grey beads), the path so far (orange beads) and the target (green).
The demonstrations may be positions (:class:`~snds.data.Demonstrations`) or poses
(:class:`~snds.data.poses.PoseDemonstrations`): only their positions are drawn.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from snds.data.demonstrations import Demonstrations
from snds.data.poses import PoseDemonstrations
from snds.plotting.draw import (
    DEMO_COLOR,
    DPI,
    PERTURBED_COLOR,
    ROLLOUT_COLOR,
    despine,
    draw_demos,
    draw_scene,
    draw_target,
    save_figure,
)
from snds.sim.arm import Arm
from snds.sim.placement import world_shapes
from snds.sim.result import SimResult
from snds.sim.robots import get_robot

__all__ = ["frame_steps", "plot_frames", "plot_path", "render_frames"]

GREY = (0.55, 0.55, 0.55, 1.0)
ORANGE = (0.85, 0.28, 0.06, 1.0)
GREEN = (0.1, 0.65, 0.25, 1.0)


def frame_steps(result: SimResult, count: int) -> np.ndarray:
    """Control steps to photograph: evenly spaced over the run, plus the one after a push."""
    last = len(result.times) - 1
    steps = set(np.linspace(0, last, count).round().astype(int).tolist())
    if result.push_time is not None:
        pushed = int(np.searchsorted(result.times, result.push_time))
        nearest = min(steps - {0, last}, key=lambda s: abs(s - pushed), default=None)
        if nearest is not None:
            steps.discard(nearest)
        steps.add(pushed)
    return np.array(sorted(steps))


def render_frames(
    result: SimResult,
    demos: Demonstrations | PoseDemonstrations | None = None,
    *,
    count: int = 6,
    width: int = 400,
    height: int = 300,
) -> tuple[list[np.ndarray], np.ndarray]:
    """Renders the arm at a few moments of a run.

    Arguments:
        result: The run.
        demos: Demonstrations to show in the scene (in the task's units), or None.
        count: Number of frames (one more may be added to show a push).
        width: Width of a frame, pixels.
        height: Height of a frame, pixels.

    Returns:
        The frames, each (height, width, 3) uint8, and their control steps.
    """
    steps = frame_steps(result, count)
    placement = result.placement
    with Arm(get_robot(result.config.robot), gravity=False) as arm:
        arm.add_floor()
        if demos is not None:
            dim = placement.target.size
            for demo in demos:
                # A phase model's demonstrations carry the phase after the positions.
                beads = demo.positions[:: max(1, len(demo.positions) // 60), :dim]
                arm.add_markers(
                    np.array([placement.to_world(x) for x in beads]), radius=0.004, rgba=GREY
                )
        arm.add_markers(placement.origin[None], radius=0.012, rgba=GREEN)
        if result.config.obstacles is not None:
            arm.add_obstacles(world_shapes(result.config.obstacles, placement))
        frames, shown = [], 0
        stride = max(1, len(result.times) // 150)
        for step in steps:
            trail = result.positions[shown : step + 1 : stride]
            if len(trail):
                arm.add_markers(trail, radius=0.006, rgba=ORANGE)
            shown = step + 1
            arm.reset(result.joints[step])
            frames.append(arm.render(width=width, height=height))
    return frames, steps


def plot_frames(result: SimResult, frames: list[np.ndarray], steps: np.ndarray, path) -> Path:
    """A strip of rendered frames with their times; the frame after a push is marked."""
    fig = Figure(figsize=(2.2 * len(frames), 2.2 * 0.75 + 0.6), dpi=DPI, layout="constrained")
    axes = fig.subplots(1, len(frames), squeeze=False)[0]
    pushed = (
        None if result.push_time is None else int(np.searchsorted(result.times, result.push_time))
    )
    for ax, frame, step in zip(axes, frames, steps):
        ax.imshow(frame)
        ax.set_xticks([])
        ax.set_yticks([])
        for spine in ax.spines.values():
            spine.set_visible(False)
        label = f"t = {result.times[step]:.1f} s"
        ax.set_title(label + (" (pushed)" if step == pushed else ""), fontsize="small")
    fig.suptitle(_headline(result), fontsize="medium")
    return save_figure(fig, path)


def plot_path(result: SimResult, demos: Demonstrations | PoseDemonstrations | None, path) -> Path:
    """The end effector's path in the task's plane against the demonstrations, and its
    distance to the target over time; for a run driven by a pose policy, also its angle to
    the target orientation over time."""
    if result.drives_orientation:
        fig = Figure(figsize=(14.0, 4.2), dpi=DPI, layout="constrained")
        plane, distance, angle = fig.subplots(1, 3, width_ratios=(1.25, 1.0, 1.0))
    else:
        fig = Figure(figsize=(10.0, 4.2), dpi=DPI, layout="constrained")
        plane, distance = fig.subplots(1, 2, width_ratios=(1.25, 1.0))
    states = result.states
    if demos is not None:
        draw_demos(plane, demos, color=DEMO_COLOR)
    pushed = None
    if result.push_time is not None:
        pushed = int(np.searchsorted(result.times, result.push_time))
        before, after = states[pushed - 1], states[pushed]
        plane.annotate(
            "",
            xy=after[:2],
            xytext=before[:2],
            arrowprops={"arrowstyle": "->", "color": PERTURBED_COLOR, "lw": 1.5},
            zorder=5,
        )
        plane.plot([], [], color=PERTURBED_COLOR, label="push")
    segments = [states] if pushed is None else [states[:pushed], states[pushed:]]
    for i, segment in enumerate(segments):
        plane.plot(
            segment[:, 0],
            segment[:, 1],
            color=ROLLOUT_COLOR,
            linewidth=1.6,
            zorder=4,
            label="end effector" if i == 0 else None,
        )
    draw_target(plane, result.placement.target)
    if result.config.obstacles is not None:
        _draw_obstacles_in_view(plane, result, demos)
    plane.set_aspect("equal", adjustable="datalim")
    plane.set_xlabel("x1 (task units)")
    plane.set_ylabel("x2 (task units)")
    plane.set_title("path in the task's plane")
    plane.legend(frameon=False, fontsize="small", loc="best")
    despine(plane)

    error = np.linalg.norm(result.positions - result.placement.origin, axis=1)
    _draw_error(distance, result, error, result.config.tolerance, recovery=True)
    distance.set_ylabel("distance to target (m)")
    distance.set_title("distance to the target")
    if result.drives_orientation:
        _draw_error(angle, result, result.orientation_errors, result.config.angle_tolerance)
        angle.set_ylabel("angle to target orientation (rad)")
        angle.set_title("orientation error")
    fig.suptitle(_headline(result), fontsize="medium")
    return save_figure(fig, path)


def _draw_obstacles_in_view(ax, result: SimResult, demos) -> None:
    """The run's obstacles (filled) and margins (dashed) over the path's view, in the plane
    of x1, x2 through the target."""
    seen = [result.states] + ([] if demos is None else [d.positions for d in demos])
    points = np.concatenate([p[:, : result.states.shape[1]] for p in seen])
    low, high = points.min(axis=0), points.max(axis=0)
    pad = 0.1 * (high - low).max()
    x1 = np.linspace(low[0] - pad, high[0] + pad, 200)
    x2 = np.linspace(low[1] - pad, high[1] + pad, 200)
    grid = np.tile(result.placement.target, (x1.size * x2.size, 1))
    mesh1, mesh2 = np.meshgrid(x1, x2)
    grid[:, 0], grid[:, 1] = mesh1.ravel(), mesh2.ravel()
    draw_scene(ax, result.config.obstacles, x1, x2, grid)


def _draw_error(
    ax, result: SimResult, error: np.ndarray, tolerance: float, *, recovery: bool = False
) -> None:
    """An error (T,) over time on a log scale, with its tolerance, the push and (if asked)
    the recovery after it."""
    # The floor keeps an error of exactly 0 (a run that starts at the target) on the axis.
    ax.semilogy(result.times, np.maximum(error, 1e-6), color=ROLLOUT_COLOR)
    ax.axhline(tolerance, color="0.5", linestyle=":", label="tolerance")
    if result.push_time is not None:
        ax.axvline(result.push_time, color=PERTURBED_COLOR, linestyle="--", label="push")
        if recovery and result.recovery_time is not None:
            ax.axvspan(
                result.push_time,
                result.push_time + result.recovery_time,
                color=PERTURBED_COLOR,
                alpha=0.12,
                label="back on the path",
            )
    ax.set_xlabel("time (s)")
    ax.legend(frameon=False, fontsize="small")
    despine(ax)


def _headline(result: SimResult) -> str:
    robot = result.config.robot
    outcome = (
        f"reached the target in {result.times[-1]:.1f} s"
        if result.reached
        else f"stopped at {result.times[-1]:.1f} s"
    )
    text = f"{robot}: {outcome}, final error {1000 * result.final_error:.1f} mm"
    if result.drives_orientation:
        text += f" and {result.final_orientation_error:.3f} rad"
    if result.recovery_time is not None:
        text += f", back on its path {result.recovery_time:.2f} s after the push"
    if result.obstacle_clearance is not None:
        text += f"; clearance {1000 * result.obstacle_clearance:.1f} mm"
        if result.contact_steps is not None:
            text += ", no contact" if result.contact_steps == 0 else ", touched an obstacle"
    return text
