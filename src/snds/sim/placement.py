"""Where a task lies in the world: a position task's coordinates (:class:`Placement`), a pose
task's positions and orientations (:class:`PosePlacement`), its scale (:func:`default_scale`)
and its obstacles' bodies (:func:`world_shapes`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from snds.errors import SimulationError
from snds.obstacles import Scene
from snds.policy import Policy
from snds.sim.robots import Robot

__all__ = ["Placement", "PosePlacement", "default_scale", "world_shapes"]


@dataclass(frozen=True)
class Placement:
    r"""Where a task's coordinates lie in the world: :math:`p = o + s A (x - x^*)`.

    Attributes:
        origin: World position of the task's target, shape (3,).
        axes: World directions of the task's coordinates, orthonormal columns, shape (3, n).
        scale: Metres per user unit.
        target: The task's target in user units, shape (n,).
    """

    origin: np.ndarray
    axes: np.ndarray
    scale: float
    target: np.ndarray

    @classmethod
    def for_task(cls, robot: Robot, target: np.ndarray, scale: float) -> Placement:
        """A 2-D task on the robot's work plane; a 3-D one with its own axes as the world's."""
        n = target.size
        if n == 2:
            axes = np.array(robot.plane_axes, dtype=float).T
        elif n == 3:
            axes = np.eye(3)
        else:
            raise SimulationError(
                f"a {n}-D model cannot drive an arm: position models are 2-D or 3-D"
            )
        return cls(np.array(robot.plane_origin, dtype=float), axes, float(scale), target)

    def to_task(self, position: np.ndarray) -> np.ndarray:
        """The task state (user units, (n,)) of a world end-effector position (3,)."""
        return self.target + self.axes.T @ (position - self.origin) / self.scale

    def to_world(self, state: np.ndarray) -> np.ndarray:
        """World position (3,) of a task state (n,)."""
        return self.origin + self.scale * self.axes @ (state - self.target)

    def velocity_to_world(self, velocity: np.ndarray) -> np.ndarray:
        """World linear velocity (3,) of a task velocity (n,)."""
        return self.scale * self.axes @ velocity

    def off_task(self, position: np.ndarray) -> np.ndarray:
        """The part of a world position's offset from the origin outside the task's span (3,).

        Zero for a 3-D task; for a 2-D one, the distance off the work plane, which the policy
        cannot see and the controller holds at zero.
        """
        offset = position - self.origin
        return offset - self.axes @ (self.axes.T @ offset)


@dataclass(frozen=True)
class PosePlacement:
    r"""Where a pose task lies in the world: positions as a 3-D task's, orientations turned by
    one fixed rotation, :math:`q_\text{world} = R \, q_\text{task}`.

    Turning every orientation by the same :math:`R` (on the left, in the world frame) maps
    the task's flow on SO(3) onto the world's exactly: with :math:`\dot R_t = [\omega]_\times
    R_t`, the world's angular velocity is :math:`R \omega`. The positions keep the task's axes
    (:meth:`Placement.for_task` of a 3-D task), so a motion drawn on a horizontal plane stays
    horizontal whatever :math:`R` is.

    Attributes:
        positions: The placement of the positions (3-D).
        rotation: :math:`R`, quaternion (x, y, z, w), shape (4,).
    """

    positions: Placement
    rotation: np.ndarray

    @classmethod
    def for_task(
        cls,
        robot: Robot,
        target_position: np.ndarray,
        target_orientation: np.ndarray,
        scale: float,
        rest_orientation: np.ndarray,
    ) -> PosePlacement:
        r"""The task's target at the robot's work point, its target orientation at the arm's
        orientation at rest (:math:`R = q_\text{rest} \, q^{*-1}`): a goal the arm reaches."""
        rotation = (
            Rotation.from_quat(rest_orientation) * Rotation.from_quat(target_orientation).inv()
        )
        return cls(Placement.for_task(robot, target_position, scale), rotation.as_quat())

    def to_task(
        self, position: np.ndarray, orientation: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The task pose (user units (3,), quaternion (4,)) of a world pose ((3,), (4,))."""
        turn = Rotation.from_quat(self.rotation).inv() * Rotation.from_quat(orientation)
        return self.positions.to_task(position), turn.as_quat()

    def to_world(
        self, position: np.ndarray, orientation: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The world pose (metres (3,), quaternion (4,)) of a task pose ((3,), (4,))."""
        turn = Rotation.from_quat(self.rotation) * Rotation.from_quat(orientation)
        return self.positions.to_world(position), turn.as_quat()

    def twist_to_world(self, twist: np.ndarray) -> np.ndarray:
        """World twist (linear m/s, angular rad/s), shape (6,), of a task twist (6,)."""
        angular = Rotation.from_quat(self.rotation).apply(twist[3:])
        return np.concatenate([self.positions.velocity_to_world(twist[:3]), angular])


def default_scale(robot: Robot, policy: Policy) -> float:
    """Metres per user unit that fit a policy's demonstrations (their position extent) into
    the robot's reach."""
    return robot.reach / float(policy.extents()[0])


def world_shapes(scene: Scene, placement: Placement, count: int = 400) -> list[np.ndarray]:
    """World vertices (M, 3) of each obstacle of a scene (not the workspace), whose convex
    hull is its collision body: a 2-D task's shapes as their 3-D analogues (see
    :meth:`snds.obstacles.Obstacle.solid`) centred on the work plane."""
    axes = placement.axes
    n = axes.shape[1]
    normal = np.cross(axes[:, 0], axes[:, 1]) if n == 2 else np.zeros(3)
    shapes = []
    for obstacle in scene.obstacles:
        points = obstacle.solid().surface_points(count)
        offset = (points[:, :n] - placement.target) @ axes.T
        if n == 2:
            offset = offset + points[:, 2:3] * normal
        shapes.append(placement.origin + placement.scale * offset)
    return shapes
