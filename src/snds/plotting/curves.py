"""Plots against time or step: the training loss, V along rollouts."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from snds.plotting.draw import (
    PERTURBED_COLOR,
    ROLLOUT_COLOR,
    V_FLOOR,
    despine,
    lyapunov_values,
    new_figure,
    require_stable,
    save_figure,
    smoothed,
)
from snds.policy import Policy

__all__ = ["plot_loss", "plot_rollout_lyapunov"]


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
    fig, ax = new_figure()
    ax.plot(steps, loss, color="#74c0fc", linewidth=0.8, alpha=0.8, label="loss")
    if loss.size >= 20:
        ax.plot(steps, smoothed(loss), color="#1864ab", linewidth=1.6, label="smoothed")
        ax.legend(frameon=False, loc="upper right")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    if loss.size:
        ax.set_title(f"Training loss (final {loss[-1]:.3g}, best {np.nanmin(loss):.3g})")
    ax.grid(True, which="major", color="0.9", linewidth=0.6)
    despine(ax)
    return save_figure(fig, path)


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
    require_stable(policy)
    fig, ax = new_figure()
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
        v = lyapunov_values(policy, group.reshape(-1, dim)).reshape(count, length)
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
    despine(ax)
    return save_figure(fig, path)
