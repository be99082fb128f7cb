"""robomimic-style HDF5 files, read with ``h5py`` (extra ``hdf5``).

Demonstrations are the groups ``data/demo_N`` (in the order of N), and the state is
``data/demo_N/obs/<key>``, shape (T, n); ``key`` may name several observations separated by
commas, put side by side (``robot0_eef_pos,robot0_eef_quat`` is a pose). The files store no
times (robomimic samples at the controller's rate): give ``rate``. Seven numbers whose last
four have unit norm are a pose (the quaternion order must then be stated; robosuite's is
``xyzw``).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from snds.data.arrays import looks_like_poses
from snds.data.options import ReadOptions, to_xyzw
from snds.data.tracks import Track
from snds.errors import DataError

__all__ = ["hdf5_tracks"]


def _open(path: Path):
    try:
        import h5py
    except ImportError as error:
        raise DataError("reading HDF5 files needs h5py: pip install 'snds[hdf5]'") from error
    try:
        return h5py.File(path, "r")
    # h5py raises OSError for a file that is not HDF5 or is truncated.
    except Exception as error:
        raise DataError(f"not a readable HDF5 file (truncated or corrupt?): {error}") from error


def _demo_number(name: str) -> int:
    match = re.fullmatch(r"demo_(\d+)", name)
    return int(match.group(1)) if match else -1


def hdf5_tracks(path: Path, options: ReadOptions) -> list[Track]:
    """One track per ``data/demo_N`` group (module doc)."""
    with _open(path) as file:
        group = file.get("data")
        names = sorted((n for n in (group or {}) if _demo_number(n) >= 0), key=_demo_number)
        if not names:
            raise DataError("no data/demo_N groups (a robomimic-style file?)")
        keys = sorted(group[names[0]].get("obs", {}))
        if options.key is None:
            raise DataError(f"choose the observation with --key from: {', '.join(keys)}")
        wanted = [part.strip() for part in options.key.split(",") if part.strip()]
        tracks = []
        for name in names:
            obs = group[name].get("obs", {})
            missing = [key for key in wanted if key not in obs]
            if missing:
                raise DataError(
                    f"{name} has no obs key {missing[0]!r}; choose --key from: "
                    + ", ".join(sorted(obs))
                )
            parts = [np.asarray(obs[key], dtype=np.float64) for key in wanted]
            if any(part.ndim != 2 for part in parts):
                shapes = [part.shape for part in parts]
                raise DataError(f"{name}: obs {wanted} must be (T, n) arrays, got {shapes}")
            tracks.append(np.concatenate(parts, axis=1))
    if looks_like_poses(np.concatenate(tracks)):
        return [
            Track(
                state[:, :3],
                to_xyzw(state[:, 3:], options.quaternion_order, what=f"obs {options.key!r}"),
                None,
                name,
            )
            for name, state in zip(names, tracks)
        ]
    return [Track(state, None, None, name) for name, state in zip(names, tracks)]
