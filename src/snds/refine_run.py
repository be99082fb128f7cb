"""A refinement run: the model of a run folder taught more demonstrations, saved and
evaluated as :func:`snds.run.train_run` saves and evaluates a fit (``snds train --init``).

    run = refine_run("runs/Sine", "more.csv", "runs/Sine-more")    # a snds.run.Run

The old demonstrations are read again from what the model's ``model.json`` records; the
refined folder holds them with the new ones in ``demonstrations.csv`` (:data:`DEMONSTRATIONS`),
which its own record names, so that ``snds evaluate``, ``snds plot`` and a further refinement
read them. The refinement itself is :func:`snds.refine.refine`.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from snds.callbacks import Callback
from snds.checkpoint import CHECKPOINT
from snds.data.demonstrations import Demonstrations, Split
from snds.data.source import DataSource
from snds.errors import ConfigError, DataError, ModelFileError
from snds.io import atomic_write
from snds.models import load_model
from snds.policy import Policy, StablePolicy
from snds.refine import RefineConfig, Refinement, added_demonstrations, kept_phase, refine
from snds.run import Run, RunWarning, complete_run, split_of
from snds.runs import RunFolder
from snds.stability import CheckConfig
from snds.train_config import TrainConfig

__all__ = [
    "DEMONSTRATIONS",
    "RefinedModel",
    "refine_model",
    "refine_run",
    "write_demonstrations",
]

#: The file of a refined model's directory that holds all its demonstrations, old and new,
#: without a phase (its ``model.json`` data record names it).
DEMONSTRATIONS = "demonstrations.csv"


@dataclass(frozen=True)
class RefinedModel:
    """A model refined by :func:`refine_model`, not yet saved.

    Attributes:
        policy: The refined policy.
        demos: All its demonstrations, in its space (a phase appended).
        split: Which samples trained.
        refinement: What the refinement did.
        record: The ``model.json`` records to save it with (``data``, ``split``, ``train``,
            ``refined_from``).
    """

    policy: Policy
    demos: Demonstrations
    split: Split
    refinement: Refinement
    record: dict


def refine_run(
    init: str | Path,
    source: DataSource | str | Path,
    out: str | Path | None = None,
    *,
    config: RefineConfig = RefineConfig(),
    check: CheckConfig = CheckConfig(),
    plots: bool = False,
    resume: bool = False,
    checkpoint_every: int = 200,
    callbacks: Sequence[Callback] = (),
    progress: bool = False,
    threads: int | None = None,
) -> Run:
    """Refines the model in ``init`` with the demonstrations of ``source``, then saves and
    evaluates it as :func:`snds.run.train_run` does (the same files, callbacks and
    ``resume``).

    Arguments:
        init: The trained model's folder.
        source: The demonstrations to add, without a phase: a :class:`DataSource` or a file.
        out: The refined model's folder (None: ``INIT-refined`` beside ``init``; never
            ``init`` itself).
        config: The refinement's schedule.
        check: The stability check's settings.
        plots: Also write the plots.
        resume: Continue from the folder's checkpoint if there is one (same arguments).
        checkpoint_every: Steps between checkpoints.
        callbacks: Hooks (:class:`snds.callbacks.Callback`).
        progress: Show a progress bar while fitting (only on a terminal).
        threads: Torch CPU threads (None: the library's choice).

    Raises:
        SNDSError: ``init`` cannot be refined, its demonstrations cannot be read, or the new
            ones do not fit it (one line naming the cause).
    """
    init = Path(init)
    if not isinstance(source, DataSource):
        source = DataSource(file=Path(source))
    folder = RunFolder(Path(out) if out is not None else init.parent / f"{init.name}-refined")
    folder.prepare(resume=resume)
    if resume and not folder.checkpoint.is_file():
        warnings.warn(f"no checkpoint in {folder.path}: refining from the start", RunWarning, 2)
    refined = refine_model(
        init,
        source.load(),
        folder.path,
        added=source.record(),
        config=config,
        callbacks=callbacks,
        progress=progress,
        checkpoint_every=checkpoint_every,
        threads=threads,
    )
    policy, demos, split = refined.policy, refined.demos, refined.split
    return complete_run(
        folder,
        policy,
        refined.refinement.result,
        demos,
        split,
        record=refined.record,
        check=check,
        callbacks=callbacks,
        threads=threads,
        plots=plots,
    )


def refine_model(
    init: Path,
    new: Demonstrations,
    out: Path,
    *,
    added: dict | None = None,
    config: RefineConfig = RefineConfig(),
    callbacks: Sequence[Callback] = (),
    progress: bool = False,
    checkpoint_every: int = 200,
    threads: int | None = None,
) -> RefinedModel:
    """Refines the model saved in ``init`` with the ``new`` demonstrations; the old ones are
    read again from what its ``model.json`` records.

    Writes ``out/demonstrations.csv`` (:data:`DEMONSTRATIONS`: old and new, which the
    returned ``data`` record names) and the fit's checkpoint ``out/checkpoint.safetensors``,
    from which a refinement started again with the same arguments resumes; the caller saves
    the model.

    Arguments:
        init: The trained model's directory.
        new: The demonstrations to add, in user units, without a phase.
        out: The refined model's directory (not ``init``: the trained model stays).
        added: Where ``new`` came from (a :meth:`DataSource.record`), for the record.
        config: The refinement's schedule.
        callbacks: The fit's hooks.
        progress: Show a progress bar (only on a terminal).
        checkpoint_every: Steps between checkpoints.
        threads: Torch CPU threads (None: the library's choice).

    Raises:
        ModelFileError: ``init`` is not a model that refinement continues.
        DataError: Its demonstrations cannot be read, or ``new`` does not fit them.
    """
    init, out = Path(init), Path(out)
    if out.resolve() == init.resolve():
        raise ConfigError(f"{out}: the refined model needs a directory of its own, not {init}")
    policy, description = load_model(init)
    if not isinstance(policy, StablePolicy) or policy.kind != StablePolicy.kind:
        raise ModelFileError(
            f"{init}: a {policy.method} model of {policy.space}; refinement continues the "
            "training of snds and bc models of positions"
        )
    recorded = description.get("data") or {}
    if "motion" not in recorded and "file" not in recorded:
        raise DataError(f"{init}/model.json records no demonstrations to refine with")
    source = DataSource.from_record(recorded)
    try:
        old = dataclasses.replace(source, phase=None).load()
    except DataError as error:
        raise DataError(
            f"{init} was trained on demonstrations that cannot be read now: {error}"
        ) from None
    phase = None if source.phase is None else kept_phase(source.phase, old)
    demos = added_demonstrations(old, new, phase=phase, max_end_spread=source.max_end_spread)
    split_record = dict(description.get("split") or {})
    # A sample split draws each demonstration's mask in turn from one seeded stream, so the
    # old demonstrations keep the masks the model trained with.
    split = split_of(demos, split_record)
    try:
        train = TrainConfig(**(description.get("train") or {}))
    except (TypeError, ConfigError) as error:
        raise ModelFileError(f"{init}/model.json: unusable training settings ({error})") from None
    write_demonstrations(added_demonstrations(old, new), out / DEMONSTRATIONS)
    refinement = refine(
        policy,
        demos,
        split,
        config=config,
        train=train,
        new=range(len(old), len(demos)),
        callbacks=callbacks,
        progress=progress,
        checkpoint=out / CHECKPOINT,
        checkpoint_every=checkpoint_every,
        threads=threads,
    )
    data = DataSource(file=out / DEMONSTRATIONS, phase=phase).record()
    record = {
        "data": data,
        "split": split_record,
        "train": refinement.train.to_dict(),
        "refined_from": {
            "model": str(init.resolve()),
            "data": recorded,
            "added": added or {},
            "refine": config.to_dict(),
            "reach": refinement.reach,
        },
    }
    return RefinedModel(policy, demos, split, refinement, record)


def write_demonstrations(demos: Demonstrations, path: Path) -> None:
    """Writes position demonstrations (no phase) as the CSV :func:`snds.data.load_csv`
    reads, velocities included; ``repr`` keeps every number exact."""
    axes = range(1, demos.dim + 1)
    lines = [",".join(["demo", "t", *(f"x{k}" for k in axes), *(f"v{k}" for k in axes)])]
    for index, demo in enumerate(demos):
        for t, x, v in zip(demo.times.tolist(), demo.positions.tolist(), demo.velocities.tolist()):
            lines.append(",".join([str(index), repr(t), *map(repr, x), *map(repr, v)]))
    text = "\n".join(lines) + "\n"
    atomic_write(path, lambda tmp: tmp.write_text(text))
