"""Loaders of user demonstration files: MATLAB ``.mat``, CSV and NumPy ``.npz``.

Every loader returns :class:`~snds.data.demonstrations.Demonstrations` whose ends lie exactly on
a common target (see :func:`~snds.data.targets.common_target`), and turns every problem with
the file into a one-line :class:`~snds.errors.DataError` that starts with the file's path.
No loader unpickles anything: a data file must not be able to run code.
"""

from __future__ import annotations

import contextlib
import csv
import itertools
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np
import scipy.io

from snds.data.demonstrations import Demonstration, Demonstrations
from snds.data.gaps import (
    DEFAULT_GAPS,
    check_gap_mode,
    estimate_time_step,
    fill_gaps,
    retime_gaps,
)
from snds.data.targets import MAX_END_SPREAD, common_target
from snds.errors import DataError

__all__ = [
    "csv_number",
    "error_context",
    "existing_file",
    "read_csv_rows",
    "real_array",
    "CSV_HEADER",
    "DEFAULT_DT",
    "LOADERS",
    "NPZ_KEYS",
    "load_csv",
    "load_demonstrations",
    "load_mat",
    "load_npz",
]

DEFAULT_DT = 0.01
"""Time step (seconds) assumed for ``.npz`` files that store neither ``t`` nor ``dt``."""

CSV_HEADER = "demo,t,x1,...,xn[,v1,...,vn]"
NPZ_KEYS = ("pos", "vel", "t", "dt")


def load_demonstrations(
    path: str | Path,
    *,
    max_end_spread: float = MAX_END_SPREAD,
    select: Sequence[int] | None = None,
    gaps: str = DEFAULT_GAPS,
) -> Demonstrations:
    """Loads a demonstrations file, choosing the reader by its extension (see :data:`LOADERS`).

    Arguments:
        path: A ``.mat``, ``.csv`` or ``.npz`` file.
        max_end_spread: Largest accepted distance of a demonstration's end from the common
            target, as a fraction of the motion's extent (see
            :func:`~snds.data.targets.common_target`).
        select: Keep only these demonstrations (0-based, in this order) before the target
            is chosen: a subset that ends at one point can be used from a file whose
            demonstrations end at several (3D-pick-box ends at two places 0.26 m apart).
        gaps: How a ``.mat`` file's recording gaps are treated, one of
            :data:`~snds.data.gaps.GAP_MODES` (see :func:`load_mat`). CSV and NPZ files carry
            their own time stamps; their samples are kept as they are.

    Raises:
        DataError: If the extension is not supported, ``gaps`` is unknown, or the file cannot
            be used.
    """
    path = Path(path)
    loader = LOADERS.get(path.suffix.lower())
    if loader is None:
        supported = ", ".join(sorted(LOADERS))
        raise DataError(f"{path}: unsupported file type {path.suffix!r} (supported: {supported})")
    check_gap_mode(gaps)
    options = {"gaps": gaps} if loader is load_mat else {}
    return loader(path, max_end_spread=max_end_spread, select=select, **options)


def load_mat(
    path: str | Path,
    *,
    max_end_spread: float = MAX_END_SPREAD,
    select: Sequence[int] | None = None,
    gaps: str = DEFAULT_GAPS,
) -> Demonstrations:
    """Loads demonstrations from a MATLAB file (v4 to v7.2) in one of the LPV-DS layouts.

    * ``Data``: a 2n x N matrix of concatenated demonstrations, rows = positions then
      velocities. Each demonstration ends with a sample of exactly zero velocity, which is where
      the matrix is split (a zero-velocity sample right after such an end starts the next
      demonstration at rest). Samples after the last zero-velocity sample form a last
      demonstration.
    * ``data``: a k x 1 (or 1 x k) cell of 2n x T_d matrices, positions then velocities.

    Either layout may store ``dt`` (1 x 1, seconds), the time step of every demonstration. Without
    it, each demonstration's step is estimated from its own samples (see
    :func:`~snds.data.gaps.estimate_time_step`): the velocities are the recorded ones, so the
    times that make them agree with the positions are the ones the demonstrator used.

    A recording that dropped samples jumps by centimetres in one step (every demonstration of
    the 3-D LPV-DS files does, once, early in the motion). With ``gaps="fill"`` (the default)
    the missing samples are put back (:func:`~snds.data.gaps.fill_gaps`): the demonstration is
    a continuous tube again, so a policy learns the motion across the gap and a reproduction
    is compared with the path the arm took, not with a jump. ``gaps="retime"`` keeps the recorded
    samples and only gives the jump the time it took (:func:`~snds.data.gaps.retime_gaps`).

    Arguments:
        path: The ``.mat`` file.
        max_end_spread: See :func:`load_demonstrations`.
        select: See :func:`load_demonstrations`.
        gaps: One of :data:`~snds.data.gaps.GAP_MODES`.

    Raises:
        DataError: If the file is missing, unreadable or truncated, lacks ``Data``/``data``,
            holds matrices of the wrong shape or with NaN/inf, or ``gaps`` is unknown.
    """
    check_gap_mode(gaps)
    path = existing_file(path)
    with error_context(str(path)):
        contents = _read_mat(path)
        dt = _mat_dt(contents)
        blocks = _mat_blocks(contents)
        demos = []
        for i, block in enumerate(blocks):
            with error_context(f"demonstration {i}"):
                demos.append(_mat_demonstration(block, dt, gaps))
        return _assemble(demos, path.stem, max_end_spread, select)


def load_csv(
    path: str | Path, *, max_end_spread: float = MAX_END_SPREAD, select: Sequence[int] | None = None
) -> Demonstrations:
    """Loads demonstrations from a CSV file with one row per sample.

    The header is ``demo,t,x1,...,xn`` optionally followed by ``v1,...,vn`` (case and spaces
    around names are ignored). ``demo`` labels the demonstration (any text or number); rows of
    one demonstration are in time order, and demonstrations keep the order in which their label
    first appears. ``t`` is in seconds.

    Without velocity columns, velocities are the second-order finite differences of the
    positions against the actual time stamps (``numpy.gradient``, so uneven steps are handled).
    They are not forced to zero at the end: the file says where the motion stops, not that it is
    at rest there.

    Arguments:
        path: The ``.csv`` file (UTF-8, comma-separated).
        max_end_spread: See :func:`load_demonstrations`.
        select: See :func:`load_demonstrations`.

    Raises:
        DataError: If the file is missing or empty, the header is misspelt (the message names
            the column), a row is malformed or non-finite, or a demonstration is invalid
            (fewer than 2 samples, repeated or decreasing times).
    """
    path = existing_file(path)
    with error_context(str(path)):
        rows = read_csv_rows(path)
        n, has_velocities = _parse_header(rows[0][1])
        samples = _group_samples(rows[1:], len(rows[0][1]))
        demos = []
        for label, values in samples.items():
            with error_context(f"demo {label!r}"):
                velocities = values[:, 1 + n :] if has_velocities else None
                demos.append(_demonstration(values[:, 1 : 1 + n], velocities, values[:, 0]))
        return _assemble(demos, path.stem, max_end_spread, select)


def load_npz(
    path: str | Path, *, max_end_spread: float = MAX_END_SPREAD, select: Sequence[int] | None = None
) -> Demonstrations:
    """Loads demonstrations from a NumPy ``.npz`` archive of equally long demonstrations.

    Keys:

    * ``pos``: positions, shape (demos, samples, n). Required.
    * ``vel``: velocities, same shape. Optional: without it, velocities are second-order finite
      differences of the positions against the times.
    * ``t``: times in seconds, shape (demos, samples), or (samples,) shared by all.
    * ``dt``: a scalar time step in seconds, instead of ``t``.

    With neither ``t`` nor ``dt`` the time step is :data:`DEFAULT_DT` = 0.01 s (100 Hz, a common
    robot logging rate); store ``t`` or ``dt`` whenever velocities matter in real units.
    Other keys are refused, so that a misspelt ``vel`` is not silently ignored.

    Arguments:
        path: The ``.npz`` file. Object (pickled) arrays are refused.
        max_end_spread: See :func:`load_demonstrations`.
        select: See :func:`load_demonstrations`.

    Raises:
        DataError: If the file is missing, not an ``.npz`` archive, has unknown or missing keys,
            arrays of the wrong shape or type, or NaN/inf values.
    """
    path = existing_file(path)
    with error_context(str(path)):
        arrays = _read_npz(path)
        positions = _npz_positions(arrays)
        velocities = arrays.get("vel")
        if velocities is not None and velocities.shape != positions.shape:
            raise DataError(f"'vel' has shape {velocities.shape}, 'pos' has {positions.shape}")
        times = _npz_times(arrays, positions.shape[:2])
        demos = []
        for i in range(positions.shape[0]):
            with error_context(f"demonstration {i}"):
                demo_velocities = None if velocities is None else velocities[i]
                demos.append(_demonstration(positions[i], demo_velocities, times[i]))
        return _assemble(demos, path.stem, max_end_spread, select)


LOADERS: dict[str, Callable[..., Demonstrations]] = {
    ".mat": load_mat,
    ".csv": load_csv,
    ".npz": load_npz,
}
"""Loader of each supported extension; each takes a path and ``max_end_spread``."""


# Shared helpers.


@contextlib.contextmanager
def error_context(where: str) -> Iterator[None]:
    """Prefixes DataErrors raised inside with ``where``, so messages say which file and demo."""
    try:
        yield
    except DataError as error:
        raise DataError(f"{where}: {error}") from error


def existing_file(path: str | Path) -> Path:
    """``path`` as a Path; a :class:`~snds.errors.DataError` if it is missing or a folder."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file")
    if not path.is_file():
        raise DataError(f"{path}: not a regular file")
    if path.stat().st_size == 0:
        raise DataError(f"{path}: file is empty")
    return path


def _demonstration(
    positions: np.ndarray, velocities: np.ndarray | None, times: np.ndarray
) -> Demonstration:
    """A demonstration, differentiating the positions when no velocities are given."""
    if velocities is None:
        # Validates shapes, finiteness and strictly increasing times before dividing by steps.
        demo = Demonstration(positions, np.zeros_like(positions, dtype=np.float64), times)
        edge_order = 2 if len(demo.times) > 2 else 1
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            velocities = np.gradient(demo.positions, demo.times, axis=0, edge_order=edge_order)
    return Demonstration(positions, velocities, times)


def _assemble(
    demos: list[Demonstration],
    name: str,
    max_end_spread: float,
    select: Sequence[int] | None = None,
) -> Demonstrations:
    if not demos:
        raise DataError("no demonstrations in the file")
    if select is not None:
        for i in select:
            if not 0 <= i < len(demos):
                raise DataError(f"demonstration index {i} out of range 0..{len(demos) - 1}")
        demos = [demos[i] for i in select]
    target, shifted = common_target(demos, max_end_spread=max_end_spread, indices=select)
    assembled = Demonstrations(shifted, target, name)
    # Refused here, inside the file's context, so that the message names the file.
    if assembled.extent() <= 0:
        raise DataError("demonstrations have zero extent (every sample is at the target)")
    return assembled


def real_array(value: object, what: str) -> np.ndarray:
    """``value`` as a float64 array, refusing text, objects and complex numbers."""
    if not isinstance(value, np.ndarray) or value.dtype.kind not in "iuf":
        kind = value.dtype if isinstance(value, np.ndarray) else type(value).__name__
        raise DataError(f"{what} must hold real numbers, got {kind}")
    return value.astype(np.float64)


# MATLAB.


def _read_mat(path: Path) -> dict[str, object]:
    try:
        return scipy.io.loadmat(path)
    except NotImplementedError as error:
        raise DataError("MATLAB v7.3 (HDF5) files are not supported; save with -v7") from error
    # scipy's reader fails with MatReadError, OSError, ValueError, IndexError or TypeError
    # depending on where a corrupt or truncated file breaks off; all mean the same to a user.
    except Exception as error:
        raise DataError(f"not a readable MATLAB file (truncated or corrupt?): {error}") from error


def _mat_dt(contents: dict[str, object]) -> float | None:
    if "dt" not in contents:
        return None
    dt = real_array(contents["dt"], "'dt'")
    if dt.size != 1 or not (np.isfinite(dt.item()) and dt.item() > 0):
        raise DataError(f"'dt' must be one positive number, got {np.ravel(dt)[:3]}")
    return dt.item()


def _mat_blocks(contents: dict[str, object]) -> list[np.ndarray]:
    """The 2n x T matrix of each demonstration."""
    if "Data" in contents and "data" in contents:
        raise DataError("holds both 'Data' and 'data'; keep one")
    if "Data" in contents:
        return _split_at_rest(real_array(contents["Data"], "'Data'"))
    if "data" in contents:
        cells = contents["data"]
        if not isinstance(cells, np.ndarray) or cells.dtype != object or cells.ndim != 2:
            raise DataError("'data' must be a k x 1 cell array of 2n x T matrices")
        return [real_array(cell, f"cell {i} of 'data'") for i, cell in enumerate(cells.ravel())]
    found = sorted(key for key in contents if not key.startswith("__"))
    raise DataError(f"no variable 'Data' or 'data' (found: {', '.join(found) or 'none'})")


def _split_at_rest(data: np.ndarray) -> list[np.ndarray]:
    """Cuts concatenated demonstrations after each zero-velocity sample."""
    if data.ndim != 2 or data.shape[0] % 2 or data.shape[0] == 0:
        raise DataError(f"'Data' must be 2n x N (positions then velocities), got {data.shape}")
    at_rest = np.all(data[data.shape[0] // 2 :] == 0, axis=0)
    blocks, start = [], 0
    for column in np.flatnonzero(at_rest):
        # A rest sample right after a cut is the next demonstration starting at rest.
        if column > start:
            blocks.append(data[:, start : column + 1])
            start = column + 1
    if start < data.shape[1]:
        blocks.append(data[:, start:])
    return blocks


def _mat_demonstration(block: np.ndarray, dt: float | None, gaps: str) -> Demonstration:
    if block.ndim != 2 or block.shape[0] % 2 or block.shape[0] == 0:
        raise DataError(f"expected a 2n x T matrix (positions then velocities), got {block.shape}")
    n = block.shape[0] // 2
    positions, velocities = block[:n].T, block[n:].T
    # Validates shapes and finiteness before estimating the time step from them.
    Demonstration(positions, velocities, np.arange(len(positions), dtype=np.float64))
    step = estimate_time_step(positions, velocities) if dt is None else dt
    if gaps == "fill":
        return Demonstration(*fill_gaps(positions, velocities, step))
    return Demonstration(positions, velocities, retime_gaps(positions, velocities, step))


# CSV.


def read_csv_rows(path: Path) -> list[tuple[int, list[str]]]:
    """Non-blank rows with their line numbers; the first is the header."""
    rows = []
    try:
        with path.open(newline="", encoding="utf-8-sig") as file:
            reader = csv.reader(file)
            for row in reader:
                rows.append((reader.line_num, row))
    except (UnicodeDecodeError, csv.Error) as error:
        raise DataError(f"not a UTF-8 CSV file: {error}") from error
    except OSError as error:
        raise DataError(f"cannot read the file: {error.strerror or error}") from error
    rows = [(line, row) for line, row in rows if any(field.strip() for field in row)]
    if len(rows) < 2:
        raise DataError(f"no samples (expected the header {CSV_HEADER} and one row per sample)")
    return rows


def _parse_header(header: list[str]) -> tuple[int, bool]:
    """The number n of coordinates, and whether velocity columns follow the positions."""
    names = [name.strip().lower() for name in header]
    n = sum(name.startswith("x") for name in names[2:])
    has_velocities = len(names) - 2 > n
    expected = ["demo", "t", *(f"x{i}" for i in range(1, n + 1))]
    expected += [f"v{i}" for i in range(1, n + 1)] if has_velocities else []
    for column, (name, want) in enumerate(itertools.zip_longest(names, expected), start=1):
        if name == want:
            continue
        if name is None:
            raise DataError(f"header lacks column {want!r} (expected {CSV_HEADER})")
        found = f"column {column} is {header[column - 1].strip()!r}"
        wanted = repr(want) if want else "no more columns"
        raise DataError(f"header {found}, expected {wanted} ({CSV_HEADER})")
    if n == 0:
        raise DataError(f"header has no position columns (expected {CSV_HEADER})")
    return n, has_velocities


def _group_samples(rows: list[tuple[int, list[str]]], width: int) -> dict[str, np.ndarray]:
    """The numbers (t, x, v) of each demo label, in order of first appearance, (T, width - 1)."""
    groups: dict[str, list[list[float]]] = {}
    for line, row in rows:
        if len(row) != width:
            raise DataError(f"line {line} has {len(row)} fields, the header {width}")
        groups.setdefault(row[0].strip(), []).append([csv_number(f, line) for f in row[1:]])
    return {label: np.asarray(values) for label, values in groups.items()}


def csv_number(field: str, line: int) -> float:
    """A CSV field as a finite float; a :class:`~snds.errors.DataError` naming the line."""
    try:
        value = float(field)
    except ValueError:
        raise DataError(f"line {line}: {field.strip()!r} is not a number") from None
    if not np.isfinite(value):
        raise DataError(f"line {line}: non-finite value {field.strip()!r}")
    return value


# NumPy.


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        loaded = np.load(path, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            raise DataError("not an .npz archive (a single .npy array?)")
        with loaded as archive:
            arrays = {key: archive[key] for key in archive.files}
    except DataError:
        raise
    # numpy raises BadZipFile, EOFError, OSError, ValueError (pickled objects refused) or zlib
    # errors depending on how the archive is damaged; all mean the same to a user.
    except Exception as error:
        raise DataError(f"not a readable .npz archive: {error}") from error
    unknown = sorted(set(arrays) - set(NPZ_KEYS))
    if unknown:
        raise DataError(f"unexpected arrays {unknown} (expected keys: {', '.join(NPZ_KEYS)})")
    return {key: real_array(value, repr(key)) for key, value in arrays.items()}


def _npz_positions(arrays: dict[str, np.ndarray]) -> np.ndarray:
    if "pos" not in arrays:
        raise DataError("no 'pos' array (positions, shape (demos, samples, n))")
    positions = arrays["pos"]
    if positions.ndim != 3 or 0 in positions.shape:
        raise DataError(f"'pos' must have shape (demos, samples, n), got {positions.shape}")
    return positions


def _npz_times(arrays: dict[str, np.ndarray], shape: tuple[int, int]) -> np.ndarray:
    """Times of every demonstration, shape (demos, samples)."""
    if "t" in arrays and "dt" in arrays:
        raise DataError("holds both 't' and 'dt'; keep one")
    if "t" in arrays:
        times = arrays["t"]
        if times.shape not in (shape, shape[1:]):
            raise DataError(f"'t' must have shape {shape} or {shape[1:]}, got {times.shape}")
        return np.broadcast_to(times, shape)
    dt = arrays["dt"] if "dt" in arrays else np.float64(DEFAULT_DT)
    if dt.size != 1 or not (np.isfinite(dt.item()) and dt.item() > 0):
        raise DataError(f"'dt' must be one positive number, got shape {dt.shape}")
    return np.broadcast_to(dt.item() * np.arange(shape[1]), shape)
