"""What a simulated run did (:class:`SimResult`), and its JSON form (``sim.json``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from snds.sim.config import SimConfig
from snds.sim.placement import Placement

__all__ = ["SimResult"]


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
            the push took the tool, :func:`~snds.sim.recovery.rest_of_path`); None without a
            push, or if it never is.
        path_tolerance: The distance to the path counted as on it, task units
            (:data:`snds.arrival.PATH_TOLERANCE` x the demonstrations' extent).
        off_path: The largest distance of the end effector from that path after the push,
            task units (None without a push).
        obstacle_clearance: Smallest distance of the tool point to an obstacle's physical
            shape (or a workspace wall) over the run, metres (None without obstacles).
        arm_obstacle_distance: Smallest distance of any link of the arm to an obstacle's
            collision body (PyBullet), metres (None without obstacle bodies).
        contact_steps: Control steps at which the arm touched an obstacle body.
        orientation_turn: For a pose policy, the turn (rotation vector, radians, world frame,
            shape (3,)) applied to the default placement of its orientations so that the arm
            follows the path within its joint limits (``SimConfig.fit_orientation``); zeros
            when the default fitted (None for a position policy).
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
    orientation_turn: np.ndarray | None = None

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
            "orientation_turn_rad": (
                None if self.orientation_turn is None else self.orientation_turn.tolist()
            ),
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
