"""Datasets in: LeRobot v3 (parquet, written with pyarrow) and robomimic-style HDF5 (written
with h5py); columns and keys, episodes as demonstrations, times, and their bad input."""

from __future__ import annotations

import numpy as np
import pytest

from snds.cli import main
from snds.data import DataSource, ReadOptions, load_recording
from snds.data.poses import PoseDemonstrations
from snds.errors import DataError

from recording_files import line_poses, write_lerobot, write_robomimic

pyarrow = pytest.importorskip("pyarrow")


def episodes() -> list[np.ndarray]:
    """Three 2-D episodes to the origin, of 20, 25 and 30 frames."""
    return [
        np.linspace(start, [0.0, 0.0], count)
        for start, count in (([1, 1], 20), ([1, 0], 25), ([0, 1], 30))
    ]


def test_lerobot_episodes_are_demonstrations_with_their_timestamps(tmp_path):
    # GIVEN a dataset of 3 episodes at 30 fps, state in observation.state
    write_lerobot(tmp_path / "ds", episodes(), fps=30)
    demos = load_recording(tmp_path / "ds")
    # THEN one demonstration per episode, in order, with the frames' times
    assert [len(demo.times) for demo in demos] == [20, 25, 30]
    np.testing.assert_allclose(demos[1].positions, episodes()[1], atol=1e-12)
    np.testing.assert_allclose(demos[2].times, np.arange(30) / 30)


def test_lerobot_without_timestamps_uses_fps_and_picks_columns(tmp_path):
    write_lerobot(tmp_path / "ds", episodes(), fps=20, column="action", timestamps=False)
    demos = load_recording(tmp_path / "ds", options=ReadOptions(columns=("action",)))
    np.testing.assert_allclose(demos[0].times, np.arange(20) / 20)
    # A dataset without the column: one line naming the columns there are.
    with pytest.raises(
        DataError, match="no column 'observation.state'; choose with --columns from: action"
    ):
        load_recording(tmp_path / "ds")


def test_lerobot_pose_state_needs_its_quaternion_order(tmp_path):
    poses = [line_poses(30), line_poses(20, turn=0.5)]
    write_lerobot(tmp_path / "ds", [np.roll(p, 0) for p in poses], fps=10)
    with pytest.raises(DataError, match="--quaternion-order"):
        load_recording(tmp_path / "ds")
    demos = load_recording(tmp_path / "ds", options=ReadOptions(quaternion_order="xyzw"))
    assert isinstance(demos, PoseDemonstrations)
    np.testing.assert_allclose(demos[0].positions, poses[0][:, :3], atol=1e-12)


def test_robomimic_demos_in_numeric_order_with_keys(tmp_path):
    h5py = pytest.importorskip("h5py")
    del h5py
    # GIVEN demo_0, demo_2, demo_10 (numeric order, not text order) with eef pos and quat
    poses = [line_poses(30), line_poses(20, turn=0.5), line_poses(25, turn=1.0)]
    demos = [
        {"eef_pos": p[:, :3], "eef_quat": p[:, 3:], "gripper": np.zeros((len(p), 2))} for p in poses
    ]
    path = write_robomimic(tmp_path / "demos.hdf5", demos)
    # THEN without a key the error lists the keys
    with pytest.raises(
        DataError, match="choose the observation with --key from: eef_pos, eef_quat, gripper"
    ):
        load_recording(path, options=ReadOptions(rate=20))
    # AND positions alone, at the stated rate, in demo_0, demo_2, demo_10 order
    positions = load_recording(path, options=ReadOptions(rate=20, key="eef_pos"))
    assert [len(demo.times) for demo in positions] == [30, 20, 25]
    np.testing.assert_allclose(positions[1].times, np.arange(20) / 20)
    # AND two keys side by side make a pose
    both = ReadOptions(rate=20, key="eef_pos,eef_quat", quaternion_order="xyzw")
    assert isinstance(load_recording(path, options=both), PoseDemonstrations)
    with pytest.raises(DataError, match="demo_0 has no obs key 'eef_vel'"):
        load_recording(path, options=ReadOptions(rate=20, key="eef_vel"))


def test_lerobot_trains_end_to_end(tmp_path):
    write_lerobot(tmp_path / "ds", episodes(), fps=30)
    out = tmp_path / "model"
    argv = ["--quiet", "train", "--data", str(tmp_path / "ds"), "--columns", "observation.state"]
    assert (
        main([*argv, "--out", str(out), "--steps", "5", "--rollouts", "5", "--samples", "50"]) == 0
    )
    assert (
        DataSource.from_record({"file": str(tmp_path / "ds"), "columns": ["observation.state"]})
        .load()
        .dim
        == 2
    )
