r"""Accuracy metrics of a learned motion: velocity MSE, DTW, Fréchet, swept area, final distance.

Pure NumPy, so that any method (SNDS, baselines, recorded data) is scored by the same code.

Two conventions of dynamic time warping are in use and give different numbers; both are here
under distinct names:

* :func:`dtw` is the paper's eq. (7) with :math:`q = 2`, the square root of the minimal *sum of
  squared* Euclidean distances along an alignment path (dtaidistance's default);
* :func:`dtw_sum` is the classic DTW, the minimal *sum of* Euclidean distances.

The paper's scale (Fig. 4) divides positions relative to the target by their largest norm
in the motion, and velocities by their largest norm (:func:`snds.evaluate.accuracy` reports
both scales).

Two shape metrics from the wider literature complete them: :func:`frechet`, the discrete
Fréchet distance (the worst gap under the best monotone pairing, where DTW sums the gaps), and
:func:`swept_error_area`, the area between a planar reproduction and its demonstration
(Khansari-Zadeh's SEA).

:func:`field_roughness` scores the field itself away from the data: how much the direction of
the velocity turns between neighbouring points of a grid over the stability check's box.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Protocol

import numpy as np
from dtaidistance import dtw as _dtw
from dtaidistance import dtw_ndim as _dtw_ndim

from snds.data.demonstrations import DemonstrationSet
from snds.errors import DataError
from snds.stability import CheckConfig

__all__ = [
    "Roughness",
    "dtw",
    "dtw_sum",
    "field_roughness",
    "final_distance",
    "frechet",
    "swept_error_area",
    "velocity_mse",
]

# Decided once: asking dtaidistance for C when its extension is missing logs a warning at
# every call, and the pure-Python fallback gives the same numbers, only slower.
_USE_C: bool = getattr(_dtw, "dtw_cc", None) is not None


def _as_sequence(x: np.ndarray, name: str) -> np.ndarray:
    """A non-empty (T, n) float64 C-contiguous copy or view, as dtaidistance's C code needs."""
    # A writable C-contiguous copy: dtaidistance's C code refuses read-only buffers, and the
    # demonstrations' arrays are read-only by design.
    x = np.array(x, dtype=np.float64, order="C", copy=True)
    if x.ndim != 2 or x.shape[0] == 0 or x.shape[1] == 0:
        raise DataError(f"{name} must have shape (T, n) with T, n >= 1, got {x.shape}")
    return x


def _as_pair(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b = _as_sequence(a, "a"), _as_sequence(b, "b")
    if a.shape[1] != b.shape[1]:
        raise DataError(f"a and b must have the same dimension, got {a.shape} and {b.shape}")
    return a, b


def velocity_mse(pred: np.ndarray, true: np.ndarray) -> float:
    r"""Mean squared error of velocities, the paper's eq. (6).

    .. math:: \mathrm{MSE} = \frac{1}{n N} \sum_{i=1}^N \| \hat{\dot x}_i - \dot x_i \|^2

    i.e. the mean over samples *and* coordinates; the paper writes :math:`1 / 2N` for its
    2-D motions.

    Arguments:
        pred: Predicted velocities, shape (N, n).
        true: Demonstrated velocities at the same states, shape (N, n).

    Returns:
        The MSE, in squared velocity units. Non-finite inputs give a non-finite result.

    Raises:
        DataError: (a ValueError) if the shapes differ, are not 2-D, or are empty.
    """
    pred, true = np.asarray(pred, dtype=np.float64), np.asarray(true, dtype=np.float64)
    if pred.shape != true.shape or pred.ndim != 2 or pred.size == 0:
        raise DataError(
            f"pred and true must have the same non-empty shape (N, n), got {pred.shape} "
            f"and {true.shape}"
        )
    return float(np.mean((pred - true) ** 2))


def dtw(a: np.ndarray, b: np.ndarray) -> float:
    r"""Dynamic time warping distance of the paper's eq. (7) with :math:`q = 2`.

    .. math:: \mathrm{DTW}(a, b) = \min_{p} \Big( \sum_{(i, j) \in p} \|a_i - b_j\|^2 \Big)^{1/2}

    over the alignment paths :math:`p` from :math:`(1, 1)` to :math:`(T_a, T_b)` with steps
    :math:`(1, 0)`, :math:`(0, 1)` or :math:`(1, 1)`. This is dtaidistance's default
    (``dtw_ndim.distance``, inner distance squared Euclidean, square root of the total),
    the dependent multivariate DTW. It is *not* the classic sum of Euclidean distances; for
    that see :func:`dtw_sum`. It is symmetric, zero for identical sequences and, like any
    DTW, unchanged by repeating samples (a change of time parametrisation).

    Arguments:
        a: First sequence, shape (T_a, n).
        b: Second sequence, shape (T_b, n).

    Returns:
        The distance, in position units. Non-finite inputs (a diverged rollout) give a
        non-finite result.

    Raises:
        DataError: (a ValueError) if a sequence is not 2-D or empty, or the dimensions differ.
    """
    a, b = _as_pair(a, b)
    return float(_dtw_ndim.distance(a, b, use_c=_USE_C))


def dtw_sum(a: np.ndarray, b: np.ndarray) -> float:
    r"""Classic dynamic time warping: the minimal sum of Euclidean distances along a path.

    .. math:: \mathrm{DTW}_1(a, b) = \min_{p} \sum_{(i, j) \in p} \|a_i - b_j\|

    with the same alignment paths as :func:`dtw` (eq. (7) with :math:`q = 1`), computed by
    dtaidistance with ``inner_dist="euclidean"``. It is never smaller than :func:`dtw`,
    since :math:`\|\cdot\|_1 \ge \|\cdot\|_2` on the vector of distances along a path.

    Arguments:
        a: First sequence, shape (T_a, n).
        b: Second sequence, shape (T_b, n).

    Returns:
        The distance, in position units, which grows with the number of aligned pairs.

    Raises:
        DataError: (a ValueError) if a sequence is not 2-D or empty, or the dimensions differ.
    """
    a, b = _as_pair(a, b)
    return float(_dtw_ndim.distance(a, b, use_c=_USE_C, inner_dist="euclidean"))


def final_distance(path: np.ndarray, target: np.ndarray) -> float:
    r"""Euclidean distance :math:`\|x_T - x^*\|` of the last point of a rollout to the target.

    Arguments:
        path: A rollout, shape (T, n).
        target: The target, shape (n,).

    Raises:
        DataError: (a ValueError) if the path is not 2-D or empty, or the shapes disagree.
    """
    path = _as_sequence(path, "path")
    target = np.asarray(target, dtype=np.float64)
    if target.shape != path.shape[1:]:
        raise DataError(f"target must have shape {path.shape[1:]}, got {target.shape}")
    return float(np.linalg.norm(path[-1] - target))


def frechet(a: np.ndarray, b: np.ndarray) -> float:
    r"""Discrete Fréchet distance (Eiter & Mannila, 1994).

    .. math:: F(a, b) = \min_{p} \max_{(i, j) \in p} \|a_i - b_j\|

    over the same alignment paths as :func:`dtw` (monotone couplings from :math:`(1, 1)` to
    :math:`(T_a, T_b)` with steps :math:`(1, 0)`, :math:`(0, 1)`, :math:`(1, 1)`): the leash
    length needed when both walkers may only wait or step forward. It is a metric on
    sequences up to repeated samples, at least the discrete Hausdorff distance (every sample
    is on the path) and at most :func:`dtw` (the maximum of the distances along DTW's optimal
    path is at most the square root of the sum of their squares).

    The recursion :math:`c_{ij} = \max(\|a_i - b_j\|, \min(c_{i-1,j}, c_{i,j-1}, c_{i-1,j-1}))`
    is run one anti-diagonal :math:`i + j = k` at a time, since each cell only needs the two
    previous anti-diagonals: :math:`T_a + T_b - 1` vectorised steps and
    :math:`O(T_a + T_b)` memory.

    Arguments:
        a: First sequence, shape (T_a, n).
        b: Second sequence, shape (T_b, n).

    Returns:
        The distance, in position units. Non-finite inputs (a diverged rollout) give a
        non-finite result.

    Raises:
        DataError: (a ValueError) if a sequence is not 2-D or empty, or the dimensions differ.
    """
    a, b = _as_pair(a, b)
    len_a, len_b = len(a), len(b)
    # Anti-diagonals are stored by row index i, shifted by one so that index 0 is a permanent
    # +inf border standing for the cells outside the grid (i = -1 or j = -1).
    before_last = np.full(len_a + 1, np.inf)
    before_last[0] = 0.0  # the virtual cell (-1, -1), so that c_00 = ||a_0 - b_0||
    last = np.full(len_a + 1, np.inf)
    for k in range(len_a + len_b - 1):
        lo, hi = max(0, k - len_b + 1), min(k, len_a - 1)  # rows i on the diagonal, j = k - i
        gaps = np.linalg.norm(a[lo : hi + 1] - b[k - hi : k - lo + 1][::-1], axis=1)
        # Shifted index i + 1 holds row i: (i - 1, j) and (i - 1, j - 1) are at i, (i, j - 1)
        # is at i + 1 of the previous diagonals.
        best_before = np.minimum(
            np.minimum(last[lo : hi + 1], last[lo + 1 : hi + 2]), before_last[lo : hi + 1]
        )
        current = np.full(len_a + 1, np.inf)
        current[lo + 1 : hi + 2] = np.maximum(gaps, best_before)
        before_last, last = last, current
    return float(last[len_a])


def _cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The planar cross products u_x v_y - u_y v_x, shapes (*, 2) to (*,)."""
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _twice_signed_area(o: np.ndarray, p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Twice the signed area of the triangles (o, p, q), positive if counter-clockwise."""
    return _cross(p - o, q - o)


def _crossed_lobes(
    p0: np.ndarray, p1: np.ndarray, p2: np.ndarray, p3: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Where the edges p0p1 and p2p3 of the quadrilaterals p0p1p2p3 cross, and the lobes' area.

    If they cross at x = p0 + u (p1 - p0), the quadrilateral is the bow-tie made of the
    triangles (p0, x, p3) and (x, p1, p2), whose areas are u |p0 p1 p3| and (1 - u) |p0 p1 p2|
    since x divides the common base p0p1 in the ratio u : 1 - u.
    """
    side0, side1 = _twice_signed_area(p2, p3, p0), _twice_signed_area(p2, p3, p1)
    side2, side3 = _twice_signed_area(p0, p1, p2), _twice_signed_area(p0, p1, p3)
    crossed = (side0 * side1 < 0) & (side2 * side3 < 0)
    # Only used where crossed, i.e. where side0 and side1 have strictly opposite signs.
    with np.errstate(divide="ignore", invalid="ignore"):
        u = side0 / (side0 - side1)
        return crossed, 0.5 * (u * np.abs(side3) + (1 - u) * np.abs(side2))


def swept_error_area(reproduction: np.ndarray, demonstration: np.ndarray) -> float:
    r"""Swept error area (SEA) between a planar reproduction and its demonstration.

    The reproduction is resampled to the demonstration's :math:`T` samples by linear
    interpolation in the sample index (sample :math:`i` of the result is at fractional index
    :math:`i (T_r - 1) / (T - 1)` of the reproduction), so that :math:`r_i` and :math:`d_i` are
    time-aligned; then

    .. math:: \mathrm{SEA} = \sum_{i=1}^{T-1} \big|Q(r_i, r_{i+1}, d_{i+1}, d_i)\big|

    where :math:`|Q|` is the area *enclosed* by the quadrilateral with these vertices in this
    order (Khansari-Zadeh & Billard, 2014):

    * a simple quadrilateral, convex or not, has the shoelace area, half the absolute cross
      product of its diagonals, :math:`\tfrac12 |(d_{i+1} - r_i) \times (d_i - r_{i+1})|`;
    * a self-intersecting one (a bow-tie: the two paths cross between samples :math:`i` and
      :math:`i + 1`, or the segments :math:`r_i d_i` and :math:`r_{i+1} d_{i+1}` cross) has
      the sum of the absolute areas of its two triangular lobes, split at the crossing point;
      the shoelace formula would subtract one lobe from the other.

    This is not the triangle split :math:`|r_i r_{i+1} d_i| + |r_{i+1} d_{i+1} d_i|` of some
    SEA implementations, which equals it on convex quadrilaterals but counts twice the part of
    a crossed or concave one that lies outside it.

    The value is symmetric in its arguments when they have the same length, invariant under
    rotations and translations, and scales as the square of the positions. A single-sample
    demonstration encloses no quadrilateral and gives 0.

    Arguments:
        reproduction: The reproduced path, shape (T_r, 2).
        demonstration: The demonstrated path, shape (T, 2).

    Returns:
        The area, in squared position units. Non-finite inputs give a non-finite result.

    Raises:
        DataError: (a ValueError) if a path is not 2-D, is empty, or its points are not
            planar (second dimension other than 2).
    """
    rep = _as_sequence(reproduction, "reproduction")
    demo = _as_sequence(demonstration, "demonstration")
    if rep.shape[1] != 2 or demo.shape[1] != 2:
        raise DataError(
            "swept_error_area is defined for planar paths of shape (T, 2), got reproduction "
            f"{rep.shape} and demonstration {demo.shape}"
        )
    index = np.linspace(0.0, len(rep) - 1.0, len(demo))
    samples = np.arange(len(rep), dtype=np.float64)
    rep = np.stack([np.interp(index, samples, rep[:, k]) for k in range(2)], axis=-1)
    p0, p1, p2, p3 = rep[:-1], rep[1:], demo[1:], demo[:-1]
    # Only one pair of opposite edges of a quadrilateral can cross; try both pairings, the
    # second by relabelling the vertices p1 p2 p3 p0.
    crossed_paths, lobes_paths = _crossed_lobes(p0, p1, p2, p3)
    crossed_rungs, lobes_rungs = _crossed_lobes(p1, p2, p3, p0)
    simple = 0.5 * np.abs(_cross(p2 - p0, p3 - p1))
    areas = np.where(crossed_paths, lobes_paths, np.where(crossed_rungs, lobes_rungs, simple))
    return float(np.sum(areas))


class Predicts(Protocol):
    """Anything with a NumPy ``predict``, as every :class:`~snds.policy.Policy` has."""

    def predict(self, x: np.ndarray) -> np.ndarray:
        """Velocities (N, k) at states (N, m)."""


#: A velocity field on NumPy states: a policy, or a function from states (N, m) to (N, k).
VelocityField = Predicts | Callable[[np.ndarray], np.ndarray]

#: Points per side of :func:`field_roughness`'s grid by default: over the stability check's
#: box (6 extents wide) a spacing of 0.06 extents, finer than any demonstrated bend.
ROUGHNESS_GRID = 101
#: Speeds at most this fraction of the fastest on the grid count as zero (no direction).
ROUGHNESS_ZERO_SPEED = 1e-9


@dataclass(frozen=True)
class Roughness:
    """How much a field's direction turns between neighbouring grid points
    (:func:`field_roughness`).

    Attributes:
        median: Median angle between the velocities of neighbouring points, degrees.
        p90: Its 90th percentile, degrees (linear interpolation, NumPy's default).
        mean: Mean angle, degrees.
        max: Largest angle, degrees (180 where the field reverses between neighbours).
        pairs: Neighbour pairs measured.
        skipped: Neighbour pairs left out because a velocity had no direction (zero up to
            :data:`ROUGHNESS_ZERO_SPEED` of the fastest on the grid, or not finite).
        spacing: The grid's spacing along each of its two axes, user units, shape (2,).
    """

    median: float
    p90: float
    mean: float
    max: float
    pairs: int
    skipped: int
    spacing: tuple[float, float]

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return asdict(self)


def _angles(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Angles in [0, pi] between unit vectors u and v (*, k): Kahan's 2 atan2(|u - v|, |u + v|),
    accurate at every angle and in every dimension (arccos of the dot product loses half the
    digits near 0 and pi)."""
    return 2.0 * np.arctan2(np.linalg.norm(u - v, axis=-1), np.linalg.norm(u + v, axis=-1))


def field_roughness(
    field: VelocityField,
    demos: DemonstrationSet | None = None,
    *,
    box: tuple[np.ndarray, np.ndarray] | None = None,
    center: np.ndarray | None = None,
    n: int = ROUGHNESS_GRID,
    box_factor: float = CheckConfig().box_factor,
) -> Roughness:
    r"""How wiggly a velocity field is: the angles between the velocities of neighbouring points
    of a regular grid, far from the data included.

    The grid has :math:`n \times n` points :math:`x_{ij}` over a box of the plane of the
    first two coordinates, the others held at ``center`` (the target: the slice that
    :mod:`snds.plotting` draws). For every pair of horizontal or vertical neighbours,

    .. math:: \theta = \angle\big(\pi(x_{ij}), \pi(x_{i,j+1})\big), \quad
              \angle(u, v) = 2 \operatorname{atan2}\big(\|\hat u - \hat v\|,
              \|\hat u + \hat v\|\big) \in [0°, 180°]

    with :math:`\hat u = u / \|u\|`, taken between the whole velocity rows (in
    :math:`\mathbb{R}^n` for an n-D field, so a field that turns out of the plane counts
    too). There are :math:`2 n (n - 1)` pairs. A pair is skipped where a velocity has no
    direction: speed at most :data:`ROUGHNESS_ZERO_SPEED` times the fastest on the grid (the
    target of a stable field), or not finite. A uniform field scores 0 everywhere; a smooth
    field scores about the grid spacing times the rate at which its direction turns, so
    compare fields on the same grid; a kink or a fold shows as the tail (``p90``, ``max``).

    The box by default is the stability check's: the square of half-width ``box_factor``
    extents around the target (:attr:`snds.stability.CheckConfig.box_factor`, 3), where the
    check starts its rollouts.

    Arguments:
        field: A policy (anything with ``predict``), or a function from states (N, m) to
            velocities (N, k), NumPy in, NumPy out, user units.
        demos: The demonstrations that define the default box and center (their target and
            extent); not needed with ``box`` and ``center``.
        box: The grid's corners ``(low, high)`` in the first two coordinates, shape (2,) each.
        center: A state, shape (m,): the coordinates beyond the first two are held at its
            values (default: the demonstrations' target); its first two coordinates are
            unused.
        n: Points per side of the grid, at least 2.
        box_factor: Half-width of the default box, in extents.

    Returns:
        The angles' median, 90th percentile, mean and maximum in degrees (NaN if no pair has
        two directions), the pairs measured and skipped, and the spacing.

    Raises:
        DataError: (a ValueError) for ``n`` < 2, an empty or inverted box, a state of fewer
            than two coordinates, neither ``demos`` nor ``box`` and ``center``, or a field
            that returns a wrong shape.
    """
    if n < 2:
        raise DataError(f"the grid needs n >= 2 points per side, got {n}")
    if center is None:
        if demos is None:
            raise DataError("field_roughness needs demos, or both box and center")
        center = demos.target
    center = np.asarray(center, dtype=np.float64)
    if center.ndim != 1 or center.shape[0] < 2:
        raise DataError(f"center must be a state of >= 2 coordinates, got shape {center.shape}")
    if box is None:
        if demos is None:
            raise DataError("field_roughness needs demos, or both box and center")
        half = box_factor * demos.extent()
        target = np.asarray(demos.target, dtype=np.float64)[:2]
        low, high = target - half, target + half
    else:
        low, high = (np.asarray(b, dtype=np.float64).reshape(2) for b in box)
    if not (high > low).all():
        raise DataError(f"the box must have high > low in both coordinates, got {low}, {high}")
    x1, x2 = np.linspace(low[0], high[0], n), np.linspace(low[1], high[1], n)
    grid1, grid2 = np.meshgrid(x1, x2)  # (n, n), x2 along rows
    points = np.tile(center, (n * n, 1))
    points[:, 0], points[:, 1] = grid1.ravel(), grid2.ravel()
    predict = getattr(field, "predict", field)
    velocity = np.asarray(predict(points), dtype=np.float64)
    if velocity.ndim != 2 or velocity.shape[0] != n * n:
        raise DataError(
            f"the field must return velocities of shape ({n * n}, k), got {velocity.shape}"
        )
    velocity = velocity.reshape(n, n, -1)
    speed = np.linalg.norm(velocity, axis=-1)
    finite = np.isfinite(speed)
    top = float(speed[finite].max()) if finite.any() else 0.0
    directed = finite & (speed > ROUGHNESS_ZERO_SPEED * top)
    # Directions only where there is one; elsewhere any unit vector, masked out below.
    unit = np.where(directed[..., None], velocity / np.where(directed, speed, 1.0)[..., None], 1.0)
    pairs = [(unit[:, :-1], unit[:, 1:], directed[:, :-1] & directed[:, 1:])]  # along x1
    pairs.append((unit[:-1], unit[1:], directed[:-1] & directed[1:]))  # along x2
    angles = np.concatenate([np.degrees(_angles(u, v))[keep] for u, v, keep in pairs])
    total = 2 * n * (n - 1)
    spacing = (float(x1[1] - x1[0]), float(x2[1] - x2[0]))
    if angles.size == 0:
        nan = float("nan")
        return Roughness(nan, nan, nan, nan, pairs=0, skipped=total, spacing=spacing)
    return Roughness(
        median=float(np.median(angles)),
        p90=float(np.percentile(angles, 90)),
        mean=float(angles.mean()),
        max=float(angles.max()),
        pairs=int(angles.size),
        skipped=total - int(angles.size),
        spacing=spacing,
    )
