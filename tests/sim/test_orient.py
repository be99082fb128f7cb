"""Turning a pose task's orientations so that an arm can follow it (snds.sim.orient)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

pytest.importorskip("pybullet", reason="the simulation tests need the sim extra")

from snds.sim.arm import Arm  # noqa: E402
from snds.sim.orient import (  # noqa: E402
    CANDIDATE_ANGLES,
    KEEP_MARGIN,
    candidate_turns,
    choose_rotation,
    path_fit,
)
from snds.sim.placement import PosePlacement  # noqa: E402
from snds.sim.robots import get_robot  # noqa: E402

TOLERANCES = {"tolerance": 1e-3, "angle_tolerance": 0.02}


def _turning_path(axis: np.ndarray, angle: float) -> np.ndarray:
    """20 task poses (x, y, z, quaternion) moving 0.2 along x while the orientation turns by
    ``angle`` about ``axis`` back to the identity, the target orientation."""
    angles = np.linspace(angle, 0.0, 20)
    return np.array(
        [
            np.concatenate([[0.2 * a / angle, 0.1, 0.0], Rotation.from_rotvec(a * axis).as_quat()])
            for a in angles
        ]
    )


@pytest.fixture(scope="module")
def panda():
    with Arm(get_robot("panda"), gravity=False) as arm:
        arm.reset(arm.rest)
        rest = arm.end_effector().orientation
        placement = PosePlacement.for_task(
            arm.robot, np.zeros(3), np.array([0, 0, 0, 1.0]), 0.5, rest
        )
        yield arm, placement


def test_candidates_are_the_identity_then_turns_about_six_axes():
    turns = candidate_turns()
    assert len(turns) == 1 + 6 * len(CANDIDATE_ANGLES)
    assert np.allclose(turns[0].as_rotvec(), 0.0)
    angles = sorted(np.linalg.norm(t.as_rotvec()) for t in turns[1:])
    assert np.allclose(angles, sorted(CANDIDATE_ANGLES * 6))


def test_a_path_the_default_fits_keeps_the_default(panda):
    arm, placement = panda
    path = _turning_path(np.array([1.0, 0.0, 0.0]), 2.0)
    chosen, fit = choose_rotation(arm, placement, path, **TOLERANCES)
    assert chosen is placement
    assert fit.followed and fit.margin >= KEEP_MARGIN
    # AND the arm is left at rest
    np.testing.assert_allclose(arm.joint_positions(), arm.rest, atol=1e-9)


def test_a_path_beyond_the_joint_limits_is_turned_until_the_arm_follows_it(panda):
    # GIVEN a path the Panda cannot follow with the target orientation at its rest one: the
    # orientation turns 2 rad about y on the way
    arm, placement = panda
    path = _turning_path(np.array([0.0, 1.0, 0.0]), 2.0)
    default = path_fit(arm, placement, path, **TOLERANCES)
    assert not default.followed and default.error > 0.1
    # THEN a turned placement is followed, every pose within the tolerances, with room left
    chosen, fit = choose_rotation(arm, placement, path, **TOLERANCES)
    assert chosen is not placement and fit.followed
    assert fit.error <= 1e-3 and fit.angle <= 0.02 and fit.margin >= KEEP_MARGIN
    assert fit == path_fit(arm, chosen, path, **TOLERANCES)
    # AND only the orientations turned, by one of the candidate turns: the positions stay
    assert chosen.positions is placement.positions
    turn = Rotation.from_quat(chosen.rotation) * Rotation.from_quat(placement.rotation).inv()
    assert np.linalg.norm(turn.as_rotvec()) == pytest.approx(
        min(CANDIDATE_ANGLES, key=lambda a: abs(a - np.linalg.norm(turn.as_rotvec())))
    )
