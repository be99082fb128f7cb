"""The JSON in and out of the page's server: request bodies read within the limits, their
numbers parsed in one place, each field checked (a :class:`~snds.errors.RequestError` with a
4xx status and one line otherwise), and JSON responses without NaN.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np
from starlette.requests import Request
from starlette.responses import Response

from snds.app.strokes import Limits, RequestError, parse_target, parse_vector
from snds.app.worker import Job
from snds.io import to_jsonable

__all__ = [
    "MAX_NUMBER_CHARACTERS",
    "SETTINGS",
    "json_ready",
    "json_response",
    "parse_grid",
    "parse_integer",
    "parse_phase",
    "parse_positive",
    "parse_pushes",
    "parse_settings",
    "read_body",
    "read_json",
    "shown_text",
]

#: Settings a train request may give (fields of :class:`~snds.app.worker.JobOptions`; the
#: rest are ``snds train``'s defaults); the ranges are in :class:`~snds.app.strokes.Limits`.
SETTINGS = ("steps", "seed", "rollouts", "samples")
#: Longest number (characters) a request body may hold: a float64 needs at most 24
#: (``-1.2345678901234567e-308``); longer is a mistake or an attack.
MAX_NUMBER_CHARACTERS = 32


def _finite(value: Any) -> Any:
    """JSON-ready data (:func:`snds.io.to_jsonable`) with non-finite floats as null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    return [_finite(v) for v in value] if isinstance(value, list) else value


def json_ready(value: Any) -> Any:
    """JSON-ready: NumPy to lists and floats, non-finite floats to null (JSON has no NaN)."""
    return _finite(to_jsonable(value))


def json_response(data: Any, status: int = 200) -> Response:
    """A JSON response of ``data`` (:func:`json_ready`: non-finite floats as null)."""
    body = json.dumps(json_ready(data), allow_nan=False, separators=(",", ":"))
    return Response(body, status_code=status, media_type="application/json")


async def read_body(request: Request, limits: Limits, *, media: str) -> bytes:
    """The request's body, refused (415, 413) unless of type ``media`` and within the limit."""
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if kind != media:
        raise RequestError(415, f"expected Content-Type {media}, got {kind or 'none'}")
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limits.max_body_bytes:
        raise RequestError(413, f"body of {int(declared)} bytes, at most {limits.max_body_bytes}")
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limits.max_body_bytes:
            raise RequestError(413, f"body larger than {limits.max_body_bytes} bytes")
        chunks.append(chunk)
    return b"".join(chunks)


def _refuse_constant(name: str) -> None:
    raise RequestError(400, f"malformed JSON: {name} is not a JSON number")


def shown_text(text: str) -> str:
    """A number's text as a message quotes it: whole if short, else its start and length."""
    return text if len(text) <= 20 else f"{text[:12]}... ({len(text)} characters)"


def _json_number(text: str) -> int | float:
    """Every number of a request body, parsed in one place (:func:`json.loads`'s hooks):
    at most :data:`MAX_NUMBER_CHARACTERS` characters and finite as a float, so that no field
    meets a number that overflows a float (``OverflowError``) or an integer too long for
    Python to read (``ValueError`` beyond 4,300 digits); each field then checks its range."""
    if len(text) > MAX_NUMBER_CHARACTERS:
        raise RequestError(
            422,
            f"a number of {len(text)} characters ({shown_text(text)}); at most "
            f"{MAX_NUMBER_CHARACTERS} are read",
        )
    number = float(text)
    if not math.isfinite(number):
        raise RequestError(
            422, f"the number {shown_text(text)} is beyond a float's range (1.8e308)"
        )
    is_integer = not any(c in text for c in ".eE")
    return int(text) if is_integer else number


async def read_json(request: Request, limits: Limits) -> dict:
    """The request's JSON object (400 if it is not one)."""
    raw = await read_body(request, limits, media="application/json")
    try:
        body = json.loads(
            raw.decode("utf-8"),
            parse_constant=_refuse_constant,
            parse_int=_json_number,
            parse_float=_json_number,
        )
    except UnicodeDecodeError:
        raise RequestError(400, "malformed JSON: not UTF-8") from None
    except json.JSONDecodeError as error:
        raise RequestError(
            400, f"malformed JSON: {error.msg} at line {error.lineno} column {error.colno}"
        ) from None
    except RecursionError:
        raise RequestError(400, "malformed JSON: nested too deeply") from None
    if not isinstance(body, dict):
        raise RequestError(400, "expected a JSON object")
    return body


def parse_integer(value: Any, name: str, low: int, high: int) -> int:
    """``value`` if it is an integer in [low, high] (a bool is not), else a 422 naming
    ``name``."""
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise RequestError(422, f"{name}: expected an integer in {low}..{high}, got {value!r}")
    return value


def parse_positive(value: Any, name: str, high: float) -> float:
    """``value`` as a float if it is a finite number in (0, high], else a 422 naming
    ``name``."""
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    if not (ok and math.isfinite(value) and 0 < value <= high):
        raise RequestError(422, f"{name}: expected a number in (0, {high:g}], got {value!r}")
    return float(value)


def parse_settings(raw: Any, limits: Limits) -> dict[str, int]:
    """A train request's ``settings`` (names of :data:`SETTINGS`, each an integer in its
    range of ``limits``); ``{}`` without any."""
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise RequestError(400, "'settings' must be an object")
    unknown = sorted(set(raw) - set(SETTINGS))
    if unknown:
        raise RequestError(422, f"unknown setting {unknown[0]!r} (known: {', '.join(SETTINGS)})")
    ranges = {
        "steps": (1, limits.max_steps),
        "seed": (0, 2**31 - 1),
        "rollouts": (1, limits.max_rollouts),
        "samples": (0, limits.max_samples),
    }
    return {k: parse_integer(v, f"settings.{k}", *ranges[k]) for k, v in raw.items()}


def parse_grid(body: dict, limits: Limits) -> tuple[np.ndarray, np.ndarray]:
    """The grid of a field request: x (nx,) and y (ny,) spread evenly over ``bounds`` [x0, x1,
    y0, y1], ``size`` [nx, ny] (default [40, 30], each in 2..``limits.max_grid``)."""
    bounds, size = body.get("bounds"), body.get("size", [40, 30])
    if not (isinstance(bounds, list) and len(bounds) == 4):
        raise RequestError(400, "'bounds' must be [x0, x1, y0, y1]")
    x0, x1 = parse_target(bounds[:2], limits, name="bounds")
    y0, y1 = parse_target(bounds[2:], limits, name="bounds")
    if not (x0 < x1 and y0 < y1):
        raise RequestError(422, "bounds: expected x0 < x1 and y0 < y1")
    if not (isinstance(size, list) and len(size) == 2):
        raise RequestError(400, "'size' must be [nx, ny]")
    nx, ny = (parse_integer(n, "size", 2, limits.max_grid) for n in size)
    return np.linspace(x0, x1, nx), np.linspace(y0, y1, ny)


def parse_phase(raw: Any, job: Job, limits: Limits) -> np.ndarray | None:
    """A rollout's phase to start with (a continuation's), or None: a new start's own."""
    if raw is None:
        return None
    size = job.extra["demos"].phase_dim
    if not size:
        raise RequestError(422, "'phase' is for a model with a phase; this one has none")
    return parse_vector(raw, size, limits, name="phase")


def parse_pushes(raw: Any, limits: Limits) -> list[tuple[float, np.ndarray]]:
    """A rollout request's ``pushes`` ``[{"at": s, "by": [dx, dy]}, ...]`` as (time,
    displacement (2,)) pairs sorted by time; ``[]`` without any."""
    if raw is None:
        return []
    if not isinstance(raw, list):
        raise RequestError(400, '\'pushes\' must be a list of {"at": s, "by": [dx, dy]}')
    if len(raw) > limits.max_pushes:
        raise RequestError(422, f"{len(raw)} pushes, at most {limits.max_pushes}")
    pushes = []
    for i, push in enumerate(raw):
        if not isinstance(push, dict) or set(push) != {"at", "by"}:
            raise RequestError(400, f'push {i}: expected {{"at": s, "by": [dx, dy]}}')
        at = push["at"]
        if isinstance(at, bool) or not isinstance(at, int | float) or not (0 <= at < math.inf):
            raise RequestError(422, f"push {i}: 'at' must be a time >= 0 in seconds")
        pushes.append((float(at), parse_target(push["by"], limits, name=f"push {i}")))
    return sorted(pushes, key=lambda push: push[0])
