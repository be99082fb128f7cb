"""Strokes drawn on the page: their limits, their validation, and the CSV that ``snds train``
reads.

A stroke is a list of ``[x, y, t]`` points (page units, seconds from the stroke's first
point). All strokes of a request share one target: by default the first stroke's end, or a
``target`` the user dragged. Each stroke's end is moved onto it by the linear-in-time ramp
that the library's loaders use for ends that differ (:func:`snds.data.targets.common_target`),
so the CSV holds demonstrations that end exactly at the target and ``snds train --data`` takes
that target as it is. Every problem is a :class:`RequestError` with an HTTP status and a
one-line reason.
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from snds.data import MAX_END_SPREAD, Demonstrations, load_demonstrations
from snds.errors import DataError, RequestError
from snds.io import atomic_write

__all__ = [
    "CSV_HEADER",
    "LIMITS",
    "Limits",
    "RequestError",
    "Strokes",
    "csv_text",
    "demonstrations_from_csv",
    "parse_strokes",
    "parse_target",
    "parse_vector",
    "strokes_from_csv",
    "write_csv",
]

CSV_HEADER = "demo,t,x1,x2"


@dataclass(frozen=True)
class Limits:
    """What the server accepts; refused beyond (``GET /api/limits`` returns them).

    Attributes:
        max_body_bytes: Largest request body (JSON or an uploaded CSV), bytes.
        max_strokes: Most strokes (demonstrations) per request.
        min_points: Fewest points of a stroke.
        max_points: Most points of one stroke.
        max_total_points: Most points of all strokes together.
        max_coordinate: Largest absolute coordinate or time accepted.
        max_grid: Most grid points per axis of a field request.
        max_rollout_steps: Most Euler steps of a rollout.
        max_pushes: Most pushes of a rollout.
        max_steps: Most optimiser steps a train request may ask for.
        max_rollouts: Most random starts of a train request's stability check.
        max_samples: Most states of a train request's decrease check.
        kept_jobs: Finished jobs kept (with their run folders); older ones are removed.
    """

    max_body_bytes: int = 2_000_000
    max_strokes: int = 10
    min_points: int = 2
    max_points: int = 5_000
    max_total_points: int = 20_000
    max_coordinate: float = 1e6
    max_grid: int = 200
    max_rollout_steps: int = 20_000
    max_pushes: int = 50
    max_steps: int = 100_000
    max_rollouts: int = 10_000
    max_samples: int = 1_000_000
    kept_jobs: int = 8

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return asdict(self)


#: The server's limits.
LIMITS = Limits()


@dataclass(frozen=True)
class Strokes:
    """Validated strokes with their common target.

    Attributes:
        positions: Each stroke's points, shape (T_i, 2), its end moved onto the target.
        times: Each stroke's times in seconds, shape (T_i,), strictly increasing.
        target: The common end point, shape (2,).
    """

    positions: tuple[np.ndarray, ...]
    times: tuple[np.ndarray, ...]
    target: np.ndarray

    def to_dict(self) -> dict:
        """The JSON form the API takes and returns: strokes of [x, y, t] and the target."""
        return {
            "strokes": [
                np.column_stack([p, t]).tolist() for p, t in zip(self.positions, self.times)
            ],
            "target": self.target.tolist(),
        }


def _number(value: Any, where: str, limits: Limits) -> float:
    # bool is an int to Python; JSON true is not a coordinate.
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise RequestError(400, f"{where}: expected a number, got {_json_type(value)}")
    number = float(value)
    if not math.isfinite(number):
        raise RequestError(422, f"{where}: non-finite value {number}")
    if abs(number) > limits.max_coordinate:
        raise RequestError(422, f"{where}: {number:g} is beyond +-{limits.max_coordinate:g}")
    return number


def _json_type(value: Any) -> str:
    """The JSON name of a parsed value's type, for messages."""
    names = {type(None): "null", bool: "a boolean", str: "a string", list: "a list"}
    return names.get(type(value), "an object" if isinstance(value, dict) else "a number")


def _point(value: Any, where: str, limits: Limits) -> list[float]:
    if not isinstance(value, list) or len(value) != 3:
        raise RequestError(400, f"{where}: expected [x, y, t], got {_json_type(value)}")
    return [_number(v, where, limits) for v in value]


def parse_vector(value: Any, size: int, limits: Limits = LIMITS, *, name: str) -> np.ndarray:
    """A list of ``size`` numbers of the request (a 422 naming ``name`` otherwise)."""
    if not isinstance(value, list) or len(value) != size:
        raise RequestError(422, f"{name}: expected a list of {size} numbers")
    return np.array([_number(v, name, limits) for v in value])


def parse_target(value: Any, limits: Limits = LIMITS, *, name: str = "target") -> np.ndarray:
    """A 2-D point of the request, ``[x, y]``."""
    if not isinstance(value, list) or len(value) != 2:
        raise RequestError(400, f"{name}: expected [x, y], got {_json_type(value)}")
    return np.array([_number(v, name, limits) for v in value])


def parse_strokes(body: dict, limits: Limits = LIMITS) -> Strokes:
    """Validates the ``strokes`` (and optional ``target``) of a request body.

    Arguments:
        body: The parsed JSON object.
        limits: What is accepted.

    Raises:
        RequestError: 400 for a malformed structure, 422 for values out of the limits or
            strokes that cannot be demonstrations (a single point, times that do not increase).
    """
    strokes = body.get("strokes")
    if not isinstance(strokes, list):
        raise RequestError(
            400, "'strokes' must be a list of strokes, each a list of [x, y, t] points"
        )
    if not strokes:
        raise RequestError(422, "no strokes: draw at least one")
    if len(strokes) > limits.max_strokes:
        raise RequestError(422, f"{len(strokes)} strokes, at most {limits.max_strokes}")
    if not all(isinstance(stroke, list) for stroke in strokes):
        raise RequestError(400, "each stroke must be a list of [x, y, t] points")
    total = sum(len(stroke) for stroke in strokes)
    if total > limits.max_total_points:
        raise RequestError(422, f"{total} points in all, at most {limits.max_total_points}")
    positions, times = [], []
    for i, stroke in enumerate(strokes):
        if len(stroke) < limits.min_points:
            raise RequestError(
                422,
                f"stroke {i} has {len(stroke)} point{'s' * (len(stroke) != 1)}; a stroke needs "
                f"at least {limits.min_points}",
            )
        if len(stroke) > limits.max_points:
            raise RequestError(
                422, f"stroke {i} has {len(stroke)} points, at most {limits.max_points}"
            )
        points = np.array(
            [_point(p, f"stroke {i}, point {k}", limits) for k, p in enumerate(stroke)]
        )
        steps = np.diff(points[:, 2])
        if (steps <= 0).any():
            k = int(np.flatnonzero(steps <= 0)[0]) + 1
            raise RequestError(
                422,
                f"stroke {i}: times must increase strictly (point {k} at {points[k, 2]:g} s "
                f"after {points[k - 1, 2]:g} s)",
            )
        positions.append(points[:, :2])
        times.append(points[:, 2] - points[0, 2])
    raw = body.get("target")
    target = positions[0][-1].copy() if raw is None else parse_target(raw, limits)
    _check_end_spread(positions, target)
    moved = tuple(_end_at(p, t, target) for p, t in zip(positions, times))
    return Strokes(moved, tuple(times), target)


def _check_end_spread(positions: list[np.ndarray], target: np.ndarray) -> None:
    """Refuses strokes whose ends lie further from the target than ``snds train`` accepts
    (:data:`snds.data.MAX_END_SPREAD` of the extent, the largest distance of a point from the
    target): the ramp that moves each end onto the target would bend a stroke out of shape."""
    ends = np.array([np.linalg.norm(p[-1] - target) for p in positions])
    extent = max(float(np.linalg.norm(p - target, axis=-1).max()) for p in positions)
    worst = int(ends.argmax())
    if extent > 0 and ends[worst] > MAX_END_SPREAD * extent:
        raise RequestError(
            422,
            f"stroke {worst} ends {ends[worst]:.4g} from the target, {ends[worst] / extent:.0%} "
            f"of the strokes' extent {extent:.4g}; ends must lie within "
            f"{MAX_END_SPREAD:.0%} of it (as for snds train): move the target (the star) to "
            "where the strokes end, or end the strokes at it",
        )


def _end_at(positions: np.ndarray, times: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Moves a stroke's end onto ``target`` by the ramp of the loaders (zero at its start)."""
    ramp = (times - times[0]) / (times[-1] - times[0])
    moved = positions + ramp[:, None] * (target - positions[-1])
    # Exactly on the target, not an ulp off, so the loader sees ends that agree.
    moved[-1] = target
    return moved


def csv_text(strokes: Strokes) -> str:
    """The strokes as the CSV ``snds train --data`` reads (see
    :func:`snds.data.files.load_csv`): one row per point; ``repr`` keeps every float exact."""
    lines = [CSV_HEADER]
    for i, (positions, times) in enumerate(zip(strokes.positions, strokes.times)):
        rows = zip(times.tolist(), positions.tolist())
        lines += [f"{i},{t!r},{x!r},{y!r}" for t, (x, y) in rows]
    return "\n".join(lines) + "\n"


def write_csv(strokes: Strokes, path: Path) -> None:
    """Writes :func:`csv_text` atomically."""
    text = csv_text(strokes)
    atomic_write(path, lambda tmp: tmp.write_text(text))


def demonstrations_from_csv(path: Path, *, shown_as: str) -> Demonstrations:
    """Loads a strokes CSV the way ``snds train --data`` does; errors name it ``shown_as``.

    Raises:
        RequestError: 422 with the loader's reason.
    """
    try:
        return load_demonstrations(path)
    except DataError as error:
        raise RequestError(422, str(error).replace(str(path), shown_as)) from None


def strokes_from_csv(text: bytes, limits: Limits = LIMITS) -> Strokes:
    """The strokes of an uploaded CSV (any file ``snds train --data`` reads, in 2-D).

    Raises:
        RequestError: 422 if the file is not such a CSV or exceeds the limits.
    """
    with tempfile.TemporaryDirectory(prefix="snds-upload-") as folder:
        path = Path(folder) / "upload.csv"
        path.write_bytes(text)
        demos = demonstrations_from_csv(path, shown_as="upload.csv")
    if demos.dim != 2:
        raise RequestError(422, f"upload.csv: has {demos.dim}-D positions; the page draws 2-D")
    body = {
        "strokes": [np.column_stack([d.positions, d.times]).tolist() for d in demos],
        "target": demos.target.tolist(),
    }
    return parse_strokes(body, limits)
