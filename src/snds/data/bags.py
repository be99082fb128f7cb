"""ROS bags: rosbag2 (a folder with ``metadata.yaml``, or one ``.db3``/``.mcap`` file) and
ROS 1 ``.bag``, read with ``rosbags`` (pure Python, no ROS installation; extra ``rosbag``).

One bag is one demonstration; a folder of bags gives one per bag, in name order. The topic
is ``topic``, or the bag's only topic of a type read here (:data:`MESSAGE_TYPES`); a
``tf2_msgs/TFMessage`` topic (``/tf``) gives the transform from ``frame`` to ``child_frame``.
Times are the header stamps; messages without a header (``Pose``), or whose stamps are all
zero (a recorder that never set them), take the time the bag logged them; messages are put
in stamp order, and of several with one stamp the first is kept. Quaternions are named
fields, so the quaternion order never applies.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from snds.data.options import ReadOptions
from snds.data.tracks import Track, labelled
from snds.errors import DataError

__all__ = ["BAG_SUFFIXES", "MESSAGE_TYPES", "bag_tracks", "is_bag"]

#: Files that are a bag by themselves.
BAG_SUFFIXES = (".bag", ".mcap", ".db3")


def _stamped(*path: str) -> Callable[[object], tuple[object, object]]:
    """The header and the pose-like field at ``path`` of a message."""

    def get(message: object) -> tuple[object, object]:
        value = message
        for name in path:
            value = getattr(value, name)
        return getattr(message, "header", None), value

    return get


#: Message types read here (ROS 2 names; ROS 1 ``pkg/Type`` is the same type), and where the
#: pose, transform or point is in each.
MESSAGE_TYPES: dict[str, Callable[[object], tuple[object, object]]] = {
    "geometry_msgs/msg/PoseStamped": _stamped("pose"),
    "geometry_msgs/msg/Pose": _stamped(),
    "geometry_msgs/msg/PoseWithCovarianceStamped": _stamped("pose", "pose"),
    "geometry_msgs/msg/TransformStamped": _stamped("transform"),
    "nav_msgs/msg/Odometry": _stamped("pose", "pose"),
    "geometry_msgs/msg/PointStamped": _stamped("point"),
    "tf2_msgs/msg/TFMessage": _stamped(),
}


def is_bag(path: Path, options: ReadOptions) -> bool:
    """A bag file, a rosbag2 folder, or a folder holding bags."""
    if path.is_file():
        return path.suffix.lower() in BAG_SUFFIXES
    return path.is_dir() and bool(_bags_in(path))


def _bags_in(folder: Path) -> list[Path]:
    if (folder / "metadata.yaml").is_file():
        return [folder]
    inside = [
        item
        for item in sorted(folder.iterdir())
        if (item.is_file() and item.suffix.lower() in BAG_SUFFIXES)
        or (item.is_dir() and (item / "metadata.yaml").is_file())
    ]
    return inside


def bag_tracks(path: Path, options: ReadOptions) -> list[Track]:
    """One track per bag (module doc)."""
    bags = _bags_in(path) if path.is_dir() else [path]
    if bags == [path]:
        return [_bag_track(path, options)]
    tracks = []
    for bag in bags:
        with labelled(bag.name):
            tracks.append(_bag_track(bag, options))
    return tracks


def _open(bag: Path):
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as error:
        raise DataError("reading ROS bags needs rosbags: pip install 'snds[rosbag]'") from error
    ros1 = bag.suffix.lower() == ".bag"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    return AnyReader([bag], default_typestore=store)


def _bag_track(bag: Path, options: ReadOptions) -> Track:
    if bag.is_file() and bag.stat().st_size == 0:
        raise DataError("file is empty")
    reader = _open(bag)
    # rosbags raises its own reader errors, OSError, EOFError, KeyError or struct errors
    # depending on where a damaged bag breaks off; all mean the same to a user.
    try:
        with reader:
            connections = _topic(reader.connections, options)
            msgtype = _ros2_name(connections[0].msgtype)
            rows = []
            for connection, logged, raw in reader.messages(connections=connections):
                message = reader.deserialize(raw, connection.msgtype)
                rows.extend(_samples(message, msgtype, logged, options))
    except DataError:
        raise
    except Exception as error:
        raise DataError(f"not a readable bag (empty, truncated or corrupt?): {error}") from error
    topic = connections[0].topic
    if not rows:
        what = f" from {options.frame!r} to {options.child_frame!r}" if options.frame else ""
        raise DataError(f"topic {topic} has no messages{what}")
    stamps = np.array([row[0] for row in rows], dtype=np.int64)
    logged = np.array([row[1] for row in rows], dtype=np.int64)
    # A recorder that never filled the headers leaves every stamp zero: the log time is all
    # the bag knows then.
    nanoseconds = logged if not stamps.any() else stamps
    order = np.argsort(nanoseconds, kind="stable")
    # A message published twice with one stamp (a republished transform) is one sample.
    order = order[np.r_[True, np.diff(nanoseconds[order]) > 0]]
    times = (nanoseconds[order] - nanoseconds[order[0]]) * 1e-9
    positions = np.array([rows[i][2] for i in order], dtype=np.float64)
    if rows[0][3] is None:
        return Track(positions, None, times, topic)
    orientations = np.array([rows[i][3] for i in order], dtype=np.float64)
    return Track(positions, orientations, times, topic)


def _ros2_name(msgtype: str) -> str:
    """``pkg/msg/Type`` for ROS 2 and ROS 1 (``pkg/Type``) names alike."""
    package, *_, name = msgtype.split("/")
    return f"{package}/msg/{name}"


def _topic(connections: list, options: ReadOptions) -> list:
    """The connections of the topic to read (module doc)."""
    topics = {connection.topic: connection.msgtype for connection in connections}
    if not topics:
        raise DataError("the bag has no topics (an empty recording?)")
    listed = ", ".join(f"{name} ({kind})" for name, kind in sorted(topics.items()))
    wanted = options.topic or ("/tf" if options.frame is not None else None)
    if wanted is None:
        # /tf holds many transforms: it is read only when a pair of frames is named.
        readable = [
            name
            for name, kind in topics.items()
            if _ros2_name(kind) in MESSAGE_TYPES and _ros2_name(kind) != "tf2_msgs/msg/TFMessage"
        ]
        if len(readable) != 1:
            raise DataError(f"choose the topic to read with --topic; the bag has: {listed}")
        wanted = readable[0]
    if wanted not in topics:
        raise DataError(f"no topic {wanted!r} in the bag; it has: {listed}")
    msgtype = _ros2_name(topics[wanted])
    if msgtype not in MESSAGE_TYPES:
        supported = ", ".join(name.replace("/msg/", "/") for name in MESSAGE_TYPES)
        raise DataError(f"topic {wanted} has type {topics[wanted]}; snds reads {supported}")
    if msgtype == "tf2_msgs/msg/TFMessage" and options.frame is None:
        raise DataError(
            f"topic {wanted} holds many transforms: name one with --frame and --child-frame"
        )
    return [connection for connection in connections if connection.topic == wanted]


def _samples(message: object, msgtype: str, logged: int, options: ReadOptions) -> list[tuple]:
    """(stamp ns, logged ns, position, quaternion or None) of each sample in a message."""
    if msgtype == "tf2_msgs/msg/TFMessage":
        parent, child = options.frame.strip("/"), options.child_frame.strip("/")
        return [
            row
            for transform in message.transforms
            if transform.header.frame_id.strip("/") == parent
            and transform.child_frame_id.strip("/") == child
            for row in _samples(transform, "geometry_msgs/msg/TransformStamped", logged, options)
        ]
    header, value = MESSAGE_TYPES[msgtype](message)
    stamp = 0 if header is None else header.stamp.sec * 1_000_000_000 + header.stamp.nanosec
    if msgtype == "geometry_msgs/msg/PointStamped":
        return [(stamp, logged, (value.x, value.y, value.z), None)]
    position = getattr(value, "position", None) or getattr(value, "translation", None)
    rotation = getattr(value, "orientation", None) or getattr(value, "rotation", None)
    quaternion = (rotation.x, rotation.y, rotation.z, rotation.w)
    return [(stamp, logged, (position.x, position.y, position.z), quaternion)]
