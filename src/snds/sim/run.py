r"""The simulate loop: a policy drives a simulated arm's end effector to its target.

At a fixed control rate the loop measures the end effector, asks a :class:`Commander` for
the twist (linear and angular velocity, world frame) the policy commands at that pose, and
hands it to the task-space controller (:func:`~snds.sim.arm.joint_velocity`), whose joint
targets the motors track while the physics runs. A push teleports the end effector
mid-motion; the run stops when the end effector has arrived at the target (after any push)
or at a time limit.

The commander is the only part that knows what kind of policy drives the arm, and is chosen
once from the policy's type (:func:`make_commander`):

- :class:`PositionCommander`, a 2-D or 3-D position policy: the task's coordinates lie in the
  world by a :class:`Placement`; the policy drives the position, the controller holds the
  orientation at the start's (and a 2-D task on its plane). It has arrived within
  :attr:`SimConfig.tolerance` of the target.
- :class:`PhasedCommander`, a position policy with a phase (:mod:`snds.phase`): as a
  position policy's, and it keeps the phase, which waits while the arm is held.
- :class:`PoseCommander`, an SE(3) :class:`~snds.se3.PosePolicy`: positions are placed as a
  3-D task's, orientations by one fixed rotation (:class:`PosePlacement`) that takes the
  task's target orientation to the arm's orientation at its rest pose, which the arm can
  reach; the policy drives both. It has arrived within the position tolerance and within
  :attr:`SimConfig.angle_tolerance` of the target orientation.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from snds.arrival import PATH_TOLERANCE, distance_to_path, recovery_time
from snds.obstacles import Scene, modulate_twist, step_fraction
from snds.phase import PhaseKeeper
from snds.policy import Policy, float64_copy
from snds.rollout import rollout, safe_velocity
from snds.se3 import PosePolicy
from snds.sim.arm import Arm, EndEffector, joint_velocity, orientation_error
from snds.sim.robots import Robot, SimulationError, get_robot
from snds.spaces import SE3, Euclidean, Phased, Space
from snds.steppers import GuardedEuler


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
        """The commander of a run on ``robot``, holding the rest orientation."""
        scale = config.scale if config.scale is not None else default_scale(robot, policy)
        return cls(
            policy, Placement.for_task(robot, policy.target, scale), rest_orientation, config
        )

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

    @classmethod
    def build(
        cls, policy: Policy, robot: Robot, rest_orientation: np.ndarray, config: SimConfig
    ) -> PhasedCommander:
        """The commander of a run on ``robot``, holding the rest orientation."""
        scale = config.scale if config.scale is not None else default_scale(robot, policy)
        target = policy.space.positions(policy.target)
        return cls(policy, Placement.for_task(robot, target, scale), rest_orientation, config)

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
        scale = config.scale if config.scale is not None else default_scale(robot, policy)
        placement = PosePlacement.for_task(
            robot,
            np.asarray(policy.config.target_position, dtype=float),
            np.asarray(policy.config.target_orientation, dtype=float),
            scale,
            rest_orientation,
        )
        return cls(policy, placement, config)

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


@dataclass(frozen=True)
class SimResult:
    """What a simulated run did.

    Attributes:
        config: The settings.
        placement: Where the task's positions were in the world.
        rotation: For a pose policy, the fixed rotation of the task's orientations into the
            world, quaternion (4,); None for a position policy (orientation held).
        goal_orientation: The world orientation aimed for, quaternion (4,): the image of a
            pose task's target orientation, or the orientation a position policy's run held.
        times: Time of each control step, seconds, shape (T,).
        positions: Measured end-effector positions, metres, shape (T, 3).
        orientations: Measured end-effector orientations, unit quaternions (x, y, z, w),
            shape (T, 4).
        states: The positions in the task's user units, shape (T, n).
        orientation_errors: Angle from the measured orientation to the goal orientation,
            radians, shape (T,).
        joints: Controlled joint positions, radians, shape (T, k).
        joint_lower: Lower joint limits, shape (k,).
        joint_upper: Upper joint limits, shape (k,).
        start_error: Distance from the end effector to the requested start when the run
            began, metres (more than a millimetre: the start was out of reach).
        start_orientation_error: Angle from the end effector to the requested start
            orientation when the run began, radians.
        reached: Whether the run stopped at the target (within the tolerance, and for a pose
            policy within the angle tolerance).
        final_error: Distance from the end effector to the target at the end, metres.
        final_orientation_error: Angle to the goal orientation at the end, radians.
        push_time: When the push happened, seconds (None without one).
        push_offset: The end effector's actual displacement by the push, metres (3,).
        recovery_time: Seconds from the push until the end effector is back on its path
            for good (:func:`snds.arrival.recovery_time`): within ``path_tolerance`` of the
            rest of the policy's own rollout from the same start without the push (from where
            the push took the tool, :func:`rest_of_path`); None without a push, or if it
            never is.
        path_tolerance: The distance to the path counted as on it, task units
            (:data:`snds.arrival.PATH_TOLERANCE` x the demonstrations' extent).
        off_path: The largest distance of the end effector from that path after the push,
            task units (None without a push).
        obstacle_clearance: Smallest distance of the tool point to an obstacle's physical
            shape (or a workspace wall) over the run, metres (None without obstacles).
        arm_obstacle_distance: Smallest distance of any link of the arm to an obstacle's
            collision body (PyBullet), metres (None without obstacle bodies).
        contact_steps: Control steps at which the arm touched an obstacle body.
    """

    config: SimConfig
    placement: Placement
    rotation: np.ndarray | None
    goal_orientation: np.ndarray
    times: np.ndarray
    positions: np.ndarray
    orientations: np.ndarray
    states: np.ndarray
    orientation_errors: np.ndarray
    joints: np.ndarray
    joint_lower: np.ndarray
    joint_upper: np.ndarray
    start_error: float
    start_orientation_error: float
    reached: bool
    final_error: float
    final_orientation_error: float
    push_time: float | None
    push_offset: np.ndarray | None
    recovery_time: float | None
    path_tolerance: float | None = None
    off_path: float | None = None
    obstacle_clearance: float | None = None
    arm_obstacle_distance: float | None = None
    contact_steps: int | None = None

    @property
    def drives_orientation(self) -> bool:
        """Whether the policy drove the orientation (a pose policy), or it was held."""
        return self.rotation is not None

    def to_dict(self) -> dict:
        """JSON-ready form: settings, then the paths and the summary numbers."""
        arrays = {
            "time": self.times,
            "end_effector_path": self.positions,
            "orientation_path": self.orientations,
            "orientation_error_path_rad": self.orientation_errors,
            "task_path": self.states,
            "joint_path": self.joints,
            "joint_lower": self.joint_lower,
            "joint_upper": self.joint_upper,
        }
        placement = {
            "origin": self.placement.origin.tolist(),
            "axes": self.placement.axes.tolist(),
            "scale_m_per_unit": self.placement.scale,
            "target": self.placement.target.tolist(),
            "rotation": None if self.rotation is None else self.rotation.tolist(),
        }
        return {
            "settings": self.config.to_dict(),
            "placement": placement,
            "drives_orientation": self.drives_orientation,
            "goal_orientation": self.goal_orientation.tolist(),
            "start_error_m": self.start_error,
            "start_orientation_error_rad": self.start_orientation_error,
            "reached": self.reached,
            "final_error_m": self.final_error,
            "final_orientation_error_rad": self.final_orientation_error,
            "duration_s": float(self.times[-1]),
            "push_time_s": self.push_time,
            "push_offset_m": None if self.push_offset is None else self.push_offset.tolist(),
            "recovery_time_s": self.recovery_time,
            "path_tolerance": self.path_tolerance,
            "off_path": self.off_path,
            "obstacle_clearance_m": self.obstacle_clearance,
            "arm_obstacle_distance_m": self.arm_obstacle_distance,
            "contact_steps": self.contact_steps,
            **{k: np.asarray(v).tolist() for k, v in arrays.items()},
        }


def default_scale(robot: Robot, policy: Policy) -> float:
    """Metres per user unit that fit a policy's demonstrations (their position extent) into
    the robot's reach."""
    return robot.reach / float(policy.extents()[0])


def simulate(policy: Policy, start: np.ndarray, config: SimConfig) -> SimResult:
    """Runs a policy on a simulated arm from a start state to its target.

    Arguments:
        policy: The policy (user units in and out): a 2-D or 3-D position policy, or an
            SE(3) :class:`~snds.se3.PosePolicy`.
        start: The start in user units: a position policy's state, shape (n,); a pose
            policy's position and unit quaternion (x, y, z, w), shape (7,).
        config: The settings.

    Returns:
        The run's record.
    """
    robot = get_robot(config.robot)
    policy = float64_copy(policy)
    dt = 1.0 / config.control_rate
    steps = int(np.ceil(config.time_limit * config.control_rate))
    with Arm(robot, physics_dt=dt / config.substeps, gravity=config.gravity) as arm:
        arm.reset(arm.rest)
        commander = make_commander(policy, robot, arm.end_effector().orientation, config)
        placement, goal = commander.placement, commander.goal_orientation
        start_position, start_orientation = commander.start_pose(start)
        bodies = []
        if config.obstacles is not None:
            bodies = arm.add_obstacles(world_shapes(config.obstacles, placement))
        contacts, arm_distance = 0, np.inf
        start_error = arm.move_to(start_position, start_orientation)
        start_angle = _angle(arm.end_effector().orientation, start_orientation)
        # The motors track an integrated reference, not "measured + one step": a reference
        # ahead of a sagging arm keeps pushing, so gravity leaves no steady-state offset.
        reference = arm.joint_positions()
        times, positions, orientations, joints = [], [], [], []
        push_time = push_offset = None
        for step in range(steps + 1):
            if config.push is not None and step == config.push.step:
                before = arm.end_effector()
                arm.move_to(
                    before.position + np.asarray(config.push.displacement), before.orientation
                )
                push_offset = arm.end_effector().position - before.position
                push_time = step * dt
                reference = arm.joint_positions()
            pose = arm.end_effector()
            q = arm.joint_positions()
            times.append(step * dt)
            positions.append(pose.position)
            orientations.append(pose.orientation)
            joints.append(q)
            pushed = config.push is None or step >= config.push.step
            distance = float(np.linalg.norm(pose.position - placement.origin))
            arrived = commander.arrived(distance, _angle(pose.orientation, goal))
            if (arrived and pushed) or step == steps:
                break
            qdot = _controller(arm, commander.twist(pose), q, 1.0 / config.control_rate)
            reference = np.clip(reference + dt * qdot, arm.lower, arm.upper)
            arm.command(reference, qdot)
            arm.step(config.substeps)
            if bodies:
                touching, nearest = arm.contact(bodies)
                contacts += int(touching)
                arm_distance = min(arm_distance, nearest)
        positions_ = np.array(positions)
        orientations_ = np.array(orientations)
        angles = np.array([_angle(o, goal) for o in orientations_])
        distance = float(np.linalg.norm(positions_[-1] - placement.origin))
        result_states = np.array([placement.to_task(p) for p in positions_])
        return SimResult(
            config=config,
            placement=placement,
            rotation=commander.rotation,
            goal_orientation=np.asarray(goal, dtype=float),
            times=np.array(times),
            positions=positions_,
            orientations=orientations_,
            states=result_states,
            orientation_errors=angles,
            joints=np.array(joints),
            joint_lower=arm.lower.copy(),
            joint_upper=arm.upper.copy(),
            start_error=float(start_error),
            start_orientation_error=start_angle,
            reached=commander.arrived(distance, float(angles[-1])),
            final_error=distance,
            final_orientation_error=float(angles[-1]),
            push_time=push_time,
            push_offset=push_offset,
            **_recovery(policy, start, result_states, np.array(times), push_time, dt),
            **_obstacle_record(config, placement, positions_, bodies, contacts, arm_distance),
        )


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


def _obstacle_record(
    config: SimConfig,
    placement: Placement,
    positions: np.ndarray,
    bodies: list[int],
    contacts: int,
    arm_distance: float,
) -> dict:
    """The run's clearances from its obstacles (the fields of :class:`SimResult`)."""
    if config.obstacles is None:
        return {}
    states = torch.as_tensor(np.array([placement.to_task(p) for p in positions]))
    clearance = float(config.obstacles.clearances(states).min()) * placement.scale
    return {
        "obstacle_clearance": clearance,
        "arm_obstacle_distance": float(arm_distance) if bodies else None,
        "contact_steps": contacts if bodies else None,
    }


def _angle(current: np.ndarray, wanted: np.ndarray) -> float:
    """Angle (radians, [0, pi]) of the rotation from one orientation to another."""
    return float(np.linalg.norm(orientation_error(current, wanted)))


#: Joints are not commanded closer than this to their position limits (radians).
LIMIT_MARGIN = 1e-3


def _controller(arm: Arm, twist: np.ndarray, q: np.ndarray, dt: float) -> np.ndarray:
    """The joint velocities of a twist (:func:`~snds.sim.arm.joint_velocity`), each clipped so
    that holding it for one period dt does not move its joint past its position limit (less
    :data:`LIMIT_MARGIN`); a joint already there may only move back."""
    qdot = joint_velocity(arm.jacobian(), twist, q, rest=arm.rest, max_speed=arm.max_speed)
    low = np.minimum((arm.lower + LIMIT_MARGIN - q) / dt, 0.0)
    high = np.maximum((arm.upper - LIMIT_MARGIN - q) / dt, 0.0)
    return np.clip(qdot, low, high)


def _recovery(
    policy: Policy,
    start: np.ndarray,
    states: np.ndarray,
    times: np.ndarray,
    push_time: float | None,
    dt: float,
) -> dict:
    """The recovery after a push (the fields of :class:`SimResult`): the time until the
    measured path (task positions, (T, n)) is back on the rest of the path the policy takes
    from the same start without the push (:func:`rest_of_path`), within
    :data:`~snds.arrival.PATH_TOLERANCE` of the extent."""
    if push_time is None:
        return {"recovery_time": None}
    tolerance = PATH_TOLERANCE * float(policy.extents()[0])
    after = times >= push_time
    path = rest_of_path(
        unpushed_path(policy, start, dt=dt, steps=len(times) - 1), states[~after][-1]
    )
    return {
        "recovery_time": recovery_time(
            times, states, path, push_time=push_time, tolerance=tolerance
        ),
        "path_tolerance": tolerance,
        "off_path": float(distance_to_path(states[after], path).max()) if after.any() else 0.0,
    }


def rest_of_path(path: np.ndarray, position: np.ndarray) -> np.ndarray:
    """The part of a path (S, n) from its sample nearest to ``position`` (n,) on: where the
    motion was when it was pushed, so that coming back near a part already passed (a loop, an
    earlier leg) is not counted as being back on the path."""
    return path[int(np.linalg.norm(path - position, axis=-1).argmin()) :]


@torch.no_grad()
def unpushed_path(policy: Policy, start: np.ndarray, *, dt: float, steps: int) -> np.ndarray:
    """The positions (T, n) of the policy's own rollout from a start, as the commander drives
    it without a push: each step the velocity :func:`~snds.rollout.safe_velocity` gives for a
    period dt, at most ``steps`` steps, stopping within 1e-4 of the extent of the target."""
    space = policy.space
    target = torch.as_tensor(space.positions(policy.target))
    close = 1e-4 * float(policy.extents()[0])

    def near(x: torch.Tensor) -> torch.Tensor:
        position = x[:, : space.position_dim]
        return ~torch.isfinite(position).all(dim=-1) | ((position - target).norm(dim=-1) <= close)

    x = torch.tensor(np.asarray(start, dtype=np.float64))[None]
    result = rollout(policy, x, dt=dt, steps=steps, stepper=GuardedEuler(), until=near)
    return space.positions(result.states[:, 0].numpy())
