import numpy as np
import torch

from snds.data import Demonstration, Demonstrations, split_samples
from snds.evaluate import accuracy, path_reference, reproduce
from snds.policy import float64_copy

from conftest import linear_policy, make_policy


def _line(samples: int) -> Demonstration:
    t = np.linspace(0.0, 4.0, samples)
    x = np.stack([np.exp(-t), 0 * t], axis=1) - np.exp(-4.0) * np.array([1.0, 0.0])
    return Demonstration(positions=x, velocities=np.gradient(x, t, axis=0), times=t)


def test_reproductions_of_several_demos_equal_one_at_a_time(spiral):
    policy = float64_copy(make_policy(spiral))
    together = reproduce(policy, spiral, [0, 1, 2])
    for i, path in enumerate(together):
        alone = reproduce(policy, spiral, [i])[0]
        # (the batch's matrix products may round apart by an ulp, then grow along the path)
        np.testing.assert_allclose(path, alone, rtol=0, atol=1e-7 * spiral.extent())
        assert path.shape == spiral[i].positions.shape


def test_a_long_demonstration_is_compared_on_a_resampled_path():
    short, long = _line(1000), _line(20_001)
    assert path_reference(short) is short.positions
    reference = path_reference(long, max_samples=5000)
    # uniform in time, ends kept, on the demonstrated curve
    assert reference.shape == (5000, 2)
    np.testing.assert_array_equal(reference[[0, -1]], long.positions[[0, -1]])
    t = np.linspace(0.0, 4.0, 5000)
    np.testing.assert_allclose(reference[:, 0], np.exp(-t) - np.exp(-4.0), atol=1e-7)
    # and the reproduction of pi = -x is measured as for the short demonstration (both are
    # exp(-4) = 0.018 off the shifted line at the end)
    records = []
    for demo in (short, long):
        demos = Demonstrations((demo,), np.zeros(2))
        split = split_samples(demos, test_fraction=0.2, seed=0)
        records.append(accuracy(linear_policy(1.0), demos, split))
    assert abs(records[0]["frechet"] - np.exp(-4.0)) < 1e-3
    # (the resampled one's Euler step is 5x shorter: 1e-4 closer to the exact flow)
    assert abs(records[1]["frechet"] - records[0]["frechet"]) < 5e-4


def test_predict_in_chunks_equals_one_batch(spiral):
    policy = make_policy(spiral)
    x = np.random.default_rng(0).normal(size=(1000, 2)) * 10
    whole = policy(torch.as_tensor(x)).detach().numpy()
    scale = np.abs(whole).max()
    np.testing.assert_allclose(policy.predict(x, chunk=97), whole, rtol=0, atol=1e-13 * scale)
    assert policy.predict(x.reshape(10, 100, 2)).shape == (10, 100, 2)


def test_a_long_pose_demonstration_keeps_its_orientations_when_resampled():
    # GIVEN a pose demonstration of 20,001 samples (positions on a line, turning about z)
    from snds.data.poses import PoseDemonstration

    line = _line(20_001)
    angle = np.linspace(0.0, 1.0, len(line.times))
    quats = np.stack([0 * angle, 0 * angle, np.sin(angle / 2), np.cos(angle / 2)], axis=1)
    demo = PoseDemonstration(np.c_[line.positions, 0 * angle], quats, line.times)
    # WHEN it is resampled for the path metrics
    reference = path_reference(demo, max_samples=5000)
    # THEN positions are interpolated, orientations are the demonstration's own samples there
    assert reference.shape == (5000, 7)
    np.testing.assert_array_equal(reference[[0, -1]], demo.states[[0, -1]])
    np.testing.assert_allclose(np.linalg.norm(reference[:, 3:], axis=1), 1.0, atol=1e-12)
    turned = 2 * np.arctan2(reference[:, 5], reference[:, 6])
    np.testing.assert_allclose(turned, np.linspace(0.0, 1.0, 5000), atol=1e-4)
