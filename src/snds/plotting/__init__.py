"""Plots: streamlines with demonstrations and rollouts, Lyapunov contours, loss, V over time.

Every function draws on its own :class:`~matplotlib.figure.Figure`, never through pyplot, so
it needs no display and leaves the user's backend alone (selecting Agg at import would
silently turn off a notebook's inline plots); it writes the PNG atomically (a reader never
sees half a file) and returns the path it wrote.

States with more than two coordinates are shown in the plane of x1 and x2 through the target,
with x3..xn held at the target's values; rollouts are projected onto that plane.

The package: :mod:`~snds.plotting.draw` (shared drawing), :mod:`~snds.plotting.plane`,
:mod:`~snds.plotting.curves`, :mod:`~snds.plotting.paths`, :mod:`~snds.plotting.rollouts` (what
the plots draw, from the engine) and :mod:`~snds.plotting.run` (every plot of a run).
"""

from snds.plotting.curves import plot_loss, plot_rollout_lyapunov
from snds.plotting.draw import figure_legend
from snds.plotting.paths import plot_paths, plot_paths_3d
from snds.plotting.plane import Panel, plot_lyapunov, plot_obstacles, plot_panels, plot_streamlines
from snds.plotting.rollouts import rollouts_until_arrival
from snds.plotting.run import plot_all

__all__ = [
    "Panel",
    "figure_legend",
    "plot_all",
    "plot_loss",
    "plot_lyapunov",
    "plot_obstacles",
    "plot_panels",
    "plot_paths",
    "plot_paths_3d",
    "plot_rollout_lyapunov",
    "plot_streamlines",
    "rollouts_until_arrival",
]
