"""Metrics against hand-computed values, and the properties any DTW must have."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from snds import metrics
from snds.metrics import (
    dtw,
    dtw_paper,
    dtw_sum,
    final_distance,
    mean_dtw,
    paper_scale,
    velocity_mse,
    velocity_mse_paper,
)

# a = (0, 1, 2), b = (0, 2) in 1-D. Cost matrix C[i, j] = |a_i - b_j|^2:
#         b=0  b=2
#   a=0    0    4
#   a=1    1    1
#   a=2    4    0
# Accumulated D[i, j] = C[i, j] + min(D[i-1, j], D[i, j-1], D[i-1, j-1]):
#   D[0, 0] = 0, D[0, 1] = 4, D[1, 0] = 1, D[1, 1] = 1 + min(0, 4, 1) = 1,
#   D[2, 0] = 5, D[2, 1] = 0 + min(1, 1, 5) = 1.
# So the best sum is 1 (e.g. path (0,0), (1,0), (2,1)) and DTW = sqrt(1) = 1. With |.| instead
# of |.|^2 the costs 0 and 1 are unchanged on that path, so the classic DTW is also 1.
A_SHORT, B_SHORT = np.array([[0.0], [1.0], [2.0]]), np.array([[0.0], [2.0]])

# a = (0, 1, 1, 0), b = (0, 0): each a_i must be aligned to a zero, so the path costs are the
# a_i themselves: squared sum 0 + 1 + 1 + 0 = 2, DTW = sqrt(2); absolute sum = 2. The two
# conventions differ here, which is why they have different names.
A_BUMP, B_BUMP = np.array([[0.0], [1.0], [1.0], [0.0]]), np.zeros((2, 1))


def reference_dtw(a: np.ndarray, b: np.ndarray, q: int) -> float:
    """Textbook O(T_a T_b) dynamic programme of eq. (7), written independently of dtaidistance."""
    cost = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1) ** q
    acc = np.full((len(a) + 1, len(b) + 1), np.inf)
    acc[0, 0] = 0.0
    for i in range(1, len(a) + 1):
        for j in range(1, len(b) + 1):
            acc[i, j] = cost[i - 1, j - 1] + min(acc[i - 1, j], acc[i, j - 1], acc[i - 1, j - 1])
    return float(acc[-1, -1] ** (1.0 / q))


# --- velocity MSE -------------------------------------------------------------------------


def test_velocity_mse_is_mean_over_samples_and_coordinates():
    # One unit error in one coordinate of one of 2 samples in 2-D: 1 / (2 * 2).
    assert velocity_mse(np.array([[1.0, 0.0], [0.0, 0.0]]), np.zeros((2, 2))) == 0.25
    # ||(1, 2)||^2 = 5 over 1 sample and 2 coordinates.
    assert velocity_mse(np.array([[1.0, 2.0]]), np.zeros((1, 2))) == 2.5
    # Symmetric in its arguments and zero on exact predictions.
    x = np.random.default_rng(0).normal(size=(7, 3))
    assert velocity_mse(x, 2 * x) == velocity_mse(2 * x, x)
    assert velocity_mse(x, x) == 0.0


def test_velocity_mse_paper_divides_velocities_by_the_scale():
    rng = np.random.default_rng(1)
    pred, true = rng.normal(size=(5, 2)), rng.normal(size=(5, 2))
    assert velocity_mse_paper(10 * pred, 10 * true, 10.0) == pytest.approx(
        velocity_mse(pred, true), rel=1e-14
    )
    assert velocity_mse_paper(pred, true, 2.0) == pytest.approx(velocity_mse(pred, true) / 4)


# --- DTW ----------------------------------------------------------------------------------


def test_dtw_hand_examples():
    assert dtw(A_SHORT, B_SHORT) == pytest.approx(1.0)
    assert dtw_sum(A_SHORT, B_SHORT) == pytest.approx(1.0)
    assert dtw(A_BUMP, B_BUMP) == pytest.approx(math.sqrt(2.0))
    assert dtw_sum(A_BUMP, B_BUMP) == pytest.approx(2.0)


def test_dtw_against_a_single_point_is_the_norm_of_all_distances():
    # With one sample in b the only path pairs every a_i with b_0.
    a = np.array([[3.0, 4.0], [0.0, 1.0], [0.0, 0.0]])
    assert dtw(a, np.zeros((1, 2))) == pytest.approx(math.sqrt(25 + 1 + 0))
    assert dtw_sum(a, np.zeros((1, 2))) == pytest.approx(5 + 1 + 0)


def test_dtw_is_symmetric():
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(13, 3)), rng.normal(size=(8, 3))
    assert dtw(a, b) == pytest.approx(dtw(b, a), rel=1e-12)
    assert dtw_sum(a, b) == pytest.approx(dtw_sum(b, a), rel=1e-12)


def test_dtw_ignores_repeated_samples_of_the_same_path():
    # A slower traversal of the same points (each sample held 1-4 steps) is a
    # re-parametrisation in time, which DTW is built to forgive.
    rng = np.random.default_rng(3)
    a = rng.normal(size=(20, 2))
    slow = np.repeat(a, rng.integers(1, 5, size=len(a)), axis=0)
    assert dtw(slow, a) == 0.0
    assert dtw(a, slow) == 0.0
    assert dtw_sum(slow, a) == 0.0


def test_dtw_accepts_non_contiguous_and_integer_input():
    a = np.arange(12).reshape(2, 6).T  # integers, Fortran-ordered view
    assert dtw(a, a.astype(np.float64)) == 0.0
    assert dtw(a[::2], a[::2] + 1) == pytest.approx(math.sqrt(3 * 2))


def test_pure_python_fallback_agrees_with_c(monkeypatch):
    rng = np.random.default_rng(4)
    a, b = rng.normal(size=(9, 2)), rng.normal(size=(6, 2))
    fast, fast_sum = dtw(a, b), dtw_sum(a, b)
    monkeypatch.setattr(metrics, "_USE_C", False)
    assert dtw(a, b) == pytest.approx(fast, rel=1e-12)
    assert dtw_sum(a, b) == pytest.approx(fast_sum, rel=1e-12)


def test_dtw_paper_divides_positions_by_the_scale():
    rng = np.random.default_rng(5)
    a, b = rng.normal(size=(10, 2)), rng.normal(size=(7, 2))
    assert dtw_paper(10 * a, 10 * b, 10.0) == pytest.approx(dtw(a, b), rel=1e-12)


def _pair(dim: int, len_a: int, len_b: int):
    elements = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
    return st.tuples(
        arrays(np.float64, (len_a, dim), elements=elements),
        arrays(np.float64, (len_b, dim), elements=elements),
    )


pairs = st.tuples(st.integers(1, 3), st.integers(1, 10), st.integers(1, 10)).flatmap(
    lambda s: _pair(*s)
)
equal_length_pairs = st.tuples(st.integers(1, 3), st.integers(1, 10)).flatmap(
    lambda s: _pair(s[0], s[1], s[1])
)


@settings(max_examples=200, deadline=None)
@given(pairs)
def test_dtw_is_a_nonnegative_minimum_over_paths(pair):
    a, b = pair
    d, d_sum = dtw(a, b), dtw_sum(a, b)
    assert d >= 0.0
    assert dtw(a, a) == 0.0
    # Same value as an independent dynamic programme, for both conventions.
    assert d == pytest.approx(reference_dtw(a, b, q=2), rel=1e-9, abs=1e-9)
    assert d_sum == pytest.approx(reference_dtw(a, b, q=1), rel=1e-9, abs=1e-9)
    # On the optimal path of dtw_sum, sum of distances >= sqrt(sum of their squares) >= dtw.
    assert d <= d_sum * (1 + 1e-12) + 1e-9


@settings(max_examples=200, deadline=None)
@given(equal_length_pairs)
def test_dtw_is_at_most_the_diagonal_path(pair):
    # The diagonal (i, i) is one admissible path, so the minimum cannot exceed its cost.
    a, b = pair
    diagonal = math.sqrt(float(np.sum((a - b) ** 2)))
    assert dtw(a, b) <= diagonal * (1 + 1e-12) + 1e-9


# --- scales, final distance, mean DTW -----------------------------------------------------


def test_paper_scale_is_the_largest_norms():
    positions = np.array([[3.0, 4.0], [0.0, 1.0], [-1.0, 0.0]])
    velocities = np.array([[1.0, 0.0], [0.0, -2.0]])
    assert paper_scale(positions, velocities) == (5.0, 2.0)


def test_final_distance_is_from_the_last_point():
    path = np.array([[100.0, 100.0], [4.0, 5.0]])
    assert final_distance(path, np.array([1.0, 1.0])) == 5.0


def test_mean_dtw_averages_pairs_and_divides_by_the_scale():
    # The two hand examples above: DTW 1 and sqrt(2).
    rollouts, demos = [A_SHORT, A_BUMP], [B_SHORT, B_BUMP]
    assert mean_dtw(rollouts, demos) == pytest.approx((1 + math.sqrt(2)) / 2)
    assert mean_dtw(rollouts, demos, scale=2.0) == pytest.approx((1 + math.sqrt(2)) / 4)


# --- bad input ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("call", "args"),
    [
        (velocity_mse, (np.zeros((3, 2)), np.zeros((3, 3)))),
        (velocity_mse, (np.zeros((3, 2)), np.zeros((2, 2)))),
        (velocity_mse, (np.zeros((0, 2)), np.zeros((0, 2)))),
        (velocity_mse, (np.zeros(3), np.zeros(3))),
        (dtw, (np.zeros((3, 2)), np.zeros((3, 3)))),
        (dtw, (np.zeros((0, 2)), np.zeros((3, 2)))),
        (dtw, (np.zeros(3), np.zeros(3))),
        (dtw_sum, (np.zeros((3, 1)), np.zeros((3, 2)))),
        (dtw_paper, (np.zeros((3, 2)), np.zeros((3, 2)), 0.0)),
        (velocity_mse_paper, (np.zeros((3, 2)), np.zeros((3, 2)), -1.0)),
        (paper_scale, (np.zeros((0, 2)), np.zeros((3, 2)))),
        (final_distance, (np.zeros((3, 2)), np.zeros(3))),
        (final_distance, (np.zeros((0, 2)), np.zeros(2))),
        (mean_dtw, ([], [])),
        (mean_dtw, ([np.zeros((3, 2))], [])),
        (mean_dtw, ([np.zeros((3, 2))], [np.zeros((3, 2))], float("nan"))),
    ],
)
def test_bad_shapes_and_scales_raise_value_error(call, args):
    with pytest.raises(ValueError):
        call(*args)
