"""Training jobs of the page: :func:`snds.run.train_run` in a worker process, watched by the
server.

Each job runs the library's training run (:func:`snds.run.train_run`, what ``snds train``
runs) on the strokes' CSV in a process of its own, so its run folder is exactly what ``snds
train`` writes with the same settings, and a crash, a kill or a runaway training cannot take
the server with it.

Importing torch and the library takes seconds, so a job's process is forked from one that
has done so once, when the server started (:mod:`multiprocessing`'s "forkserver", with
:data:`PRELOADED` imported): a job starts in milliseconds, however soon it follows the last
one. Where a platform cannot fork, each job's process starts afresh ("spawn").

The worker reports to the server in messages on a pipe, from the run's callbacks
(:class:`Reporter`): the training steps as they happen, the moment the model is saved (the
page draws the field then, while the stability check runs), and the end. A new job cancels
the one running (its process is killed); a worker that dies is reported as an error on its
job, and the next job gets a new process.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.forkserver
import os
import resource
import shutil
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field, replace
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from snds.app.fields import grid_field
from snds.callbacks import Callback, EndEvent, SavedEvent, StepEvent
from snds.data import DataSource
from snds.errors import ConfigError, SNDSError
from snds.phase import start_rule
from snds.policy import float64_copy
from snds.recipes import RECIPES
from snds.refine_run import refine_run
from snds.run import train_run
from snds.stability import ROLLOUTS, SAMPLES, CheckConfig

__all__ = [
    "ADDED_FILE",
    "FINAL_STATES",
    "METHODS",
    "STROKES_FILE",
    "Job",
    "JobOptions",
    "Jobs",
    "PREVIEW_EVERY",
    "PRELOADED",
    "Preview",
    "Reporter",
    "Worker",
    "run_job",
]

#: States after which a job changes no more.
FINAL_STATES = frozenset({"done", "error", "cancelled"})
#: Seconds between two progress reports of a worker (and the last step always).
REPORT_EVERY = 0.1
#: Seconds between two previews of the field while a job trains (:class:`Preview`).
PREVIEW_EVERY = 1.0
#: The methods the page trains, with whether the policy is stable (``snds train
#: --unconstrained`` for BC).
METHODS: dict[str, bool] = {"snds": True, "bc": False}
#: The strokes' CSV in a job's model folder: the file the run reads.
STROKES_FILE = "strokes.csv"
#: The strokes a refinement adds, in its job's model folder (:func:`snds.refine_run.refine_run`).
ADDED_FILE = "added.csv"
#: Modules the process that workers fork from imports once: the library's run, and torch's
#: compiler guard, which the first optimiser of a process would otherwise import (about 1 s).
PRELOADED = ("snds.app.worker", "torch._dynamo")


@dataclass(frozen=True, kw_only=True)
class JobOptions:
    """What a page's training job runs: the settings a request may give, with the defaults of
    ``snds train`` (the ranges a request may ask for are in :class:`~snds.app.strokes.Limits`).

    Attributes:
        method: "snds" or "bc" (:data:`METHODS`).
        steps: Optimiser steps.
        seed: Seed of the weights, the split, the fit and the check.
        rollouts: Random starts of the stability check.
        samples: States of the decrease check.
        init: A model folder to refine with the strokes of ``added.csv`` (:data:`ADDED_FILE`,
            :func:`snds.refine_run.refine_run`) instead of training on ``strokes.csv``; None:
            train.
        preview: The page's grid, ``{"x": [...], "y": [...]}``, on which the worker sends the
            field of the policy being trained every :data:`PREVIEW_EVERY` seconds
            (:class:`Preview`); None: no previews.
    """

    method: str = "snds"
    steps: int = RECIPES["default"].train.steps
    seed: int = 0
    rollouts: int = ROLLOUTS
    samples: int = SAMPLES
    init: str | None = None
    preview: dict | None = None

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ConfigError(f"unknown method {self.method!r} (known: {', '.join(METHODS)})")

    def to_dict(self) -> dict:
        """JSON-ready form (what the worker reads)."""
        return asdict(self)


# --- In the worker process ---------------------------------------------------------------------


class Reporter(Callback):
    """The run's callback in the worker: each event becomes a JSON message to the server.

    Progress (``step`` done, ``total``, the smoothed ``loss``) goes at most every
    :data:`REPORT_EVERY` seconds and at the last step; ``saved`` when the model is written.

    Arguments:
        send: Writes one message.
    """

    def __init__(self, send: Callable[[dict], None]) -> None:
        self.send = send
        self.last = 0.0
        self.latest: dict | None = None

    def on_step(self, event: StepEvent) -> None:
        self.latest = {
            "event": "progress",
            "step": event.step + 1,
            "total": event.total,
            "loss": event.smoothed,
        }
        now = time.perf_counter()
        if now - self.last >= REPORT_EVERY or event.step + 1 == event.total:
            self.last = now
            self.send(self.latest)

    def on_end(self, event: EndEvent) -> None:
        if self.latest is not None:  # the last step reached, also after an early stop
            self.send(self.latest)

    def on_saved(self, event: SavedEvent) -> None:
        self.send({"event": "saved"})


class Preview(Callback):
    """The run's callback that shows the field while training: every ``every`` seconds of
    training it sends the live policy's field on the page's grid
    (:func:`snds.app.fields.grid_field`) as a ``preview`` message, with the step it shows.

    Arguments:
        send: Writes one message.
        xs: The grid's x values (nx,).
        ys: The grid's y values (ny,).
        starts: The state a start at each grid point takes (None: the point itself).
        every: Seconds between two previews; the first comes after as many.
    """

    def __init__(
        self,
        send: Callable[[dict], None],
        xs: np.ndarray,
        ys: np.ndarray,
        starts: Callable[[np.ndarray], np.ndarray] | None,
        every: float = PREVIEW_EVERY,
    ) -> None:
        self.send, self.xs, self.ys, self.starts, self.every = send, xs, ys, starts, every
        self.last = time.perf_counter()

    def on_step(self, event: StepEvent) -> None:
        now = time.perf_counter()
        if now - self.last < self.every or event.step + 1 == event.total:
            return  # the saved model's field follows the last step
        field = grid_field(float64_copy(event.policy), self.xs, self.ys, self.starts)
        self.send({"event": "preview", "step": event.step + 1, "field": field})
        self.last = time.perf_counter()


def _preview(options: JobOptions, source: DataSource, send: Callable[[dict], None]) -> list:
    """The :class:`Preview` callback of a training job that asked for one (none otherwise)."""
    if options.preview is None:
        return []
    demos = source.load()
    rule = start_rule(demos) if demos.phase_dim else None
    xs, ys = (np.asarray(options.preview[k], dtype=np.float64) for k in ("x", "y"))
    return [Preview(send, xs, ys, None if rule is None else rule.start_states)]


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run_job(options: JobOptions, folder: Path, send: Callable[[dict], None]) -> None:
    """Trains on ``folder / strokes.csv`` into ``folder`` as ``snds train`` would with the
    same settings, reporting each event to ``send``.

    Events: ``progress`` (step, total, loss), ``saved`` (the model is written, the stability
    check starts), then ``done`` or ``error`` (a one-line message); each with the CPU
    seconds the job has taken so far.
    """
    before = _cpu_seconds()

    def report(message: dict) -> None:
        send({**message, "cpu_seconds": _cpu_seconds() - before})

    recipe = RECIPES["default"]
    recipe = replace(
        recipe,
        policy=replace(recipe.policy, stable=METHODS[options.method]),
        train=replace(recipe.train, steps=options.steps),
    )
    check = CheckConfig(rollouts=options.rollouts, samples=options.samples, seed=options.seed)
    source = DataSource(
        file=folder / STROKES_FILE, phase=recipe.phase, orientation_seed=options.seed
    )
    try:
        if options.init is not None:
            refine_run(
                options.init, folder / ADDED_FILE, folder, check=check, callbacks=[Reporter(report)]
            )
        else:
            train_run(
                source,
                folder,
                recipe=recipe,
                seed=options.seed,
                check=check,
                callbacks=[Reporter(report), *_preview(options, source, report)],
            )
        report({"event": "done"})
    except SNDSError as error:
        report({"event": "error", "message": str(error)})
    except Exception as error:  # a bug must still reach the page as one line
        report({"event": "error", "message": f"{type(error).__name__}: {error}"})


def _child(request: dict, events: Connection) -> None:
    """A worker process: runs the job of ``request`` (:class:`JobOptions` and ``folder``),
    sending its events on ``events``."""
    # Anything the library prints must not reach the server's standard output.
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    options = dict(request)
    folder = Path(options.pop("folder"))
    try:
        run_job(JobOptions(**options), folder, events.send)
    finally:
        events.close()


# --- In the server -----------------------------------------------------------------------------


def _context() -> multiprocessing.context.BaseContext:
    method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
    return multiprocessing.get_context(method)


class Worker:
    """The process of one job, started at once with its request.

    Arguments:
        request: The job's options (:meth:`JobOptions.to_dict`) and ``folder``.
    """

    def __init__(self, request: dict) -> None:
        context = _context()
        self.events, sender = context.Pipe(duplex=False)
        self.process = context.Process(
            target=_child, args=(request, sender), name="snds-worker", daemon=True
        )
        self.process.start()
        sender.close()  # the worker holds the only sending end: its exit ends the stream

    @property
    def pid(self) -> int | None:
        """The process id."""
        return self.process.pid

    def poll(self) -> int | None:
        """The exit code (minus the signal's number if killed by one), or None while it runs."""
        return self.process.exitcode

    def kill(self) -> None:
        """Kills the process (SIGKILL)."""
        if self.process.exitcode is None:
            self.process.kill()

    def wait(self, timeout: float | None = None) -> int | None:
        """Waits for the process to end (at most ``timeout`` seconds); its exit code."""
        self.process.join(timeout)
        return self.process.exitcode

    def messages(self) -> Iterator[dict]:
        """The worker's events, until its process has ended."""
        with contextlib.suppress(EOFError, OSError):
            while True:
                yield self.events.recv()

    def close(self) -> None:
        """Closes the event pipe (after the process has ended)."""
        self.events.close()


@dataclass
class Job:
    """One training of the page, as the server sees it.

    Attributes:
        id: Its name in the API (hex).
        method: "snds" or "bc".
        folder: Its run folder; the model is in ``folder / "model"``.
        settings: The settings the request asked for (the rest are ``snds train``'s).
        state: "training", "checking" (model saved, stability check running), "done",
            "error" or "cancelled".
        step: Optimiser steps done.
        total: Optimiser steps planned.
        loss: The smoothed training loss.
        error: The one-line reason of an error.
        started: ``time.perf_counter()`` at the start.
        saved_after: Seconds from the start until the model was saved.
        finished_after: Seconds from the start until the job ended.
        worker_cpu_seconds: CPU seconds the worker used.
        saved_cpu_seconds: CPU seconds the worker had used when the model was saved.
        previews: Previews of the field received while training (the latest is in
            ``extra["preview"]``).
        version: Bumped at every change (the event stream sends each).
        milestones: The status at each change of state, in order.
    """

    id: str
    method: str
    folder: Path
    settings: dict
    state: str = "training"
    step: int = 0
    total: int | None = None
    loss: float | None = None
    error: str | None = None
    started: float = field(default_factory=time.perf_counter)
    saved_after: float | None = None
    finished_after: float | None = None
    worker_cpu_seconds: float = 0.0
    saved_cpu_seconds: float | None = None
    previews: int = 0
    version: int = 0
    process: Any = field(default=None, repr=False)
    cancelled: bool = False
    extra: dict = field(default_factory=dict, repr=False)
    milestones: list[dict] = field(default_factory=list, repr=False)
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @property
    def model(self) -> Path:
        """The model directory (what ``snds train --out`` wrote)."""
        return self.folder / "model"

    @property
    def final(self) -> bool:
        """Whether the job has ended."""
        return self.state in FINAL_STATES

    def status(self) -> dict:
        """The job's JSON status (without results)."""
        return {
            "id": self.id,
            "method": self.method,
            "state": self.state,
            "step": self.step,
            "total": self.total,
            "loss": self.loss,
            "error": self.error,
            "settings": self.settings,
            "seconds": (
                self.finished_after
                if self.finished_after is not None
                else time.perf_counter() - self.started
            ),
            "saved_after": self.saved_after,
            "worker_cpu_seconds": self.worker_cpu_seconds,
            "saved_cpu_seconds": self.saved_cpu_seconds,
            "previews": self.previews,
        }


class Jobs:
    """The server's training jobs: at most one runs; a new one cancels it.

    Arguments:
        runs: The server's temporary runs folder (one subfolder per job).
        kept: Finished jobs kept; the oldest beyond are removed with their folders.
        on_saved: Called (in a watcher thread) with a job whose model was just saved, before
            the job is marked "checking"; it may store results in ``job.extra``.
    """

    def __init__(
        self, runs: Path, *, kept: int = 8, on_saved: Callable[[Job], None] | None = None
    ) -> None:
        self.runs = Path(runs)
        self.kept = kept
        self.on_saved = on_saved
        self.jobs: dict[str, Job] = {}
        self.lock = threading.Lock()
        self.starting = threading.Lock()

    def warm_up(self) -> None:
        """Starts the process that workers fork from, which imports :data:`PRELOADED` while
        nobody waits (nothing to do where workers start afresh)."""
        context = _context()
        if isinstance(context, multiprocessing.context.ForkServerContext):
            context.set_forkserver_preload(list(PRELOADED))
            multiprocessing.forkserver.ensure_running()

    def get(self, job_id: str) -> Job | None:
        """The job of that id, if the server still keeps it."""
        with self.lock:
            return self.jobs.get(job_id)

    def running(self) -> list[Job]:
        """Jobs that have not ended."""
        with self.lock:
            return [job for job in self.jobs.values() if not job.final]

    def start(self, options: JobOptions, settings: dict, prepare: Callable[[Path], None]) -> Job:
        """Starts a training run of ``options`` for a new job, cancelling the one running.

        Arguments:
            options: What the job trains.
            settings: The request's settings, for the status.
            prepare: Writes the job's inputs into its model directory and checks them; what
                it raises is raised here, before any job is cancelled or started.
        """
        job_id = uuid.uuid4().hex
        job = Job(id=job_id, method=options.method, folder=self.runs / job_id, settings=settings)
        job.model.mkdir(parents=True)
        try:
            prepare(job.model)
        except BaseException:
            shutil.rmtree(job.folder, ignore_errors=True)
            raise
        request = options.to_dict() | {"folder": str(job.model)}
        # One start at a time: two requests at once must not leave two jobs running.
        with self.starting:
            for running in self.running():
                self.cancel(running)
            job.started = time.perf_counter()
            job.process = Worker(request)
            with self.lock:
                self.jobs[job_id] = job
        threading.Thread(
            target=self._watch, args=(job,), name=f"snds-job-{job_id[:8]}", daemon=True
        ).start()
        self._prune()
        return job

    def cancel(self, job: Job) -> None:
        """Stops a job's worker (it is then "cancelled")."""
        if job.final:
            return
        job.cancelled = True
        if job.process is not None and job.process.poll() is None:
            job.process.kill()

    def close(self) -> None:
        """Stops every worker and waits for them (at shutdown)."""
        for job in self.running():
            self.cancel(job)
        for job in list(self.jobs.values()):
            if job.process is not None:
                job.process.wait(timeout=5)

    def _update(self, job: Job, **changes: Any) -> None:
        with job.lock:
            moved = changes.get("state", job.state) != job.state
            for name, value in changes.items():
                setattr(job, name, value)
            job.version += 1
            if moved:
                # A stream that polls may miss a state that lasted a moment; it replays these.
                job.milestones.append(job.status())

    def _watch(self, job: Job) -> None:
        """Applies a worker's events to its job until the worker is gone."""
        ended = False
        for message in job.process.messages():
            if not (job.cancelled or ended):
                ended = self._apply(job, message)
        code = job.process.wait()
        job.process.close()
        if job.cancelled:
            self._finish(job, "cancelled")
        elif not ended:
            how = f"was killed by signal {-code}" if code < 0 else f"exited with code {code}"
            self._finish(
                job,
                "error",
                error=f"the training worker stopped unexpectedly (it {how}); train again",
            )

    def _apply(self, job: Job, message: dict) -> bool:
        """Applies one event; True once the job has ended."""
        cpu = float(message.get("cpu_seconds", job.worker_cpu_seconds))
        event = message.get("event")
        if event == "progress":
            self._update(
                job,
                step=int(message["step"]),
                total=message.get("total"),
                loss=message.get("loss"),
                worker_cpu_seconds=cpu,
            )
        elif event == "preview":
            if job.state == "training":
                job.extra["preview"] = {**message["field"], "step": int(message["step"])}
                self._update(job, previews=job.previews + 1, worker_cpu_seconds=cpu)
        elif event == "saved":
            saved_after = time.perf_counter() - job.started
            try:
                if self.on_saved is not None:
                    self.on_saved(job)
            except Exception as error:  # the saved model could not be read back: say so
                self._finish(job, "error", error=f"{type(error).__name__}: {error}")
                job.process.kill()
                return True
            self._update(
                job,
                state="checking",
                saved_after=saved_after,
                saved_cpu_seconds=cpu,
                worker_cpu_seconds=cpu,
            )
        elif event in ("done", "error"):
            self._finish(job, event, error=message.get("message"), worker_cpu_seconds=cpu)
            return True
        return False

    def _finish(self, job: Job, state: str, **changes: Any) -> None:
        if job.final:
            return
        self._update(job, state=state, finished_after=time.perf_counter() - job.started, **changes)

    def _prune(self) -> None:
        """Removes the oldest finished jobs beyond :attr:`kept`, with their folders."""
        with self.lock:
            finished = [job for job in self.jobs.values() if job.final]
            for job in finished[: max(0, len(finished) - self.kept)]:
                del self.jobs[job.id]
                shutil.rmtree(job.folder, ignore_errors=True)
