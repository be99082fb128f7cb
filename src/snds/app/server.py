"""The page's web server: a JSON API over the library, and the page itself as static files.

Routes (all JSON unless said; errors are ``{"error": "one line"}`` with a 4xx status):

* ``GET /``: the page; ``GET /static/...``: its script and style (files of this package).
* ``GET /api/health``, ``GET /api/limits``.
* ``POST /api/train``: ``{"strokes": [[[x, y, t], ...], ...], "target": [x, y]?,
  "method": "snds" | "bc"?, "settings": {"steps", "seed", "rollouts", "samples"}?}``;
  starts ``snds train`` on them in a worker process (cancelling the job running) and answers
  202 with the job's status.
* ``POST /api/jobs/{id}/refine``: the body of ``/api/train`` with the job's strokes and
  target followed by new strokes; starts ``snds train --init`` on the job's model with the new
  strokes (:func:`snds.refine_run.refine_run`: about a second) as a new job, answered as
  ``/api/train`` is.
  409 if the strokes do not start with the job's own.
* ``GET /api/jobs/{id}``: the status; with ``result`` (demonstrations, reproductions from
  their starts, target, time step) once the model is saved and ``metrics`` (``snds train``'s
  metrics.json: the stability check) once done. ``GET /api/jobs/{id}/events``: the same as a
  stream of server-sent events, one per change, until the job ends. ``DELETE``: cancels it.
* ``POST /api/jobs/{id}/field``: ``{"bounds": [x0, x1, y0, y1], "size": [nx, ny]}``: the
  policy's velocities and V on that grid.
* ``POST /api/jobs/{id}/rollout``: ``{"start": [x, y], "pushes": [{"at": s, "by": [dx,
  dy]}]?, "duration": s?, "dt": s?}``: a rollout (:func:`snds.rollout.rollout`) with the
  guarded step (:class:`snds.steppers.GuardedEuler`; plain Euler for BC), stopping at the
  target.
* ``GET /api/jobs/{id}/model.zip``, ``/policy.onnx``, ``/strokes.csv``: downloads.
* ``POST /api/strokes.csv``: strokes (JSON) to the CSV ``snds train --data`` reads;
  ``POST /api/strokes/upload`` (``text/csv``): such a CSV back to strokes.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import math
import shutil
import socket
import tempfile
import threading
import webbrowser
import zipfile
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import Headers
from starlette.exceptions import HTTPException
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import FileResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from snds import __version__
from snds.app.strokes import (
    LIMITS,
    Limits,
    RequestError,
    Strokes,
    csv_text,
    demonstrations_from_csv,
    parse_strokes,
    parse_target,
    parse_vector,
    strokes_from_csv,
    write_csv,
)
from snds.app.worker import ADDED_FILE, METHODS, STROKES_FILE, Job, JobOptions, Jobs
from snds.arrival import ARRIVAL_TOLERANCE
from snds.data import Normalization
from snds.errors import SNDSError
from snds.evaluate import reproduce
from snds.io import to_jsonable
from snds.models import load_model
from snds.phase import Phase, start_rule
from snds.policy import PolicyConfig, StablePolicy, float64_copy
from snds.rollout import policy_guard, rollout
from snds.steppers import GuardedEuler

__all__ = [
    "LOCAL_HOSTS",
    "MAX_NUMBER_CHARACTERS",
    "SETTINGS",
    "STATIC",
    "LocalHostsOnly",
    "create_app",
    "serve",
]

STATIC = Path(__file__).parent / "static"
#: Host names a server bound to the loopback answers to (others are refused, which stops a
#: web page elsewhere from reaching it through DNS rebinding).
LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1", "[::1]")
#: Settings a train request may give (fields of :class:`~snds.app.worker.JobOptions`; the
#: rest are ``snds train``'s defaults); the ranges are in :class:`~snds.app.strokes.Limits`.
SETTINGS = ("steps", "seed", "rollouts", "samples")
#: Longest number (characters) a request body may hold: a float64 needs at most 24
#: (``-1.2345678901234567e-308``); longer is a mistake or an attack.
MAX_NUMBER_CHARACTERS = 32


# --- Requests and responses --------------------------------------------------------------------


def _finite(value: Any) -> Any:
    """JSON-ready data (:func:`snds.io.to_jsonable`) with non-finite floats as null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    return [_finite(v) for v in value] if isinstance(value, list) else value


def _clean(value: Any) -> Any:
    """JSON-ready: NumPy to lists and floats, non-finite floats to null (JSON has no NaN)."""
    return _finite(to_jsonable(value))


def _json(data: Any, status: int = 200) -> Response:
    body = json.dumps(_clean(data), allow_nan=False, separators=(",", ":"))
    return Response(body, status_code=status, media_type="application/json")


async def _body(request: Request, limits: Limits, *, media: str) -> bytes:
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


def _shown(text: str) -> str:
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
            f"a number of {len(text)} characters ({_shown(text)}); at most "
            f"{MAX_NUMBER_CHARACTERS} are read",
        )
    number = float(text)
    if not math.isfinite(number):
        raise RequestError(422, f"the number {_shown(text)} is beyond a float's range (1.8e308)")
    is_integer = not any(c in text for c in ".eE")
    return int(text) if is_integer else number


async def _json_body(request: Request, limits: Limits) -> dict:
    """The request's JSON object (400 if it is not one)."""
    raw = await _body(request, limits, media="application/json")
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


def _integer(value: Any, name: str, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise RequestError(422, f"{name}: expected an integer in {low}..{high}, got {value!r}")
    return value


def _positive(value: Any, name: str, high: float) -> float:
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    if not (ok and math.isfinite(value) and 0 < value <= high):
        raise RequestError(422, f"{name}: expected a number in (0, {high:g}], got {value!r}")
    return float(value)


def _settings(raw: Any, limits: Limits) -> dict[str, int]:
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
    return {k: _integer(v, f"settings.{k}", *ranges[k]) for k, v in raw.items()}


# --- Results -----------------------------------------------------------------------------------


def _warm_up() -> None:
    """Builds and runs a policy once: torch's first use of these layers takes over a second,
    which the first trained model's field would otherwise wait for."""
    normalization = Normalization(center=np.zeros(2), length=1.0, time=1.0)
    policy = float64_copy(StablePolicy(dim=2, normalization=normalization, config=PolicyConfig()))
    with torch.no_grad():
        policy(torch.zeros(2, 2, dtype=torch.float64))
        policy_guard(policy)[0](torch.ones(2, 2, dtype=torch.float64))


def _load_results(job: Job) -> None:
    """Reads a job's saved model and data (in the job's watcher thread, once)."""
    policy, description = load_model(job.model)
    policy64 = float64_copy(policy)
    demos = demonstrations_from_csv(job.model / STROKES_FILE, shown_as=STROKES_FILE)
    phase = description.get("data", {}).get("phase")
    if phase is not None:
        # The model's states carry the phase it was trained with (snds.phase).
        demos = Phase.from_record(phase).apply(demos)
    paths = reproduce(policy64, demos, list(range(len(demos))))
    extent = demos.extent()
    job.extra.update(
        policy=policy64,
        demos=demos,
        # How a click gets its phase, built once for every field and rollout of the job.
        start_rule=start_rule(demos) if demos.phase_dim else None,
        result={
            "stable": policy64.stable,
            "target": demos.target[:2],
            "demos": [d.positions[:, :2] for d in demos],
            "reproductions": [path[:, :2] for path in paths],
            "dt": demos.mean_dt(),
            "duration": demos.max_duration(),
            "extent": extent,
            # As the stability check counts a rollout arrived (snds.arrival).
            "tolerance": ARRIVAL_TOLERANCE * extent,
        },
    )


def _export_onnx(job: Job, path: Path) -> None:
    """Writes a job's model as ONNX (float32) with its start rule, as ``snds export`` does,
    and checks it against the library on 10,000 random states (seed 0); a file that fails
    the check is removed.

    Raises:
        ImportError: Without the export extra.
        ExportError: The file's outputs differ from the library's.
    """
    from snds import export  # the export extra: onnx, onnxruntime

    policy, _ = load_model(job.model)
    extra = {"start_rule": job.extra["start_rule"]} if policy.space.phase_dim else {}
    written = export.export_onnx(policy, path, dtype=torch.float32, **extra)
    check = export.verify(written, policy, samples=10_000, seed=0)
    if not check.passed:
        written.unlink(missing_ok=True)
        raise export.ExportError(f"{written.name}: {check.summary()}")


def _report(job: Job) -> dict:
    """The job's status, with its results as far as they exist."""
    report = job.status()
    if "result" in job.extra:
        report["result"] = job.extra["result"]
    if job.state == "done":
        if "metrics" not in job.extra:
            job.extra["metrics"] = json.loads((job.model / "metrics.json").read_text())
        report["metrics"] = job.extra["metrics"]
    return report


def _grid(body: dict, limits: Limits) -> tuple[np.ndarray, np.ndarray]:
    bounds, size = body.get("bounds"), body.get("size", [40, 30])
    if not (isinstance(bounds, list) and len(bounds) == 4):
        raise RequestError(400, "'bounds' must be [x0, x1, y0, y1]")
    x0, x1 = parse_target(bounds[:2], limits, name="bounds")
    y0, y1 = parse_target(bounds[2:], limits, name="bounds")
    if not (x0 < x1 and y0 < y1):
        raise RequestError(422, "bounds: expected x0 < x1 and y0 < y1")
    if not (isinstance(size, list) and len(size) == 2):
        raise RequestError(400, "'size' must be [nx, ny]")
    nx, ny = (_integer(n, "size", 2, limits.max_grid) for n in size)
    return np.linspace(x0, x1, nx), np.linspace(y0, y1, ny)


def _states(job: Job, points: np.ndarray) -> np.ndarray:
    """The states a start at each point (B, 2) takes: the point, with a model's phase the
    phase a new start there gets (:func:`snds.phase.start_rule`)."""
    rule = job.extra["start_rule"]
    return points if rule is None else rule.start_states(points)


@torch.no_grad()
def field_on_grid(job: Job, xs: np.ndarray, ys: np.ndarray) -> dict:
    """Velocities (ny, nx, 2) and V (ny, nx; None without one) of a job's policy on a grid:
    for a model with a phase, the velocity a new start at each point begins with."""
    policy = job.extra["policy"]
    points = _states(job, np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2))
    velocity = policy.predict(points)[:, :2].reshape(len(ys), len(xs), 2)
    value = None
    if policy.stable:
        lyapunov, _ = policy_guard(policy)
        value = lyapunov(torch.from_numpy(points)).numpy().reshape(len(ys), len(xs))
    return {"x": xs, "y": ys, "velocity": velocity, "V": value}


def _phase(raw: Any, job: Job, limits: Limits) -> np.ndarray | None:
    """A rollout's phase to start with (a continuation's), or None: a new start's own."""
    if raw is None:
        return None
    size = job.extra["demos"].phase_dim
    if not size:
        raise RequestError(422, "'phase' is for a model with a phase; this one has none")
    return parse_vector(raw, size, limits, name="phase")


def _pushes(raw: Any, limits: Limits) -> list[tuple[float, np.ndarray]]:
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


@torch.no_grad()
def rollout_from(
    job: Job,
    start: np.ndarray,
    *,
    phase: np.ndarray | None = None,
    pushes: list[tuple[float, np.ndarray]],
    duration: float,
    dt: float,
    max_steps: int,
) -> dict:
    """A rollout of a job's policy: the guarded step for a stable policy, else plain Euler.

    A model with a phase starts with ``phase``, or, without one, with the phase a new start
    gets (:func:`snds.phase.start_rule`); each push displaces the position at its time and
    the phase keeps its value. The rollout ends at ``duration`` (or after
    ``max_steps`` steps), or when the state is within the stability check's tolerance of the
    target with no push left.
    """
    policy = job.extra["policy"]
    result = job.extra["result"]
    target = torch.tensor(np.array(result["target"], dtype=np.float64))
    tolerance = result["tolerance"]
    steps = math.ceil(duration / dt)
    if steps > max_steps:
        raise RequestError(
            422, f"duration / dt = {steps} steps, at most {max_steps}; take a longer dt"
        )
    state = _states(job, np.reshape(start, (1, 2))) if phase is None else [[*start, *phase]]
    x = torch.as_tensor(np.asarray(state), dtype=torch.float64)
    # A push moves the position; a phase keeps its value.
    pad = [0.0] * (x.shape[1] - 2)
    t, times, states, shortened = 0.0, [0.0], [x[0, :2].tolist()], 0
    phases = [x[0, 2:].tolist()]
    pending = list(pushes)

    def stop(x: torch.Tensor) -> torch.Tensor:
        finite = torch.isfinite(x).all(dim=-1)
        arrived = (x[:, :2] - target).norm(dim=-1) <= tolerance
        return ~finite | (arrived if not pending else torch.zeros_like(finite))

    used = 0
    # Until the duration: the guard's shorter steps take more of them (at most max_steps).
    while used < max_steps and t < duration:
        while pending and pending[0][0] <= t:
            x = x + torch.as_tensor([*pending.pop(0)[1], *pad])
            times.append(t)
            states.append(x[0, :2].tolist())
            phases.append(x[0, 2:].tolist())
        # One piece of the rollout: to the next push, the end, or arrival.
        until = min(duration, pending[0][0]) if pending else duration
        piece = rollout(
            policy,
            x,
            dt=dt,
            steps=max_steps - used,
            stepper=GuardedEuler(),
            start_time=t,
            duration=until,
            until=stop,
        )
        times += piece.times[1:, 0].tolist()
        states += piece.states[1:, 0, :2].tolist()
        phases += piece.states[1:, 0, 2:].tolist()
        shortened += int((piece.taken < dt).sum())
        x, t, used = piece.final, float(piece.final_time[0]), used + piece.steps
        if bool(stop(x)[0]):
            break
    distance = float((x[0, :2] - target).norm())
    return {
        "t": times,
        "states": states,
        "phases": phases,
        "arrived": distance <= tolerance,
        "final_distance": distance,
        "tolerance": tolerance,
        "integrator": "guarded euler" if policy.stable else "euler",
        "shortened_steps": shortened,
        "dt": dt,
    }


def _zip_model(folder: Path, name: str) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for path in sorted(folder.iterdir()):
            # atomic_write's temporaries (".name.tmp") are not part of the model.
            if path.is_file() and not path.name.startswith("."):
                archive.write(path, f"{name}/{path.name}")
    return buffer.getvalue()


# --- The application ---------------------------------------------------------------------------


def _host_name(header: str) -> str:
    """The host name of a ``Host`` header, without its port (``[::1]:8765`` -> ``[::1]``)."""
    if header.startswith("["):
        return header[: header.find("]") + 1]
    return header.split(":")[0]


class LocalHostsOnly:
    """ASGI middleware that answers a request for another host name with the JSON 400 of
    every refusal (``{"error": ...}``): a page elsewhere that rebinds its DNS name to the
    loopback (DNS rebinding) does not reach the API.

    Arguments:
        app: The application.
        allowed: Host names answered (``"*"``: any).
    """

    def __init__(self, app: Any, allowed: tuple[str, ...] | list[str]) -> None:
        self.app = app
        self.allowed = set(allowed)

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] in ("http", "websocket") and "*" not in self.allowed:
            host = _host_name(Headers(scope=scope).get("host", ""))
            if host not in self.allowed:
                reason = (
                    f"host {_shown(host)!r} is not served here (only "
                    f"{', '.join(sorted(self.allowed))}); open the page at its address"
                )
                await _json({"error": reason}, 400)(scope, receive, send)
                return
        await self.app(scope, receive, send)


def create_app(
    *,
    limits: Limits = LIMITS,
    allowed_hosts: tuple[str, ...] | list[str] = LOCAL_HOSTS,
    runs_parent: Path | None = None,
) -> Starlette:
    """The page's server as an ASGI application.

    Its temporary runs folder (one subfolder per job) is made at startup, under
    ``runs_parent`` (default: the system's temporary folder), and removed at shutdown with
    every worker stopped.

    Arguments:
        limits: What requests may hold.
        allowed_hosts: Host names it answers to (``["*"]``: any).
        runs_parent: Where to make the runs folder.
    """

    def jobs_of(request: Request) -> Jobs:
        return request.app.state.jobs

    def job_of(request: Request, *, saved: bool = False, done: bool = False) -> Job:
        job = jobs_of(request).get(request.path_params["job"])
        if job is None:
            raise RequestError(404, f"no job {request.path_params['job']!r} on this server")
        if (saved and "policy" not in job.extra) or (done and job.state != "done"):
            if job.state in ("error", "cancelled"):
                raise RequestError(409, f"job {job.id} ended without a model ({job.state})")
            need = "finished" if done else "trained"
            raise RequestError(409, f"job {job.id} is not {need} yet ({job.state})")
        return job

    async def index(request: Request) -> Response:
        return FileResponse(STATIC / "index.html")

    async def favicon(request: Request) -> Response:
        # Browsers ask for /favicon.ico whatever the page links; the page's icon is an SVG.
        return FileResponse(STATIC / "favicon.svg", media_type="image/svg+xml")

    async def health(request: Request) -> Response:
        return _json(
            {"ok": True, "version": __version__, "running": len(jobs_of(request).running())}
        )

    async def get_limits(request: Request) -> Response:
        return _json(limits.to_dict())

    async def train(request: Request) -> Response:
        body = await _json_body(request, limits)
        strokes = parse_strokes(body, limits)
        method = body.get("method", "snds")
        if method not in METHODS:
            raise RequestError(422, f"unknown method {method!r} (known: {', '.join(METHODS)})")
        settings = _settings(body.get("settings"), limits)
        options = JobOptions(method=method, **settings)

        def write_inputs(model: Path) -> None:
            write_csv(strokes, model / STROKES_FILE)
            # Refused now, as snds train would refuse it, rather than as a failed job.
            demonstrations_from_csv(model / STROKES_FILE, shown_as="the strokes")

        job = await run_in_threadpool(jobs_of(request).start, options, settings, write_inputs)
        return _json(_report(job), status=202)

    async def refine(request: Request) -> Response:
        base = job_of(request, saved=True)
        body = await _json_body(request, limits)
        strokes = parse_strokes(body, limits)
        trained = (base.model / STROKES_FILE).read_text()
        count = len(base.extra["demos"])
        kept = Strokes(strokes.positions[:count], strokes.times[:count], strokes.target)
        if len(strokes.positions) <= count or csv_text(kept) != trained:
            raise RequestError(
                409,
                f"job {base.id} was trained on other strokes: refining adds strokes after "
                "its own, with its target; train again instead",
            )
        added = Strokes(strokes.positions[count:], strokes.times[count:], strokes.target)
        options = JobOptions(method=base.method, **base.settings, init=str(base.model))

        def write_inputs(model: Path) -> None:
            write_csv(strokes, model / STROKES_FILE)
            write_csv(added, model / ADDED_FILE)
            demonstrations_from_csv(model / ADDED_FILE, shown_as="the added strokes")

        job = await run_in_threadpool(jobs_of(request).start, options, base.settings, write_inputs)
        job.extra["refined_from"] = base.id
        return _json(_report(job), status=202)

    async def status(request: Request) -> Response:
        return _json(_report(job_of(request)))

    async def cancel(request: Request) -> Response:
        job = job_of(request)
        jobs_of(request).cancel(job)
        return _json(_report(job))

    async def events(request: Request) -> Response:
        job = job_of(request)

        def event(report: dict) -> str:
            return f"data: {json.dumps(_clean(report), allow_nan=False)}\n\n"

        async def stream() -> AsyncIterator[str]:
            version, quiet, seen = -1, 0.0, 0
            while True:
                if job.version != version:
                    version = job.version
                    # States that came and went between two looks, then the present.
                    milestones = list(job.milestones)
                    for missed in milestones[seen:-1]:
                        result = {"result": job.extra["result"]} if "result" in job.extra else {}
                        yield event({**missed, **result})
                    seen = max(seen, len(milestones))
                    yield event(_report(job))
                    quiet = 0.0
                    if job.final:
                        return
                elif quiet >= 15:
                    yield ": keep-alive\n\n"
                    quiet = 0.0
                await asyncio.sleep(0.05)
                quiet += 0.05

        return StreamingResponse(
            stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"}
        )

    async def field(request: Request) -> Response:
        job = job_of(request, saved=True)
        xs, ys = _grid(await _json_body(request, limits), limits)
        return _json(await run_in_threadpool(field_on_grid, job, xs, ys))

    async def rollout(request: Request) -> Response:
        job = job_of(request, saved=True)
        body = await _json_body(request, limits)
        if "start" not in body:
            raise RequestError(400, "'start' must be [x, y]")
        start = parse_target(body["start"], limits, name="start")
        phase = _phase(body.get("phase"), job, limits)
        pushes = _pushes(body.get("pushes"), limits)
        result = job.extra["result"]
        dt = _positive(body.get("dt", result["dt"]), "dt", 1e3)
        duration = _positive(body.get("duration", 10 * result["duration"]), "duration", 1e6)
        answer = await run_in_threadpool(
            rollout_from,
            job,
            start,
            phase=phase,
            pushes=pushes,
            duration=duration,
            dt=dt,
            max_steps=limits.max_rollout_steps,
        )
        return _json(answer)

    async def model_zip(request: Request) -> Response:
        job = job_of(request, done=True)
        name = f"snds-{job.method}-{job.id[:8]}"
        data = await run_in_threadpool(_zip_model, job.model, name)
        return Response(
            data,
            media_type="application/zip",
            headers={"Content-Disposition": f'attachment; filename="{name}.zip"'},
        )

    async def onnx(request: Request) -> Response:
        job = job_of(request, saved=True)
        path = job.folder / "export" / "policy.onnx"

        def export() -> None:
            _export_onnx(job, path)

        async with export_lock:
            if not path.is_file():
                try:
                    await run_in_threadpool(export)
                except ImportError as error:
                    raise RequestError(
                        501, f"ONNX export needs the export extra ({error.name} is missing)"
                    ) from None
                except SNDSError as error:
                    raise RequestError(422, str(error)) from None
        return FileResponse(
            path,
            media_type="application/octet-stream",
            filename=f"snds-{job.method}-{job.id[:8]}.onnx",
        )

    async def job_strokes(request: Request) -> Response:
        job = job_of(request)
        return FileResponse(job.model / STROKES_FILE, media_type="text/csv", filename=STROKES_FILE)

    async def strokes_csv(request: Request) -> Response:
        strokes = parse_strokes(await _json_body(request, limits), limits)
        return Response(
            csv_text(strokes),
            media_type="text/csv",
            headers={"Content-Disposition": f'attachment; filename="{STROKES_FILE}"'},
        )

    async def upload(request: Request) -> Response:
        raw = await _body(request, limits, media="text/csv")
        strokes = await run_in_threadpool(strokes_from_csv, raw, limits)
        return _json(strokes.to_dict())

    async def refused(request: Request, error: Exception) -> Response:
        assert isinstance(error, RequestError)
        return _json({"error": error.reason}, status=error.status)

    async def http_error(request: Request, error: Exception) -> Response:
        assert isinstance(error, HTTPException)
        reason = {404: f"not found: {request.url.path}", 405: "method not allowed"}
        return _json({"error": reason.get(error.status_code, str(error.detail))}, error.status_code)

    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        runs = Path(tempfile.mkdtemp(prefix="snds-app-", dir=runs_parent))
        jobs = Jobs(runs, kept=limits.kept_jobs, on_saved=_load_results)
        jobs.warm_up()
        threading.Thread(target=_warm_up, name="snds-app-warm-up", daemon=True).start()
        app.state.runs, app.state.jobs = runs, jobs
        try:
            yield
        finally:
            jobs.close()
            shutil.rmtree(runs, ignore_errors=True)

    export_lock = asyncio.Lock()
    job_path = "/api/jobs/{job:str}"
    routes = [
        Route("/", index),
        Route("/favicon.ico", favicon),
        Route("/api/health", health),
        Route("/api/limits", get_limits),
        Route("/api/train", train, methods=["POST"]),
        Route(f"{job_path}/refine", refine, methods=["POST"]),
        Route(job_path, status),
        Route(job_path, cancel, methods=["DELETE"]),
        Route(f"{job_path}/events", events),
        Route(f"{job_path}/field", field, methods=["POST"]),
        Route(f"{job_path}/rollout", rollout, methods=["POST"]),
        Route(f"{job_path}/model.zip", model_zip),
        Route(f"{job_path}/policy.onnx", onnx),
        Route(f"{job_path}/strokes.csv", job_strokes),
        Route("/api/strokes.csv", strokes_csv, methods=["POST"]),
        Route("/api/strokes/upload", upload, methods=["POST"]),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ]
    return Starlette(
        routes=routes,
        middleware=[Middleware(LocalHostsOnly, allowed=tuple(allowed_hosts))],
        exception_handlers={RequestError: refused, HTTPException: http_error},
        lifespan=lifespan,
    )


def serve(
    *, host: str = "127.0.0.1", port: int = 8765, open_browser: bool = False, quiet: bool = False
) -> int:
    """Runs the page's server until interrupted (``snds app``); returns the exit code.

    Arguments:
        host: Address to bind; the loopback by default, so only this machine reaches it.
        port: Port (0: any free one).
        open_browser: Open the page in the default web browser.
        quiet: Print nothing.
    """
    import uvicorn

    local = host in LOCAL_HOSTS
    try:
        sock = socket.create_server(
            (host.strip("[]"), port),
            family=socket.AF_INET6 if ":" in host else socket.AF_INET,
        )
    except OSError as error:
        raise SNDSError(f"cannot listen on {host}:{port}: {error.strerror or error}") from None
    bound = sock.getsockname()[1]
    url = f"http://{'[' + host.strip('[]') + ']' if ':' in host else host}:{bound}/"
    if not quiet:
        print(f"snds app: {url} (Ctrl-C stops it and removes its temporary files)")
        if not local:
            print(f"snds app: listening on {host}: anyone who can reach it can train on it")
    app = create_app(allowed_hosts=LOCAL_HOSTS if local else ("*",))
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
    if open_browser:
        threading.Timer(1.0, webbrowser.open, args=(url,)).start()
    server.run(sockets=[sock])
    return 0
