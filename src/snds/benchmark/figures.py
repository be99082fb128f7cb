"""The figures of a sweep: errors, train time and convergence per motion and method, and the
streamlines of each run's model (the paper's Fig. 4 to 6)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from snds.benchmark.summary import row_groups
from snds.benchmark.tasks import Task
from snds.io import atomic_write
from snds.models import load_model
from snds.plotting import Panel, figure_legend, plot_panels
from snds.policy import float64_copy

__all__ = ["benchmark_figures", "plot_benchmark"]


def _save(fig, path: Path) -> Path:
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=120))
    return path


def plot_benchmark(rows: Sequence[dict], out: Path) -> list[Path]:
    """Writes the sweep's figures (:func:`benchmark_figures`) into ``out``, then
    ``streamlines.png``: one row per method, one column per motion, the lowest seed's model
    (from ``out/models``) with its rollouts; the paper's Fig. 5 and 6. Skipped for runs whose
    model is not there."""
    out = Path(out)
    paths = [_save(fig, out / name) for name, fig in benchmark_figures(rows).items()]
    cells = {(motion, method): group for motion, method, group in row_groups(rows)}
    motions = list(dict.fromkeys(motion for motion, _ in cells))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    panels = _panels(cells, out, motions, methods)
    if any(panel is not None for row in panels for panel in row):
        paths.append(plot_panels(panels, out / "streamlines.png"))
    return paths


def benchmark_figures(rows: Sequence[dict]) -> dict[str, Figure]:
    """The sweep's figures by file name, each legend above its axes (it hides no bar or dot):

    * ``mse_violin.png``: log10 of the velocity MSE (paper scale), one violin per method and
      motion, every run a dot (a violin needs two runs or more); the paper's Fig. 4.
    * ``dtw_violin.png``: the same for the DTW of rollouts from the demonstrations' starts.
    * ``train_time.png``: train seconds, mean and std over seeds.
    * ``converged.png``: the fraction of random starts that reached the target, mean over
      seeds with the worst seed marked.
    """
    # The rows of each (motion, method) cell, each row's label read once.
    cells = {(motion, method): group for motion, method, group in row_groups(rows)}
    motions = list(dict.fromkeys(motion for motion, _ in cells))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    width = 0.8 / max(1, len(methods))
    size = (max(5.0, 1.2 * len(motions) * max(1, len(methods)) ** 0.5 + 2), 4.0)

    def offsets(i: int) -> np.ndarray:
        return np.arange(len(motions)) + (i - (len(methods) - 1) / 2) * width

    def values(motion: str, method: str, key: str) -> np.ndarray:
        return np.array([r[key] for r in cells.get((motion, method), [])], dtype=float)

    def violins(key: str, label: str) -> Figure:
        fig = Figure(figsize=size, layout="constrained")
        ax = fig.subplots()
        for i, method in enumerate(methods):
            color = f"C{i}"
            for x, motion in zip(offsets(i), motions):
                logs = np.log10(np.clip(values(motion, method, key), 1e-12, None))
                logs = logs[np.isfinite(logs)]
                if len(logs) > 1 and np.ptp(logs) > 0:
                    parts = ax.violinplot(
                        [logs], positions=[x], widths=0.9 * width, showextrema=False
                    )
                    for body in parts["bodies"]:
                        body.set_facecolor(color)
                        body.set_alpha(0.4)
                # One run per cell gives no violin: a larger mark, so it reads as a result.
                mark = 10 if len(logs) > 1 else 36
                ax.scatter(np.full(len(logs), x), logs, s=mark, color=color, zorder=3)
            ax.scatter([], [], color=color, label=method)
        ax.set_xticks(range(len(motions)), motions, rotation=30, ha="right")
        ax.set_xlim(-0.5, len(motions) - 0.5)
        ax.set_ylabel(label)
        if all(len(group) == 1 for group in cells.values()):
            ax.set_title("one run per method and motion (no violins)", fontsize="small")
        _legend_above(fig, ax)
        return fig

    figures = {
        "mse_violin.png": violins("velocity_mse_paper", "log10 velocity MSE (paper scale)"),
        "dtw_violin.png": violins("dtw_paper", "log10 DTW (paper scale)"),
    }

    fig = Figure(figsize=size, layout="constrained")
    ax = fig.subplots()
    for i, method in enumerate(methods):
        seconds = [values(motion, method, "train_seconds") for motion in motions]
        means = [v.mean() if v.size else np.nan for v in seconds]
        stds = [v.std() if v.size else np.nan for v in seconds]
        ax.bar(offsets(i), means, width=width, yerr=stds, label=method, color=f"C{i}")
    ax.set_xticks(range(len(motions)), motions, rotation=30, ha="right")
    ax.set_ylabel("train seconds (mean ± std over seeds)")
    _legend_above(fig, ax)
    figures["train_time.png"] = fig

    fig = Figure(figsize=size, layout="constrained")
    ax = fig.subplots()
    for i, method in enumerate(methods):
        fractions = [values(motion, method, "converged_fraction") for motion in motions]
        means = [v.mean() if v.size else np.nan for v in fractions]
        worst = [v.min() if v.size else np.nan for v in fractions]
        ax.bar(offsets(i), means, width=width, label=method, color=f"C{i}")
        ax.scatter(offsets(i), worst, marker="_", s=120, color="black", zorder=3)
    ax.scatter([], [], marker="_", s=120, color="black", label="worst seed")
    ax.set_xticks(range(len(motions)), motions, rotation=30, ha="right")
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("converged fraction of random starts")
    _legend_above(fig, ax)
    figures["converged.png"] = fig
    return figures


def _legend_above(fig, ax) -> None:
    """The axes' legend above them, in the figure (:func:`snds.plotting.figure_legend`):
    bars that reach 1 and dots anywhere on the scale stay in view."""
    handles, labels = ax.get_legend_handles_labels()
    figure_legend(fig, handles, labels, loc="outside upper center")


def _panels(
    cells: dict[tuple[str, str], list[dict]], out: Path, motions: list[str], methods: list[str]
) -> list:
    """The streamline panels: the lowest seed's saved model per method (row) and motion
    (``cells``: the rows of each (motion label, method))."""
    grid = []
    for method in methods:
        line = []
        for motion in motions:
            runs = cells.get((motion, method), [])
            task = Task.from_row(min(runs, key=lambda r: r["seed"])) if runs else None
            folder = out / task.model_dir if task else None
            if folder is None or not folder.is_dir():
                line.append(None)
                continue
            policy, _ = load_model(folder)
            if policy.space.dim != 2:
                # Streamlines need a plane: 3-D positions and poses have none.
                line.append(None)
                continue
            demos = task.source().load()
            line.append(Panel(float64_copy(policy), demos, f"{motion} — {method}"))
        grid.append(line)
    return grid
