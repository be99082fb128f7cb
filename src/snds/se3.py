r"""SE(3) pose policies: the stable policy on position and rotation vector, rolled out on SO(3).

A pose is a position :math:`p \in \mathbb{R}^3` and a unit quaternion :math:`q` (x, y, z, w;
:math:`q` and :math:`-q` are the same orientation). Relative to the target pose
:math:`(p^*, q^*)` the learned state is

.. math:: \xi = (p - p^*, \; r), \qquad r = \log(q \, q^{*-1}) \in \mathbb{R}^3,

the rotation vector of the rotation that takes the target orientation to :math:`q`, in the
world frame (SPEC's convention). The log is canonical, with angle :math:`|r| \in [0, \pi]`
(:func:`snds.so3.relative_rotvec`), so :math:`q` and :math:`-q` give the same state and so the same
policy output: the double cover is handled where the state is made.

**Units.** Metres and radians must not share one length scale. The network sees
:math:`y = ((p - p^*) / L_p, \; r / L_r)` with :math:`L_p` the position extent of the
demonstrations and :math:`L_r` their largest angle from the target, so that both blocks span
about one unit; :class:`PosePolicy` is the ordinary :class:`~snds.policy.StablePolicy` on
:math:`y \in \mathbb{R}^6` (its guarantee :math:`\nabla V^\top \dot y \le -a` unchanged) whose
:attr:`~PosePolicy.space` is :class:`~snds.spaces.SE3`: it takes poses (x, y, z, qx, qy, qz,
qw) and returns twists in user units (metres, radians, seconds), so rollouts, the stability
check, the metrics, plots, simulation and export treat it as every other policy.

**Angular velocity.** The policy's rotation block is :math:`\dot r`; the robot needs the
angular velocity :math:`\omega` in the world frame, with :math:`\dot R = [\omega]_\times R`.
Since :math:`R^*` is constant, :math:`\omega = J_l(r) \, \dot r` with :math:`J_l` the left
Jacobian of SO(3) (:func:`snds.so3.left_jacobian`). With this map the flow on SO(3) is exactly the
flow of the policy in the chart, so V decreases along the robot's true motion, not only in
the learned coordinates. Rollouts integrate :math:`q \leftarrow \exp(\Delta t\, \omega) \, q`
(:meth:`snds.spaces.SE3.advance`), so the orientation stays on SO(3).

The chart covers every orientation (:math:`|r| \le \pi`); a trajectory that crossed
:math:`|r| = \pi` would reappear at the antipodal rotation vector (the same orientation), where
V can differ. The guarantee is therefore proved in the chart and checked on SO(3) by
:func:`snds.stability.check_stability` from random orientations spanning all of SO(3).

Quaternion algebra is roma's (XYZW, the order of SciPy and of the data files).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import Tensor

from snds.data.demonstrations import Demonstration, Demonstrations, Normalization
from snds.data.poses import PoseDemonstrations, angles_to
from snds.errors import DataError
from snds.policy import DEFAULT_WARP_LAYERS, PolicyConfig, StablePolicy
from snds.so3 import left_jacobian, left_jacobian_inverse, relative_rotvec
from snds.spaces import SE3, Phased, Space

__all__ = ["PoseConfig", "PosePolicy", "make_pose_policy", "pose_scales", "tangent_demonstrations"]


@dataclass(frozen=True, kw_only=True)
class PoseConfig(PolicyConfig):
    """Architecture of a pose policy: a :class:`~snds.policy.PolicyConfig` on the 6-D state,
    plus the target pose and the two length scales; saved beside the weights.

    ``warp_layers`` None means :data:`~snds.policy.DEFAULT_WARP_LAYERS` here (the chart is
    6-D, see docs/design.md).

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
        if self.warp_layers is None:
            object.__setattr__(self, "warp_layers", DEFAULT_WARP_LAYERS)
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
    :math:`y = ((p - p^*)/L_p, \log(q q^{*-1})/L_r) \in \mathbb{R}^6` (:meth:`chart`), so
    the projection, the Lyapunov checks, training and saving are the ones of every policy;
    ``forward`` maps poses (*, 7) to twists (*, 6) in user units, as every policy maps states
    to velocities in its :attr:`space`.

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
        if dim != 6 + config.phase_dim:
            raise ValueError(
                f"a pose policy has a 6-D state and its phase, got dim={dim} with phase_dim="
                f"{config.phase_dim}"
            )
        super().__init__(dim=dim, normalization=normalization, config=config, seed=seed)
        # Rebuilt from the config on load, so not saved with the weights.
        self.register_buffer(
            "target_position", torch.tensor(config.target_position), persistent=False
        )
        self.register_buffer(
            "target_orientation", torch.tensor(config.target_orientation), persistent=False
        )
        # A phase is a length (snds.phase): it is scaled as the positions are.
        scales = [config.position_scale] * 3 + [config.rotation_scale] * 3
        scales += [config.position_scale] * config.phase_dim
        self.register_buffer("scales", torch.tensor(scales), persistent=False)

    @property
    def space(self) -> Space:
        """Poses (x, y, z, qx, qy, qz, qw) and twists: :class:`~snds.spaces.SE3`; with a
        phase after the pose, :class:`~snds.spaces.Phased` on it."""
        phase_dim = self.config.phase_dim
        return Phased(SE3(), phase_dim) if phase_dim else SE3()

    def chart(self, x: Tensor) -> Tensor:
        """The scaled state y, shape (*, 6 + m), of poses x (*, 7 + m) (m: the phase)."""
        dtype = x.dtype
        p = x[..., :3] - self.target_position.to(dtype)
        r = relative_rotvec(x[..., 3:7], self.target_orientation.to(dtype))
        return torch.cat([p, r, x[..., 7:]], -1) / self.scales.to(dtype)

    def to_model(self, x: Tensor) -> Tensor:
        """Poses (*, 7 + m) to model coordinates (*, 6 + m): the normalised :meth:`chart`."""
        return super().to_model(self.chart(x))

    @property
    def target(self) -> np.ndarray:
        """The target pose (x, y, z, qx, qy, qz, qw), then m zeros of a phase, shape (7 + m,),
        float64."""
        config = self.config
        pose = [*config.target_position, *config.target_orientation]
        return np.array(pose + [0.0] * config.phase_dim, dtype=np.float64)

    def extents(self) -> np.ndarray:
        """The position extent L_p and the rotation scale L_r (radians), shape (2,)."""
        return self.chart_scales()

    def chart_scales(self) -> np.ndarray:
        """The chart y divides positions by L_p and rotation vectors by L_r: (L_p, L_r)."""
        config = self.config
        return np.array([config.position_scale, config.rotation_scale], dtype=np.float64)

    def velocity_to_user(self, z: Tensor, velocity: Tensor) -> Tensor:
        r"""Model velocities (*, 6) at model coordinates z (*, 6) to twists
        :math:`(v, \omega)` (*, 6): :math:`\dot y` in user units per second, then
        :math:`\omega = J_l(r)\,\dot r` with the rotation vector r read back from z (the
        normalisation's inverse, so the log map is taken once per state)."""
        scales = self.scales.to(z.dtype)
        rates = super().velocity_to_user(z, velocity) * scales
        y = z * self.length + self.center.to(z.dtype)
        r = y[..., 3:6] * scales[3:6]
        omega = (left_jacobian(r) @ rates[..., 3:6, None])[..., 0]
        return torch.cat([rates[..., :3], omega, rates[..., 6:]], -1)

    def training_demonstrations(self, demos: PoseDemonstrations) -> Demonstrations:
        """The pose demonstrations in the scaled state y (:func:`tangent_demonstrations`)."""
        config = self.config
        return tangent_demonstrations(
            demos, position_scale=config.position_scale, rotation_scale=config.rotation_scale
        )


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
    (:attr:`~snds.data.PoseDemonstration.velocities`), the exact inverse of the map the policy
    uses; a phase is scaled as the positions are.

    Arguments:
        demos: Pose demonstrations ending at their target.
        position_scale: :math:`L_p`.
        rotation_scale: :math:`L_r`.
    """
    target = torch.tensor(demos.target_orientation)
    out = []
    for demo in demos:
        r = relative_rotvec(torch.tensor(demo.orientations), target)
        omega = torch.as_tensor(demo.velocities[:, 3:6])
        r_dot = (left_jacobian_inverse(r) @ omega[..., None])[..., 0]
        velocities = demo.velocities
        y = np.concatenate(
            [
                (demo.positions - demos.target_position) / position_scale,
                r.numpy() / rotation_scale,
                demo.states[:, 7:] / position_scale,
            ],
            axis=1,
        )
        y_dot = np.concatenate(
            [
                velocities[:, :3] / position_scale,
                r_dot.numpy() / rotation_scale,
                velocities[:, 6:] / position_scale,
            ],
            axis=1,
        )
        out.append(Demonstration(y, y_dot, demo.times))
    return Demonstrations(tuple(out), np.zeros(6 + demos.phase_dim), demos.name, demos.phase_dim)


def make_pose_policy(
    demos: PoseDemonstrations, *, config: PolicyConfig | None = None, seed: int = 0
) -> PosePolicy:
    """A fresh pose policy for ``demos`` (:func:`snds.train.fit` trains it on them).

    Arguments:
        demos: The pose demonstrations (refused if one crosses the chart's cut, see
            :func:`check_pose_data`).
        config: The architecture of the 6-D stable policy (default :class:`PolicyConfig`());
            ``stable=False`` gives behavioural cloning. Its ``anchors`` are ignored: a pose
            policy's decay rate has no data kernel.
        seed: Seed of the initial weights.
    """
    check_pose_data(demos)
    base = asdict(config or PolicyConfig())
    for key in ("position_scale", "rotation_scale", "target_position", "target_orientation"):
        base.pop(key, None)
    position_scale, rotation_scale = pose_scales(demos)
    base["phase_dim"] = demos.phase_dim
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
    return PosePolicy(
        dim=tangent.dim, normalization=Normalization.fit(tangent), config=pose_config, seed=seed
    )


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
