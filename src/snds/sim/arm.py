r"""A PyBullet arm driven in task space: end-effector velocities in, joint commands out.

:func:`joint_velocity` is the controller (damped least squares with a null-space posture
term and the joint speed limits); :class:`Arm` wraps one headless PyBullet world
(``p.DIRECT``) with one fixed-base robot in it: measuring the end effector, its Jacobian,
sending joint position targets to the motors, stepping the physics and rendering frames
with the TinyRenderer, which needs no display.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from snds.errors import SimulationError
from snds.sim.robots import Robot

__all__ = ["Arm", "EndEffector", "joint_velocity", "orientation_angle", "orientation_error"]


def joint_velocity(
    jacobian: np.ndarray,
    twist: np.ndarray,
    q: np.ndarray,
    *,
    rest: np.ndarray,
    max_speed: np.ndarray,
    damping: float = 0.05,
    posture_gain: float = 1.0,
) -> np.ndarray:
    r"""Joint velocities that produce an end-effector twist: damped least squares.

    .. math:: \dot q = J^\top (J J^\top + \lambda^2 I)^{-1} \xi
              + (I - J^+ J)\, k (q_\text{rest} - q)

    The damping :math:`\lambda` keeps the solution bounded near singularities; the second
    term pulls the redundant joints towards the rest posture without moving the end
    effector. The result is scaled down as a whole (so the twist keeps its direction)
    when a joint would exceed its speed limit.

    Arguments:
        jacobian: The end effector's Jacobian, shape (m, k): m = 3 (position) or 6 (position
            and orientation) rows, k controlled joints.
        twist: The wanted velocity (linear, then angular), shape (m,).
        q: Joint positions, shape (k,).
        rest: The rest posture, shape (k,).
        max_speed: Joint speed limits, shape (k,).
        damping: :math:`\lambda` (metres per second per radian per second).
        posture_gain: k (1/s).

    Returns:
        Joint velocities, shape (k,).
    """
    m = jacobian.shape[0]
    gram = jacobian @ jacobian.T + damping**2 * np.eye(m)
    damped = jacobian.T @ np.linalg.solve(gram, np.eye(m))
    # The exact projector onto the null space: one built from the damped inverse leaks the
    # posture term into the end effector's motion.
    null = np.eye(q.size) - np.linalg.pinv(jacobian, rcond=1e-6) @ jacobian
    qdot = damped @ twist + null @ (posture_gain * (rest - q))
    excess = np.max(np.abs(qdot) / max_speed)
    return qdot / excess if excess > 1.0 else qdot


def orientation_error(current: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """The rotation vector (axis times angle, world frame) from ``current`` to ``wanted``.

    Arguments:
        current: A quaternion (x, y, z, w), PyBullet's order.
        wanted: A quaternion (x, y, z, w).
    """
    return (Rotation.from_quat(wanted) * Rotation.from_quat(current).inv()).as_rotvec()


def orientation_angle(current: np.ndarray, wanted: np.ndarray) -> float:
    """Angle (radians, [0, pi]) of the rotation from one orientation (x, y, z, w) to another."""
    return float(np.linalg.norm(orientation_error(current, wanted)))


@dataclass(frozen=True)
class EndEffector:
    """A measured end-effector pose: the state the policy sees.

    Attributes:
        position: World position of the tool point (see :attr:`Robot.tool`), metres, (3,).
        orientation: Its orientation, quaternion (x, y, z, w), shape (4,).
    """

    position: np.ndarray
    orientation: np.ndarray


@contextlib.contextmanager
def _quiet_output() -> Iterator[None]:
    # PyBullet prints its build time (stderr) and argv (stdout) from C on import and
    # connect; keep a command's output to what it means to say.
    streams = [sys.stdout, sys.stderr]
    try:
        fds = [stream.fileno() for stream in streams]
    except (AttributeError, OSError, ValueError):
        yield
        return
    for stream in streams:
        stream.flush()
    saved = [os.dup(fd) for fd in fds]
    with open(os.devnull, "w") as null:
        for fd in fds:
            os.dup2(null.fileno(), fd)
        try:
            yield
        finally:
            # C's stdio may still buffer what PyBullet printed: flush it into /dev/null, not
            # later into the restored streams.
            with contextlib.suppress(OSError, AttributeError):
                ctypes.CDLL(None).fflush(None)
            for fd, copy in zip(fds, saved):
                os.dup2(copy, fd)
                os.close(copy)


def _pybullet():
    try:
        with _quiet_output():
            import pybullet
            from pybullet_utils import bullet_client
    except ImportError as error:
        raise SimulationError("simulation needs PyBullet: pip install 'snds[sim]'") from error
    return pybullet, bullet_client


class Arm:
    """One robot in its own headless PyBullet world.

    Arguments:
        robot: Which arm, and where.
        physics_dt: The physics time step, seconds.
        gravity: Whether gravity acts (the motors hold the arm against it).
    """

    def __init__(self, robot: Robot, *, physics_dt: float = 1.0 / 400.0, gravity: bool = True):
        pb, bullet_client = _pybullet()
        self._pb = pb
        self.robot = robot
        with _quiet_output():
            self.client = bullet_client.BulletClient(connection_mode=pb.DIRECT)
        self.client.setTimeStep(physics_dt)
        self.client.setGravity(0.0, 0.0, -9.81 if gravity else 0.0)
        with tempfile.TemporaryDirectory(prefix="snds-urdf-") as scratch:
            urdf = robot.urdf_path(Path(scratch))
            if not urdf.is_file():
                raise SimulationError(f"{urdf}: robot model missing")
            self.body = self.client.loadURDF(
                str(urdf), useFixedBase=True, flags=pb.URDF_USE_INERTIA_FROM_FILE
            )
        self._read_joints()

    def _read_joints(self) -> None:
        c, pb = self.client, self._pb
        movable, links = [], {}
        for j in range(c.getNumJoints(self.body)):
            info = c.getJointInfo(self.body, j)
            links[info[12].decode()] = j
            if info[2] != pb.JOINT_FIXED:
                movable.append(j)
        if self.robot.end_effector not in links:
            raise SimulationError(
                f"{self.robot.name}: no link {self.robot.end_effector!r} in its model"
            )
        k = len(self.robot.rest_pose)
        if len(movable) < k:
            raise SimulationError(
                f"{self.robot.name}: the rest pose has {k} joints, the model {len(movable)}"
            )
        #: PyBullet indices of the movable joints; the first k are controlled, the rest
        #: (fingers) are held where they are.
        self.movable = movable
        self.joints = movable[:k]
        self.end_effector_link = links[self.robot.end_effector]
        infos = [c.getJointInfo(self.body, j) for j in self.joints]
        self.lower = np.array([i[8] for i in infos])
        self.upper = np.array([i[9] for i in infos])
        self.max_speed = np.array([i[11] if i[11] > 0 else 1.0 for i in infos])
        self.max_force = np.array([i[10] if i[10] > 0 else 100.0 for i in infos])
        rest = np.asarray(self.robot.rest_pose, dtype=float)
        if np.any(rest < self.lower) or np.any(rest > self.upper):
            raise SimulationError(f"{self.robot.name}: the rest pose is outside the joint limits")
        self.rest = rest

    def reset(self, q: np.ndarray) -> None:
        """Puts the controlled joints at ``q`` at rest (a teleport, no physics)."""
        for j, value in zip(self.joints, q):
            self.client.resetJointState(self.body, j, float(value), 0.0)
        self.command(np.asarray(q, dtype=float), np.zeros(len(self.joints)))

    def joint_positions(self) -> np.ndarray:
        """Positions of the controlled joints, shape (k,)."""
        return np.array([s[0] for s in self.client.getJointStates(self.body, self.joints)])

    def end_effector(self) -> EndEffector:
        """The measured end-effector pose."""
        state = self.client.getLinkState(
            self.body, self.end_effector_link, computeForwardKinematics=True
        )
        return EndEffector(self._tool_point(state), np.array(state[5]))

    def _tool_point(self, state: tuple) -> np.ndarray:
        rotation = np.array(self.client.getMatrixFromQuaternion(state[5])).reshape(3, 3)
        return np.array(state[4]) + rotation @ np.asarray(self.robot.tool, dtype=float)

    def jacobian(self) -> np.ndarray:
        """The tool point's Jacobian at the current joints, shape (6, k): linear, angular."""
        c = self.client
        state = c.getLinkState(self.body, self.end_effector_link, computeForwardKinematics=True)
        # PyBullet takes the point in the link's centre-of-mass frame, not the link frame.
        com_rotation = np.array(c.getMatrixFromQuaternion(state[1])).reshape(3, 3)
        local = com_rotation.T @ (self._tool_point(state) - np.array(state[0]))
        positions = [s[0] for s in c.getJointStates(self.body, self.movable)]
        zeros = [0.0] * len(self.movable)
        linear, angular = c.calculateJacobian(
            self.body, self.end_effector_link, local.tolist(), positions, zeros, zeros
        )
        full = np.vstack([np.array(linear), np.array(angular)])
        return full[:, : len(self.joints)]

    def command(self, q_target: np.ndarray, qdot_target: np.ndarray) -> None:
        """Sends joint position (and feed-forward velocity) targets to the motors."""
        self.client.setJointMotorControlArray(
            self.body,
            self.joints,
            self._pb.POSITION_CONTROL,
            targetPositions=q_target.tolist(),
            targetVelocities=qdot_target.tolist(),
            forces=self.max_force.tolist(),
            positionGains=[0.3] * len(self.joints),
            velocityGains=[1.0] * len(self.joints),
        )

    def step(self, count: int = 1) -> None:
        """Advances the physics by ``count`` time steps."""
        for _ in range(count):
            self.client.stepSimulation()

    def move_to(
        self,
        position: np.ndarray,
        orientation: np.ndarray,
        *,
        tolerance: float = 1e-5,
        angle_tolerance: float = 1e-4,
    ) -> float:
        """Places the end effector at a pose by resolved-rate steps without physics.

        Used to set up a start and to apply a displacement; joints stay within their limits.

        Arguments:
            position: World position of the tool point, shape (3,).
            orientation: Its orientation, quaternion (x, y, z, w), shape (4,).
            tolerance: Distance (metres) counted as there.
            angle_tolerance: Angle (radians) counted as there: a pose policy's start
                orientation is a state like its position, not only a hold.

        Returns:
            The remaining position error, metres.
        """
        q = self.joint_positions()
        error = np.inf
        for _ in range(500):
            pose = self.end_effector()
            offset = position - pose.position
            turn = orientation_error(pose.orientation, orientation)
            error = float(np.linalg.norm(offset))
            if error <= tolerance and np.linalg.norm(turn) <= angle_tolerance:
                break
            twist = np.concatenate([offset, turn])
            step = joint_velocity(
                self.jacobian(), twist, q, rest=self.rest, max_speed=np.full(q.size, 0.2)
            )
            q = np.clip(q + step, self.lower, self.upper)
            for j, value in zip(self.joints, q):
                self.client.resetJointState(self.body, j, float(value), 0.0)
        self.reset(q)
        return error

    def add_markers(self, points: np.ndarray, *, radius: float, rgba: tuple) -> None:
        """Adds visual-only spheres (no collision, no mass) at world points (B, 3)."""
        shape = self.client.createVisualShape(
            self._pb.GEOM_SPHERE, radius=radius, rgbaColor=list(rgba)
        )
        for point in np.asarray(points, dtype=float):
            self.client.createMultiBody(baseVisualShapeIndex=shape, basePosition=point.tolist())

    def add_obstacles(
        self, shapes: list[np.ndarray], *, rgba: tuple = (0.45, 0.5, 0.55, 1.0)
    ) -> list[int]:
        """Adds fixed (massless) collision bodies: the convex hull of each vertex set (M, 3),
        world metres; returns their body ids."""
        from scipy.spatial import ConvexHull

        bodies = []
        for vertices in shapes:
            hull = ConvexHull(vertices)
            triangles = hull.simplices.copy()
            # Wind every triangle outwards (its normal along the hull facet's), for rendering.
            a, b, c = (vertices[triangles[:, i]] for i in range(3))
            flip = (np.cross(b - a, c - a) * hull.equations[:, :3]).sum(-1) < 0
            triangles[flip] = triangles[flip][:, ::-1]
            collision = self.client.createCollisionShape(
                self._pb.GEOM_MESH, vertices=vertices.tolist()
            )
            visual = self.client.createVisualShape(
                self._pb.GEOM_MESH,
                vertices=vertices.tolist(),
                indices=triangles.ravel().tolist(),
                rgbaColor=list(rgba),
            )
            bodies.append(
                self.client.createMultiBody(
                    baseMass=0.0,
                    baseCollisionShapeIndex=collision,
                    baseVisualShapeIndex=visual,
                )
            )
        return bodies

    def contact(self, bodies: list[int], *, within: float = 1.0) -> tuple[bool, float]:
        """Whether the arm touches any of these bodies, and its smallest distance to them
        (metres; ``within`` if none is nearer), from PyBullet's collision detection."""
        c = self.client
        c.performCollisionDetection()
        touching = any(c.getContactPoints(bodyA=self.body, bodyB=b) for b in bodies)
        nearest = within
        for b in bodies:
            for point in c.getClosestPoints(bodyA=self.body, bodyB=b, distance=within):
                nearest = min(nearest, point[8])
        return touching, float(nearest)

    def add_floor(self, *, rgba: tuple = (0.86, 0.86, 0.84, 1.0)) -> None:
        """Adds a visual-only floor under the robot, for pictures."""
        shape = self.client.createVisualShape(
            self._pb.GEOM_BOX, halfExtents=[1.5, 1.5, 0.005], rgbaColor=list(rgba)
        )
        self.client.createMultiBody(baseVisualShapeIndex=shape, basePosition=[0.0, 0.0, -0.006])

    def render(self, *, width: int = 320, height: int = 240) -> np.ndarray:
        """An RGB picture (height, width, 3) from the robot's camera, TinyRenderer.

        The camera looks at a point between the base and the work plane, nearer the plane.
        """
        distance, yaw, pitch = self.robot.camera
        base = np.array(self.client.getBasePositionAndOrientation(self.body)[0])
        look_at = 0.35 * base + 0.65 * np.array(self.robot.plane_origin) + np.array([0, 0, 0.1])
        view = self.client.computeViewMatrixFromYawPitchRoll(
            cameraTargetPosition=look_at.tolist(),
            distance=distance,
            yaw=yaw,
            pitch=pitch,
            roll=0.0,
            upAxisIndex=2,
        )
        projection = self.client.computeProjectionMatrixFOV(
            fov=45.0, aspect=width / height, nearVal=0.05, farVal=5.0
        )
        _, _, rgba, _, _ = self.client.getCameraImage(
            width,
            height,
            viewMatrix=view,
            projectionMatrix=projection,
            renderer=self._pb.ER_TINY_RENDERER,
        )
        return np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[..., :3]

    def close(self) -> None:
        """Disconnects the PyBullet world."""
        with contextlib.suppress(Exception):
            self.client.disconnect()

    def __enter__(self) -> Arm:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
