r"""Readers of bare arrays: NumPy ``.npy`` files and pose matrices in MATLAB ``.mat`` files.

Their columns are not named, so the layout is read from the shape, and what the numbers
cannot say is stated with :class:`~snds.data.options.ReadOptions` (rate, quaternion order,
length unit).

``.npy`` (one array, never unpickled):

* (D, T, 4, 4) or (T, 4, 4): homogeneous transforms (poses); the rotation blocks are
  projected onto SO(3) (:func:`project_rotations`);
* (D, T, 7) or (T, 7) whose last four columns have unit norm on every sample: x, y, z and a
  quaternion (poses, ``quaternion_order`` required);
* (D, T, n) or (T, n) otherwise: positions.

D demonstrations of T samples each; no times (``rate`` required).

``.npz`` of transforms: one array of shape (D, T, 4, 4) or (T, 4, 4) (named by ``key``, or
the only such array), with optional times ``t`` (D, T) or (T,), or a scalar step ``dt``;
else ``rate``. Other ``.npz`` files are the table layout of :func:`~snds.data.load_npz`.

``.mat`` pose matrices (any file without the LPV-DS ``Data``/``data`` variables, or with
``key`` given): a matrix of 7 or 8 rows (or columns), x, y, z, a quaternion, and in the
8th a time row in seconds; it is a variable, a field of a struct variable
(``key="variable.field"``), or a cell array of such matrices (one per demonstration).
Without a time row, a ``dt`` beside the matrix (in the struct, or a variable) gives the step,
else ``rate``. Without ``key`` the file must hold exactly one such matrix.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import scipy.io
from scipy.spatial.transform import Rotation

from snds.data.files import real_array
from snds.data.options import DataWarning, ReadOptions, to_xyzw
from snds.data.tracks import Track
from snds.errors import DataError

__all__ = [
    "ROTATION_ERROR",
    "ROTATION_WARNING",
    "UNIT_TOLERANCE",
    "looks_like_poses",
    "holds_transforms",
    "mat_pose_tracks",
    "npy_tracks",
    "npz_transform_tracks",
    "project_rotations",
]

#: Largest deviation of a rotation block from SO(3) that is projected silently (logger rounding).
ROTATION_WARNING = 1e-3
#: Deviation beyond which a block is not a rotation (a scale, a shear, a reflection).
ROTATION_ERROR = 0.1
#: Largest deviation of a quaternion's norm from 1 for columns to count as quaternions.
UNIT_TOLERANCE = 1e-2


def project_rotations(matrices: np.ndarray) -> tuple[np.ndarray, float]:
    r"""Nearest rotations (Frobenius norm) to 3x3 matrices, and how far the farthest was.

    With the SVD :math:`M = U \Sigma V^T`, the closest rotation is :math:`R = U
    \operatorname{diag}(1, 1, \det(U V^T)) V^T`. The deviation is the largest
    :math:`|\sigma_i - 1|` over the matrices, with :math:`\sigma_3` negated for a reflection
    (:math:`\det M < 0`), so a reflection deviates by at least 2.

    Arguments:
        matrices: Shape (..., 3, 3).

    Returns:
        Unit quaternions (x, y, z, w) of the rotations, shape (..., 4), and the deviation.
    """
    u, sigma, vt = np.linalg.svd(matrices)
    sign = np.where(np.linalg.det(u @ vt) < 0, -1.0, 1.0)
    u[..., :, 2] *= sign[..., None]
    signed = sigma.copy()
    signed[..., 2] *= sign
    deviation = float(np.max(np.abs(signed - 1.0))) if signed.size else 0.0
    quaternions = Rotation.from_matrix((u @ vt).reshape(-1, 3, 3)).as_quat()
    return quaternions.reshape(*matrices.shape[:-2], 4), deviation


def looks_like_poses(array: np.ndarray) -> bool:
    """Whether samples (..., 7) are x, y, z and a quaternion: the last four numbers have unit
    norm (within :data:`UNIT_TOLERANCE`) on every sample, which 7-D positions never do."""
    if array.shape[-1] != 7 or array.size == 0:
        return False
    with np.errstate(over="ignore", invalid="ignore"):
        norms = np.linalg.norm(array[..., 3:], axis=-1)
    return bool(np.all(np.abs(norms - 1.0) <= UNIT_TOLERANCE))


def npy_tracks(path: Path, options: ReadOptions) -> list[Track]:
    """The demonstrations of a ``.npy`` file (layouts in the module doc)."""
    array = _numeric(_load_npy(path), "the array")
    if array.ndim >= 3 and array.shape[-2:] == (4, 4):
        return _transform_tracks(array[None] if array.ndim == 3 else array)
    if array.ndim == 2:
        array = array[None]
    if array.ndim != 3 or 0 in array.shape:
        raise DataError(
            f"expected an array (demos, samples, n), (demos, samples, 4, 4) or (samples, n), "
            f"got shape {array.shape}"
        )
    if looks_like_poses(array):
        quaternions = to_xyzw(array[..., 3:], options.quaternion_order, what="the array")
        return [
            Track(array[i, :, :3], quaternions[i], None, f"demonstration {i}")
            for i in range(len(array))
        ]
    return [Track(array[i], None, None, f"demonstration {i}") for i in range(len(array))]


def _load_npy(path: Path) -> np.ndarray:
    try:
        array = np.load(path, allow_pickle=False)
    # numpy raises ValueError (pickled objects refused, bad header), EOFError or OSError
    # depending on how the file is damaged; all mean the same to a user.
    except Exception as error:
        raise DataError(f"not a readable .npy array: {error}") from error
    if not isinstance(array, np.ndarray):
        raise DataError("not a single .npy array (an .npz archive? name it .npz)")
    return array


def _numeric(value: object, what: str) -> np.ndarray:
    array = real_array(value, what)
    if not np.all(np.isfinite(array)):
        raise DataError(f"{what} contains NaN or inf values")
    return array


def _transform_tracks(transforms: np.ndarray) -> list[Track]:
    """Tracks of (D, T, 4, 4) homogeneous transforms."""
    bottom = transforms[..., 3, :]
    if not np.allclose(bottom, [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        worst = np.unravel_index(
            np.argmax(np.abs(bottom - [0, 0, 0, 1]).max(-1)), bottom.shape[:-1]
        )
        raise DataError(
            f"transform {tuple(int(i) for i in worst)} is not homogeneous: its last row is "
            f"{np.round(bottom[worst], 4).tolist()}, expected [0, 0, 0, 1]"
        )
    quaternions, deviation = project_rotations(transforms[..., :3, :3])
    if deviation > ROTATION_ERROR:
        raise DataError(
            f"the 3x3 blocks are not rotations: a singular value is {deviation:.3g} from 1 "
            f"(more than {ROTATION_ERROR:g}; a scale, shear or reflection?)"
        )
    if deviation > ROTATION_WARNING:
        warnings.warn(
            f"rotation blocks deviate from SO(3) by up to {deviation:.3g}; projected onto the "
            "nearest rotations",
            DataWarning,
            stacklevel=2,
        )
    positions = transforms[..., :3, 3]
    return [
        Track(positions[i], quaternions[i], None, f"demonstration {i}")
        for i in range(len(transforms))
    ]


# NPZ transforms.


def _npz_arrays(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as archive:
            return {key: archive[key] for key in archive.files}
    # numpy raises several kinds of error for a damaged archive; all mean the same to a user.
    except Exception as error:
        raise DataError(f"not a readable .npz archive: {error}") from error


def _transform_keys(arrays: dict[str, np.ndarray]) -> list[str]:
    return [k for k, v in arrays.items() if v.ndim in (3, 4) and v.shape[-2:] == (4, 4)]


def holds_transforms(path: Path, options: ReadOptions) -> bool:
    """An ``.npz`` file with an array of 4x4 transforms (or with ``key`` given)."""
    if not (path.is_file() and path.suffix.lower() == ".npz"):
        return False
    if options.key is not None:
        return True
    try:
        with np.load(path, allow_pickle=False) as archive:
            return any(
                archive[key].ndim in (3, 4) and archive[key].shape[-2:] == (4, 4)
                for key in archive.files
            )
    # An unreadable archive goes to the table reader, whose errors already say why.
    except Exception:
        return False


def npz_transform_tracks(path: Path, options: ReadOptions) -> list[Track]:
    """The demonstrations of an ``.npz`` of transforms (layout in the module doc)."""
    arrays = _npz_arrays(path)
    keys = _transform_keys(arrays)
    key = options.key
    if key is None:
        if len(keys) != 1:
            raise DataError(f"choose the transforms with --key from: {', '.join(keys)}")
        key = keys[0]
    if key not in keys:
        found = ", ".join(keys) or "none"
        raise DataError(f"no array {key!r} of 4x4 transforms (found: {found})")
    transforms = _numeric(arrays[key], repr(key))
    transforms = transforms[None] if transforms.ndim == 3 else transforms
    tracks = _transform_tracks(transforms)
    shape = transforms.shape[:2]
    if "t" in arrays:
        times = _numeric(arrays["t"], "'t'")
        if times.shape not in (shape, shape[1:]):
            raise DataError(f"'t' must have shape {shape} or {shape[1:]}, got {times.shape}")
        times = np.broadcast_to(times, shape)
    elif "dt" in arrays:
        step = _numeric(arrays["dt"], "'dt'")
        if step.size != 1 or step.item() <= 0:
            raise DataError(f"'dt' must be one positive number, got shape {step.shape}")
        times = np.broadcast_to(step.item() * np.arange(shape[1]), shape)
    else:
        return tracks
    return [Track(t.positions, t.orientations, times[i], t.label) for i, t in enumerate(tracks)]


# MATLAB pose matrices.


def mat_pose_tracks(path: Path, options: ReadOptions) -> list[Track]:
    """The demonstrations of a ``.mat`` pose matrix (layout in the module doc)."""
    contents = _read_mat(path)
    candidates = _candidates(contents)
    if options.key is not None:
        if options.key not in candidates:
            found = ", ".join(sorted(candidates)) or "none"
            raise DataError(f"no pose matrix {options.key!r} (pose matrices found: {found})")
        key = options.key
    elif len(candidates) == 1:
        key = next(iter(candidates))
    elif not candidates:
        names = sorted(name for name in contents if not name.startswith("__"))
        raise DataError(
            "no variable 'Data' or 'data' (LPV-DS) and no pose matrix of 7 or 8 rows (x, y, z, "
            f"quaternion[, t]) (found: {', '.join(names) or 'none'})"
        )
    else:
        found = ", ".join(sorted(candidates)) or "none"
        raise DataError(
            "expected 'Data'/'data' (LPV-DS) or one matrix of 7 or 8 rows (x, y, z, "
            f"quaternion[, t]); pose matrices found: {found}; choose one with --key"
        )
    matrices, dt = candidates[key]
    return [_mat_track(matrix, dt, options, f"{key} {i}") for i, matrix in enumerate(matrices)]


def _read_mat(path: Path) -> dict:
    try:
        return scipy.io.loadmat(path, simplify_cells=True)
    except NotImplementedError as error:
        raise DataError("MATLAB v7.3 (HDF5) files are not supported; save with -v7") from error
    # scipy's reader fails with several exception types depending on where a damaged file
    # breaks off; all mean the same to a user.
    except Exception as error:
        raise DataError(f"not a readable MATLAB file (truncated or corrupt?): {error}") from error


def _candidates(contents: dict) -> dict[str, tuple[list[np.ndarray], float | None]]:
    """Every pose matrix (or cell of them) in the file, by key, with a ``dt`` beside it."""
    found: dict[str, tuple[list[np.ndarray], float | None]] = {}
    top_dt = _scalar(contents.get("dt"))
    for name, value in contents.items():
        if name.startswith("__"):
            continue
        if isinstance(value, dict):
            dt = _scalar(value.get("dt"))
            for field, inner in value.items():
                matrices = _pose_matrices(inner)
                if matrices:
                    found[f"{name}.{field}"] = (matrices, dt if dt is not None else top_dt)
        else:
            matrices = _pose_matrices(value)
            if matrices:
                found[name] = (matrices, top_dt)
    return found


def _scalar(value: object) -> float | None:
    if isinstance(value, (int, float)) and np.isfinite(value) and value > 0:
        return float(value)
    return None


def _pose_matrices(value: object) -> list[np.ndarray]:
    """The matrices of 7 or 8 rows (samples as columns) in ``value``, one or a cell of them."""
    cells = list(value) if isinstance(value, (list, tuple)) else [value]
    if isinstance(value, np.ndarray) and value.dtype == object:
        cells = list(value.ravel())
    matrices = []
    for cell in cells:
        if not isinstance(cell, np.ndarray) or cell.ndim != 2 or cell.dtype.kind not in "iuf":
            return []
        # Samples are the longer side: a 7 x 7 matrix is ambiguous and left alone.
        rows = cell if cell.shape[0] in (7, 8) and cell.shape[1] > cell.shape[0] else cell.T
        if rows.shape[0] not in (7, 8) or rows.shape[1] <= rows.shape[0]:
            return []
        if not looks_like_poses(rows[:7].T):
            return []
        matrices.append(rows.astype(np.float64))
    return matrices


def _mat_track(rows: np.ndarray, dt: float | None, options: ReadOptions, label: str) -> Track:
    if not np.all(np.isfinite(rows)):
        raise DataError(f"{label}: contains NaN or inf values")
    quaternions = to_xyzw(rows[3:7].T, options.quaternion_order, what=f"the matrix {label}")
    times = rows[7] if len(rows) == 8 else None
    if times is None and dt is not None and options.rate is None:
        times = dt * np.arange(rows.shape[1])
    return Track(rows[:3].T, quaternions, times, label)
