"""Properties of the demonstration containers, the normalisation, the splits and the target."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from snds.data import (
    Demonstration,
    Demonstrations,
    Normalization,
    Split,
    common_target,
    no_split,
    split_demos,
    split_samples,
)
from snds.errors import DataError


def spiral(length: int, dt: float, start: np.ndarray, end: np.ndarray) -> Demonstration:
    """A decaying spiral from ``start`` to ``end`` with its exact velocities."""
    times = dt * np.arange(length)
    s = times / times[-1]
    decay = np.cos(np.pi * s / 2)  # 1 at the start, 0 at the end
    turn = np.stack([np.cos(3 * s), np.sin(3 * s)], axis=-1)
    radius = np.linalg.norm(start - end)
    positions = end + radius * decay[:, None] * turn
    positions[0], positions[-1] = start, end  # cos(pi / 2) is not exactly 0
    velocities = np.gradient(positions, times, axis=0)
    return Demonstration(positions, velocities, times)


@pytest.fixture
def demos() -> Demonstrations:
    target = np.array([2.0, -1.0])
    rng = np.random.default_rng(0)
    return Demonstrations(
        tuple(
            spiral(length, dt, target + rng.normal(size=2) * 5, target)
            for length, dt in [(101, 0.01), (150, 0.02), (77, 0.005)]
        ),
        target,
        "spirals",
    )


# Demonstration and Demonstrations.


def test_demonstration_copies_and_freezes_its_arrays():
    positions = np.zeros((3, 2))
    demo = Demonstration(positions, np.zeros((3, 2)), np.arange(3.0))
    positions[0, 0] = 7.0
    assert demo.positions[0, 0] == 0.0
    with pytest.raises(ValueError):
        demo.positions[0, 0] = 1.0


@pytest.mark.parametrize(
    "positions, velocities, times, message",
    [
        (np.zeros((1, 2)), np.zeros((1, 2)), np.zeros(1), "at least 2"),
        (np.zeros((3, 2)), np.zeros((3, 3)), np.arange(3.0), "differs"),
        (np.zeros((3, 2)), np.zeros((3, 2)), np.arange(4.0), "times has 4"),
        (np.zeros((3, 2)), np.zeros((3, 2)), np.array([0.0, 1.0, 1.0]), "strictly increasing"),
        (np.zeros((3, 2)), np.zeros((3, 2)), np.array([0.0, 2.0, 1.0]), "strictly increasing"),
        (np.full((3, 2), np.nan), np.zeros((3, 2)), np.arange(3.0), "NaN or inf"),
        (np.zeros((3, 2)), np.full((3, 2), np.inf), np.arange(3.0), "NaN or inf"),
        (np.zeros(3), np.zeros(3), np.arange(3.0), "dimension"),
    ],
)
def test_demonstration_rejects_malformed_arrays(positions, velocities, times, message):
    with pytest.raises(DataError, match=message):
        Demonstration(positions, velocities, times)


def test_demonstrations_reject_mixed_dimensions_and_bad_targets(demos):
    three_d = Demonstration(np.zeros((2, 3)), np.zeros((2, 3)), np.arange(2.0))
    with pytest.raises(DataError, match="different dimensions"):
        Demonstrations((demos[0], three_d), np.zeros(2))
    with pytest.raises(DataError, match="target has dimension 3"):
        Demonstrations(demos.demos, np.zeros(3))
    with pytest.raises(DataError, match="no demonstrations"):
        Demonstrations((), np.zeros(2))


def test_select_and_first_keep_order_and_target(demos):
    picked = demos.select([2, 0])
    assert picked.demos == (demos[2], demos[0])
    np.testing.assert_array_equal(picked.target, demos.target)
    assert demos.first(2).demos == demos.demos[:2]
    with pytest.raises(DataError):
        demos.select([3])
    with pytest.raises(DataError):
        demos.first(0)


def test_summaries_match_hand_computed_values(demos):
    assert demos.positions().shape == (101 + 150 + 77, 2)
    distances = [np.linalg.norm(d.positions - demos.target, axis=1).max() for d in demos]
    assert demos.extent() == pytest.approx(max(distances))
    assert demos.max_duration() == pytest.approx(149 * 0.02)
    assert demos.mean_dt() == pytest.approx((100 * 0.01 + 149 * 0.02 + 76 * 0.005) / 325)


# Normalization.


def test_normalization_maps_target_to_zero_extent_and_max_speed_to_one(demos):
    norm = Normalization.fit(demos)
    np.testing.assert_allclose(norm.positions_to_model(demos.target), 0.0, atol=1e-15)
    radii = np.linalg.norm(norm.positions_to_model(demos.positions()), axis=-1)
    speeds = np.linalg.norm(norm.velocities_to_model(demos.velocities()), axis=-1)
    assert radii.max() == pytest.approx(1.0, rel=1e-12)
    assert speeds.max() == pytest.approx(1.0, rel=1e-12)


@settings(deadline=None, max_examples=50)
@given(
    center=st.lists(st.floats(-1e3, 1e3), min_size=3, max_size=3),
    length=st.floats(1e-3, 1e3),
    time=st.floats(1e-3, 1e3),
    seed=st.integers(0, 2**32 - 1),
)
def test_normalization_round_trips(center, length, time, seed):
    norm = Normalization(np.array(center), length, time)
    x = np.random.default_rng(seed).normal(scale=100.0, size=(20, 3))
    np.testing.assert_allclose(norm.positions_from_model(norm.positions_to_model(x)), x, atol=1e-9)
    np.testing.assert_allclose(
        norm.velocities_from_model(norm.velocities_to_model(x)), x, rtol=1e-12
    )


def test_normalized_velocities_are_derivatives_in_normalized_time(demos):
    # GIVEN a short step h along each velocity, i.e. x(t + h) ~ x + h v
    norm = Normalization.fit(demos)
    x, v, h = demos.positions(), demos.velocities(), 1e-6
    # THEN the model displacement over model time h / tau is the model velocity
    model_step = norm.positions_to_model(x + h * v) - norm.positions_to_model(x)
    np.testing.assert_allclose(model_step / (h / norm.time), norm.velocities_to_model(v), atol=1e-6)


def test_normalization_survives_json(demos):
    norm = Normalization.fit(demos)
    again = Normalization.from_dict(json.loads(json.dumps(norm.to_dict())))
    np.testing.assert_array_equal(again.center, norm.center)
    assert (again.length, again.time) == (norm.length, norm.time)


@pytest.mark.parametrize(
    "record", [{}, {"center": [0.0], "length": 1.0}, {"center": [0.0], "length": 0, "time": 1}]
)
def test_malformed_normalization_records_raise_data_error(record):
    with pytest.raises(DataError):
        Normalization.from_dict(record)


def test_normalization_refuses_motionless_data():
    still = Demonstration(np.zeros((3, 2)), np.zeros((3, 2)), np.arange(3.0))
    with pytest.raises(DataError, match="zero extent"):
        Normalization.fit(Demonstrations((still,), np.zeros(2)))


# Splits.


@pytest.mark.parametrize("fraction", [0.0, 0.2, 0.5, 0.9])
def test_split_samples_holds_out_the_fraction_of_each_demo(demos, fraction):
    split = split_samples(demos, test_fraction=fraction, seed=3)
    for demo, train, test in zip(demos, split.train, split.test(), strict=True):
        assert train.shape == test.shape == demo.times.shape
        assert not (train & test).any() and (train | test).all()
        assert abs(test.sum() - fraction * len(demo.times)) <= 1


def test_split_samples_is_reproducible_and_depends_on_the_seed(demos):
    first = split_samples(demos, test_fraction=0.2, seed=7)
    again = split_samples(demos, test_fraction=0.2, seed=7)
    other = split_samples(demos, test_fraction=0.2, seed=8)
    assert all(np.array_equal(a, b) for a, b in zip(first.train, again.train, strict=True))
    assert not all(np.array_equal(a, b) for a, b in zip(first.train, other.train, strict=True))


@pytest.mark.parametrize("fraction", [-0.1, 1.0, 1.5])
def test_split_samples_rejects_fractions_outside_zero_one(demos, fraction):
    with pytest.raises(DataError, match="test_fraction"):
        split_samples(demos, test_fraction=fraction, seed=0)


def test_split_demos_holds_out_whole_demonstrations(demos):
    split = split_demos(demos, test_demos=[1])
    assert [mask.all() for mask in split.train] == [True, False, True]
    assert [not mask.any() for mask in split.train] == [False, True, False]
    with pytest.raises(DataError, match="out of range"):
        split_demos(demos, test_demos=[3])
    with pytest.raises(DataError, match="nothing left"):
        split_demos(demos, test_demos=[0, 1, 2])


def test_no_split_trains_on_everything(demos):
    split = no_split(demos)
    assert isinstance(split, Split)
    for mask, demo in zip(split.train, demos, strict=True):
        assert mask.all() and mask.shape == demo.times.shape


# The common target.


def test_common_target_moves_ends_onto_the_mean_end_and_keeps_starts():
    # GIVEN demonstrations ending near, not at, (1, 1)
    ends = [np.array([1.02, 0.99]), np.array([0.97, 1.0]), np.array([1.01, 1.01])]
    raw = [spiral(50 + 10 * i, 0.01, np.array([-3.0, 2.0 + i]), end) for i, end in enumerate(ends)]
    # WHEN they are moved onto a common target
    target, moved = common_target(raw, max_end_spread=0.25)
    # THEN the target is the mean end, every end is exactly on it, every start is unchanged
    np.testing.assert_allclose(target, np.mean(ends, axis=0), rtol=1e-15)
    for before, after in zip(raw, moved, strict=True):
        assert np.array_equal(after.positions[-1], target)
        np.testing.assert_array_equal(after.positions[0], before.positions[0])
        np.testing.assert_array_equal(after.times, before.times)
        # AND the shift is a linear ramp whose constant rate is the velocities' shift
        offset = target - before.positions[-1]
        ramp = (before.times - before.times[0]) / before.duration
        shift = after.positions - before.positions
        np.testing.assert_allclose(shift, ramp[:, None] * offset, atol=1e-14)
        rate = after.velocities - before.velocities
        np.testing.assert_allclose(
            rate, np.broadcast_to(offset / before.duration, rate.shape), atol=1e-13
        )


def test_common_target_leaves_demos_already_at_it_untouched(demos):
    target, moved = common_target(demos.demos, max_end_spread=0.0)
    np.testing.assert_array_equal(target, demos.target)
    assert all(a is b for a, b in zip(moved, demos.demos, strict=True))


def test_common_target_refuses_ends_farther_apart_than_allowed():
    # Two straight motions of extent ~10 whose ends are 2 apart: each 1 from their mean.
    a = Demonstration(np.array([[10.0, 0.0], [0.0, 1.0]]), np.zeros((2, 2)), np.arange(2.0))
    b = Demonstration(np.array([[10.0, 0.0], [0.0, -1.0]]), np.zeros((2, 2)), np.arange(2.0))
    extent = np.hypot(10.0, 0.0)
    with pytest.raises(DataError, match="do not end at a common target"):
        common_target([a, b], max_end_spread=0.99 / extent)
    target, _ = common_target([a, b], max_end_spread=1.01 / extent)
    np.testing.assert_array_equal(target, [0.0, 0.0])


def test_common_target_rejects_bad_input(demos):
    three_d = Demonstration(np.zeros((2, 3)), np.zeros((2, 3)), np.arange(2.0))
    with pytest.raises(DataError, match="different dimensions"):
        common_target([demos[0], three_d], max_end_spread=0.25)
    with pytest.raises(DataError, match="no demonstrations"):
        common_target([], max_end_spread=0.25)
    with pytest.raises(DataError, match="max_end_spread"):
        common_target(demos.demos, max_end_spread=-1.0)


@settings(deadline=None, max_examples=50)
@given(
    seed=st.integers(0, 2**32 - 1),
    count=st.integers(1, 6),
    dim=st.integers(1, 4),
    scale=st.floats(1e-6, 1e6),
)
def test_common_target_always_hits_the_target_exactly(seed, count, dim, scale):
    rng = np.random.default_rng(seed)
    raw = []
    for _ in range(count):
        length = int(rng.integers(2, 40))
        times = np.cumsum(rng.uniform(0.001, 0.1, size=length))
        raw.append(
            Demonstration(scale * rng.normal(size=(length, dim)), np.zeros((length, dim)), times)
        )
    try:
        target, moved = common_target(raw, max_end_spread=1.0)
    except DataError:
        return  # ends too far apart for this random draw; the refusal is the property
    assert all(np.array_equal(demo.positions[-1], target) for demo in moved)
