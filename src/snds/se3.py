r"""SE(3) pose policies: the stable policy on position and rotation vector, rolled out on SO(3).

A pose is a position :math:`p \in \mathbb{R}^3` and a unit quaternion :math:`q` (x, y, z, w;
:math:`q` and :math:`-q` are the same orientation). Relative to the target pose
:math:`(p^*, q^*)` the learned state is

.. math:: \xi = (p - p^*, \; r), \qquad r = \log(q \, q^{*-1}) \in \mathbb{R}^3,

the rotation vector of the rotation that takes the target orientation to :math:`q`, in the
world frame (SPEC's convention). The log is canonical, with angle :math:`|r| \in [0, \pi]`
(:func:`relative_rotvec`), so :math:`q` and :math:`-q` give the same state and so the same
policy output: the double cover is handled where the state is made.

**Units.** Metres and radians must not share one length scale. The network sees
:math:`y = ((p - p^*) / L_p, \; r / L_r)` with :math:`L_p` the position extent of the
demonstrations and :math:`L_r` their largest angle from the target, so that both blocks span
about one unit; :class:`PosePolicy` is the ordinary :class:`~snds.policy.StablePolicy` on
:math:`y \in \mathbb{R}^6` (its guarantee :math:`\nabla V^\top \dot y \le -a` unchanged), and
its pose methods take and return user units (metres, radians, seconds).

**Angular velocity.** The policy's rotation block is :math:`\dot r`; the robot needs the
angular velocity :math:`\omega` in the world frame, with :math:`\dot R = [\omega]_\times R`.
Since :math:`R^*` is constant, :math:`\omega = J_l(r) \, \dot r` with :math:`J_l` the left
Jacobian of SO(3) (:func:`left_jacobian`). With this map the flow on SO(3) is exactly the
flow of the policy in the chart, so V decreases along the robot's true motion, not only in
the learned coordinates. Rollouts integrate :math:`q \leftarrow \exp(\Delta t\, \omega) \, q`
(:func:`rollout_poses`), so the orientation stays on SO(3).

The chart covers every orientation (:math:`|r| \le \pi`); a trajectory that crossed
:math:`|r| = \pi` would reappear at the antipodal rotation vector (the same orientation), where
V can differ. The guarantee is therefore proved in the chart and checked on SO(3) by
:func:`check_pose_stability` from random orientations spanning all of SO(3).

Quaternion algebra is roma's (XYZW, the order of SciPy and of the data files).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import roma
import torch
from dtaidistance import dtw_ndim
from scipy.spatial.transform import Rotation
from torch import Tensor

from snds.data.demonstrations import Demonstration, Demonstrations, Normalization, Split
from snds.data.poses import PoseDemonstrations, angles_to
from snds.errors import DataError
from snds.metrics import dtw
from snds.policy import PolicyConfig, StablePolicy, float64_copy
from snds.rollout import guarded_step, policy_guard
from snds.stability import (
    ROLLOUTS,
    SAMPLES,
    decrease_violations,
    largest_safe_step,
    settle_level,
)

# --- SO(3) maths -------------------------------------------------------------------------------


def relative_rotvec(q: Tensor, q_target: Tensor) -> Tensor:
    r"""The rotation vector :math:`\log(q \, q^{*-1})`, angle in :math:`[0, \pi]`.

    Canonical (shortest arc), so :math:`q` and :math:`-q` (and :math:`\pm q^*`) give the same
    vector.

    Arguments:
        q: Unit quaternions (x, y, z, w), shape (*, 4).
        q_target: The target orientation, shape (4,) or (*, 4).

    Returns:
        Rotation vectors, shape (*, 3).
    """
    relative = roma.quat_product(q, roma.quat_conjugation(q_target.expand_as(q)))
    return roma.unitquat_to_rotvec(relative, shortest_arc=True)


def rotate(rotvec: Tensor, q: Tensor) -> Tensor:
    r""":math:`\exp(r) \, q`: the orientation ``q`` (*, 4) turned by ``rotvec`` (*, 3) in the
    world frame."""
    return roma.quat_product(roma.rotvec_to_unitquat(rotvec), q)


def _hat(r: Tensor) -> Tensor:
    """The skew matrix [r]_x, shape (*, 3, 3), with [r]_x u = r x u."""
    zero = torch.zeros_like(r[..., 0])
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    return torch.stack(
        [
            torch.stack([zero, -z, y], -1),
            torch.stack([z, zero, -x], -1),
            torch.stack([-y, x, zero], -1),
        ],
        -2,
    )


def left_jacobian(r: Tensor) -> Tensor:
    r"""The left Jacobian of SO(3), :math:`\exp(r + \delta) \approx \exp(J_l(r)\delta)\exp(r)`.

    .. math:: J_l(r) = I + \frac{1 - \cos\theta}{\theta^2} [r]_\times
              + \frac{\theta - \sin\theta}{\theta^3} [r]_\times^2, \qquad \theta = |r|,

    with the Taylor series of the coefficients below :math:`\theta = 10^{-3}` (where the
    closed forms lose their digits to cancellation). roma offers no Jacobian of the exponential
    map, hence these few lines.

    Arguments:
        r: Rotation vectors, shape (*, 3).

    Returns:
        The matrices, shape (*, 3, 3).
    """
    theta2 = (r * r).sum(-1)
    theta = theta2.sqrt()
    small = theta < 1e-3
    safe = torch.where(small, torch.ones_like(theta), theta)
    a = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(safe)) / safe**2)
    b = torch.where(small, 1 / 6 - theta2 / 120, (safe - torch.sin(safe)) / safe**3)
    hat = _hat(r)
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand_as(hat)
    return eye + a[..., None, None] * hat + b[..., None, None] * (hat @ hat)


def left_jacobian_inverse(r: Tensor) -> Tensor:
    r"""The inverse of :func:`left_jacobian`, for :math:`|r| < 2\pi`.

    .. math:: J_l^{-1}(r) = I - \tfrac12 [r]_\times + \Big(\frac{1}{\theta^2}
              - \frac{1 + \cos\theta}{2 \theta \sin\theta}\Big) [r]_\times^2

    (series below :math:`\theta = 10^{-3}`; the coefficient tends to :math:`1 / \pi^2` at
    :math:`\theta = \pi`, where its closed form is 0/0).

    Arguments:
        r: Rotation vectors, shape (*, 3).

    Returns:
        The matrices, shape (*, 3, 3).
    """
    theta2 = (r * r).sum(-1)
    theta = theta2.sqrt()
    small = theta < 1e-3
    near_pi = (torch.pi - theta).abs() < 1e-6
    safe = torch.where(small | near_pi, torch.full_like(theta, 1.0), theta)
    c = 1 / safe**2 - (1 + torch.cos(safe)) / (2 * safe * torch.sin(safe))
    c = torch.where(small, 1 / 12 + theta2 / 720, c)
    c = torch.where(near_pi, torch.full_like(theta, 1 / torch.pi**2), c)
    hat = _hat(r)
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand_as(hat)
    return eye - 0.5 * hat + c[..., None, None] * (hat @ hat)


def geodesic_angle(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Angle (radians, [0, pi]) of the rotation between orientations (*, 4), sign-blind."""
    dots = np.abs(np.sum(np.asarray(q1) * np.asarray(q2), axis=-1))
    return 2.0 * np.arccos(np.clip(dots, 0.0, 1.0))


def angular_velocities(orientations: np.ndarray, times: np.ndarray) -> np.ndarray:
    r"""World-frame angular velocities :math:`\omega` of a sampled orientation path.

    Central differences on SO(3), :math:`\omega_k = \log(q_{k+1} q_{k-1}^{-1}) /
    (t_{k+1} - t_{k-1})` (one-sided at the ends): each log is of a small rotation, so the
    double cover never enters.

    Arguments:
        orientations: Unit quaternions, shape (T, 4), T >= 2.
        times: Sample times, shape (T,).

    Returns:
        Angular velocities in rad/s, shape (T, 3).
    """
    rotations = Rotation.from_quat(orientations)
    ahead = np.r_[1 : len(times), len(times) - 1]
    behind = np.r_[0, 0 : len(times) - 1]
    turn = (rotations[ahead] * rotations[behind].inv()).as_rotvec()
    return turn / (times[ahead] - times[behind])[:, None]


# --- the policy --------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class PoseConfig(PolicyConfig):
    """Architecture of a pose policy: a :class:`~snds.policy.PolicyConfig` on the 6-D state,
    plus the target pose and the two length scales; saved beside the weights.

    ``warp_layers`` None means 0 here: a warped V has not been measured on poses.

    Attributes:
        position_scale: :math:`L_p` in user length units (metres for arm data).
        rotation_scale: :math:`L_r` in radians.
        target_position: :math:`p^*`, 3 numbers.
        target_orientation: :math:`q^*` (x, y, z, w), 4 numbers.
    """

    position_scale: float = 1.0
    rotation_scale: float = 1.0
    target_position: tuple[float, ...] = (0.0, 0.0, 0.0)
    target_orientation: tuple[float, ...] = (0.0, 0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        super().__post_init__()
        # A warped V is unmeasured on poses (the convex one on a 6-D lift of one demonstration
        # was already stiff without the shape penalty), so the default here is no warp.
        if self.warp_layers is None:
            object.__setattr__(self, "warp_layers", 0)
        object.__setattr__(self, "target_position", tuple(map(float, self.target_position)))
        object.__setattr__(self, "target_orientation", tuple(map(float, self.target_orientation)))
        if len(self.target_position) != 3 or len(self.target_orientation) != 4:
            raise ValueError("target_position needs 3 numbers, target_orientation 4")
        if abs(np.linalg.norm(self.target_orientation) - 1) > 1e-6:
            raise ValueError(f"target_orientation {self.target_orientation} is not unit")
        for scale in (self.position_scale, self.rotation_scale):
            if not (np.isfinite(scale) and scale > 0):
                raise ValueError(f"scales must be positive and finite, got {scale}")


class PosePolicy(StablePolicy):
    r"""A stable policy for poses: linear and angular velocity at every pose, reaching the
    target pose from every position and every orientation.

    It is a :class:`~snds.policy.StablePolicy` on the scaled state
    :math:`y = ((p - p^*)/L_p, \log(q q^{*-1})/L_r) \in \mathbb{R}^6` (``forward`` maps
    :math:`y` to :math:`\dot y` per second), so the projection, the Lyapunov checks, training
    and saving are the ones of every policy; :meth:`twist` and :func:`rollout_poses` work on
    poses in user units.

    Arguments:
        dim: Must be 6.
        normalization: The affine map of :math:`y` to model coordinates.
        config: The architecture, target pose and scales.
        seed: Seed of the initial weights.
    """

    kind = "se3"
    config_class = PoseConfig
    config: PoseConfig

    def __init__(
        self, *, dim: int, normalization: Normalization, config: PoseConfig, seed: int = 0
    ) -> None:
        if dim != 6:
            raise ValueError(f"a pose policy has a 6-D state, got dim={dim}")
        super().__init__(dim=6, normalization=normalization, config=config, seed=seed)
        # Rebuilt from the config on load, so not saved with the weights.
        self.register_buffer(
            "target_position", torch.tensor(config.target_position), persistent=False
        )
        self.register_buffer(
            "target_orientation", torch.tensor(config.target_orientation), persistent=False
        )
        scales = [config.position_scale] * 3 + [config.rotation_scale] * 3
        self.register_buffer("scales", torch.tensor(scales), persistent=False)

    def tangent(self, position: Tensor, orientation: Tensor) -> Tensor:
        """The scaled state y, shape (*, 6), of poses: positions (*, 3), quaternions (*, 4)."""
        p = position - self.target_position.to(position.dtype)
        r = relative_rotvec(orientation, self.target_orientation.to(orientation.dtype))
        return torch.cat([p, r], -1) / self.scales.to(position.dtype)

    def pose(self, y: Tensor) -> tuple[Tensor, Tensor]:
        """Inverse of :meth:`tangent`: positions (*, 3) and unit quaternions (*, 4)."""
        xi = y * self.scales.to(y.dtype)
        target = self.target_orientation.to(y.dtype).expand(*y.shape[:-1], 4)
        return xi[..., :3] + self.target_position.to(y.dtype), rotate(xi[..., 3:], target)

    def twist(self, position: Tensor, orientation: Tensor) -> Tensor:
        r"""Linear velocity and world-frame angular velocity :math:`(v, \omega)`, shape (*, 6),
        in user units per second, at poses: positions (*, 3), quaternions (*, 4)."""
        y = self.tangent(position, orientation)
        rates = self(y) * self.scales.to(y.dtype)
        r = y[..., 3:] * self.scales[3:].to(y.dtype)
        omega = (left_jacobian(r) @ rates[..., 3:, None])[..., 0]
        return torch.cat([rates[..., :3], omega], -1)

    @torch.no_grad()
    def predict_twist(self, positions: np.ndarray, orientations: np.ndarray) -> np.ndarray:
        """NumPy convenience: :meth:`twist` at positions (*, 3) and quaternions (*, 4)."""
        param = next(self.parameters())
        as_tensor = lambda a: torch.as_tensor(a, dtype=param.dtype, device=param.device)  # noqa: E731
        return self.twist(as_tensor(positions), as_tensor(orientations)).cpu().numpy()


def pose_scales(demos: PoseDemonstrations) -> tuple[float, float]:
    r"""The length scales :math:`(L_p, L_r)`: the largest distance of a demonstrated position
    from the target, and the largest angle of a demonstrated orientation from the target's.

    A block that never moves (all orientations equal to the target, say) gets the scale of
    the whole space it lives in instead (the position extent's 1, or :math:`\pi` radians), so
    that states off the data are still of order one.
    """
    extent, angle = demos.extent(), demos.angle_extent()
    return (extent if extent > 1e-9 else 1.0), (angle if angle > 1e-6 else float(np.pi))


def tangent_demonstrations(
    demos: PoseDemonstrations, *, position_scale: float, rotation_scale: float
) -> Demonstrations:
    r"""The demonstrations in the policy's scaled state :math:`y` (target 0), with
    :math:`\dot y`: linear velocities by second-order differences against the times, and
    :math:`\dot r = J_l^{-1}(r)\,\omega` from the angular velocities
    (:func:`angular_velocities`), the exact inverse of the map the policy uses.

    Arguments:
        demos: Pose demonstrations ending at their target.
        position_scale: :math:`L_p`.
        rotation_scale: :math:`L_r`.
    """
    target = torch.tensor(demos.target_orientation)
    out = []
    for demo in demos:
        edge = 2 if len(demo.times) > 2 else 1
        v = np.gradient(demo.positions, demo.times, axis=0, edge_order=edge)
        r = relative_rotvec(torch.tensor(demo.orientations), target)
        omega = torch.as_tensor(angular_velocities(demo.orientations, demo.times))
        r_dot = (left_jacobian_inverse(r) @ omega[..., None])[..., 0]
        y = np.concatenate(
            [(demo.positions - demos.target_position) / position_scale, r.numpy() / rotation_scale],
            axis=1,
        )
        y_dot = np.concatenate([v / position_scale, r_dot.numpy() / rotation_scale], axis=1)
        out.append(Demonstration(y, y_dot, demo.times))
    return Demonstrations(tuple(out), np.zeros(6), demos.name)


def make_pose_policy(
    demos: PoseDemonstrations, *, config: PolicyConfig | None = None, seed: int = 0
) -> tuple[PosePolicy, Demonstrations]:
    """A fresh pose policy for ``demos``, and the demonstrations in its scaled state.

    Arguments:
        demos: The pose demonstrations.
        config: The architecture of the 6-D stable policy (default :class:`PolicyConfig`());
            ``stable=False`` gives behavioural cloning.
        seed: Seed of the initial weights.
    """
    base = asdict(config or PolicyConfig())
    for key in ("position_scale", "rotation_scale", "target_position", "target_orientation"):
        base.pop(key, None)
    position_scale, rotation_scale = pose_scales(demos)
    pose_config = PoseConfig(
        **base,
        position_scale=position_scale,
        rotation_scale=rotation_scale,
        target_position=tuple(demos.target_position),
        target_orientation=tuple(demos.target_orientation),
    )
    tangent = tangent_demonstrations(
        demos, position_scale=position_scale, rotation_scale=rotation_scale
    )
    policy = PosePolicy(
        dim=6, normalization=Normalization.fit(tangent), config=pose_config, seed=seed
    )
    return policy, tangent


# --- rollouts ----------------------------------------------------------------------------------


@torch.no_grad()
def rollout_poses(
    policy: PosePolicy, positions: Tensor, orientations: Tensor, *, dt: float, steps: int
) -> tuple[Tensor, Tensor]:
    r"""Integrates the pose policy: :math:`p \leftarrow p + \Delta t\, v`,
    :math:`q \leftarrow \exp(\Delta t\, \omega)\, q` (the exponential map, so the orientation
    never leaves SO(3); each step is renormalised so that rounding cannot accumulate).

    Arguments:
        policy: The pose policy.
        positions: Start positions, shape (B, 3).
        orientations: Start unit quaternions, shape (B, 4).
        dt: Time step in seconds.
        steps: Number of steps.

    Returns:
        Positions (steps + 1, B, 3) and quaternions (steps + 1, B, 4), starting at the start.
    """
    p, q = positions, orientations
    ps, qs = [p], [q]
    for _ in range(steps):
        twist = policy.twist(p, q)
        p = p + dt * twist[..., :3]
        q = roma.quat_normalize(rotate(dt * twist[..., 3:], q))
        ps.append(p)
        qs.append(q)
    return torch.stack(ps), torch.stack(qs)


def rollout_poses_numpy(
    policy: PosePolicy, positions: np.ndarray, orientations: np.ndarray, *, dt: float, steps: int
) -> tuple[np.ndarray, np.ndarray]:
    """NumPy convenience, in float64: positions (B, steps + 1, 3), quaternions (B, steps + 1, 4)."""
    policy = float64_copy(policy)
    p, q = rollout_poses(
        policy,
        torch.tensor(np.asarray(positions, dtype=np.float64)),
        torch.tensor(np.asarray(orientations, dtype=np.float64)),
        dt=dt,
        steps=steps,
    )
    return p.transpose(0, 1).numpy(), q.transpose(0, 1).numpy()


# --- metrics -----------------------------------------------------------------------------------


def reproduce_poses(
    policy: PosePolicy, demos: PoseDemonstrations, indices: list[int]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Rollouts from the start poses of demonstrations, each with its mean step and length."""
    out = []
    for i in indices:
        demo = demos[i]
        steps = len(demo.times) - 1
        p, q = rollout_poses_numpy(
            policy, demo.positions[:1], demo.orientations[:1], dt=demo.duration / steps, steps=steps
        )
        out.append((p[0], q[0]))
    return out


def orientation_error_along(
    positions: np.ndarray,
    orientations: np.ndarray,
    reference_positions: np.ndarray,
    reference_orientations: np.ndarray,
) -> float:
    """Mean geodesic angle (radians) between the orientations of samples paired by the
    position DTW alignment: the orientation error at matching places along the path.

    Arguments:
        positions: A rollout's positions, shape (T, 3).
        orientations: Its quaternions, shape (T, 4).
        reference_positions: The demonstration's positions, shape (S, 3).
        reference_orientations: Its quaternions, shape (S, 4).
    """
    path = dtw_ndim.warping_path(
        np.ascontiguousarray(positions, dtype=np.float64),
        np.ascontiguousarray(reference_positions, dtype=np.float64),
    )
    i, j = np.asarray(path).T
    return float(geodesic_angle(orientations[i], reference_orientations[j]).mean())


def pose_accuracy(
    policy: PosePolicy, demos: PoseDemonstrations, split: Split, indices: list[int]
) -> dict[str, float]:
    """Position DTW (paper eq. 7, q = 2) and final position error in user units; orientation
    error along the path (:func:`orientation_error_along`) and at the end, in radians; the
    velocity MSE of the twist on the test samples (linear and angular separately).

    Arguments:
        policy: The pose policy.
        demos: All demonstrations.
        split: The train / test split (test samples for the velocity MSE).
        indices: The demonstrations to reproduce from their starts.
    """
    paths = reproduce_poses(policy, demos, indices)
    position_dtw = [dtw(p, demos[i].positions) for (p, _), i in zip(paths, indices)]
    along = [
        orientation_error_along(p, q, demos[i].positions, demos[i].orientations)
        for (p, q), i in zip(paths, indices)
    ]
    final_position = [np.linalg.norm(p[-1] - demos.target_position) for p, _ in paths]
    final_angle = [float(angles_to(q[-1:], demos.target_orientation)[0]) for _, q in paths]
    test = split.test()
    masks = test if any(m.any() for m in test) else split.train
    positions = np.concatenate([d.positions[m] for d, m in zip(demos, masks)])
    orientations = np.concatenate([d.orientations[m] for d, m in zip(demos, masks)])
    linear = np.concatenate(
        [np.gradient(d.positions, d.times, axis=0)[m] for d, m in zip(demos, masks)]
    )
    angular = np.concatenate(
        [angular_velocities(d.orientations, d.times)[m] for d, m in zip(demos, masks)]
    )
    twist = float64_copy(policy).predict_twist(positions, orientations)
    extent = demos.extent()
    return {
        "position_dtw": float(np.mean(position_dtw)),
        "position_dtw_paper": float(np.mean(position_dtw) / extent),
        "final_position_error": float(np.max(final_position)),
        "orientation_error_along": float(np.mean(along)),
        "final_orientation_error": float(np.max(final_angle)),
        "linear_velocity_mse": float(np.mean((twist[:, :3] - linear) ** 2)),
        "angular_velocity_mse": float(np.mean((twist[:, 3:] - angular) ** 2)),
    }


@dataclass(frozen=True)
class PoseStabilityReport:
    """Outcome of :func:`check_pose_stability`.

    Attributes:
        rollouts: Rollouts from random poses.
        converged_fraction: Fraction ending within both tolerances of the target pose.
        max_final_distance: Largest distance of a rollout's end position from the target.
        max_final_angle: Largest angle (radians) of a rollout's end orientation from the
            target's.
        median_time_to_converge: Median time (s) to enter both tolerances for good, over the
            converged rollouts (NaN if none converged).
        v_rises: Steps of the SO(3) rollouts at which V rose even after ``max_halvings``
            halvings (0 for a policy without V): the discrete decrease along the robot's
            real motion.
        shortened_fraction: Fraction of rollouts in which the guard shortened a step.
        integrator: "guarded euler on SO(3)" (with V) or "euler on SO(3)".
        samples_checked: Random poses at which the decrease condition was checked.
        decrease_violations: Poses where grad V . y_dot > -a(y) beyond rounding.
        largest_safe_dt: Largest Euler step (s) in the chart decreasing V at every sample.
        box: Half-width of the box of random start positions (user units).
        horizon: Duration of each rollout (s).
        dt: Time step (s).
        position_tolerance: Distance counted as arrived (user units).
        angle_tolerance: Angle counted as arrived (radians).
    """

    rollouts: int
    converged_fraction: float
    max_final_distance: float
    max_final_angle: float
    median_time_to_converge: float
    v_rises: int
    shortened_fraction: float
    integrator: str
    samples_checked: int
    decrease_violations: int
    largest_safe_dt: float
    box: float
    horizon: float
    dt: float
    position_tolerance: float
    angle_tolerance: float

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return asdict(self)


class PoseGuard:
    r"""A pose policy in the form :func:`snds.rollout.guarded_step` takes: a pose is one row
    (p, q) of 7 numbers, its velocity the twist :math:`(v, \omega)`, and a step the
    exponential map on SO(3).

    Arguments:
        policy: A pose policy with a Lyapunov function (for :meth:`lyapunov` and :meth:`rate`).
    """

    def __init__(self, policy: PosePolicy) -> None:
        self.policy = policy
        # V and its rate in the tangent space, built once (policy_guard only makes closures).
        self._tangent_v, self._tangent_rate = policy_guard(policy)

    def field(self, x: Tensor) -> Tensor:
        """Twists (B, 6) at poses (B, 7)."""
        return self.policy.twist(x[:, :3], x[:, 3:])

    def lyapunov(self, x: Tensor) -> Tensor:
        """V (model units) at poses (B, 7), shape (B,)."""
        return self._tangent_v(self.policy.tangent(x[:, :3], x[:, 3:]))

    def rate(self, x: Tensor, value: Tensor) -> Tensor:
        """The promised decrease rate of V per second at poses (B, 7), shape (B,)."""
        return self._tangent_rate(self.policy.tangent(x[:, :3], x[:, 3:]), value)

    @staticmethod
    def advance(x: Tensor, h: Tensor, twist: Tensor) -> Tensor:
        """Poses (B, 7) moved by their twists (B, 6) for h (B,) seconds."""
        h = h[:, None]
        orientation = roma.quat_normalize(rotate(h * twist[:, 3:], x[:, 3:]))
        return torch.cat([x[:, :3] + h * twist[:, :3], orientation], -1)

    def safe_twist(self, x: Tensor, dt: float) -> tuple[Tensor, Tensor]:
        """The twists at poses (B, 7), each scaled by h / dt for the guarded step h <= dt.

        A controller that holds a twist for one period dt moves the pose by about
        :func:`advance`; scaled so, that step satisfies the sufficient-decrease condition of
        :func:`snds.rollout.guarded_step`, and a stiff field cannot make the arm chatter on a
        discrete cycle at constant V.

        Returns:
            The scaled twists, shape (B, 6), and h, shape (B,).
        """
        twist = self.field(x)
        # The twist is evaluated once: the guarded step only asks for it at x.
        _, h, _ = guarded_step(
            lambda _: twist, self.lyapunov, x, dt=dt, rate=self.rate, advance=self.advance
        )
        return twist * (h / dt).unsqueeze(-1), h


def random_poses(
    center: np.ndarray, half_width: float, count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Positions uniform in a cube around ``center`` and orientations uniform on SO(3)
    (Haar measure: normalised 4-D Gaussians), shapes (count, 3) and (count, 4)."""
    positions = center + rng.uniform(-half_width, half_width, size=(count, 3))
    quats = rng.standard_normal((count, 4))
    return positions, quats / np.linalg.norm(quats, axis=1, keepdims=True)


@torch.no_grad()
def check_pose_stability(
    policy: PosePolicy,
    demos: PoseDemonstrations,
    *,
    rollouts: int = ROLLOUTS,
    box_factor: float = 3.0,
    horizon_factor: float = 10.0,
    tolerance_factor: float = 0.01,
    samples: int = SAMPLES,
    sample_box_factor: float = 10.0,
    seed: int = 0,
    chunk: int = 20_000,
    max_halvings: int = 30,
) -> PoseStabilityReport:
    """Rolls out on SE(3) from random poses and checks the decrease condition on random poses.

    Start positions are uniform in a box of half-width ``box_factor`` x the position extent
    around the target; start orientations are uniform over all of SO(3) (angles up to pi from
    the target). Rollouts (:func:`rollout_poses`, float64) run ``horizon_factor`` x the longest
    demonstration's duration at the demonstrations' mean step (for a policy with V, the
    guarded step of every policy's check, :func:`snds.rollout.guarded_step`, with the
    exponential map as its step, so V falls at every step) and have converged if they end
    within ``tolerance_factor`` x the position extent and ``tolerance_factor`` x pi radians
    of the target pose. The decrease condition is checked, as for every policy, by
    :func:`snds.stability.decrease_violations` at random poses (positions in a box of
    ``sample_box_factor`` x the extent, orientations all of SO(3)).

    Arguments:
        policy: The pose policy (a float64 copy is used).
        demos: The demonstrations that define the extent, time step and horizon.
        rollouts: Random start poses.
        box_factor: Half-width of the start positions' box, in extents.
        horizon_factor: Rollout duration, in longest-demonstration durations.
        tolerance_factor: Arrival tolerance, in extents and in units of pi radians.
        samples: Random poses of the decrease check (0 to skip).
        sample_box_factor: Half-width of their positions' box, in extents.
        seed: Seed of the random poses.
        chunk: Poses per batch of the decrease check.
        max_halvings: Halvings of a step that does not decrease V before it is taken anyway.
    """
    policy = float64_copy(policy)
    rng = np.random.default_rng(seed)
    extent = demos.extent()
    dt, horizon = demos.mean_dt(), horizon_factor * demos.max_duration()
    steps = int(np.ceil(horizon / dt))
    position_tolerance, angle_tolerance = tolerance_factor * extent, tolerance_factor * np.pi
    target_p = torch.tensor(demos.target_position)
    target_q = torch.tensor(demos.target_orientation)
    p0, q0 = random_poses(demos.target_position, box_factor * extent, rollouts, rng)
    p, q = torch.as_tensor(p0), torch.as_tensor(q0)

    def errors(p: Tensor, q: Tensor) -> tuple[Tensor, Tensor]:
        distance = (p - target_p).norm(dim=-1)
        angle = relative_rotvec(q, target_q).norm(dim=-1)
        return distance, angle

    last_outside = torch.full((rollouts,), -1, dtype=torch.long)
    rises = 0
    active = torch.arange(rollouts)
    shortened = torch.zeros(rollouts, dtype=torch.bool)
    # A pose is one row (p, q) of 7 numbers, so that the guarded step of every policy's check
    # (snds.rollout.guarded_step) applies, with the exponential map as its step.
    pose = torch.cat([p, q], -1)
    guard = PoseGuard(policy)
    field, lyapunov, rate, advance = guard.field, guard.lyapunov, guard.rate, guard.advance
    value = level = None
    if policy.stable:
        value = lyapunov(pose)
        # Inside {V < c} (snds.stability.settle_level, ball of radius rho in model units) a
        # rollout stays within half of both tolerances for good, since guarded steps never
        # increase V: it is settled and no longer integrated, so the check costs the time
        # rollouts take to arrive.
        to_model = policy.scales.numpy() * policy.normalization.length
        radius = 0.5 * min(position_tolerance / to_model[0], angle_tolerance / to_model[3])
        level = settle_level(policy.lyapunov, radius, dim=6)

    for step in range(1, steps + 1):
        now = pose[active]
        if value is None:
            pose[active] = advance(now, torch.full((len(now),), dt, dtype=now.dtype), field(now))
        else:
            pose[active], h, new = guarded_step(
                field,
                lyapunov,
                now,
                dt=dt,
                rate=rate,
                max_halvings=max_halvings,
                value=value[active],
                advance=advance,
            )
            shortened[active[h < dt]] = True
            before = value[active]
            # Only a step that ran out of halvings can raise V (V below 1e-12 is the target up
            # to rounding).
            rises += int(((new > before * (1 + 1e-9)) & (before > 1e-12)).sum())
            value[active] = new
        distance, angle = errors(pose[active, :3], pose[active, 3:])
        outside = (distance > position_tolerance) | (angle > angle_tolerance)
        last_outside[active[outside]] = step
        if value is not None and step % 10 == 0:
            active = active[value[active] >= level]
        if len(active) == 0:
            break
    p, q = pose[:, :3], pose[:, 3:]
    distance, angle = errors(p, q)
    inside = (distance <= position_tolerance) & (angle <= angle_tolerance)
    times = (last_outside[inside] + 1).double() * dt
    violations, checked, safe_dt = 0, 0, float("nan")
    if policy.stable and samples > 0:
        safe_dt = 10.0 * demos.max_duration()
        for begin in range(0, samples, chunk):
            count = min(chunk, samples - begin)
            ps, qs = random_poses(demos.target_position, sample_box_factor * extent, count, rng)
            y = policy.tangent(torch.as_tensor(ps), torch.as_tensor(qs))
            violations += decrease_violations(policy, y)
            safe_dt = min(safe_dt, largest_safe_step(policy, y, upper=safe_dt))
        checked = samples
    finite = torch.isfinite(distance) & torch.isfinite(angle)

    def largest(values: Tensor) -> float:
        if len(values) == 0:
            return float("nan")
        return float(values.max()) if bool(finite.all()) else float("inf")

    return PoseStabilityReport(
        rollouts=rollouts,
        converged_fraction=float((inside & finite).double().mean()) if rollouts else float("nan"),
        max_final_distance=largest(distance),
        max_final_angle=largest(angle),
        median_time_to_converge=float(times.median()) if len(times) else float("nan"),
        v_rises=rises,
        shortened_fraction=float(shortened.double().mean()) if rollouts else float("nan"),
        integrator="guarded euler on SO(3)" if policy.stable else "euler on SO(3)",
        samples_checked=checked,
        decrease_violations=violations,
        largest_safe_dt=safe_dt,
        box=box_factor * extent,
        horizon=horizon,
        dt=dt,
        position_tolerance=position_tolerance,
        angle_tolerance=angle_tolerance,
    )


def evaluate_pose(
    policy: PosePolicy,
    demos: PoseDemonstrations,
    split: Split,
    *,
    seed: int = 0,
    rollouts: int = ROLLOUTS,
    samples: int = SAMPLES,
) -> dict[str, Any]:
    """Accuracy (:func:`pose_accuracy`, from the held-out demonstrations' starts, or all under a
    sample split) and the SE(3) stability report, as one JSON-ready record."""
    held_out = [i for i, mask in enumerate(split.train) if not mask.any()]
    record: dict[str, Any] = pose_accuracy(
        policy, demos, split, held_out or list(range(len(demos)))
    )
    report = check_pose_stability(policy, demos, rollouts=rollouts, samples=samples, seed=seed)
    record["stability"] = report.to_dict()
    return record


def check_pose_data(demos: PoseDemonstrations) -> None:
    """Refuses pose demonstrations that cannot train a policy (a demonstration whose
    orientation passes through the cut |r| = pi would make the learned state jump)."""
    for i, demo in enumerate(demos):
        angles = angles_to(demo.orientations, demos.target_orientation)
        if angles.max() > np.pi - 1e-3:
            raise DataError(
                f"demonstration {i} turns to {angles.max():.4f} rad from the target "
                "orientation, at the cut of the rotation-vector chart (pi)"
            )


# --- plots -------------------------------------------------------------------------------------


def plot_pose_policy(
    policy: PosePolicy,
    demos: PoseDemonstrations,
    out_dir: str | Path,
    *,
    history: list[float] | None = None,
    seed: int = 0,
) -> list[Path]:
    """Writes the plots of a pose policy into ``out_dir``.

    ``paths3d.png``: demonstrations and rollouts from their start poses with orientation
    frames along them, and rollouts from 4 random poses (positions in the demonstrations'
    box enlarged 1.5 times, orientations uniform on SO(3)); ``rollout_lyapunov.png`` (a
    stable policy): V along all these rollouts; ``loss.png`` when ``history`` is given.
    Rollouts last 1.5 x the longest demonstration.

    Returns:
        The paths written.
    """
    from snds.plotting import plot_loss, plot_paths_3d, plot_rollout_lyapunov

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    policy64 = float64_copy(policy)
    rng = np.random.default_rng(seed)
    dt = demos.mean_dt()
    steps = int(1.5 * demos.max_duration() / dt)
    starts_p = np.stack([demo.positions[0] for demo in demos])
    starts_q = np.stack([demo.orientations[0] for demo in demos])
    positions = demos.positions()
    centre = (positions.min(axis=0) + positions.max(axis=0)) / 2
    half = 0.75 * float((positions.max(axis=0) - positions.min(axis=0)).max())
    random_p, random_q = random_poses(centre, half, 4, rng)
    p, q = rollout_poses_numpy(policy64, starts_p, starts_q, dt=dt, steps=steps)
    rp, rq = rollout_poses_numpy(policy64, random_p, random_q, dt=dt, steps=steps)
    kind = "stable pose policy" if policy.stable else "unconstrained pose policy"
    paths = [
        plot_paths_3d(
            [demo.positions for demo in demos],
            list(p),
            demos.target_position,
            out / "paths3d.png",
            demo_orientations=[demo.orientations for demo in demos],
            rollout_orientations=list(q),
            perturbed=list(rp),
            title=f"{demos.name} — {kind}" if demos.name else kind,
        )
    ]
    if policy.stable:
        with torch.no_grad():
            y = policy64.tangent(torch.tensor(p), torch.tensor(q)).numpy()
            y_random = policy64.tangent(torch.tensor(rp), torch.tensor(rq)).numpy()
        paths.append(
            plot_rollout_lyapunov(policy64, y, dt, out / "rollout_lyapunov.png", perturbed=y_random)
        )
    if history:
        paths.append(plot_loss(history, out / "loss.png"))
    return paths
