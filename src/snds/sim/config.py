"""The settings of a simulated run (:class:`SimConfig`) and of a push in it (:class:`Push`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from snds.errors import SimulationError
from snds.obstacles import Scene

__all__ = ["Push", "SimConfig"]


@dataclass(frozen=True, kw_only=True)
class Push:
    """A displacement of the end effector at one control step.

    The orientation is kept: a push moves the tool, it does not turn it.

    Attributes:
        step: The control step at which it happens (0-based).
        displacement: Metres in the world frame, (dx, dy, dz).
    """

    step: int
    displacement: tuple[float, float, float]

    def __post_init__(self) -> None:
        object.__setattr__(self, "displacement", tuple(float(d) for d in self.displacement))
        if self.step < 0 or len(self.displacement) != 3:
            raise SimulationError("a push needs a step >= 0 and three displacements")


@dataclass(frozen=True, kw_only=True)
class SimConfig:
    """Settings of a simulated run; written beside its results.

    Attributes:
        robot: A key of :data:`~snds.sim.robots.ROBOTS`.
        scale: Metres per user unit of the task's positions (None: fit the demonstrations'
            extent into the robot's reach).
        control_rate: Control loop frequency, Hz.
        substeps: Physics steps per control step.
        time_limit: Longest simulated time, seconds.
        tolerance: Distance to the target (metres) at which the run stops.
        angle_tolerance: Angle to the target orientation (radians) within which a pose
            policy's run stops (with the distance within ``tolerance``); a position policy
            does not drive the orientation, and its run stops on the distance alone.
        push: An optional push.
        obstacles: A :class:`~snds.obstacles.Scene` in the task's user units (static): the
            policy's velocity is modulated around them and each step shortened so that the
            commanded tool point stays out of their margins; they are collision bodies in the
            PyBullet world (a 2-D task's shapes as their 3-D analogues centred on the plane).
        hold_gain: Gain (1/s) of the holds on what a position policy does not drive: the
            orientation, and for a 2-D task the distance off the work plane.
        gravity: Whether gravity acts on the arm.
        max_speed: Speed limit of the task's positions, user units/s (None: none;
            :func:`snds.rollout.safe_velocity`).
        fit_orientation: For a pose policy, turn the task's orientations so that the arm
            follows the policy's path from the start within its joint limits
            (:func:`snds.sim.orient.choose_rotation`); False: the target orientation at the
            arm's orientation at rest, whatever the path asks.
    """

    robot: str = "iiwa"
    scale: float | None = None
    control_rate: float = 100.0
    substeps: int = 4
    time_limit: float = 30.0
    tolerance: float = 0.001
    angle_tolerance: float = 0.02
    push: Push | None = None
    obstacles: Scene | None = None
    hold_gain: float = 5.0
    gravity: bool = True
    max_speed: float | None = None
    fit_orientation: bool = True

    def __post_init__(self) -> None:
        if self.scale is not None and not self.scale > 0:
            raise SimulationError(f"the scale must be positive, got {self.scale}")
        if self.max_speed is not None and not self.max_speed > 0:
            raise SimulationError(f"--max-speed must be positive, got {self.max_speed}")
        if not (self.control_rate > 0 and self.substeps >= 1 and self.time_limit > 0):
            raise SimulationError("control rate, substeps and time limit must be positive")
        if not self.tolerance > 0:
            raise SimulationError(f"the tolerance must be positive, got {self.tolerance}")
        if not self.angle_tolerance > 0:
            raise SimulationError(
                f"the angle tolerance must be positive, got {self.angle_tolerance}"
            )
        if self.obstacles is not None and self.obstacles.moving:
            raise SimulationError("moving obstacles are not simulated (the bodies are static)")

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return dataclasses.asdict(self)
