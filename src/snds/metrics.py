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
"""

from __future__ import annotations

import numpy as np
from dtaidistance import dtw as _dtw
from dtaidistance import dtw_ndim as _dtw_ndim

from snds.errors import DataError

__all__ = [
    "dtw",
    "dtw_sum",
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
