r"""The simulate loop: a policy drives a simulated arm's end effector to its target.

At a fixed control rate the loop measures the end effector, maps its position into the
task's coordinates (:class:`Placement`), asks the policy for a velocity, maps it back into
the world and hands it, with an orientation hold, to the task-space controller
(:func:`~snds.sim.arm.joint_velocity`), whose joint targets the motors track while the
physics runs. A push teleports the end effector mid-motion; the run stops when the end
effector is within a tolerance of the target (after any push) or at a time limit.

The state the policy sees is built in one place (:meth:`Placement.to_task`), so an SE(3)
policy (position and rotation vector) plugs in there and in :meth:`Placement.to_world`:
today the policies are position-only and the orientation is held at the start's.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from snds.policy import Policy, float64_copy
from snds.sim.arm import Arm, joint_velocity, orientation_error
from snds.sim.robots import Robot, SimulationError, get_robot


@dataclass(frozen=True, kw_only=True)
class Push:
    """A displacement of the end effector at one control step.

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
        scale: Metres per user unit of the task (None: fit the demonstrations' extent into
            the robot's reach).
        control_rate: Control loop frequency, Hz.
        substeps: Physics steps per control step.
        time_limit: Longest simulated time, seconds.
        tolerance: Distance to the target (metres) at which the run stops.
        push: An optional push.
        hold_gain: Gain (1/s) of the holds on what the policy does not drive: the
            orientation, and for a 2-D task the distance off the work plane.
        gravity: Whether gravity acts on the arm.
    """

    robot: str = "iiwa"
    scale: float | None = None
    control_rate: float = 100.0
    substeps: int = 4
    time_limit: float = 30.0
    tolerance: float = 0.001
    push: Push | None = None
    hold_gain: float = 5.0
    gravity: bool = True

    def __post_init__(self) -> None:
        if self.scale is not None and not self.scale > 0:
            raise SimulationError(f"the scale must be positive, got {self.scale}")
        if not (self.control_rate > 0 and self.substeps >= 1 and self.time_limit > 0):
            raise SimulationError("control rate, substeps and time limit must be positive")
        if not self.tolerance > 0:
            raise SimulationError(f"the tolerance must be positive, got {self.tolerance}")

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
class SimResult:
    """What a simulated run did.

    Attributes:
        config: The settings.
        placement: Where the task was in the world.
        times: Time of each control step, seconds, shape (T,).
        positions: Measured end-effector positions, metres, shape (T, 3).
        states: The same in the task's user units, shape (T, n).
        joints: Controlled joint positions, radians, shape (T, k).
        joint_lower: Lower joint limits, shape (k,).
        joint_upper: Upper joint limits, shape (k,).
        start_error: Distance from the end effector to the requested start when the run
            began, metres (more than a millimetre: the start was out of reach).
        reached: Whether the run stopped within the tolerance of the target.
        final_error: Distance from the end effector to the target at the end, metres.
        push_time: When the push happened, seconds (None without one).
        push_offset: The end effector's actual displacement by the push, metres (3,).
        recovery_time: Seconds from the push until the end effector is again as close to
            the target as it was just before the push (0 for a push towards the target);
            None without a push, or if it never is.
    """

    config: SimConfig
    placement: Placement
    times: np.ndarray
    positions: np.ndarray
    states: np.ndarray
    joints: np.ndarray
    joint_lower: np.ndarray
    joint_upper: np.ndarray
    start_error: float
    reached: bool
    final_error: float
    push_time: float | None
    push_offset: np.ndarray | None
    recovery_time: float | None

    def to_dict(self) -> dict:
        """JSON-ready form: settings, then the paths and the summary numbers."""
        arrays = {
            "time": self.times,
            "end_effector_path": self.positions,
            "task_path": self.states,
            "joint_path": self.joints,
            "joint_lower": self.joint_lower,
            "joint_upper": self.joint_upper,
        }
        return {
            "settings": self.config.to_dict(),
            "placement": {
                "origin": self.placement.origin.tolist(),
                "axes": self.placement.axes.tolist(),
                "scale_m_per_unit": self.placement.scale,
                "target": self.placement.target.tolist(),
            },
            "start_error_m": self.start_error,
            "reached": self.reached,
            "final_error_m": self.final_error,
            "duration_s": float(self.times[-1]),
            "push_time_s": self.push_time,
            "push_offset_m": None if self.push_offset is None else self.push_offset.tolist(),
            "recovery_time_s": self.recovery_time,
            **{k: np.asarray(v).tolist() for k, v in arrays.items()},
        }


def default_scale(robot: Robot, policy: Policy) -> float:
    """Metres per user unit that fit the demonstrations' extent into the robot's reach."""
    return robot.reach / float(policy.normalization.length)


def simulate(policy: Policy, start: np.ndarray, config: SimConfig) -> SimResult:
    """Runs a policy on a simulated arm from a start state to its target.

    Arguments:
        policy: The policy (user units in and out; positions 2-D or 3-D).
        start: The start state in user units, shape (n,).
        config: The settings.

    Returns:
        The run's record.
    """
    robot = get_robot(config.robot)
    policy = float64_copy(policy)
    target = np.asarray(policy.normalization.center, dtype=float)
    start = np.asarray(start, dtype=float)
    if start.shape != target.shape:
        raise SimulationError(
            f"the start has shape {start.shape}, the model's states {target.shape}"
        )
    scale = config.scale if config.scale is not None else default_scale(robot, policy)
    placement = Placement.for_task(robot, target, scale)
    dt = 1.0 / config.control_rate
    steps = int(np.ceil(config.time_limit * config.control_rate))
    with Arm(robot, physics_dt=dt / config.substeps, gravity=config.gravity) as arm:
        arm.reset(arm.rest)
        hold = arm.end_effector().orientation
        start_error = arm.move_to(placement.to_world(start), hold)
        # The motors track an integrated reference, not "measured + one step": a reference
        # ahead of a sagging arm keeps pushing, so gravity leaves no steady-state offset.
        reference = arm.joint_positions()
        times, positions, joints = [], [], []
        push_time = push_offset = None
        for step in range(steps + 1):
            if config.push is not None and step == config.push.step:
                before = arm.end_effector().position
                arm.move_to(before + np.asarray(config.push.displacement), hold)
                push_offset = arm.end_effector().position - before
                push_time = step * dt
                reference = arm.joint_positions()
            pose = arm.end_effector()
            q = arm.joint_positions()
            times.append(step * dt)
            positions.append(pose.position)
            joints.append(q)
            pushed = config.push is None or step >= config.push.step
            arrived = np.linalg.norm(pose.position - placement.origin) <= config.tolerance
            if (arrived and pushed) or step == steps:
                break
            state = placement.to_task(pose.position)
            with torch.no_grad():
                velocity = policy(torch.as_tensor(state)[None])[0].numpy()
            twist = np.concatenate(
                [
                    placement.velocity_to_world(velocity)
                    - config.hold_gain * placement.off_task(pose.position),
                    config.hold_gain * orientation_error(pose.orientation, hold),
                ]
            )
            qdot = _controller(arm, twist, q)
            reference = np.clip(reference + dt * qdot, arm.lower, arm.upper)
            arm.command(reference, qdot)
            arm.step(config.substeps)
        positions_ = np.array(positions)
        states = np.array([placement.to_task(p) for p in positions_])
        final_error = float(np.linalg.norm(positions_[-1] - placement.origin))
        return SimResult(
            config=config,
            placement=placement,
            times=np.array(times),
            positions=positions_,
            states=states,
            joints=np.array(joints),
            joint_lower=arm.lower.copy(),
            joint_upper=arm.upper.copy(),
            start_error=float(start_error),
            reached=final_error <= config.tolerance,
            final_error=final_error,
            push_time=push_time,
            push_offset=push_offset,
            recovery_time=_recovery_time(positions_, placement.origin, np.array(times), push_time),
        )


def _controller(arm: Arm, twist: np.ndarray, q: np.ndarray) -> np.ndarray:
    return joint_velocity(arm.jacobian(), twist, q, rest=arm.rest, max_speed=arm.max_speed)


def _recovery_time(
    positions: np.ndarray, origin: np.ndarray, times: np.ndarray, push_time: float | None
) -> float | None:
    """Seconds from the push until the distance to the target is back to its pre-push value."""
    if push_time is None:
        return None
    index = int(np.searchsorted(times, push_time))
    if index == 0 or index >= len(times):
        return None
    distance = np.linalg.norm(positions - origin, axis=1)
    back = np.nonzero(distance[index:] <= distance[index - 1])[0]
    return float(times[index + back[0]] - push_time) if back.size else None
