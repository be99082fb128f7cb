"""Writers of real recordings for the reader tests, with the formats' own libraries: ROS bags
with rosbags' writers (rosbag2 MCAP and sqlite3, ROS 1), LeRobot v3 tables with pyarrow,
robomimic HDF5 with h5py. No binary fixture is committed; each test writes its files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

#: A wall-clock start (ns) for the stamps, as a real recording has.
EPOCH = 1_700_000_000_123_456_789


def line_poses(count: int = 40, *, turn: float = 0.8) -> np.ndarray:
    """Poses (count, 7) from (0.4, 0.2, 0.3) to (0, 0, 0), turning about z by ``turn`` rad
    down to the identity, quaternions (x, y, z, w)."""
    s = np.linspace(0.0, 1.0, count)
    positions = (1 - s)[:, None] * np.array([0.4, 0.2, 0.3])
    angles = (1 - s) * turn
    quaternions = np.stack(
        [np.zeros(count), np.zeros(count), np.sin(angles / 2), np.cos(angles / 2)], axis=1
    )
    return np.concatenate([positions, quaternions], axis=1)


def _ros(store: str):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if store == "ros1" else Stores.ROS2_HUMBLE)


def _message(types, msgtype: str, pose: np.ndarray, stamp: int, *, ros1: bool):
    """A message of ``msgtype`` carrying ``pose`` (7,) stamped ``stamp`` ns."""
    t = types.types
    time = t["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
    header_type = t["std_msgs/msg/Header"]
    header = header_type(seq=0, stamp=time, frame_id="base") if ros1 else header_type(time, "base")
    point = t["geometry_msgs/msg/Point"](*pose[:3])
    quaternion = t["geometry_msgs/msg/Quaternion"](*pose[3:])
    body = t["geometry_msgs/msg/Pose"](point, quaternion)
    if msgtype == "geometry_msgs/msg/Pose":
        return body
    if msgtype == "geometry_msgs/msg/PoseStamped":
        return t[msgtype](header, body)
    if msgtype == "geometry_msgs/msg/PointStamped":
        return t[msgtype](header, point)
    covariance = np.zeros(36)
    pose_cov = t["geometry_msgs/msg/PoseWithCovariance"](body, covariance)
    if msgtype == "geometry_msgs/msg/PoseWithCovarianceStamped":
        return t[msgtype](header, pose_cov)
    if msgtype == "nav_msgs/msg/Odometry":
        twist = t["geometry_msgs/msg/TwistWithCovariance"](
            t["geometry_msgs/msg/Twist"](
                t["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
                t["geometry_msgs/msg/Vector3"](0.0, 0.0, 0.0),
            ),
            covariance,
        )
        return t[msgtype](header, "ee", pose_cov, twist)
    transform = t["geometry_msgs/msg/Transform"](
        t["geometry_msgs/msg/Vector3"](*pose[:3]), quaternion
    )
    stamped = t["geometry_msgs/msg/TransformStamped"](header, "tool", transform)
    if msgtype == "geometry_msgs/msg/TransformStamped":
        return stamped
    # A /tf message: the wanted transform beside another one, as a robot's tree publishes.
    other = t["geometry_msgs/msg/TransformStamped"](header, "camera", transform)
    return t["tf2_msgs/msg/TFMessage"]([other, stamped])


def write_bag(
    path: Path,
    poses: np.ndarray,
    *,
    storage: str = "mcap",
    topic: str = "/ee_pose",
    msgtype: str = "geometry_msgs/msg/PoseStamped",
    rate: float = 100.0,
    log_delay: float = 0.003,
    zero_stamps: bool = False,
    others: dict[str, str] | None = None,
    repeat: int = 1,
) -> Path:
    """A bag of one message per pose at ``rate`` Hz, logged ``log_delay`` s after its stamp
    (with a jitter, so that stamps and log times differ). ``storage``: ``"mcap"``,
    ``"sqlite3"`` (rosbag2 folders) or ``"ros1"`` (``path`` is the ``.bag``); ``others``: more
    topics (name: type) with no messages; ``repeat``: each message published that many
    times with its one stamp (1 ms apart in the log). Returns the path to give to the reader."""
    types = _ros(storage)
    ros1 = storage == "ros1"
    stamps = EPOCH + np.round(np.arange(len(poses)) * 1e9 / rate).astype(np.int64)
    jitter = np.round(1e9 * log_delay * (1 + 0.5 * np.sin(np.arange(len(poses))))).astype(np.int64)
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
        serialize = types.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer(path, version=9, storage_plugin=plugin)
        serialize = types.serialize_cdr
    with writer:
        connection = writer.add_connection(topic, msgtype, typestore=types)
        for name, kind in (others or {}).items():
            writer.add_connection(name, kind, typestore=types)
        for pose, stamp, delay in zip(poses, stamps, jitter):
            message = _message(types, msgtype, pose, 0 if zero_stamps else int(stamp), ros1=ros1)
            for k in range(repeat):
                writer.write(
                    connection, int(stamp + delay + k * 10**6), serialize(message, msgtype)
                )
    return path


def write_lerobot(
    folder: Path,
    episodes: list[np.ndarray],
    *,
    fps: float = 30.0,
    column: str = "observation.state",
    timestamps: bool = True,
) -> Path:
    """A LeRobot v3 dataset: ``meta/info.json`` and one parquet table, one row per frame,
    the state as a list column, episodes in order."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    (folder / "meta").mkdir(parents=True)
    (folder / "data" / "chunk-000").mkdir(parents=True)
    width = episodes[0].shape[1]
    info = {"codebase_version": "v3.0", "fps": fps, "features": {column: {"shape": [width]}}}
    (folder / "meta" / "info.json").write_text(json.dumps(info))
    rows = {column: [], "episode_index": [], "frame_index": [], "timestamp": []}
    for index, states in enumerate(episodes):
        rows[column] += [list(map(float, state)) for state in states]
        rows["episode_index"] += [index] * len(states)
        rows["frame_index"] += list(range(len(states)))
        rows["timestamp"] += list(np.arange(len(states)) / fps)
    if not timestamps:
        del rows["timestamp"]
    pq.write_table(pa.table(rows), folder / "data" / "chunk-000" / "file-000.parquet")
    return folder


def write_robomimic(path: Path, demos: list[dict[str, np.ndarray]]) -> Path:
    """A robomimic-style HDF5 file: ``data/demo_N/obs/<key>`` for each demo's arrays."""
    import h5py

    with h5py.File(path, "w") as file:
        data = file.create_group("data")
        # Numbered out of order on purpose: demo_10 comes after demo_2.
        for number, arrays in zip([0, 2, 10, 11][: len(demos)], demos):
            obs = data.create_group(f"demo_{number}/obs")
            for key, array in arrays.items():
                obs.create_dataset(key, data=array)
    return path
