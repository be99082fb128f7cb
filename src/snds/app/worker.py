"""Training jobs of the page: ``snds train`` in a worker process, watched by the server.

Each job runs the command line's own ``snds train --data strokes.csv --out MODEL`` in a
process of its own (``python -m snds.app.worker``), so its run folder is exactly what
``snds train`` writes, and a crash, a kill or a runaway training cannot take the server with
it. Importing torch and the library takes seconds, so the server keeps one spare worker that
has done so and waits for its command line on its standard input; a job takes the spare and
a new spare starts behind it.

The worker reports to the server in JSON lines on its standard output: the training steps
as they happen, the moment the model is saved (the page draws the field then, while the
stability check runs), and the end. A new job cancels the one running (its process is
killed); a worker that dies is reported as an error on its job, and the next job gets a new
process.
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import shutil
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

__all__ = ["FINAL_STATES", "Job", "Jobs", "run_job"]

#: States after which a job changes no more.
FINAL_STATES = frozenset({"done", "error", "cancelled"})
#: Seconds between two progress reports of a worker (and the last step always).
REPORT_EVERY = 0.1


# --- In the worker process ---------------------------------------------------------------------


class _ReportingBar:
    """Stands in for ``tqdm`` inside :func:`snds.train.fit`: reports each step to the server.

    ``fit`` has no progress callback; it shows its progress with a tqdm bar, which it builds
    over its range of steps. In the worker (a process of its own, nothing else runs there)
    that name is rebound to this class, which passes the real step count on.
    """

    send: Callable[[dict], None] = staticmethod(lambda message: None)

    def __init__(self, iterable: Iterable | None = None, *, initial: int = 0, total=None, **_):
        self.iterable = iterable if iterable is not None else ()
        self.n = initial
        self.total = total
        self.loss: float | None = None
        self.last = 0.0

    def __iter__(self) -> Iterator:
        for item in self.iterable:
            yield item
            self.update()

    def update(self, n: int = 1) -> None:
        """Counts ``n`` more steps, reporting at most every :data:`REPORT_EVERY` seconds."""
        self.n += n
        now = time.perf_counter()
        if now - self.last >= REPORT_EVERY or self.n == self.total:
            self.last = now
            self.send({"event": "progress", "step": self.n, "total": self.total, "loss": self.loss})

    def set_postfix(self, loss: str | None = None, **_: Any) -> None:
        """Keeps the smoothed loss that ``fit`` shows."""
        with contextlib.suppress(TypeError, ValueError):
            self.loss = float(loss)

    def close(self) -> None:
        """Reports the last step."""
        self.send({"event": "progress", "step": self.n, "total": self.total, "loss": self.loss})

    def __getattr__(self, name: str) -> Callable[..., None]:
        # Any other tqdm method fit may call (refresh, set_description, ...) does nothing.
        return lambda *args, **kwargs: None


def _cpu_seconds() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run_job(argv: list[str], send: Callable[[dict], None]) -> None:
    """Runs ``snds ARGV`` (a ``train`` command line), reporting each event to ``send``.

    Events: ``progress`` (step, total, loss), ``saved`` (the model is written, the stability
    check starts), then ``done`` or ``error`` (a one-line message); each with the CPU
    seconds the job has taken so far.
    """
    import torch

    import snds.cli
    import snds.cli.train
    import snds.train
    from snds.errors import SNDSError

    before = _cpu_seconds()

    def report(message: dict) -> None:
        send({**message, "cpu_seconds": _cpu_seconds() - before})

    _ReportingBar.send = staticmethod(report)
    snds.train.tqdm = _ReportingBar
    # snds train evaluates through its module's `evaluate` attribute, which is wrapped here.
    evaluate = snds.cli.train.evaluate

    def saved_then_evaluate(*args: Any, **kwargs: Any) -> dict:
        # snds train saves the model, then evaluates it: the page can draw the field now.
        report({"event": "saved"})
        return evaluate(*args, **kwargs)

    snds.cli.train.evaluate = saved_then_evaluate
    try:
        args = snds.cli._build_parser().parse_args(argv)
        torch.set_num_threads(args.threads)
        args.run(args)
        report({"event": "done"})
    except SNDSError as error:
        report({"event": "error", "message": str(error)})
    except Exception as error:  # a bug must still reach the page as one line
        report({"event": "error", "message": f"{type(error).__name__}: {error}"})


def main() -> None:
    """``python -m snds.app.worker``: imports the library, then runs the one job whose
    command line (a JSON list) arrives on standard input; events go to standard output."""
    # Anything the library prints must not mix with the events: stdout becomes stderr.
    events = os.fdopen(os.dup(sys.stdout.fileno()), "w")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    import snds.cli

    # The slow part, done before the job arrives: torch, the library, and the modules the
    # command line's parser imports (the simulator's settings).
    snds.cli._build_parser()

    line = sys.stdin.readline()
    if not line:
        return

    def send(message: dict) -> None:
        events.write(json.dumps(message) + "\n")
        events.flush()

    run_job(json.loads(line), send)
    events.close()


# --- In the server -----------------------------------------------------------------------------


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
        self.spare: subprocess.Popen | None = None
        self.closed = False

    def _worker(self) -> subprocess.Popen:
        return subprocess.Popen(
            [sys.executable, "-c", "from snds.app.worker import main; main()"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )

    def warm_up(self) -> None:
        """Starts the spare worker (it imports torch and the library while nobody waits)."""
        with self.lock:
            if self.spare is None and not self.closed:
                self.spare = self._worker()

    def get(self, job_id: str) -> Job | None:
        """The job of that id, if the server still keeps it."""
        with self.lock:
            return self.jobs.get(job_id)

    def running(self) -> list[Job]:
        """Jobs that have not ended."""
        with self.lock:
            return [job for job in self.jobs.values() if not job.final]

    def start(
        self, method: str, settings: dict, argv: list[str], prepare: Callable[[Path], None]
    ) -> Job:
        """Starts ``snds ARGV`` for a new job, cancelling the one running.

        Arguments:
            method: "snds" or "bc".
            settings: The request's settings, for the status.
            argv: The command line, with ``{model}`` standing for the model directory.
            prepare: Writes the job's inputs into its model directory and checks them; what
                it raises is raised here, before any job is cancelled or started.
        """
        job_id = uuid.uuid4().hex
        job = Job(id=job_id, method=method, folder=self.runs / job_id, settings=settings)
        job.model.mkdir(parents=True)
        try:
            prepare(job.model)
        except BaseException:
            shutil.rmtree(job.folder, ignore_errors=True)
            raise
        # One start at a time: two requests at once must not leave two jobs running.
        with self.starting:
            for running in self.running():
                self.cancel(running)
            with self.lock:
                spare, self.spare = self.spare, None
            worker = spare if spare is not None and spare.poll() is None else self._worker()
            job.process = worker
            job.started = time.perf_counter()
            with self.lock:
                self.jobs[job_id] = job
        argv = [part.replace("{model}", str(job.model)) for part in argv]
        try:
            worker.stdin.write(json.dumps(argv) + "\n")
            worker.stdin.close()
        except OSError:
            pass  # the worker died: its watcher reports it
        threading.Thread(
            target=self._watch,
            args=(job, worker.stdout),
            name=f"snds-job-{job_id[:8]}",
            daemon=True,
        ).start()
        self.warm_up()
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
        """Stops every worker and the spare, and waits for them (at shutdown)."""
        with self.lock:
            self.closed = True
            spare, self.spare = self.spare, None
        for job in self.running():
            self.cancel(job)
        workers = [job.process for job in list(self.jobs.values()) if job.process is not None]
        if spare is not None:
            spare.kill()
            workers.append(spare)
        for worker in workers:
            with contextlib.suppress(subprocess.TimeoutExpired):
                worker.wait(timeout=5)
            for stream in (worker.stdin, worker.stdout):
                if stream is not None:
                    with contextlib.suppress(OSError):
                        stream.close()

    def _update(self, job: Job, **changes: Any) -> None:
        with job.lock:
            moved = changes.get("state", job.state) != job.state
            for name, value in changes.items():
                setattr(job, name, value)
            job.version += 1
            if moved:
                # A stream that polls may miss a state that lasted a moment; it replays these.
                job.milestones.append(job.status())

    def _watch(self, job: Job, lines: IO[str]) -> None:
        """Applies a worker's events to its job until the worker is gone."""
        ended = False
        with contextlib.suppress(OSError, ValueError):
            for line in lines:
                if job.cancelled or ended:
                    continue
                try:
                    message = json.loads(line)
                except json.JSONDecodeError:
                    continue
                ended = self._apply(job, message)
        code = job.process.wait()
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


if __name__ == "__main__":
    main()
