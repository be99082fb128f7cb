r"""The simulate loop: a policy drives a simulated arm's end effector to its target.

At a fixed control rate the loop measures the end effector, asks a
:class:`~snds.sim.commanders.Commander` for the twist (linear and angular velocity, world
frame) the policy commands at that pose, and hands it to the task-space controller
(:func:`~snds.sim.arm.joint_velocity`), whose joint targets the motors track while the
physics runs. A push teleports the end effector mid-motion; the run stops when the end
effector has arrived at the target (after any push) or at a time limit.

The loop's parts live in their own modules: the settings (:mod:`snds.sim.config`), where the
task lies in the world (:mod:`snds.sim.placement`), what each kind of policy commands
(:mod:`snds.sim.commanders`), the record (:mod:`snds.sim.result`) and the recovery after a
push (:mod:`snds.sim.recovery`). Their names stay importable from here.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from snds.policy import Policy, float64_copy
from snds.sim.arm import Arm, joint_velocity, orientation_angle
from snds.sim.commanders import (
    COMMANDERS,
    PHASED_COMMANDERS,
    Commander,
    PhasedCommander,
    PhasedPoseCommander,
    PoseCommander,
    PositionCommander,
    make_commander,
)
from snds.sim.config import Push, SimConfig
from snds.sim.placement import Placement, PosePlacement, default_scale, world_shapes
from snds.sim.recovery import push_recovery, rest_of_path, unpushed_path
from snds.sim.result import SimResult
from snds.sim.robots import get_robot

__all__ = [
    "LIMIT_MARGIN",
    "simulate",
    # Defined in the modules above; importable from here as they were before the split.
    "COMMANDERS",
    "PHASED_COMMANDERS",
    "Commander",
    "Placement",
    "PhasedCommander",
    "PhasedPoseCommander",
    "PoseCommander",
    "PosePlacement",
    "PositionCommander",
    "Push",
    "SimConfig",
    "SimResult",
    "default_scale",
    "make_commander",
    "rest_of_path",
    "unpushed_path",
    "world_shapes",
]


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
        default = commander.rotation
        if config.fit_orientation:
            commander = commander.fit_to(arm, start)
        placement, goal = commander.placement, commander.goal_orientation
        start_position, start_orientation = commander.start_pose(start)
        bodies = []
        if config.obstacles is not None:
            bodies = arm.add_obstacles(world_shapes(config.obstacles, placement))
        contacts, arm_distance = 0, np.inf
        start_error = arm.move_to(start_position, start_orientation)
        start_angle = orientation_angle(arm.end_effector().orientation, start_orientation)
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
            arrived = commander.arrived(distance, orientation_angle(pose.orientation, goal))
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
        angles = np.array([orientation_angle(o, goal) for o in orientations_])
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
            orientation_turn=_turn(default, commander.rotation),
            **push_recovery(policy, start, result_states, np.array(times), push_time, dt),
            **_obstacle_record(config, placement, positions_, bodies, contacts, arm_distance),
        )


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


def _turn(default: np.ndarray | None, chosen: np.ndarray | None) -> np.ndarray | None:
    """The rotation vector (3,) from a pose task's default rotation to the chosen one."""
    if default is None or chosen is None:
        return None
    return (Rotation.from_quat(chosen) * Rotation.from_quat(default).inv()).as_rotvec()


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
