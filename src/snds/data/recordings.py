"""One entry for every kind of demonstrations file: which reader takes it, and whether it
holds poses.

:func:`load_recording` chooses the reader by what the path is (:data:`READERS`, first match):
a ROS bag (rosbag2 folder, ``.mcap``, ``.db3``, ROS 1 ``.bag``) or a folder of them, a LeRobot
dataset folder, an HDF5 file, a ``.npy`` array, an ``.npz`` of 4x4 transforms, a ``.mat``
pose matrix; anything else is a
table file (``.csv``, ``.npz``, LPV-DS ``.mat``) read by :func:`~snds.data.load_demonstrations`
or :func:`~snds.data.poses.load_poses`. Recordings go through
:func:`~snds.data.tracks.assemble_tracks`, so the :class:`~snds.data.options.ReadOptions` act
the same on all of them.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from snds.data import arrays, bags, hdf5, lerobot
from snds.data.demonstrations import Demonstration, Demonstrations
from snds.data.files import load_demonstrations
from snds.data.gaps import DEFAULT_GAPS
from snds.data.options import ReadOptions
from snds.data.poses import PoseDemonstration, PoseDemonstrations, is_pose_file, load_poses
from snds.data.targets import MAX_END_SPREAD
from snds.data.tracks import Track, assemble_tracks, labelled
from snds.errors import DataError

__all__ = ["READERS", "Reader", "holds_poses", "load_recording"]


@dataclass(frozen=True)
class Reader:
    """A kind of recording.

    Attributes:
        name: How docs and errors call it.
        takes: Whether a path (and the options) is of this kind.
        tracks: Reads its motions.
    """

    name: str
    takes: Callable[[Path, ReadOptions], bool]
    tracks: Callable[[Path, ReadOptions], list[Track]]


def _suffix(*suffixes: str) -> Callable[[Path, ReadOptions], bool]:
    return lambda path, options: path.is_file() and path.suffix.lower() in suffixes


def _mat_pose(path: Path, options: ReadOptions) -> bool:
    """A ``.mat`` file read as pose matrices: ``key`` given, or no LPV-DS variable in it."""
    if not (path.is_file() and path.suffix.lower() == ".mat"):
        return False
    if options.key is not None:
        return True
    try:
        import scipy.io

        names = {name for name, *_ in scipy.io.whosmat(path)}
    # An unreadable file goes to the LPV-DS reader, whose errors already say why.
    except Exception:
        return False
    return not names & {"Data", "data"}


#: The readers of recordings, tried in order; a path none takes is a table file.
READERS = (
    Reader("ROS bag", bags.is_bag, bags.bag_tracks),
    Reader("LeRobot dataset", lerobot.is_dataset, lerobot.dataset_tracks),
    Reader("HDF5 (robomimic)", _suffix(".hdf5", ".h5"), hdf5.hdf5_tracks),
    Reader(".npy array", _suffix(".npy"), arrays.npy_tracks),
    Reader(".npz of transforms", arrays.holds_transforms, arrays.npz_transform_tracks),
    Reader(".mat pose matrix", _mat_pose, arrays.mat_pose_tracks),
)

#: Options that only recordings (not table files) take, with their CLI flags.
_RECORDING_ONLY = {
    "trim_idle": "--trim-idle",
    "split_rests": "--split-rests",
    "topic": "--topic",
    "frame": "--frame",
    "columns": "--columns",
    "key": "--key",
}


def _reader(path: Path, options: ReadOptions) -> Reader | None:
    return next((reader for reader in READERS if reader.takes(path, options)), None)


def load_recording(
    path: str | Path,
    *,
    options: ReadOptions = ReadOptions(),
    select: Sequence[int] | None = None,
    max_end_spread: float = MAX_END_SPREAD,
    gaps: str = DEFAULT_GAPS,
) -> Demonstrations | PoseDemonstrations:
    """The demonstrations of any supported file or folder, positions or poses as it holds.

    Arguments:
        path: The file or folder.
        options: How to read it (rate, quaternion order, unit, ...).
        select: Keep only these demonstrations (0-based, in this order) before the target is
            chosen.
        max_end_spread: See :func:`~snds.data.targets.common_target`.
        gaps: How an LPV-DS ``.mat`` file's recording gaps are treated (see
            :func:`~snds.data.load_mat`).

    Raises:
        DataError: If the path cannot be used; the message starts with it.
    """
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file")
    reader = _reader(path, options)
    if reader is None:
        _check_table(path)
        return _table(path, options, select, max_end_spread, gaps)
    with labelled(str(path)):
        tracks = _tracks(reader, path, options)
        return assemble_tracks(
            tracks,
            options=options,
            name=path.stem,
            select=select,
            max_end_spread=max_end_spread,
            what=f"a {reader.name}",
        )


def _tracks(reader: Reader, path: Path, options: ReadOptions) -> tuple[Track, ...]:
    """The reader's tracks, read once for a :class:`~snds.data.DataSource`'s check of what the
    file holds and its load (a long bag takes seconds to deserialise)."""
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    stamp = tuple((str(f), f.stat().st_mtime_ns, f.stat().st_size) for f in files)
    return _read_once(reader, path, stamp, options)


@functools.lru_cache(maxsize=2)
def _read_once(reader: Reader, path: Path, stamp: tuple, options: ReadOptions) -> tuple[Track, ...]:
    # ``stamp`` (every file's name, time and size) is part of the key: a rewritten file is
    # read again.
    return tuple(reader.tracks(path, options))


def holds_poses(path: str | Path, options: ReadOptions = ReadOptions()) -> bool:
    """Whether a file holds poses (False if it cannot be read: loading it says why)."""
    path = Path(path)
    try:
        reader = _reader(path, options)
        if reader is None:
            return is_pose_file(path)
        tracks = _tracks(reader, path, options)
    except DataError:
        return False
    return bool(tracks) and tracks[0].orientations is not None


#: What :func:`load_recording` reads, for the message about anything else.
SUPPORTED = (
    ".bag, .csv, .db3, .h5, .hdf5, .mat, .mcap, .npy, .npz, or a folder: rosbag2, bags, "
    "LeRobot dataset"
)


def _check_table(path: Path) -> None:
    if path.is_dir():
        raise DataError(
            f"{path}: not a rosbag2 folder (metadata.yaml), a folder of bags or a LeRobot "
            "dataset (meta/info.json)"
        )
    if path.suffix.lower() not in (".csv", ".npz", ".mat"):
        raise DataError(f"{path}: unsupported file type {path.suffix!r} (supported: {SUPPORTED})")


def _table(
    path: Path,
    options: ReadOptions,
    select: Sequence[int] | None,
    max_end_spread: float,
    gaps: str,
) -> Demonstrations | PoseDemonstrations:
    """A CSV, NPZ or LPV-DS ``.mat`` file, read as before, then converted to metres."""
    given = [flag for name, flag in _RECORDING_ONLY.items() if getattr(options, name)]
    if given:
        raise DataError(
            f"{path}: {', '.join(given)} apply to recordings (.npy, .npz transforms, .mat "
            "pose matrices, ROS bags, LeRobot, HDF5), not to a CSV, NPZ or LPV-DS .mat file"
        )
    if options.rate is not None or options.quaternion_order not in (None, "xyzw"):
        raise DataError(
            f"{path}: a CSV, NPZ or LPV-DS .mat file names its times and quaternion columns; "
            "--rate and --quaternion-order wxyz are for .npy, .mat pose matrices, HDF5 and "
            "LeRobot files (an .npz stores 'dt' instead)"
        )
    if is_pose_file(path):
        demos = load_poses(path, select=select, max_end_spread=max_end_spread)
    else:
        demos = load_demonstrations(path, select=select, max_end_spread=max_end_spread, gaps=gaps)
    return demos if options.length_unit is None else _scaled(demos, options.metres)


def _scaled(
    demos: Demonstrations | PoseDemonstrations, factor: float
) -> Demonstrations | PoseDemonstrations:
    """The demonstrations with positions (and linear velocities) times ``factor``: exact after
    the common target, which is linear in the positions."""
    if isinstance(demos, PoseDemonstrations):
        scaled = tuple(
            PoseDemonstration(demo.positions * factor, demo.orientations, demo.times)
            for demo in demos
        )
        return dataclasses.replace(
            demos, demos=scaled, target_position=demos.target_position * factor
        )
    scaled = tuple(
        Demonstration(demo.positions * factor, demo.velocities * factor, demo.times)
        for demo in demos
    )
    return Demonstrations(scaled, np.asarray(demos.target) * factor, demos.name)
