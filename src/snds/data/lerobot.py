"""LeRobot datasets (v3 layout), read with ``pyarrow`` (extra ``lerobot``).

A dataset is a folder with ``meta/info.json`` (its ``fps``) and ``data/chunk-*/file-*.parquet``
tables of one row per frame. Each episode (``episode_index``) is one demonstration, its rows
in ``frame_index`` order. The state is ``columns``: one vector column (the default
``observation.state``) or several, side by side. Times are the ``timestamp`` column, or
``frame_index / fps`` without it. Seven numbers whose last four have unit norm are a pose (the
quaternion order must then be stated).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from snds.data.arrays import looks_like_poses
from snds.data.options import ReadOptions, to_xyzw
from snds.data.tracks import Track
from snds.errors import DataError

__all__ = ["DEFAULT_COLUMNS", "dataset_tracks", "is_dataset"]

#: The state columns read when none are named.
DEFAULT_COLUMNS = ("observation.state",)


def is_dataset(path: Path, options: ReadOptions) -> bool:
    """A folder with ``meta/info.json``."""
    return path.is_dir() and (path / "meta" / "info.json").is_file()


def _read_table(path: Path):
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError as error:
        raise DataError(
            "reading LeRobot datasets needs pyarrow: pip install 'snds[lerobot]'"
        ) from error
    files = sorted((path / "data").glob("chunk-*/file-*.parquet"))
    if not files:
        raise DataError("no data/chunk-*/file-*.parquet tables (a LeRobot v3 dataset?)")
    try:
        return pa.concat_tables([pq.read_table(file) for file in files], promote_options="default")
    # pyarrow raises ArrowInvalid, OSError or others for a damaged table; all mean the same.
    except Exception as error:
        raise DataError(f"unreadable parquet table (truncated or corrupt?): {error}") from error


def _fps(path: Path) -> float | None:
    try:
        info = json.loads((path / "meta" / "info.json").read_text())
    except (OSError, ValueError) as error:
        raise DataError(f"meta/info.json is not readable JSON: {error}") from error
    fps = info.get("fps") if isinstance(info, dict) else None
    return float(fps) if isinstance(fps, (int, float)) and fps > 0 else None


def _column(table, name: str) -> np.ndarray:
    """A column as (rows, width) floats: a list column's lists side by side, a scalar as one."""
    values = table.column(name).combine_chunks()
    if hasattr(values, "flatten") and hasattr(values, "value_lengths"):
        lengths = np.asarray(values.value_lengths())
        if len(lengths) and np.any(lengths != lengths[0]):
            raise DataError(f"column {name!r} holds vectors of different lengths")
        flat = np.asarray(values.flatten().to_numpy(zero_copy_only=False), dtype=np.float64)
        return flat.reshape(len(values), -1)
    try:
        return np.asarray(values.to_numpy(zero_copy_only=False), dtype=np.float64)[:, None]
    except (TypeError, ValueError) as error:
        raise DataError(f"column {name!r} does not hold numbers") from error


def dataset_tracks(path: Path, options: ReadOptions) -> list[Track]:
    """One track per episode (module doc)."""
    table = _read_table(path)
    names = table.column_names
    columns = options.columns or DEFAULT_COLUMNS
    for name in (*columns, "episode_index"):
        if name not in names:
            raise DataError(
                f"the dataset has no column {name!r}; choose with --columns from: "
                + ", ".join(names)
            )
    state = np.concatenate([_column(table, name) for name in columns], axis=1)
    episodes = _column(table, "episode_index")[:, 0]
    frames = _column(table, "frame_index")[:, 0] if "frame_index" in names else None
    stamps = _column(table, "timestamp")[:, 0] if "timestamp" in names else None
    fps = _fps(path)
    if stamps is None and (frames is None or fps is None):
        raise DataError("no 'timestamp' column, and no 'frame_index' with an fps in meta/info.json")
    poses = looks_like_poses(state)
    tracks = []
    for episode in np.unique(episodes):
        rows = np.flatnonzero(episodes == episode)
        if frames is not None:
            rows = rows[np.argsort(frames[rows], kind="stable")]
        times = stamps[rows] if stamps is not None else frames[rows] / fps
        label = f"episode {int(episode)}"
        if poses:
            quaternions = to_xyzw(state[rows, 3:], options.quaternion_order, what=f"{columns}")
            tracks.append(Track(state[rows, :3], quaternions, times - times[0], label))
        else:
            tracks.append(Track(state[rows], None, times - times[0], label))
    return tracks
