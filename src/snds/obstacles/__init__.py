r"""Obstacles and workspace limits: any policy's field, modulated so that it goes around them.

The modulation of Khansari-Zadeh & Billard (Auton. Robots 2012) in the form of Huber, Billard
& Slotine (RA-L 2019): near each obstacle k the velocity :math:`v = \pi(x)` is rewritten in a
basis of the reference direction :math:`r_k(x)` (from the obstacle's reference point, its
centre, to x) and the tangent plane of the obstacle's distance level set through x (normal
:math:`n_k(x)`), and the radial part is damped while the tangent part is sped up:

.. math:: M_k(x) = E_k D_k E_k^{-1}, \quad E_k = [r_k, e_1, \dots, e_{n-1}], \quad
          D_k = \mathrm{diag}(\lambda_r, \lambda_e, \dots, \lambda_e).

Written without a matrix inverse: with :math:`a = n^\top v / n^\top r` (the radial
coordinate, since every :math:`e_i \perp n`), :math:`M v = \lambda_r a r + \lambda_e (v - a
r)`. Here :math:`\lambda_r = 1 - h` when v approaches the obstacle (:math:`a < 0`) and 1
when it moves away (Huber's removal of the "tail effect"), :math:`\lambda_e = 1 + h`, and the
weight :math:`h \in [0, 1]` is 1 on the (inflated) boundary and 0 beyond the obstacle's
influence distance, so the field is exactly unchanged there. On the boundary
:math:`n^\top M v = 0`: the flow cannot enter (impenetrability). Several obstacles compose
as :math:`M = M_K \cdots M_1` with Khansari's weights :math:`w_k` (1 at obstacle k's
boundary, 0 at every other boundary), :math:`h_k \to w_k h_k`. An obstacle moving with
velocity :math:`u_k` modulates the velocity relative to it:
:math:`\dot x = M (v - u) + u`, :math:`u = \sum_k w_k h_k u_k`.

Distance functions. Each shape gives :math:`d(x)`, a lower bound of the Euclidean distance
from x to the physical shape that is exact for spheres and boxes (for an ellipsoid it is
:math:`(\sqrt{\sum_i (y_i / a_i)^2} - 1) \min_i a_i`, exact along the shortest axis), convex
outside the shape with the reference point inside its sublevel sets (so
:math:`n^\top r > 0`), and its gradient. With the safety margin m and influence distance
:math:`\rho`, :math:`\Gamma(x) = 1 + (d(x) - m) / \rho` is the paper's distance function:
:math:`\Gamma > 1` in free space, 1 on the inflated boundary, and :math:`\Gamma > 1` implies a
clearance :math:`d > m` from the physical shape. :math:`h = \mathrm{clip}(2 - \Gamma, 0,
1)^2`. A :class:`Workspace` (the inside of a box) is the same with the distance to its walls
(a smooth minimum over the faces, below the true one) and the reference direction pointing
inwards.

Discrete time: a robot steps :math:`x \leftarrow x + h \dot x`. The guarded step
(:class:`snds.steppers.GuardedEuler` with a scene, in every :func:`snds.rollout.rollout`) halves a
step until every :math:`\Gamma > 1` at the state reached (and, away from every obstacle's
influence, until a stable policy's V decreases, as :func:`snds.rollout.guarded_step` does),
and holds the state if no halving is safe: a guarded rollout never ends a step inside an
inflated obstacle. See docs/obstacles.md for which guarantee holds for which scene.

The package: :mod:`~snds.obstacles.shapes` (the distance functions),
:mod:`~snds.obstacles.spec` (``--obstacle`` specs), :mod:`~snds.obstacles.scene` (a scene, the
modulation, scene files) and :mod:`~snds.obstacles.check` (the stability report under them).
Rollouts among obstacles are :func:`snds.rollout.rollout` with ``scene=``.
"""

from snds.obstacles.check import ObstacleReport, RolloutCheck, check_obstacles, free_starts
from snds.obstacles.scene import ModulatedPolicy, Scene, load_scene, modulate_twist, step_fraction
from snds.obstacles.shapes import SHAPES, WORKSPACES, Box, Ellipsoid, Obstacle, Sphere, Workspace
from snds.obstacles.spec import parse_obstacle, parse_workspace

__all__ = [
    "SHAPES",
    "WORKSPACES",
    "Box",
    "Ellipsoid",
    "ModulatedPolicy",
    "Obstacle",
    "ObstacleReport",
    "RolloutCheck",
    "Scene",
    "Sphere",
    "Workspace",
    "check_obstacles",
    "free_starts",
    "load_scene",
    "modulate_twist",
    "parse_obstacle",
    "parse_workspace",
    "step_fraction",
]
