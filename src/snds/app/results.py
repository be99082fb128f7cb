"""What the page's server computes from a job: its saved model and data loaded once
(:func:`load_results`), its status report, its field on a grid, a rollout with pushes, its
model as a zip and as checked ONNX.
"""

from __future__ import annotations

import io
import json
import math
import zipfile
from pathlib import Path

import numpy as np
import torch

from snds.app.fields import grid_field
from snds.app.strokes import RequestError, demonstrations_from_csv
from snds.app.worker import STROKES_FILE, Job
from snds.arrival import ARRIVAL_TOLERANCE
from snds.data import Normalization
from snds.evaluate import reproduce
from snds.models import load_model
from snds.phase import Phase, start_rule
from snds.policy import PolicyConfig, StablePolicy, float64_copy
from snds.rollout import policy_guard, rollout
from snds.steppers import GuardedEuler

__all__ = [
    "field_on_grid",
    "load_results",
    "report",
    "rollout_from",
    "start_states",
    "warm_up_policy",
    "write_onnx",
    "zip_model",
]


def warm_up_policy() -> None:
    """Builds and runs a policy once: torch's first use of these layers takes over a second,
    which the first trained model's field would otherwise wait for."""
    normalization = Normalization(center=np.zeros(2), length=1.0, time=1.0)
    policy = float64_copy(StablePolicy(dim=2, normalization=normalization, config=PolicyConfig()))
    with torch.no_grad():
        policy(torch.zeros(2, 2, dtype=torch.float64))
        policy_guard(policy)[0](torch.ones(2, 2, dtype=torch.float64))


def load_results(job: Job) -> None:
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


def write_onnx(job: Job, path: Path) -> None:
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


def report(job: Job) -> dict:
    """The job's status, with its results as far as they exist."""
    report = job.status()
    if "result" in job.extra:
        report["result"] = job.extra["result"]
    if job.state == "done":
        if "metrics" not in job.extra:
            job.extra["metrics"] = json.loads((job.model / "metrics.json").read_text())
        report["metrics"] = job.extra["metrics"]
    return report


def start_states(job: Job, points: np.ndarray) -> np.ndarray:
    """The states a start at each point (B, 2) takes: the point, with a model's phase the
    phase a new start there gets (:func:`snds.phase.start_rule`)."""
    rule = job.extra["start_rule"]
    return points if rule is None else rule.start_states(points)


def field_on_grid(job: Job, xs: np.ndarray, ys: np.ndarray) -> dict:
    """Velocities (ny, nx, 2) and V (ny, nx; None without one) of a job's policy on a grid
    (:func:`snds.app.fields.grid_field`): for a model with a phase, the velocity a new start
    at each point begins with."""
    return grid_field(job.extra["policy"], xs, ys, lambda points: start_states(job, points))


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
    state = start_states(job, np.reshape(start, (1, 2))) if phase is None else [[*start, *phase]]
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


def zip_model(folder: Path, name: str) -> bytes:
    """A zip archive of a model folder's files, inside a folder ``name``."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for path in sorted(folder.iterdir()):
            # atomic_write's temporaries (".name.tmp") are not part of the model.
            if path.is_file() and not path.name.startswith("."):
                archive.write(path, f"{name}/{path.name}")
    return buffer.getvalue()
