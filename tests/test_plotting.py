"""Plots: every file is a real, non-trivial PNG, written atomically, for 2-D and n-D tasks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from snds.data import Demonstration, Demonstrations, Normalization
from snds.plotting import (
    Panel,
    plot_all,
    plot_loss,
    plot_lyapunov,
    plot_panels,
    plot_rollout_lyapunov,
)
from snds.plotting.draw import plane_grid
from snds.policy import PolicyConfig, StablePolicy

TINY = PolicyConfig(hidden=(16,), fourier_features=8, lyapunov_hidden=(8,))
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def line_demos(dim: int = 2) -> Demonstrations:
    """Two 50-sample demonstrations along straight lines to the origin, over one second."""
    times = np.linspace(0.0, 1.0, 50)
    starts = np.zeros((2, dim))
    starts[0, 0], starts[1, 1] = 4.0, 3.0
    starts[:, 2:] = 1.0  # off the x1-x2 plane in n > 2, so the slice is a real choice
    demos = [
        Demonstration(
            positions=start * (1.0 - times)[:, None],
            velocities=np.tile(-start, (times.size, 1)),
            times=times,
        )
        for start in starts
    ]
    return Demonstrations(tuple(demos), np.zeros(dim), "lines")


def tiny_policy(demos: Demonstrations, *, stable: bool = True) -> StablePolicy:
    config = PolicyConfig(**{**TINY.to_dict(), "stable": stable})
    policy = StablePolicy(dim=demos.dim, normalization=Normalization.fit(demos), config=config)
    return policy.to(torch.float64).eval()


def assert_png(path: Path) -> None:
    assert path.is_file(), path
    assert path.read_bytes()[:8] == PNG_MAGIC, f"{path} is not a PNG"
    assert path.stat().st_size > 10_000, f"{path} is nearly empty ({path.stat().st_size} B)"


@pytest.mark.parametrize("dim", [2, 3])
def test_plot_all_writes_every_plot_of_a_stable_policy(tmp_path: Path, dim: int) -> None:
    # GIVEN a stable policy (in 3-D, plotted in the slice x3 = target and as 3-D paths)
    # and a loss history
    demos = line_demos(dim)
    policy = tiny_policy(demos)
    history = list(np.geomspace(1.0, 1e-3, 200))
    # WHEN every plot is written into a folder that does not exist yet
    paths = plot_all(policy, demos, tmp_path / "plots", history=history)
    # THEN each is a real PNG, and nothing else (no temporary file) is left in the folder
    names = ["streamlines.png", "lyapunov.png", "rollout_lyapunov.png"]
    names += ["paths3d.png"] if dim == 3 else []
    names += ["loss.png"]
    assert [p.name for p in paths] == names
    for path in paths:
        assert_png(path)
    assert sorted(p.name for p in (tmp_path / "plots").iterdir()) == sorted(names)


def test_unconstrained_policy_gets_no_lyapunov_plots(tmp_path: Path) -> None:
    demos = line_demos()
    policy = tiny_policy(demos, stable=False)
    paths = plot_all(policy, demos, tmp_path)
    assert [p.name for p in paths] == ["streamlines.png"]
    assert_png(paths[0])
    with pytest.raises(ValueError, match="stable"):
        plot_lyapunov(policy, demos, tmp_path / "lyapunov.png")
    with pytest.raises(ValueError, match="stable"):
        plot_rollout_lyapunov(policy, np.zeros((1, 3, 2)), 0.1, tmp_path / "v.png")
    assert not (tmp_path / "lyapunov.png").exists()


def test_plots_overwrite_and_return_the_path_written(tmp_path: Path) -> None:
    target = tmp_path / "nested" / "loss.png"
    first = plot_loss(list(np.geomspace(1.0, 1e-2, 50)), target)
    second = plot_loss([3.0, 2.0, 1.0], str(target))
    assert first == second == target
    assert_png(target)
    assert sorted(p.name for p in target.parent.iterdir()) == ["loss.png"]


def test_slice_holds_other_coordinates_at_the_target() -> None:
    # GIVEN a 4-D task whose target is off the origin in every coordinate
    base = line_demos(4)
    shift = np.array([1.0, -2.0, 3.0, -4.0])
    demos = Demonstrations(
        tuple(
            Demonstration(positions=d.positions + shift, velocities=d.velocities, times=d.times)
            for d in base
        ),
        base.target + shift,
    )
    (x1, x2), points = plane_grid(demos)
    # THEN x3, x4 sit at the target, and the view contains the data and the target with room
    assert np.all(points[:, 2:] == demos.target[2:])
    data = demos.positions()[:, :2]
    assert x1[0] < data[:, 0].min() and x1[-1] > data[:, 0].max()
    assert x2[0] < data[:, 1].min() and x2[-1] > data[:, 1].max()
    assert x1[0] < demos.target[0] < x1[-1] and x2[0] < demos.target[1] < x2[-1]


def test_panels_grid_with_an_empty_cell(tmp_path: Path) -> None:
    # GIVEN a stable and an unconstrained policy on one task, and a second column half empty
    demos = line_demos()
    rows = [
        [Panel(tiny_policy(demos), demos, "stable"), Panel(tiny_policy(demos), demos, "again")],
        [Panel(tiny_policy(demos, stable=False), demos, "bc"), None],
    ]
    # WHEN the grid is drawn
    path = plot_panels(rows, tmp_path / "panels.png", random_starts=3)
    # THEN one real PNG and nothing else is written
    assert_png(path)
    assert [p.name for p in tmp_path.iterdir()] == ["panels.png"]
    with pytest.raises(ValueError, match="at least one panel"):
        plot_panels([], tmp_path / "none.png")


def test_panels_roll_out_on_one_torch_thread_and_restore_the_callers(tmp_path: Path) -> None:
    # GIVEN a caller on two torch threads (a script's default on two cores) and a policy that
    # records the threads it is evaluated with: on a busy machine several threads made the
    # panels' thousands of small calls (an SDS-EF rollout: 29-65 s against 2-3 s) look hung
    demos = line_demos()
    policy = tiny_policy(demos)
    seen: list[int] = []
    field = policy.field

    def recording(z: torch.Tensor) -> torch.Tensor:
        seen.append(torch.get_num_threads())
        return field(z)

    policy.field = recording
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        # WHEN the panels are drawn
        plot_panels([[Panel(policy, demos, "stable")]], tmp_path / "panels.png", random_starts=2)
        after = torch.get_num_threads()
    finally:
        torch.set_num_threads(before)
    # THEN every evaluation (rollouts and the streamlines' grid) ran on one thread, and the
    # caller's two threads are back
    assert seen and set(seen) == {1}
    assert after == 2


def test_a_figure_legend_takes_as_many_columns_as_fit_the_figure():
    # GIVEN a one-panel figure 2.9 inches wide (a grid of one motion) and five entries
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from snds.plotting import figure_legend

    fig = Figure(figsize=(2.9, 3.0), dpi=100, layout="constrained")
    ax = fig.subplots()
    labels = ["demonstration", "rollout from demo start", "rollout from random start", "a", "b"]
    handles = [ax.plot([0, 1], [k, k])[0] for k in range(len(labels))]
    legend = figure_legend(fig, handles, labels, loc="outside lower center")
    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw(renderer)
    box = legend.get_window_extent(renderer)
    # THEN it is not cut at the figure's sides (one row of five was 2x the figure's width)
    assert 0 <= box.x0 and box.x1 <= fig.bbox.x1
    assert legend._ncols < len(labels)
