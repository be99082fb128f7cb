"""How to turn a pose task in the world so that an arm can follow it: a search over the
rotation of its orientations (:func:`choose_rotation`).

A pose task's orientations are placed by one fixed rotation :math:`R` (:class:`~snds.sim.
placement.PosePlacement`): by default the one that puts the target orientation at the arm's
orientation at rest. A task whose orientations turn far from the target's (pouring, placing a
bottle on a shelf) can then ask for joint angles beyond an arm's limits on the way, and the
arm stalls there. Which turn of the task fits depends on the arm: the same recording fits an
iiwa one way and a Panda another.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from snds.sim.arm import Arm, orientation_angle
from snds.sim.placement import PosePlacement

__all__ = ["CANDIDATE_ANGLES", "PathFit", "candidate_turns", "choose_rotation", "path_fit"]

#: Angles (radians) of the turns tried about each of the six world axis directions.
CANDIDATE_ANGLES = (0.5, 1.0, 1.5)

#: The default placement is kept while every joint stays at least this far (radians) from its
#: limits along the path.
KEEP_MARGIN = 0.1


@dataclass(frozen=True)
class PathFit:
    """How well an arm follows a sequence of poses, each reached from the last without
    physics (:meth:`~snds.sim.arm.Arm.move_to`).

    Attributes:
        error: The largest position error left at a pose, metres.
        angle: The largest orientation error left at a pose, radians.
        margin: The smallest distance of a joint from its limits along the path, radians.
        followed: Whether every pose was reached within the tolerances.
    """

    error: float
    angle: float
    margin: float
    followed: bool


def candidate_turns() -> list[Rotation]:
    """The identity, then turns of each of :data:`CANDIDATE_ANGLES` about +x, +y, +z, -x, -y
    and -z of the world, in that order."""
    axes = np.vstack([np.eye(3), -np.eye(3)])
    return [Rotation.identity()] + [
        Rotation.from_rotvec(angle * axis) for axis in axes for angle in CANDIDATE_ANGLES
    ]


def path_fit(
    arm: Arm,
    placement: PosePlacement,
    poses: np.ndarray,
    *,
    tolerance: float,
    angle_tolerance: float,
) -> PathFit:
    """Follows task poses (B, 7: position, unit quaternion (x, y, z, w)) from the arm's rest
    posture through a placement; stops at the first pose it cannot reach. The arm is left at
    rest."""
    arm.reset(arm.rest)
    error = angle = 0.0
    margin = np.inf
    followed = True
    for pose in poses:
        position, orientation = placement.to_world(pose[:3], pose[3:7])
        error = max(error, arm.move_to(position, orientation))
        angle = max(angle, orientation_angle(arm.end_effector().orientation, orientation))
        q = arm.joint_positions()
        margin = min(margin, float(np.min(np.minimum(q - arm.lower, arm.upper - q))))
        if error > tolerance or angle > angle_tolerance:
            followed = False
            break
    arm.reset(arm.rest)
    return PathFit(error, angle, margin, followed)


def choose_rotation(
    arm: Arm,
    placement: PosePlacement,
    poses: np.ndarray,
    *,
    tolerance: float,
    angle_tolerance: float,
) -> tuple[PosePlacement, PathFit]:
    """The placement whose orientations the arm follows along ``poses`` with the most room.

    The given placement is kept when the arm follows the poses with every joint at least
    :data:`KEEP_MARGIN` from its limits. Otherwise each turn of :func:`candidate_turns` is
    applied on the left of its rotation, :math:`R' = T R`, and the one followed with the
    largest joint margin is taken (the smallest position error if none is followed). A turn of
    every orientation by one rotation keeps the task's flow exact (see
    :class:`~snds.sim.placement.PosePlacement`); the positions are not moved.

    Arguments:
        arm: The arm, at rest; left at rest.
        placement: The default placement.
        poses: Task poses along the path to follow, (B, 7).
        tolerance: Position error (metres) counted as reached.
        angle_tolerance: Orientation error (radians) counted as reached.

    Returns:
        The chosen placement and how the arm followed the path through it.
    """
    options = {"tolerance": tolerance, "angle_tolerance": angle_tolerance}
    kept = path_fit(arm, placement, poses, **options)
    if kept.followed and kept.margin >= KEEP_MARGIN:
        return placement, kept
    best, best_fit = placement, kept
    rotation = Rotation.from_quat(placement.rotation)
    for turn in candidate_turns()[1:]:
        turned = PosePlacement(placement.positions, (turn * rotation).as_quat())
        fit = path_fit(arm, turned, poses, **options)
        if _better(fit, best_fit):
            best, best_fit = turned, fit
    return best, best_fit


def _better(fit: PathFit, than: PathFit) -> bool:
    if fit.followed != than.followed:
        return fit.followed
    if fit.followed:
        return fit.margin > than.margin
    return fit.error < than.error
