"""Metrics against hand-computed values, and the properties any DTW, Fréchet or area must have."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from snds import metrics
from snds.data import Demonstration, Demonstrations
from snds.errors import DataError
from snds.metrics import (
    dtw,
    dtw_sum,
    final_distance,
    frechet,
    swept_error_area,
    velocity_mse,
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


# --- discrete Fréchet distance -----------------------------------------------------------


def reference_frechet(a: np.ndarray, b: np.ndarray) -> float:
    """Eiter & Mannila's recursion cell by cell, written independently of the vectorised one."""
    gap = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)
    acc = np.full((len(a) + 1, len(b) + 1), np.inf)
    acc[0, 0] = 0.0
    for i in range(1, len(a) + 1):
        for j in range(1, len(b) + 1):
            best = min(acc[i - 1, j], acc[i, j - 1], acc[i - 1, j - 1])
            acc[i, j] = max(gap[i - 1, j - 1], best)
    return float(acc[-1, -1])


def test_frechet_hand_example():
    # a = (0, 1, 2), b = (0, 2). Gaps |a_i - b_j|:
    #         b=0  b=2
    #   a=0    0    2
    #   a=1    1    1
    #   a=2    2    0
    # c[i, j] = max(gap[i, j], min(c[i-1, j], c[i, j-1], c[i-1, j-1])):
    #   c[0, 0] = 0, c[0, 1] = max(2, 0) = 2, c[1, 0] = max(1, 0) = 1,
    #   c[1, 1] = max(1, min(2, 1, 0)) = 1, c[2, 0] = max(2, 1) = 2,
    #   c[2, 1] = max(0, min(c[1, 1], c[2, 0], c[1, 0])) = max(0, min(1, 2, 1)) = 1.
    # So F = 1: a_1 = 1 must be paired with b_0 = 0 or b_1 = 2, one unit away either way.
    assert frechet(A_SHORT, B_SHORT) == 1.0
    assert frechet(B_SHORT, A_SHORT) == 1.0
    # a = (0, 1, 1, 0) against b = (0, 0): every a_i meets a zero, so F = max |a_i| = 1,
    # where DTW adds the gaps up (sqrt(2), see above).
    assert frechet(A_BUMP, B_BUMP) == 1.0


def test_frechet_against_a_single_point_is_the_largest_distance():
    # With one sample in b the only path pairs every a_i with b_0.
    a = np.array([[3.0, 4.0], [0.0, 1.0], [0.0, 0.0]])
    assert frechet(a, np.zeros((1, 2))) == 5.0
    assert frechet(np.zeros((1, 2)), a) == 5.0


def test_frechet_ignores_repeated_samples_of_the_same_path():
    rng = np.random.default_rng(6)
    a = rng.normal(size=(30, 3))
    slow = np.repeat(a, rng.integers(1, 5, size=len(a)), axis=0)
    assert frechet(a, a) == 0.0
    assert frechet(slow, a) == 0.0
    assert frechet(a, slow) == 0.0


@settings(max_examples=300, deadline=None)
@given(pairs)
def test_frechet_is_the_min_max_over_paths(pair):
    a, b = pair
    f = frechet(a, b)
    # The same distances computed in another order may differ in the last bit (hypothesis
    # found 1712.1297045613346 against ...348): compare to a few ulps, not bit for bit.
    ulps = 1e-13
    assert f == pytest.approx(reference_frechet(a, b), rel=ulps, abs=1e-300)
    assert f == pytest.approx(frechet(b, a), rel=ulps, abs=1e-300)
    assert frechet(a, a) == 0.0
    # Every path starts at (0, 0) and ends at (T_a - 1, T_b - 1).
    ends = max(np.linalg.norm(a[0] - b[0]), np.linalg.norm(a[-1] - b[-1]))
    assert f >= ends * (1 - ulps)
    # Every sample of either sequence is on the path, paired with some sample of the other
    # no farther than f: f is at least the discrete Hausdorff distance.
    gap = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=-1)
    assert f >= max(gap.min(axis=1).max(), gap.min(axis=0).max()) * (1 - ulps)
    # On DTW's optimal path, the largest gap is at most the root of the sum of squared gaps.
    assert f <= dtw(a, b) * (1 + 1e-12) + 1e-9


@settings(max_examples=200, deadline=None)
@given(equal_length_pairs)
def test_frechet_is_at_most_the_diagonal_path(pair):
    a, b = pair
    assert frechet(a, b) <= np.linalg.norm(a - b, axis=-1).max()


def test_frechet_of_long_unequal_sequences_matches_the_reference():
    # Speed is measured by benchmarks, not here; this checks the anti-diagonal sweep on long,
    # unequal lengths, where an off-by-one in the diagonal bounds would show.
    rng = np.random.default_rng(7)
    a, b = rng.normal(size=(300, 2)).cumsum(0), rng.normal(size=(170, 2)).cumsum(0)
    assert frechet(a, b) == reference_frechet(a, b)


# --- swept error area ---------------------------------------------------------------------


def even_odd_area(quad: np.ndarray, cells: int = 600) -> tuple[float, float]:
    """Area inside a quadrilateral by counting grid cell centres, and the error bound.

    A quadrilateral winds at most once around any point, so the even-odd rule finds the
    region it encloses, bow-tie lobes included. The count is off by at most the cells the
    boundary crosses, about perimeter / h cells of area h^2.
    """
    low, high = quad.min(0), quad.max(0)
    h = float((high - low).max()) / cells
    xs = np.arange(low[0] + h / 2, high[0], h)
    ys = np.arange(low[1] + h / 2, high[1], h)
    x, y = np.meshgrid(xs, ys)
    inside = np.zeros_like(x, dtype=bool)
    for p, q in zip(quad, np.roll(quad, -1, axis=0)):
        # The ray from (x, y) towards +x crosses pq if pq straddles height y right of x.
        straddles = (p[1] > y) != (q[1] > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_cross = p[0] + (y - p[1]) * (q[0] - p[0]) / (q[1] - p[1])
        inside ^= straddles & (x < x_cross)
    perimeter = float(np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1).sum())
    return float(inside.sum()) * h * h, 2 * perimeter * h


def _quad_sea(p0, p1, p2, p3) -> float:
    """SEA of one quadrilateral (r_0, r_1, d_1, d_0) = (p0, p1, p2, p3)."""
    return swept_error_area(np.array([p0, p1]), np.array([p3, p2]))


def test_swept_area_between_parallel_segments():
    # r from (0, 0) to (2, 0), d from (0, 1) to (2, 1), 3 samples each: two unit squares.
    demo = np.array([[0.0, 1.0], [1.0, 1.0], [2.0, 1.0]])
    rep = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    assert swept_error_area(rep, demo) == 2.0
    assert swept_error_area(demo, rep) == 2.0
    # The reproduction is resampled onto the demonstration's 3 samples, uniform in index:
    # from 2 or 5 evenly spaced samples of the same segment it becomes rep exactly.
    assert swept_error_area(rep[[0, 2]], demo) == 2.0
    assert swept_error_area(np.linspace(rep[0], rep[-1], 5), demo) == 2.0
    # Against a demonstration of length 3 in 4 samples, the reproduction's samples land at
    # x = 0, 2/3, 4/3, 2: together the quadrilaterals tile the trapezoid with parallel sides 2
    # and 3 at distance 1, of area (2 + 3) / 2.
    assert swept_error_area(rep, np.linspace([0.0, 1.0], [3.0, 1.0], 4)) == pytest.approx(2.5)


def test_swept_area_of_identical_paths_is_zero():
    rng = np.random.default_rng(8)
    path = rng.normal(size=(25, 2))
    assert swept_error_area(path, path) == 0.0
    line = np.linspace([0.0, 0.0], [3.0, -1.0], 7)
    assert swept_error_area(line[[0, -1]], line) == pytest.approx(0.0, abs=1e-15)
    # One demonstration sample encloses nothing.
    assert swept_error_area(path, path[:1] + 1.0) == 0.0


def test_swept_area_of_crossing_paths_counts_both_lobes():
    # r from (0, 0) to (1, 1) and d from (0, 1) to (1, 0) cross at (1/2, 1/2): the bow-tie
    # (0,0) (1,1) (1,0) (0,1) has two lobes of base 1 and height 1/2, 1/4 each. The shoelace
    # formula would give 1/4 - 1/4 = 0, the triangle split |(0,0)(1,1)(0,1)| +
    # |(1,1)(1,0)(0,1)| = 1/2 + 1/2 = 1.
    assert _quad_sea([0, 0], [1, 1], [1, 0], [0, 1]) == 0.5
    # Same when the rungs r_0 d_0 and r_1 d_1 cross instead: (0,0) (1,0) (0,1) (1,1).
    assert _quad_sea([0, 0], [1, 0], [0, 1], [1, 1]) == 0.5


def test_swept_area_of_a_concave_quadrilateral():
    # (1, 1/2) (0, 0) (2, 0) (1, 1) is the triangle (0,0) (2,0) (1,1) of area 1 with the notch
    # (0,0) (1,1/2) (1,1) of area |(1, 1/2) x (1, 1)| / 2 = 1/4 cut out: 3/4. The triangle
    # split |(1,1/2)(0,0)(1,1)| + |(0,0)(2,0)(1,1)| = 1/4 + 1 would count the notch twice.
    assert _quad_sea([1, 0.5], [0, 0], [2, 0], [1, 1]) == 0.75


def test_swept_area_matches_a_grid_count_on_random_quadrilaterals():
    # Random quadrilaterals are convex, concave and crossed in comparable numbers.
    rng = np.random.default_rng(9)
    for quad in rng.normal(size=(40, 4, 2)):
        area, tolerance = even_odd_area(quad)
        assert _quad_sea(*quad) == pytest.approx(area, abs=tolerance)


plane_pairs = st.integers(1, 10).flatmap(lambda t: _pair(2, t, t))


@settings(max_examples=200, deadline=None)
@given(plane_pairs, st.floats(-math.pi, math.pi), st.floats(0.1, 10.0))
def test_swept_area_is_a_euclidean_area(pair, angle, scale):
    rep, demo = pair
    sea = swept_error_area(rep, demo)
    assert sea >= 0.0
    # The same quadrilaterals in reverse vertex order.
    assert swept_error_area(demo, rep) == pytest.approx(sea, rel=1e-9, abs=1e-6)
    # Unchanged by a rigid motion, multiplied by scale^2 under a scaling.
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    shift = np.array([3.0, -7.0])
    moved = swept_error_area(rep @ rotation.T + shift, demo @ rotation.T + shift)
    assert moved == pytest.approx(sea, rel=1e-6, abs=1e-3)
    assert swept_error_area(scale * rep, scale * demo) == pytest.approx(
        scale**2 * sea, rel=1e-6, abs=1e-3
    )


# --- final distance -----------------------------------------------------


def test_final_distance_is_from_the_last_point():
    path = np.array([[100.0, 100.0], [4.0, 5.0]])
    assert final_distance(path, np.array([1.0, 1.0])) == 5.0


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
        (frechet, (np.zeros((3, 1)), np.zeros((3, 2)))),
        (frechet, (np.zeros((0, 2)), np.zeros((3, 2)))),
        (frechet, (np.zeros(3), np.zeros(3))),
        (swept_error_area, (np.zeros((3, 3)), np.zeros((3, 3)))),
        (swept_error_area, (np.zeros((3, 2)), np.zeros((3, 1)))),
        (swept_error_area, (np.zeros(3), np.zeros(3))),
        (swept_error_area, (np.zeros((0, 2)), np.zeros((3, 2)))),
        (final_distance, (np.zeros((3, 2)), np.zeros(3))),
        (final_distance, (np.zeros((0, 2)), np.zeros(2))),
    ],
)
def test_bad_shapes_and_scales_raise_data_error(call, args):
    with pytest.raises(DataError):
        call(*args)


def test_swept_area_names_the_planar_requirement():
    with pytest.raises(DataError, match=r"planar paths of shape \(T, 2\)"):
        swept_error_area(np.zeros((3, 3)), np.zeros((3, 3)))


# --- field_roughness -------------------------------------------------------------------------

# The rotation field pi(x) = A x, A = [[0, -1], [1, 0]], turns each position by 90 degrees, so
# the angle between the velocities at two points is the angle between the points as seen from
# the origin. On the 3 x 3 grid x1 in {1, 2, 3}, x2 in {0, 1, 2} the points' polar angles are
# atan2(x2, x1):
#            x1=1     x1=2     x1=3
#   x2=0     0        0        0
#   x2=1     45       26.565   18.435
#   x2=2     63.435   45       33.690
# Horizontal neighbours: 0, 0 | 18.435, 8.130 | 18.435, 11.310; vertical ones: 45, 18.435 |
# 26.565, 18.435 | 18.435, 15.255. Sorted, the 12 angles are 0, 0, 8.130, 11.310, 15.255,
# 18.435 (five times), 26.565, 45: median 18.435 (= atan(1/3)), mean 198.435 / 12, and the
# 90th percentile at index 0.9 * 11 = 9.9, between 18.435 and 26.565: 18.435 + 0.9 * 8.130.
ROTATION = np.array([[0.0, -1.0], [1.0, 0.0]])
ROTATION_BOX = (np.array([1.0, 0.0]), np.array([3.0, 2.0]))
ATAN_THIRD, ATAN_HALF = math.degrees(math.atan(1 / 3)), math.degrees(math.atan(1 / 2))


def test_a_uniform_field_has_zero_roughness() -> None:
    result = metrics.field_roughness(
        lambda x: np.tile([2.0, -1.0], (len(x), 1)),
        box=(np.zeros(2), np.ones(2)),
        center=np.zeros(2),
        n=7,
    )
    assert result.median == result.p90 == result.max == 0.0
    assert (result.pairs, result.skipped) == (2 * 7 * 6, 0)


def test_a_rotation_field_gives_the_hand_computed_angles() -> None:
    result = metrics.field_roughness(
        lambda x: x @ ROTATION.T, box=ROTATION_BOX, center=np.zeros(2), n=3
    )
    assert result.median == pytest.approx(ATAN_THIRD, rel=1e-12)
    assert result.p90 == pytest.approx(ATAN_THIRD + 0.9 * (ATAN_HALF - ATAN_THIRD), rel=1e-12)
    assert result.mean == pytest.approx(198.435 / 12, rel=1e-5)
    assert result.max == pytest.approx(45.0, rel=1e-12)
    assert (result.pairs, result.skipped, result.spacing) == (12, 0, (1.0, 1.0))


def test_a_kink_shows_in_the_tail_not_the_median() -> None:
    # GIVEN a field that turns by 45 degrees across x2 = 0.5: on the 4 x 4 grid over [0, 1]^2
    # (x2 in 0, 1/3, 2/3, 1) only the 4 vertical pairs across the line differ, of 24 pairs.
    def kinked(x: np.ndarray) -> np.ndarray:
        return np.where((x[:, 1] > 0.5)[:, None], [1.0, 1.0], [3.0, 0.0])

    result = metrics.field_roughness(kinked, box=(np.zeros(2), np.ones(2)), center=np.zeros(2), n=4)
    # THEN 20 angles are 0 and 4 are 45: median 0, 90th percentile at index 20.7 (a 45), mean 7.5.
    assert (result.median, result.pairs) == (0.0, 24)
    assert result.p90 == pytest.approx(45.0)
    assert result.mean == pytest.approx(7.5)


def test_pairs_without_a_direction_are_skipped() -> None:
    # GIVEN the rotation field at the origin's grid: the centre of the 3 x 3 grid over
    # [-1, 1]^2 is the origin, where the velocity is 0, and one more point returns NaN.
    def field(x: np.ndarray) -> np.ndarray:
        v = x @ ROTATION.T
        v[np.all(x == [1.0, 1.0], axis=1)] = np.nan
        return v

    result = metrics.field_roughness(field, box=(-np.ones(2), np.ones(2)), center=np.zeros(2), n=3)
    # THEN the 4 pairs with the origin and the 2 with (1, 1) are skipped; the other 6 pairs
    # are neighbours one step apart on the square's rim, each 45 degrees apart as seen from it.
    assert (result.pairs, result.skipped) == (6, 6)
    assert result.median == result.max == pytest.approx(45.0)


def test_a_field_without_any_direction_gives_nan() -> None:
    result = metrics.field_roughness(
        np.zeros_like, box=(np.zeros(2), np.ones(2)), center=np.zeros(2), n=3
    )
    assert math.isnan(result.median) and (result.pairs, result.skipped) == (0, 12)


def test_roughness_defaults_to_the_stability_checks_box_and_the_slice_through_the_target() -> None:
    # GIVEN 3-D demonstrations with target (1, 2, 5) and extent 2, and a field that is uniform
    # only in the slice x3 = 5 and records the states it was asked about
    path = np.array([[3.0, 2.0, 5.0], [1.0, 2.0, 5.0]])
    demo = Demonstration(positions=path, velocities=np.zeros_like(path), times=np.arange(2.0))
    demos = Demonstrations((demo,), path[-1])
    asked = []

    def field(x: np.ndarray) -> np.ndarray:
        asked.append(x)
        return np.where(np.isclose(x[:, 2:], 5.0), 1.0, x[:, :1] * x[:, 1:2]) * [1.0, 0.0, 0.0]

    result = metrics.field_roughness(field, demos, n=5)
    # THEN it scores 0 on the grid over target +- 3 extents with x3 held at the target's 5
    (x,) = asked
    assert result.max == 0.0 and result.pairs == 40
    assert x[:, 0].min() == -5.0 and x[:, 0].max() == 7.0
    assert x[:, 1].min() == -4.0 and x[:, 1].max() == 8.0
    assert (x[:, 2] == 5.0).all()
    assert result.spacing == (3.0, 3.0)


def test_roughness_of_a_policy_uses_its_predict(policy64, spiral: Demonstrations) -> None:
    # A policy is scored through predict (user states in, user velocities out).
    result = metrics.field_roughness(policy64, spiral, n=9)
    expected = metrics.field_roughness(policy64.predict, spiral, n=9)
    assert result == expected and 0 < result.median < 180


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"n": 1}, "n >= 2"),
        ({"box": (np.ones(2), np.ones(2))}, "high > low"),
        ({"center": None}, "needs demos"),
        ({"center": np.zeros(1)}, ">= 2 coordinates"),
    ],
)
def test_roughness_refuses_bad_grids(kwargs: dict, match: str) -> None:
    settings = {"box": (np.zeros(2), np.ones(2)), "center": np.zeros(2)} | kwargs
    with pytest.raises(DataError, match=match):
        metrics.field_roughness(lambda x: x, **settings)
