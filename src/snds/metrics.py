r"""Accuracy metrics of a learned motion: velocity MSE, DTW and distance to the target.

Pure NumPy, so that any method (SNDS, baselines, recorded data) is scored by the same code.

Two conventions of dynamic time warping are in use and give different numbers; both are here
under distinct names:

* :func:`dtw` is the paper's eq. (7) with :math:`q = 2`, the square root of the minimal *sum of
  squared* Euclidean distances along an alignment path (dtaidistance's default);
* :func:`dtw_sum` is the classic DTW, the minimal *sum of* Euclidean distances.

The paper's scale (Fig. 4) divides positions relative to the target by their largest norm
in the motion, and velocities by their largest norm; :func:`paper_scale` computes both and
:func:`velocity_mse_paper` and :func:`dtw_paper` apply them.
"""

from __future__ import annotations

import numpy as np
from dtaidistance import dtw as _dtw
from dtaidistance import dtw_ndim as _dtw_ndim

from snds.errors import DataError

__all__ = [
    "dtw",
    "dtw_paper",
    "dtw_sum",
    "final_distance",
    "mean_dtw",
    "paper_scale",
    "velocity_mse",
    "velocity_mse_paper",
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


def _check_scale(scale: float, name: str) -> float:
    scale = float(scale)
    if not (np.isfinite(scale) and scale > 0):
        raise DataError(f"{name} must be finite and positive, got {scale}")
    return scale


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


def paper_scale(positions: np.ndarray, velocities: np.ndarray) -> tuple[float, float]:
    r"""The paper's normalisation constants of a motion.

    Returns :math:`\max_i \|x_i - x^*\|` and :math:`\max_i \|\dot x_i\|` over all the
    samples of all the demonstrations of the motion, so that dividing by them puts every
    motion on the scale of the paper's Fig. 4.

    Arguments:
        positions: Positions *relative to the target*, :math:`x - x^*`, of all demonstrations
            stacked, shape (N, n).
        velocities: Velocities of all demonstrations stacked, shape (M, n).

    Returns:
        The position scale and the velocity scale.

    Raises:
        DataError: (a ValueError) if an array is not 2-D or is empty.
    """
    positions = _as_sequence(positions, "positions")
    velocities = _as_sequence(velocities, "velocities")
    return (
        float(np.linalg.norm(positions, axis=-1).max()),
        float(np.linalg.norm(velocities, axis=-1).max()),
    )


def velocity_mse_paper(pred: np.ndarray, true: np.ndarray, velocity_scale: float) -> float:
    r"""Velocity MSE in the paper's scale: :func:`velocity_mse` of ``pred / s`` and ``true / s``.

    Arguments:
        pred: Predicted velocities, shape (N, n).
        true: Demonstrated velocities, shape (N, n).
        velocity_scale: The largest velocity norm of the motion, :math:`s > 0`
            (second output of :func:`paper_scale`).

    Returns:
        The dimensionless MSE, equal to :math:`\mathrm{MSE} / s^2`.
    """
    s = _check_scale(velocity_scale, "velocity_scale")
    return velocity_mse(np.asarray(pred) / s, np.asarray(true) / s)


def dtw_paper(a: np.ndarray, b: np.ndarray, position_scale: float) -> float:
    r"""DTW in the paper's scale: :func:`dtw` of ``a / s`` and ``b / s``.

    Arguments:
        a: First sequence, shape (T_a, n).
        b: Second sequence, shape (T_b, n).
        position_scale: The largest norm of positions relative to the target in the motion,
            :math:`s > 0` (first output of :func:`paper_scale`).

    Returns:
        The dimensionless distance, equal to :math:`\mathrm{DTW}(a, b) / s`.
    """
    s = _check_scale(position_scale, "position_scale")
    return dtw(np.asarray(a) / s, np.asarray(b) / s)


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


def mean_dtw(rollouts: list[np.ndarray], demos: list[np.ndarray], scale: float = 1.0) -> float:
    r"""Mean of :func:`dtw` over pairs, rollout :math:`i` against demonstration :math:`i`.

    .. math:: \frac{1}{K} \sum_{i=1}^K \mathrm{DTW}(r_i / s, d_i / s)

    Arguments:
        rollouts: K rollouts, shapes (T_i, n).
        demos: The K demonstrations they reproduce, shapes (T'_i, n).
        scale: The divisor :math:`s > 0`, e.g. the position scale of :func:`paper_scale`
            (pass positions relative to the target if the scale is relative to it; DTW only
            sees differences, so a common shift does not matter).

    Raises:
        DataError: (a ValueError) if the lists are empty or of different lengths.
    """
    s = _check_scale(scale, "scale")
    if len(rollouts) != len(demos) or len(rollouts) == 0:
        raise DataError(
            f"need as many rollouts as demonstrations, at least one, got {len(rollouts)} "
            f"and {len(demos)}"
        )
    return float(np.mean([dtw_paper(r, d, s) for r, d in zip(rollouts, demos, strict=True)]))
