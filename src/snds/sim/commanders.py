r"""What a policy commands an arm to do: the one part of the simulate loop
(:func:`snds.sim.simulate`) that knows what kind of policy drives the arm.

The commander is chosen once from the policy's type (:func:`make_commander`):

- :class:`PositionCommander`, a 2-D or 3-D position policy: the task's coordinates lie in the
  world by a :class:`~snds.sim.placement.Placement`; the policy drives the position, the
  controller holds the orientation at the start's (and a 2-D task on its plane). It has
  arrived within :attr:`SimConfig.tolerance <snds.sim.config.SimConfig.tolerance>` of the
  target.
- :class:`PhasedCommander`, a position policy with a phase (:mod:`snds.phase`): as a
  position policy's, and it keeps the phase, which waits while the arm is held.
- :class:`PoseCommander`, an SE(3) :class:`~snds.se3.PosePolicy`: positions are placed as a
  3-D task's, orientations by one fixed rotation
  (:class:`~snds.sim.placement.PosePlacement`) that takes the task's target orientation to
  the arm's orientation at its rest pose, which the arm can reach; the policy drives both.
  It has arrived within the position tolerance and within
  :attr:`SimConfig.angle_tolerance <snds.sim.config.SimConfig.angle_tolerance>` of the
  target orientation.
- :class:`PhasedPoseCommander`, a pose policy with a phase: as a pose policy's, and it keeps
  the phase.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np
import torch

from snds.errors import SimulationError
from snds.obstacles import modulate_twist, step_fraction
from snds.phase import PhaseKeeper
from snds.policy import Policy
from snds.rollout import rollout_numpy, safe_velocity
from snds.se3 import PosePolicy
from snds.sim.arm import Arm, EndEffector, orientation_error
from snds.sim.config import SimConfig
from snds.sim.orient import choose_rotation
from snds.sim.placement import Placement, PosePlacement, default_scale
from snds.sim.robots import Robot
from snds.spaces import SE3, Euclidean, Phased, Space
from snds.steppers import GuardedEuler

__all__ = [
    "COMMANDERS",
    "PHASED_COMMANDERS",
    "PLANNED_POSES",
    "Commander",
    "PhasedCommander",
    "PhasedPoseCommander",
    "PoseCommander",
    "PositionCommander",
    "make_commander",
]

#: Poses along the policy's path that :meth:`PoseCommander.fit_to` checks.
PLANNED_POSES = 40


class Commander(Protocol):
    """What a policy commands at a measured end-effector pose: the one part of the loop that
    knows the kind of policy (see the module's docstring).

    Attributes:
        placement: Where the task's positions lie in the world.
        rotation: The fixed rotation of a pose task's orientations, quaternion (4,); None if
            the policy does not drive the orientation.
        goal_orientation: The world orientation the run aims for, quaternion (4,).
    """

    placement: Placement
    rotation: np.ndarray | None
    goal_orientation: np.ndarray

    def start_pose(self, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The world pose (position (3,), quaternion (4,)) of a start state in user units."""
        ...

    def twist(self, pose: EndEffector) -> np.ndarray:
        """The world twist (linear, angular), shape (6,), to command at a measured pose."""
        ...

    def arrived(self, distance: float, angle: float) -> bool:
        """Whether a pose at ``distance`` metres and ``angle`` radians from the target is there."""
        ...

    def fit_to(self, arm: Arm, start: np.ndarray) -> Commander:
        """The commander whose placement the arm (at rest) can follow from ``start``: another
        turn of a pose task's orientations, or itself."""
        ...


class PositionCommander:
    """A 2-D or 3-D position policy: it drives the position; the orientation is held.

    Arguments:
        policy: The position policy (float64).
        placement: Where the task lies.
        hold: The orientation held, quaternion (4,).
        config: The run's settings (tolerance, hold gain).
    """

    rotation = None

    def __init__(
        self, policy: Policy, placement: Placement, hold: np.ndarray, config: SimConfig
    ) -> None:
        self.policy = policy
        self.placement = placement
        self.goal_orientation = hold
        self.config = config

    @classmethod
    def build(
        cls, policy: Policy, robot: Robot, rest_orientation: np.ndarray, config: SimConfig
    ) -> PositionCommander:
        """The commander of a run on ``robot``, holding the rest orientation; the task's
        target is the position part of the policy's (a phase left out)."""
        target = policy.space.positions(policy.target)
        placement = Placement.for_task(robot, target, _scale(robot, policy, config))
        return cls(policy, placement, rest_orientation, config)

    def start_pose(self, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The world pose of a start state (n,): its position, the held orientation."""
        start = np.asarray(start, dtype=float)
        if start.shape != self.placement.target.shape:
            raise SimulationError(
                f"the start has shape {start.shape}, the model's states "
                f"{self.placement.target.shape}"
            )
        return self.placement.to_world(start), self.goal_orientation

    def twist(self, pose: EndEffector) -> np.ndarray:
        """The policy's velocity at the measured position; the holds on the rest.

        With a Lyapunov function the velocity is scaled down so that holding it for one
        control period decreases V enough (:func:`snds.rollout.safe_velocity`), as for pose
        policies.
        """
        return self._world_twist(pose, self._velocity(self.placement.to_task(pose.position)))

    def _velocity(self, state: np.ndarray) -> np.ndarray:
        """The guarded (and, with obstacles, modulated) velocity at a task state (user units)."""
        state = torch.as_tensor(state)[None]
        scene = self.config.obstacles
        with torch.no_grad():
            # With obstacles, modulated around them, the step shortened to stay out of them
            # (and to decrease V where no obstacle is in reach).
            velocity = safe_velocity(
                self.policy,
                state,
                1.0 / self.config.control_rate,
                max_speed=self.config.max_speed,
                scene=scene,
            )[0]
        return velocity[0].numpy()

    def _world_twist(self, pose: EndEffector, velocity: np.ndarray) -> np.ndarray:
        """The world twist of a task velocity of the positions, the holds added."""
        gain = self.config.hold_gain
        return np.concatenate(
            [
                self.placement.velocity_to_world(velocity)
                - gain * self.placement.off_task(pose.position),
                gain * orientation_error(pose.orientation, self.goal_orientation),
            ]
        )

    def arrived(self, distance: float, angle: float) -> bool:
        """Within the position tolerance: the held orientation is not the policy's to reach."""
        return distance <= self.config.tolerance

    def fit_to(self, arm: Arm, start: np.ndarray) -> PositionCommander:
        """Itself: the orientation is held, and the positions keep the task's placement."""
        return self


class PhasedCommander(PositionCommander):
    """A position policy with a phase in its state (:class:`~snds.spaces.Phased`): it drives
    the position, and the commander keeps the phase, advancing it by the share of each
    commanded step that the arm made (:func:`snds.phase.phase_step`), so that a held arm's
    phase waits for it. A start is a whole state, phase included (``start_pose``).

    Arguments:
        policy: The phased policy (float64).
        placement: Where the task's positions lie.
        hold: The orientation held, quaternion (4,).
        config: The run's settings; obstacles are refused (their modulation of a phased
            field is not defined).
    """

    def __init__(
        self, policy: Policy, placement: Placement, hold: np.ndarray, config: SimConfig
    ) -> None:
        if config.obstacles is not None:
            raise SimulationError("obstacles cannot be simulated with a model that has a phase")
        super().__init__(policy, placement, hold, config)
        self.position_dim = policy.space.position_dim
        self.keeper = PhaseKeeper(position_dim=self.position_dim)

    def start_pose(self, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The world pose of a start state (n + m,): its position, the held orientation; its
        phase starts the commander's."""
        start = np.asarray(start, dtype=float)
        if start.shape != self.policy.target.shape:
            raise SimulationError(
                f"the start has shape {start.shape}, the model's states (position and phase) "
                f"{self.policy.target.shape}"
            )
        self.keeper.start(start)
        return self.placement.to_world(start[: self.position_dim]), self.goal_orientation

    def twist(self, pose: EndEffector) -> np.ndarray:
        """The policy's velocity at the measured position and the kept phase."""
        if self.keeper.state is None:
            raise SimulationError("a phased run needs its start (start_pose) before a twist")
        measured = self.placement.to_task(pose.position)
        state = self.keeper.step(measured, 1.0 / self.config.control_rate)
        velocity = self._velocity(state)
        self.keeper.command(velocity)
        return self._world_twist(pose, velocity[: self.position_dim])


class PoseCommander:
    """An SE(3) pose policy: it drives position and orientation.

    Arguments:
        policy: The pose policy (float64).
        placement: Where the task lies.
        config: The run's settings (tolerances).
    """

    def __init__(self, policy: PosePolicy, placement: PosePlacement, config: SimConfig) -> None:
        self.policy = policy
        self.pose_placement = placement
        self.placement = placement.positions
        self.rotation = placement.rotation
        target = np.asarray(policy.config.target_orientation, dtype=float)
        self.goal_orientation = placement.to_world(self.placement.target, target)[1]
        self.config = config

    @classmethod
    def build(
        cls, policy: PosePolicy, robot: Robot, rest_orientation: np.ndarray, config: SimConfig
    ) -> PoseCommander:
        """The commander of a run on ``robot``, the target orientation at the rest one."""
        placement = PosePlacement.for_task(
            robot,
            np.asarray(policy.config.target_position, dtype=float),
            np.asarray(policy.config.target_orientation, dtype=float),
            _scale(robot, policy, config),
            rest_orientation,
        )
        return cls(policy, placement, config)

    def planned_poses(self, start: np.ndarray, count: int = PLANNED_POSES) -> np.ndarray:
        """``count`` task poses (count, 7) evenly spaced in time along the policy's own rollout
        from ``start`` (guarded Euler steps at the control rate, for the run's time limit)."""
        rate = self.config.control_rate
        steps = int(np.ceil(self.config.time_limit * rate))
        start = np.array(start, dtype=float)
        start[3:7] /= np.linalg.norm(start[3:7])
        path = rollout_numpy(
            self.policy,
            start[None],
            dt=1.0 / rate,
            steps=steps,
            stepper=GuardedEuler(),
        )[0, :, :7]
        return path[np.linspace(0, steps, count).round().astype(int)]

    def fit_to(self, arm: Arm, start: np.ndarray) -> PoseCommander:
        """The same commander with the task's orientations turned so that the arm follows the
        policy's path from ``start`` within its joint limits
        (:func:`snds.sim.orient.choose_rotation`); itself where the default turn already
        fits."""
        self.start_pose(start)  # the start's shape and quaternion, checked first
        placement, _ = choose_rotation(
            arm,
            self.pose_placement,
            self.planned_poses(start),
            tolerance=self.config.tolerance,
            angle_tolerance=self.config.angle_tolerance,
        )
        if placement is self.pose_placement:
            return self
        return type(self)(self.policy, placement, self.config)

    def start_pose(self, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The world pose of a start pose (7,): position (3) and unit quaternion (4)."""
        start = np.asarray(start, dtype=float)
        if start.shape != (7,):
            raise SimulationError(
                f"a pose model starts from a position and a quaternion (7 numbers), got "
                f"shape {start.shape}"
            )
        norm = np.linalg.norm(start[3:])
        if not abs(norm - 1.0) <= 1e-6:
            raise SimulationError(f"the start orientation is not a unit quaternion (norm {norm})")
        return self.pose_placement.to_world(start[:3], start[3:] / norm)

    def twist(self, pose: EndEffector) -> np.ndarray:
        """The policy's linear and angular velocity at the measured pose, in the world.

        With a Lyapunov function the twist is scaled down so that holding it for one control
        period decreases V enough (:func:`snds.rollout.safe_velocity`): a stiff field
        would otherwise make the arm chatter between two poses at constant V, the commanded
        joint velocities flipping sign every period (docs/design.md).
        """
        position, orientation = self.pose_placement.to_task(pose.position, pose.orientation)
        x = torch.as_tensor(np.concatenate([position, orientation]))[None]
        with torch.no_grad():
            twist = safe_velocity(
                self.policy, x, 1.0 / self.config.control_rate, max_speed=self.config.max_speed
            )[0][0]
            scene = self.config.obstacles
            if scene is not None:
                # The position part goes around the obstacles; the whole twist is shortened
                # so that the position stays out of their margins.
                place = x[:, :3]
                target = torch.as_tensor(self.policy.config.target_position).to(place)
                twist = modulate_twist(scene, place, twist[None], target)
                dt = 1.0 / self.config.control_rate
                twist = (twist * step_fraction(scene, place, twist[:, :3], dt).unsqueeze(-1))[0]
        return self.pose_placement.twist_to_world(twist.numpy())

    def arrived(self, distance: float, angle: float) -> bool:
        """Within both tolerances."""
        return distance <= self.config.tolerance and angle <= self.config.angle_tolerance


class PhasedPoseCommander(PoseCommander):
    """A pose policy with a phase in its state: it drives position and orientation, and keeps
    the phase as :class:`PhasedCommander` does (:func:`snds.phase.phase_step`). A start is a
    whole state: position, unit quaternion and phase.

    Arguments:
        policy: The phased pose policy (float64).
        placement: Where the task lies.
        config: The run's settings; obstacles are refused.
    """

    def __init__(self, policy: PosePolicy, placement: PosePlacement, config: SimConfig) -> None:
        if config.obstacles is not None:
            raise SimulationError("obstacles cannot be simulated with a model that has a phase")
        super().__init__(policy, placement, config)
        self.keeper = PhaseKeeper(position_dim=3)

    def start_pose(self, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The world pose of a start state (7 + m,); its phase starts the commander's."""
        start = np.asarray(start, dtype=float)
        if start.shape != self.policy.target.shape:
            raise SimulationError(
                f"the start has shape {start.shape}, the model's states (pose and phase) "
                f"{self.policy.target.shape}"
            )
        pose = super().start_pose(start[:7])
        self.keeper.start(start)
        return pose

    def twist(self, pose: EndEffector) -> np.ndarray:
        """The policy's twist at the measured pose and the kept phase, in the world."""
        if self.keeper.state is None:
            raise SimulationError("a phased run needs its start (start_pose) before a twist")
        position, orientation = self.pose_placement.to_task(pose.position, pose.orientation)
        dt = 1.0 / self.config.control_rate
        state = self.keeper.step(np.concatenate([position, orientation]), dt)
        with torch.no_grad():
            twist = safe_velocity(self.policy, torch.as_tensor(state)[None], dt)[0][0].numpy()
        self.keeper.command(twist)
        return self.pose_placement.twist_to_world(twist[:6])


#: The commander of each state space: a position policy drives the position and holds the
#: orientation; a pose policy drives both.
COMMANDERS: dict[type[Space], Any] = {Euclidean: PositionCommander, SE3: PoseCommander}

#: The commander of each base space with a phase after it (:class:`~snds.spaces.Phased`).
PHASED_COMMANDERS: dict[type[Space], Any] = {Euclidean: PhasedCommander, SE3: PhasedPoseCommander}


def _scale(robot: Robot, policy: Policy, config: SimConfig) -> float:
    """Metres per user unit: the run's ``scale``, else one that fits the task into the reach."""
    return config.scale if config.scale is not None else default_scale(robot, policy)


def make_commander(
    policy: Policy, robot: Robot, rest_orientation: np.ndarray, config: SimConfig
) -> Commander:
    """The commander of a policy, chosen from its type: poses or positions.

    Arguments:
        policy: The policy (float64, eval mode).
        robot: The arm.
        rest_orientation: The end effector's orientation at the rest pose, quaternion (4,).
        config: The run's settings.
    """
    space = policy.space
    if isinstance(space, Phased):
        commander = PHASED_COMMANDERS[type(space.base)]
    else:
        commander = COMMANDERS[type(space)]
    return commander.build(policy, robot, rest_orientation, config)
