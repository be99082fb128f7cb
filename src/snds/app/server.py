"""The page's web server: a JSON API over the library, and the page itself as static files.

Routes (all JSON unless said; errors are ``{"error": "one line"}`` with a 4xx status):

* ``GET /``: the page; ``GET /static/...``: its script and style (files of this package).
* ``GET /api/health``, ``GET /api/limits``.
* ``POST /api/train``: ``{"strokes": [[[x, y, t], ...], ...], "target": [x, y]?,
  "method": "snds" | "bc"?, "settings": {"steps", "seed", "rollouts", "samples"}?,
  "preview": {"bounds", "size"}?}``; starts ``snds train`` on them in a worker process
  (cancelling the job running) and answers 202 with the job's status. With ``preview``, the
  worker computes the field of the policy being trained on that grid about every second.
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
  policy's velocities and V on that grid. ``GET /api/jobs/{id}/preview``: the latest field
  of the policy while it trains (``previews`` in the status counts them), with its ``step``;
  409 before the first.
* ``POST /api/jobs/{id}/rollout``: ``{"start": [x, y], "pushes": [{"at": s, "by": [dx,
  dy]}]?, "duration": s?, "dt": s?}``: a rollout (:func:`snds.rollout.rollout`) with the
  guarded step (:class:`snds.steppers.GuardedEuler`; plain Euler for BC), stopping at the
  target.
* ``GET /api/jobs/{id}/model.zip``, ``/policy.onnx``, ``/strokes.csv``: downloads.
* ``POST /api/strokes.csv``: strokes (JSON) to the CSV ``snds train --data`` reads;
  ``POST /api/strokes/upload`` (``text/csv``): such a CSV back to strokes.

The routes are here; what they read and answer is in :mod:`snds.app.messages`, what they
compute from a job in :mod:`snds.app.results`, the jobs themselves in :mod:`snds.app.worker`,
and the host check in :mod:`snds.app.hosts`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import shutil
import socket
import tempfile
import threading
import webbrowser
from collections.abc import AsyncIterator
from pathlib import Path

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import FileResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from snds import __version__
from snds.app.hosts import LOCAL_HOSTS, LocalHostsOnly
from snds.app.messages import (
    MAX_NUMBER_CHARACTERS,
    SETTINGS,
    json_ready,
    json_response,
    parse_grid,
    parse_phase,
    parse_positive,
    parse_pushes,
    parse_settings,
    read_body,
    read_json,
)
from snds.app.results import (
    field_on_grid,
    load_results,
    report,
    rollout_from,
    warm_up_policy,
    write_onnx,
    zip_model,
)
from snds.app.strokes import (
    LIMITS,
    Limits,
    RequestError,
    Strokes,
    csv_text,
    demonstrations_from_csv,
    parse_strokes,
    parse_target,
    strokes_from_csv,
    write_csv,
)
from snds.app.worker import ADDED_FILE, METHODS, STROKES_FILE, Job, JobOptions, Jobs
from snds.errors import SNDSError

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
        return json_response(
            {"ok": True, "version": __version__, "running": len(jobs_of(request).running())}
        )

    async def get_limits(request: Request) -> Response:
        return json_response(limits.to_dict())

    async def train(request: Request) -> Response:
        body = await read_json(request, limits)
        strokes = parse_strokes(body, limits)
        method = body.get("method", "snds")
        if method not in METHODS:
            raise RequestError(422, f"unknown method {method!r} (known: {', '.join(METHODS)})")
        settings = parse_settings(body.get("settings"), limits)
        preview = None
        if body.get("preview") is not None:
            if not isinstance(body["preview"], dict):
                raise RequestError(
                    400, "'preview' must be {bounds: [x0, x1, y0, y1], size: [nx, ny]}"
                )
            xs, ys = parse_grid(body["preview"], limits)
            preview = {"x": xs.tolist(), "y": ys.tolist()}
        options = JobOptions(method=method, **settings, preview=preview)

        def write_inputs(model: Path) -> None:
            write_csv(strokes, model / STROKES_FILE)
            # Refused now, as snds train would refuse it, rather than as a failed job.
            demonstrations_from_csv(model / STROKES_FILE, shown_as="the strokes")

        job = await run_in_threadpool(jobs_of(request).start, options, settings, write_inputs)
        return json_response(report(job), status=202)

    async def refine(request: Request) -> Response:
        base = job_of(request, saved=True)
        body = await read_json(request, limits)
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
        return json_response(report(job), status=202)

    async def status(request: Request) -> Response:
        return json_response(report(job_of(request)))

    async def cancel(request: Request) -> Response:
        job = job_of(request)
        jobs_of(request).cancel(job)
        return json_response(report(job))

    async def events(request: Request) -> Response:
        job = job_of(request)

        def event(data: dict) -> str:
            return f"data: {json.dumps(json_ready(data), allow_nan=False)}\n\n"

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
                    yield event(report(job))
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
        xs, ys = parse_grid(await read_json(request, limits), limits)
        return json_response(await run_in_threadpool(field_on_grid, job, xs, ys))

    async def preview(request: Request) -> Response:
        job = job_of(request)
        latest = job.extra.get("preview")
        if latest is None:
            raise RequestError(
                409, f"job {job.id} has no preview of its field ({job.state}, {job.previews} sent)"
            )
        return json_response(latest)

    async def rollout(request: Request) -> Response:
        job = job_of(request, saved=True)
        body = await read_json(request, limits)
        if "start" not in body:
            raise RequestError(400, "'start' must be [x, y]")
        start = parse_target(body["start"], limits, name="start")
        phase = parse_phase(body.get("phase"), job, limits)
        pushes = parse_pushes(body.get("pushes"), limits)
        result = job.extra["result"]
        dt = parse_positive(body.get("dt", result["dt"]), "dt", 1e3)
        duration = parse_positive(body.get("duration", 10 * result["duration"]), "duration", 1e6)
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
        return json_response(answer)

    async def model_zip(request: Request) -> Response:
        job = job_of(request, done=True)
        name = f"snds-{job.method}-{job.id[:8]}"
        data = await run_in_threadpool(zip_model, job.model, name)
        return Response(
            data,
            media_type="application/zip",
            headers={"Content-Disposition": f'attachment; filename="{name}.zip"'},
        )

    async def onnx(request: Request) -> Response:
        job = job_of(request, saved=True)
        path = job.folder / "export" / "policy.onnx"

        def export() -> None:
            write_onnx(job, path)

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
        strokes = parse_strokes(await read_json(request, limits), limits)
        return Response(
            csv_text(strokes),
            media_type="text/csv",
            headers={"Content-Disposition": f'attachment; filename="{STROKES_FILE}"'},
        )

    async def upload(request: Request) -> Response:
        raw = await read_body(request, limits, media="text/csv")
        strokes = await run_in_threadpool(strokes_from_csv, raw, limits)
        return json_response(strokes.to_dict())

    async def refused(request: Request, error: Exception) -> Response:
        assert isinstance(error, RequestError)
        return json_response({"error": error.reason}, status=error.status)

    async def http_error(request: Request, error: Exception) -> Response:
        assert isinstance(error, HTTPException)
        reason = {404: f"not found: {request.url.path}", 405: "method not allowed"}
        return json_response(
            {"error": reason.get(error.status_code, str(error.detail))}, error.status_code
        )

    @contextlib.asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        runs = Path(tempfile.mkdtemp(prefix="snds-app-", dir=runs_parent))
        jobs = Jobs(runs, kept=limits.kept_jobs, on_saved=load_results)
        jobs.warm_up()
        threading.Thread(target=warm_up_policy, name="snds-app-warm-up", daemon=True).start()
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
        Route(f"{job_path}/preview", preview),
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
