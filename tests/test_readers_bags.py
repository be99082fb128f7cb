"""ROS bags in: rosbag2 (MCAP, sqlite3) and ROS 1 written by rosbags' own writers, every
message type read, times from the header stamps, the bad bags of docs/bad-input.md."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("rosbags")

from snds.cli import main  # noqa: E402
from snds.data import DataSource, ReadOptions, load_recording  # noqa: E402
from snds.data.poses import PoseDemonstrations  # noqa: E402
from snds.errors import DataError  # noqa: E402

from recording_files import EPOCH, line_poses, write_bag  # noqa: E402

RATE = 100.0


def expected_times(count: int) -> np.ndarray:
    stamps = EPOCH + np.round(np.arange(count) * 1e9 / RATE).astype(np.int64)
    return (stamps - stamps[0]) * 1e-9


@pytest.mark.parametrize("storage", ["mcap", "sqlite3", "ros1"])
def test_pose_stamped_reads_poses_and_header_times(tmp_path, storage):
    # GIVEN a bag of 40 PoseStamped from (0.4, 0.2, 0.3) at 0.8 rad about z to the origin
    poses = line_poses(40)
    path = tmp_path / ("rec.bag" if storage == "ros1" else "rec")
    write_bag(path, poses, storage=storage)
    # WHEN it is read
    demos = load_recording(path)
    # THEN it is one pose demonstration, with the written poses (the ends meet the target)
    assert isinstance(demos, PoseDemonstrations) and len(demos) == 1
    np.testing.assert_allclose(demos[0].positions, poses[:, :3], atol=1e-12)
    np.testing.assert_allclose(np.abs(np.sum(demos[0].orientations * poses[:, 3:], 1)), 1, 1e-12)
    # AND the times are the header stamps from 0 (the log times are 3-4.5 ms later, jittered)
    np.testing.assert_allclose(demos[0].times, expected_times(40), atol=1e-9)


def test_a_message_published_twice_with_one_stamp_is_one_sample(tmp_path):
    poses = line_poses(30)
    write_bag(tmp_path / "rec", poses, repeat=2)
    demo = load_recording(tmp_path / "rec")[0]
    np.testing.assert_allclose(demo.times, expected_times(30), atol=1e-9)


def test_a_storage_file_inside_a_rosbag2_folder_reads_as_the_folder(tmp_path):
    write_bag(tmp_path / "rec", line_poses(30), storage="mcap")
    mcap = next((tmp_path / "rec").glob("*.mcap"))
    np.testing.assert_array_equal(
        load_recording(mcap)[0].positions, load_recording(tmp_path / "rec")[0].positions
    )


@pytest.mark.parametrize(
    "msgtype",
    [
        "geometry_msgs/msg/TransformStamped",
        "nav_msgs/msg/Odometry",
        "geometry_msgs/msg/PoseWithCovarianceStamped",
    ],
)
def test_every_pose_message_type_gives_the_same_poses(tmp_path, msgtype):
    poses = line_poses(30)
    write_bag(tmp_path / "rec", poses, msgtype=msgtype, topic="/pose")
    demo = load_recording(tmp_path / "rec")[0]
    np.testing.assert_allclose(demo.positions, poses[:, :3], atol=1e-12)
    np.testing.assert_allclose(demo.times, expected_times(30), atol=1e-9)


def test_tf_reads_the_named_transform_only(tmp_path):
    # GIVEN /tf messages holding base->camera (a fixed-looking decoy) and base->tool
    poses = line_poses(30)
    write_bag(tmp_path / "rec", poses, msgtype="tf2_msgs/msg/TFMessage", topic="/tf")
    # WHEN base->tool is asked for
    options = ReadOptions(frame="base", child_frame="tool")
    demo = load_recording(tmp_path / "rec", options=options)[0]
    # THEN one sample per message (the camera transform left out)
    assert len(demo.times) == 30
    np.testing.assert_allclose(demo.positions, poses[:, :3], atol=1e-12)
    # AND without the frames the error says how to name one
    with pytest.raises(DataError, match="--frame and --child-frame"):
        load_recording(tmp_path / "rec", options=ReadOptions(topic="/tf"))
    # AND a pair that is not there is named
    with pytest.raises(DataError, match="no messages from 'base' to 'gripper'"):
        load_recording(tmp_path / "rec", options=ReadOptions(frame="base", child_frame="gripper"))


def test_point_stamped_gives_positions(tmp_path):
    poses = line_poses(30)
    write_bag(tmp_path / "rec", poses, msgtype="geometry_msgs/msg/PointStamped", topic="/p")
    demos = load_recording(tmp_path / "rec")
    assert not isinstance(demos, PoseDemonstrations)
    np.testing.assert_allclose(demos[0].positions, poses[:, :3], atol=1e-12)
    # The velocity of a straight line at constant speed: (0 - 0.4) / 0.29 s along x.
    np.testing.assert_allclose(demos[0].velocities[:, 0], -0.4 / 0.29, rtol=1e-6)


def test_unstamped_messages_take_the_log_time(tmp_path):
    # GIVEN Pose messages (no header), and PoseStamped whose stamps were never set
    for name, kwargs in {
        "pose": {"msgtype": "geometry_msgs/msg/Pose"},
        "zero": {"zero_stamps": True},
    }.items():
        write_bag(tmp_path / name, line_poses(20), **kwargs)
        times = load_recording(tmp_path / name)[0].times
        # THEN the times are the log times: the stamps' plus the jittered delay
        delay = 0.003 * (1 + 0.5 * np.sin(np.arange(20)))
        np.testing.assert_allclose(times, expected_times(20) + delay - delay[0], atol=2e-9)


def test_a_folder_of_bags_gives_one_demonstration_each(tmp_path):
    folder = tmp_path / "recordings"
    folder.mkdir()
    for k, turn in enumerate([0.8, 0.7, 0.9]):
        poses = line_poses(30 + 5 * k, turn=turn)
        write_bag(folder / f"demo_{k}", poses, storage="sqlite3" if k == 1 else "mcap")
    demos = load_recording(folder)
    assert [len(demo.times) for demo in demos] == [30, 35, 40]
    # The errors name the bag.
    with pytest.raises(DataError, match="recordings: demo_0: no topic '/nope'"):
        load_recording(folder, options=ReadOptions(topic="/nope"))


def test_one_long_recording_splits_at_its_rests(tmp_path):
    # GIVEN one bag at 100 Hz: a motion to the origin, 1 s still, the arm taken back to
    # another start, 1 s still, a second motion to the origin
    first, second = line_poses(40), line_poses(40, turn=0.6)
    second[:, :3] *= [1.0, -1.0, 1.0]
    back = second[::-1]
    still = [np.repeat(pose[None], 100, axis=0) for pose in (first[-1], second[0])]
    write_bag(tmp_path / "rec", np.concatenate([first, still[0], back, still[1], second]))
    # WHEN it is split at rests of at least 0.5 s
    # THEN there are three motions, each from its last sample at rest to its first one again,
    # and the error names the way back as the outlier
    with pytest.raises(DataError, match=r"outlying: demonstration 1 .*--demos 0,2"):
        load_recording(tmp_path / "rec", options=ReadOptions(split_rests=0.5))
    demos = load_recording(tmp_path / "rec", options=ReadOptions(split_rests=0.5), select=[0, 2])
    np.testing.assert_allclose(demos[0].positions, first[:, :3], atol=1e-12)
    np.testing.assert_allclose(demos[1].positions, second[:, :3], atol=1e-12)
    # AND the second starts 2.4 s into the recording (40 + 100 + 40 + 100 samples, less one)
    assert len(demos[1].times) == 40


def test_bag_trains_end_to_end_and_the_model_rebuilds_its_data(tmp_path):
    # GIVEN a rosbag2 MCAP file of PoseStamped on /ee_pose, and a second topic
    poses = line_poses(60)
    write_bag(tmp_path / "rec", poses, others={"/joint_states": "sensor_msgs/msg/JointState"})
    mcap = next((tmp_path / "rec").glob("*.mcap"))
    out = tmp_path / "model"
    # WHEN snds trains on it with the topic named
    argv = ["--quiet", "train", "--data", str(mcap), "--topic", "/ee_pose", "--out", str(out)]
    assert main([*argv, "--steps", "100", "--rollouts", "5", "--samples", "50"]) == 0
    # THEN the model is a pose model whose record names the topic, and rebuilds the data
    record = json.loads((out / "model.json").read_text())["data"]
    assert record["topic"] == "/ee_pose"
    rebuilt = DataSource.from_record(record, poses=True).load()
    np.testing.assert_allclose(rebuilt[0].positions, poses[:, :3], atol=1e-12)
    assert main(["--quiet", "evaluate", str(out), "--rollouts", "5", "--samples", "50"]) == 0


def test_missing_topic_lists_the_topics_and_their_types(tmp_path):
    write_bag(
        tmp_path / "rec", line_poses(10), others={"/joint_states": "sensor_msgs/msg/JointState"}
    )
    with pytest.raises(DataError) as error:
        load_recording(tmp_path / "rec", options=ReadOptions(topic="/ee"))
    message = str(error.value)
    assert "no topic '/ee' in the bag" in message
    assert "/ee_pose (geometry_msgs/msg/PoseStamped)" in message
    assert "/joint_states (sensor_msgs/msg/JointState)" in message


def test_unsupported_type_and_empty_and_truncated_bags(tmp_path):
    write_bag(
        tmp_path / "rec", line_poses(10), others={"/joint_states": "sensor_msgs/msg/JointState"}
    )
    with pytest.raises(DataError, match="topic /joint_states has type sensor_msgs/msg/JointState"):
        load_recording(tmp_path / "rec", options=ReadOptions(topic="/joint_states"))
    # A bag whose topic has no messages.
    write_bag(tmp_path / "empty", line_poses(0))
    with pytest.raises(DataError, match="topic /ee_pose has no messages"):
        load_recording(tmp_path / "empty")
    # A file cut anywhere: one error, never a traceback.
    mcap = next((tmp_path / "rec").glob("*.mcap"))
    data = mcap.read_bytes()
    for cut in (len(data) // 3, len(data) // 2, len(data) - 20):
        (tmp_path / "cut.mcap").write_bytes(data[:cut])
        with pytest.raises(DataError, match="cut.mcap"):
            load_recording(tmp_path / "cut.mcap")
