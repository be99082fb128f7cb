"""Bare arrays in (.npy, .mat pose matrices, 4x4 transforms) and the reading options: rate,
quaternion order, length unit, idle trimming, and the end-spread error that names the
outlier. The real pose recordings of ../shared/data load through the options alone."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
import scipy.io
from scipy.spatial.transform import Rotation

from snds.cli import build_parser
from snds.cli._common import data_source
from snds.data import DataSource, ReadOptions, load_recording
from snds.data.arrays import project_rotations
from snds.data.options import DataWarning
from snds.data.poses import PoseDemonstrations
from snds.errors import DataError

from conftest import SHARED_DATA
from recording_files import line_poses

CLFD = SHARED_DATA / "clfd"
PANDA = SHARED_DATA / "panda_kinesthetic_pose.mat"


def wxyz(poses: np.ndarray) -> np.ndarray:
    """Poses (..., 7) with the quaternion written (w, x, y, z)."""
    return np.concatenate([poses[..., :3], np.roll(poses[..., 3:], 1, axis=-1)], axis=-1)


def two_demos() -> np.ndarray:
    """(2, 40, 7): two pose demonstrations ending at the origin, (x, y, z, w)."""
    second = line_poses(40, turn=0.6)
    second[:, :3] *= [1.0, -1.0, 1.0]
    return np.stack([line_poses(40), second])


def test_npy_poses_need_their_rate_and_quaternion_order(tmp_path):
    # GIVEN a (2, 40, 7) array in centimetres with (w, x, y, z) quaternions and no times
    path = tmp_path / "demos.npy"
    poses = two_demos()
    np.save(path, wxyz(poses) * [100, 100, 100, 1, 1, 1, 1])
    # THEN reading it without the order, or without the rate, names the missing option
    with pytest.raises(DataError, match="demos.npy: .*--quaternion-order xyzw or wxyz"):
        load_recording(path, options=ReadOptions(rate=50))
    with pytest.raises(DataError, match="demos.npy: .*stores no time stamps.*--rate HZ"):
        load_recording(path, options=ReadOptions(quaternion_order="wxyz"))
    # AND with all three, the poses are the written ones in metres at 50 Hz
    options = ReadOptions(rate=50, quaternion_order="wxyz", length_unit="cm")
    demos = load_recording(path, options=options)
    assert isinstance(demos, PoseDemonstrations) and len(demos) == 2
    np.testing.assert_allclose(demos[0].positions, poses[0, :, :3], atol=1e-12)
    np.testing.assert_allclose(np.abs(np.sum(demos[0].orientations * poses[0, :, 3:], 1)), 1)
    np.testing.assert_allclose(demos[0].times, np.arange(40) / 50)


def test_centimetres_without_a_unit_warn_that_a_pose_task_is_50_m_wide(tmp_path):
    path = tmp_path / "demos.npy"
    np.save(path, two_demos() * [100, 100, 100, 1, 1, 1, 1])
    options = ReadOptions(rate=50, quaternion_order="xyzw")
    with pytest.warns(DataWarning, match="span 40 m.*--length-unit cm"):
        load_recording(path, options=options)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_recording(
            path, options=ReadOptions(rate=50, quaternion_order="xyzw", length_unit="cm")
        )


def test_the_wrong_quaternion_order_keeps_every_angle_so_only_the_user_can_say_it():
    # The reason the order is an option, not a guess: permuting the four numbers keeps
    # |q_a . q_b| for every pair, so a misread path turns at the very same angular speeds.
    rng = np.random.default_rng(0)
    q = Rotation.random(50, random_state=1).as_quat()
    misread = np.roll(q, 1, axis=1)
    i, j = rng.integers(0, 50, (2, 200))
    np.testing.assert_allclose(
        np.abs(np.sum(q[i] * q[j], 1)), np.abs(np.sum(misread[i] * misread[j], 1)), atol=1e-15
    )
    # ... yet they are other rotations.
    assert not Rotation.from_quat(misread[0]).approx_equal(Rotation.from_quat(q[0])).any()


def test_npy_positions_and_a_single_demonstration(tmp_path):
    # (T, 2): one demonstration of a straight line at 10 Hz, velocity (-1, -0.5) units/s.
    t = np.arange(11) / 10
    line = np.stack([1 - t, 0.5 - 0.5 * t], axis=1)
    np.save(tmp_path / "line.npy", line)
    demos = load_recording(tmp_path / "line.npy", options=ReadOptions(rate=10))
    assert len(demos) == 1 and demos.dim == 2
    np.testing.assert_allclose(demos[0].velocities, np.tile([-1.0, -0.5], (11, 1)), atol=1e-12)
    # mm to metres: positions and velocities divided by 1000.
    metres = load_recording(tmp_path / "line.npy", options=ReadOptions(rate=10, length_unit="mm"))
    np.testing.assert_allclose(metres[0].velocities, demos[0].velocities / 1000, atol=1e-15)


def transforms(poses: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transforms (..., 4, 4) of poses (..., 7)."""
    out = np.zeros((*poses.shape[:-1], 4, 4))
    out[..., :3, :3] = (
        Rotation.from_quat(poses[..., 3:].reshape(-1, 4))
        .as_matrix()
        .reshape(*poses.shape[:-1], 3, 3)
    )
    out[..., :3, 3] = poses[..., :3]
    out[..., 3, 3] = 1.0
    return out


def test_transforms_are_projected_onto_rotations_and_their_deviation_reported(tmp_path):
    # GIVEN (2, 40, 4, 4) transforms whose rotation blocks carry 0.4 % noise
    poses = two_demos()
    noisy = transforms(poses)
    noisy[..., :3, :3] += 0.004 * np.random.default_rng(0).uniform(-1, 1, (2, 40, 3, 3))
    np.save(tmp_path / "tf.npy", noisy)
    # WHEN read: a warning reports the deviation, and the rotations are the nearest ones
    with pytest.warns(DataWarning, match=r"deviate from SO\(3\) by up to 0\.0"):
        demos = load_recording(tmp_path / "tf.npy", options=ReadOptions(rate=30))
    angles = (
        Rotation.from_quat(demos[0].orientations[:-1]) * Rotation.from_quat(poses[0, :-1, 3:]).inv()
    ).magnitude()
    assert angles.max() < 0.01
    # AND exact transforms, one demonstration (T, 4, 4), read silently
    np.save(tmp_path / "one.npy", transforms(poses[0]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        one = load_recording(tmp_path / "one.npy", options=ReadOptions(rate=30))
    np.testing.assert_allclose(one[0].positions, poses[0, :, :3], atol=1e-12)


def test_a_reflection_or_a_scale_is_not_a_rotation(tmp_path):
    tf = transforms(two_demos())
    mirrored = tf.copy()
    mirrored[1, 5, :3, 0] *= -1
    np.save(tmp_path / "mirror.npy", mirrored)
    with pytest.raises(DataError, match="mirror.npy: the 3x3 blocks are not rotations"):
        load_recording(tmp_path / "mirror.npy", options=ReadOptions(rate=30))
    tf[0, 3, 3, 0] = 0.5
    np.save(tmp_path / "bottom.npy", tf)
    with pytest.raises(DataError, match=r"transform \(0, 3\) is not homogeneous"):
        load_recording(tmp_path / "bottom.npy", options=ReadOptions(rate=30))


def test_projection_is_the_nearest_rotation():
    rotation = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    quaternion, deviation = project_rotations(rotation * 1.002)
    assert deviation == pytest.approx(0.002, rel=1e-9)
    assert Rotation.from_quat(quaternion).approx_equal(Rotation.from_matrix(rotation), 1e-12)


def test_mat_pose_matrix_with_a_time_row_and_the_key_option(tmp_path):
    # GIVEN a struct whose field holds 8 x T: x, y, z, (w, x, y, z), t at uneven steps
    poses = line_poses(40)
    t = np.cumsum(np.r_[0, np.full(39, 0.002) + 0.001 * (np.arange(39) % 2)])
    pose = np.concatenate([wxyz(poses).T, t[None]])
    path = tmp_path / "rec.mat"
    scipy.io.savemat(path, {"ee": {"pose": pose, "dt": 0.0025}, "other": np.eye(3)})
    demos = load_recording(path, options=ReadOptions(quaternion_order="wxyz"))
    np.testing.assert_allclose(demos[0].times, t)
    np.testing.assert_allclose(demos[0].positions, poses[:, :3], atol=1e-12)
    # WHEN a second candidate appears, the key picks one and without it the error lists both
    scipy.io.savemat(path, {"ee": {"pose": pose}, "goal": pose[:7]})
    with pytest.raises(
        DataError, match="pose matrices found: ee.pose, goal; choose one with --key"
    ):
        load_recording(path, options=ReadOptions(quaternion_order="wxyz"))
    # AND 7 rows (no time row) take the stated rate
    picked = load_recording(path, options=ReadOptions(quaternion_order="wxyz", key="goal", rate=4))
    np.testing.assert_allclose(picked[0].times, np.arange(40) / 4)


def test_trim_idle_drops_the_still_start_and_end_only(tmp_path):
    # GIVEN a motion of 30 samples with 20 still samples before and 10 after, plus sensor
    # noise of 1e-6 (0.01 % of the top step)
    moving = np.linspace([1.0, 0.5], [0.0, 0.0], 30)
    samples = np.concatenate([np.repeat(moving[:1], 20, 0), moving, np.repeat(moving[-1:], 10, 0)])
    samples += 1e-6 * np.random.default_rng(0).standard_normal(samples.shape)
    np.save(tmp_path / "idle.npy", samples)
    # WHEN trimmed at 1 % of the top speed
    demos = load_recording(tmp_path / "idle.npy", options=ReadOptions(rate=10, trim_idle=0.01))
    # THEN the 30 samples of the motion remain (its first and last are where it was held)
    assert len(demos[0].times) == 30
    np.testing.assert_allclose(demos[0].positions[0], samples[20], atol=1e-12)
    # AND off (the default) every sample stays
    assert len(load_recording(tmp_path / "idle.npy", options=ReadOptions(rate=10))[0].times) == 60


def test_end_spread_error_names_the_outlier_and_the_fixes(tmp_path):
    # GIVEN 4 demonstrations to the origin, the third ending 0.5 away (a stroke cut short)
    lines = [np.linspace(start, [0.0, 0.0], 20) for start in ([1, 1], [1, 0], [0, 1], [1, -1])]
    lines[2] = np.linspace([0.0, 1.0], [0.5, 0.0], 20)
    np.save(tmp_path / "four.npy", np.stack(lines))
    with pytest.raises(DataError) as error:
        load_recording(tmp_path / "four.npy", options=ReadOptions(rate=10))
    message = str(error.value)
    # the extent is the farthest sample from the mean end (0.125, 0): |(0.875, 1)| = 1.3288;
    # the outlier is 0.5 from the median end (0, 0): 0.376 extents
    assert "outlying: demonstration 2 (0.38 extents)" in message
    assert "drop it (--demos 0,1,3)" in message
    # the limit is on the distance from the mean end: 0.375 / 1.3288 = 0.2822, rounded up
    assert "raise --max-end-spread to 0.29" in message
    # AND a stroke split in two: demonstration 2 ends where a fifth starts
    lines.append(np.linspace([0.5, 0.0], [0.0, 0.0], 20))
    np.save(tmp_path / "split.npy", np.stack(lines))
    with pytest.raises(DataError, match="demonstration 2 ends where demonstration 4 starts"):
        load_recording(tmp_path / "split.npy", options=ReadOptions(rate=10))


def test_table_files_refuse_options_they_cannot_take(tmp_path):
    path = tmp_path / "demos.csv"
    path.write_text("demo,t,x1,x2\n0,0,1,1\n0,1,0,0\n1,0,1.2,0.9\n1,1,0,0\n")
    with pytest.raises(DataError, match="--rate and --quaternion-order wxyz are for"):
        load_recording(path, options=ReadOptions(rate=10))
    with pytest.raises(DataError, match="--trim-idle apply to recordings"):
        load_recording(path, options=ReadOptions(trim_idle=0.01))
    # The unit applies: metres from millimetres.
    mm = load_recording(path, options=ReadOptions(length_unit="mm"))
    np.testing.assert_allclose(mm[1].positions[0], [0.0012, 0.0009])


def test_the_options_go_through_the_flags_and_the_record(tmp_path):
    path = tmp_path / "demos.npy"
    np.save(path, wxyz(two_demos()) * [10, 10, 10, 1, 1, 1, 1])
    flags = ["--rate", "25", "--quaternion-order", "wxyz", "--length-unit", "dm"]
    args = build_parser().parse_args(["train", "--data", str(path), *flags, "--trim-idle", "0.01"])
    source = data_source(args)
    assert (source.rate, source.quaternion_order, source.length_unit) == (25.0, "wxyz", "dm")
    assert source.poses
    record = json.loads(json.dumps(source.record()))
    assert record["rate"] == 25.0 and record["trim_idle"] == 0.01
    rebuilt = DataSource.from_record(record, poses=True)
    assert rebuilt == source
    np.testing.assert_allclose(rebuilt.load()[0].positions, two_demos()[0, :, :3], atol=1e-12)
    # An older record (no options) reads as before.
    assert DataSource.from_record({"motion": "Sine", "demos": 2}).options == ReadOptions()


@pytest.mark.skipif(not CLFD.is_dir(), reason="../shared/data/clfd is not present")
@pytest.mark.parametrize("task", ["pouring", "bottle2shelf"])
def test_clfd_recordings_load_through_the_user_options(task):
    source = DataSource(
        file=CLFD / f"{task}.npy", rate=60, quaternion_order="wxyz", length_unit="cm"
    )
    demos = source.load()
    assert source.poses and isinstance(demos, PoseDemonstrations) and len(demos) == 9
    # 1000 samples at 60 Hz; an arm's task of about half a metre
    assert demos[0].duration == pytest.approx(999 / 60)
    assert 0.3 < demos.extent() < 1.0


@pytest.mark.skipif(not PANDA.is_file(), reason="../shared/data/panda_kinesthetic_pose.mat absent")
def test_panda_recording_loads_with_its_time_row():
    source = DataSource(file=PANDA, quaternion_order="wxyz")
    demos = source.load()
    assert len(demos) == 1 and len(demos[0].times) == 1986
    assert demos[0].duration == pytest.approx(3.668, abs=1e-3)
    # The arm is held still for 0.33 s first: 1 % of the top speed trims it.
    trimmed = DataSource(file=PANDA, quaternion_order="wxyz", trim_idle=0.01).load()
    assert 1700 < len(trimmed[0].times) < 1986


def test_the_cli_prints_a_data_warning_as_one_line(tmp_path, capsys):
    from snds.cli import main

    path = tmp_path / "cm.npy"
    np.save(path, two_demos() * [100, 100, 100, 1, 1, 1, 1])
    argv = ["--quiet", "train", "--data", str(path), "--rate", "50", "--quaternion-order", "xyzw"]
    out = ["--out", str(tmp_path / "model"), "--steps", "3", "--rollouts", "5", "--samples", "50"]
    assert main([*argv, *out]) == 0
    err = capsys.readouterr().err
    assert err.startswith("snds: warning: pose positions span 40 m") and err.count("\n") == 1, err


def test_npz_of_transforms_with_times_or_a_key(tmp_path):
    poses = two_demos()
    t = np.cumsum(np.r_[0, np.full(39, 0.01) + 0.002 * (np.arange(39) % 3)])
    np.savez(tmp_path / "tf.npz", pose=transforms(poses), t=t)
    demos = load_recording(tmp_path / "tf.npz")
    np.testing.assert_allclose(demos[1].times, t)
    np.testing.assert_allclose(demos[1].positions, poses[1, :, :3], atol=1e-12)
    # The stamps are the file's: a rate beside them is refused.
    with pytest.raises(DataError, match="stores its time stamps; --rate"):
        load_recording(tmp_path / "tf.npz", options=ReadOptions(rate=100))
    # Two arrays of transforms: the key chooses.
    np.savez(tmp_path / "two.npz", a=transforms(poses), b=transforms(poses[:1]), dt=0.02)
    with pytest.raises(DataError, match="choose the transforms with --key from: a, b"):
        load_recording(tmp_path / "two.npz")
    one = load_recording(tmp_path / "two.npz", options=ReadOptions(key="b"))
    assert len(one) == 1 and one[0].duration == pytest.approx(39 * 0.02)


def test_a_mat_file_with_neither_layout_says_what_it_found(tmp_path):
    scipy.io.savemat(tmp_path / "other.mat", {"joints": np.ones((7, 7)), "q": np.zeros((3, 50))})
    with pytest.raises(DataError, match=r"no variable 'Data' or 'data' .*\(found: joints, q\)"):
        DataSource(file=tmp_path / "other.mat").load()
