"""The one definition of "arrived" and "recovered" (snds.arrival), on hand-made motions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from snds.arrival import arrival_time, distance_to_path, recovery_time


def test_arrival_is_the_first_time_from_which_the_motion_stays_within_the_tolerance():
    times = np.arange(6.0)
    # GIVEN a motion that enters the tolerance at t=1, leaves at t=2 and enters for good at t=3
    distances = np.array([5.0, 0.5, 2.0, 0.9, 0.1, 0.0])
    # THEN it arrived at t=3, not at its first entry
    assert arrival_time(times, distances, 1.0) == 3.0
    # a motion that ends outside has not arrived; one that starts inside arrived at once
    assert math.isnan(arrival_time(times, distances[::-1], 1.0))
    assert arrival_time(times, np.zeros(6), 1.0) == 0.0
    # a non-finite distance is never within the tolerance
    assert math.isnan(arrival_time(times[:2], np.array([0.0, np.nan]), 1.0))


def test_arrival_of_several_error_components_needs_every_one_within_its_tolerance():
    times = np.arange(4.0)
    errors = np.array([[2.0, 0.5], [0.1, 0.5], [0.1, 0.05], [0.0, 0.0]])  # distance, angle
    assert arrival_time(times, errors, np.array([1.0, 0.1])) == 2.0


def test_distance_to_a_polyline_is_to_its_segments_not_its_vertices():
    path = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    points = np.array([[5.0, 3.0], [12.0, 5.0], [-4.0, -3.0], [10.0, 0.0]])
    np.testing.assert_allclose(distance_to_path(points, path), [3.0, 2.0, 5.0, 0.0])


def test_recovered_means_back_on_the_path_not_back_at_the_same_distance_to_the_target():
    # GIVEN a straight path to the target at the origin, walked at unit speed from (10, 0)
    path = np.column_stack([np.linspace(10.0, 0.0, 11), np.zeros(11)])
    times = np.arange(11.0)
    # WHEN a push at t=2 moves the motion 4 sideways, on the circle of its distance to the
    # target, and it then returns to the path by 1 a second, moving along it at the same time
    radius = 8.0
    side = [4.0, 3.0, 2.0, 1.0, 0.0, 0.0, 0.0]
    pushed = [np.array([radius - k, s]) for k, s in enumerate(side)]
    positions = np.vstack([path[:2], *pushed, path[9:]])
    # THEN it is back on the path (within 0.5) 4 s after the push, when the sideways offset
    # is gone, although it was never further from the target than before the push
    assert np.linalg.norm(positions[2]) <= np.linalg.norm(path[1]) + 1.0
    assert recovery_time(times, positions, path, push_time=2.0, tolerance=0.5) == 4.0
    # a push within the tolerance needs no recovery; one that ends off the path never recovers
    assert recovery_time(times, path, path, push_time=2.0, tolerance=0.5) == 0.0
    off = positions + np.array([0.0, 1.0])
    assert recovery_time(times, off, path, push_time=2.0, tolerance=0.5) is None


@pytest.mark.parametrize("push_time", [20.0])
def test_a_push_after_the_end_has_no_recovery(push_time: float):
    times = np.arange(3.0)
    path = np.zeros((3, 2))
    assert recovery_time(times, path, path, push_time=push_time, tolerance=0.1) is None
