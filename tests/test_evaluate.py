import numpy as np
import pytest
import torch

from snds.data import Demonstration, Demonstrations, split_samples
from snds.evaluate import accuracy, evaluate, path_reference, reproduce
from snds.policy import float64_copy
from snds.stability import CheckConfig

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


def test_retrace_measures_every_demonstration_over_one_and_a_half_durations():
    # GIVEN pi = -x and a demonstration along x(t) = e^-t - e^-4 (shifted to end at 0): the
    # rollout from its start, (1 - e^-4) e^-t, runs 1.5 x 4 s and ends (1 - e^-4) e^-6 from
    # the target
    from snds.evaluate import retrace

    demos = Demonstrations((_line(1000),), np.zeros(2))
    record, _ = retrace(linear_policy(1.0), demos)
    extent = demos.extent()
    assert record["retrace_durations"] == 1.5
    end = (1 - np.exp(-4.0)) * np.exp(-6.0) / extent
    assert abs(record["retrace_final_max"] - end) < 1e-4
    # both walk the same segment of the x axis, so the Frechet leash is the end gap (the
    # leash may wait: timing is not compared)
    assert record["retrace_frechet_max"] >= record["retrace_final_max"]
    assert abs(record["retrace_frechet_max"] - end) < 1e-4
    assert record["retrace_frechet_median"] == record["retrace_frechet_max"]  # one demo


def test_a_demonstration_of_few_samples_is_retraced_as_the_line_through_them():
    # GIVEN the same motion sampled at 3 points only: Euler steps of its 2 s spacing would be
    # no rollout at all (1 - 2 = -1: it would jump across the target)
    from snds.evaluate import RETRACE_SAMPLES, retrace

    t = np.array([0.0, 2.0, 4.0])
    x = np.stack([np.exp(-t) - np.exp(-4.0), 0 * t], axis=1)
    demo = Demonstration(positions=x, velocities=np.gradient(x, t, axis=0), times=t)
    demos = Demonstrations((demo,), np.zeros(2))
    assert path_reference(demo, min_samples=RETRACE_SAMPLES).shape == (RETRACE_SAMPLES, 2)
    record, _ = retrace(linear_policy(1.0), demos)
    # THEN the rollout takes 200 steps per duration (not 2 of 2 s) and the demonstration is
    # the line through its points: on the same axis, the gap is the end's
    # (Euler's (1 - 0.02)^300 is e^-6.06: 6 % short of the exact flow's end)
    end = (1 - np.exp(-4.0)) * np.exp(-6.0) / demos.extent()
    assert abs(record["retrace_final_max"] - end) < 0.07 * end
    # and the discrete leash is within the resampled polyline's spacing (0.0086) of that gap,
    # where Euler steps of 2 s (x -> -x) would have put it near the whole extent
    assert record["retrace_frechet_max"] < record["retrace_final_max"] + 0.0087


def test_warnings_say_what_fails_and_nothing_when_all_is_well():
    from snds.evaluate import warnings

    good = {
        "retrace_frechet_max": 0.02,
        "retrace_final_max": 0.001,
        "retrace_durations": 1.5,
        "stability": {
            "largest_safe_dt": 0.02,
            "dt": 0.01,
            "rollouts": 500,
            "converged_fraction": 1.0,
            "horizon": 40.0,
            "decrease_violations": 0,
        },
    }
    assert warnings(good) == []
    bad = {
        **good,
        "retrace_frechet_max": 0.28,
        "stability": {**good["stability"], "largest_safe_dt": 3.3e-5, "converged_fraction": 0.9},
    }
    said = warnings(bad)
    assert len(said) == 3
    assert said[0].startswith("rollouts from the demonstrations' starts do not retrace them: ")
    assert "up to 28 % of the extent (over 5 %)" in said[0] and "--phase-codes" in said[0]
    assert "--phase-codes" not in warnings(bad, hint=False)[0]
    assert said[1] == (
        "stiff field: the largest safe Euler step 3.3e-05 s is below the data's step 0.01 s "
        "(a controller at the data's rate needs the guarded step)"
    )
    assert said[2] == "50 of 500 random starts had not arrived after 40 s"


def test_accuracy_reuses_the_retrace_rollouts_as_its_own(spiral):
    # GIVEN the rollouts of retrace (1.5 durations) from every start of 400-sample demos
    from snds.evaluate import retrace

    policy = float64_copy(make_policy(spiral))
    _, prefixes = retrace(policy, spiral)
    # THEN their first duration is accuracy's own reproduction, to the batch's rounding
    assert sorted(prefixes) == [0, 1, 2]
    for i, path in enumerate(reproduce(policy, spiral, [0, 1, 2])):
        np.testing.assert_allclose(prefixes[i], path, rtol=0, atol=1e-7 * spiral.extent())
    split = split_samples(spiral, test_fraction=0.2, seed=0)
    given = accuracy(policy, spiral, split, paths=prefixes)
    own = accuracy(policy, spiral, split)
    assert given["dtw"] == pytest.approx(own["dtw"], rel=1e-6)


def test_an_evaluation_is_typed_and_writes_the_records_keys(spiral):
    # GIVEN the exact policy pi(x) = -x evaluated with a small check
    policy = linear_policy(1.0)
    split = split_samples(spiral, test_fraction=0.2, seed=0)
    check = CheckConfig(rollouts=3, samples=50)
    evaluation = evaluate(policy, spiral, split, check=check, threads=1)
    record = evaluation.to_dict()
    # THEN the record is metrics.json's: accuracy, retrace, stability, warnings, in that order
    assert list(record) == [*evaluation.accuracy, *evaluation.retrace, "stability", "warnings"]
    assert record["stability"] == evaluation.stability.to_dict()
    assert record["warnings"] == list(evaluation.warnings)
    assert evaluation.stability.rollouts == 3 and evaluation.stability.samples_checked == 50
    # typed figures, and the old dict-style reads give the same numbers
    assert evaluation.dtw_paper == record["dtw_paper"] == evaluation["dtw_paper"]
    assert evaluation.velocity_mse_paper == record["velocity_mse_paper"]
    assert {**evaluation}.keys() == record.keys() and "stability" in evaluation
    # a run adds the fit's time, and nothing else changes
    timed = evaluation.with_train_seconds(2.5).to_dict()
    assert timed == {**record, "train_seconds": 2.5}
