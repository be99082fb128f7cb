"""Simulation: a learned policy drives a simulated robot arm (PyBullet, headless).

Needs the ``sim`` extra (``pip install 'snds[sim]'``); the Kinova Jaco2 also needs the
``jaco2`` extra. :func:`simulate` runs one motion of a position or an SE(3) pose policy;
:mod:`snds.sim.plots` draws it.
"""

from snds.errors import SimulationError
from snds.sim.config import Push, SimConfig
from snds.sim.placement import Placement, PosePlacement
from snds.sim.result import SimResult
from snds.sim.robots import ROBOTS, Robot, get_robot
from snds.sim.run import simulate

__all__ = [
    "ROBOTS",
    "Placement",
    "PosePlacement",
    "Push",
    "Robot",
    "SimConfig",
    "SimResult",
    "SimulationError",
    "get_robot",
    "simulate",
]
