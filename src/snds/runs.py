"""The run folder: one trained model with the record of how it was trained and its results.

A run folder holds

- ``model.safetensors`` + ``model.json``: the model and how it was trained (:mod:`snds.models`);
- ``loss.json``: the training loss history;
- ``metrics.json``: the accuracy and the stability report of its last evaluation;
- ``checkpoint.safetensors`` while a training runs (``snds train --resume`` continues from it).

Every file is written through a temporary file and a rename (:func:`snds.io.atomic_write`),
and results are removed before a new model is written, so that whatever kills a run, the
folder never shows the results of one model beside another model.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import tempfile
from pathlib import Path

from snds.checkpoint import CHECKPOINT, TrainResult
from snds.errors import ConfigError
from snds.io import atomic_write, remove_temporaries, to_jsonable, write_json
from snds.models import DESCRIPTION, WEIGHTS, load_model, read_description, save_model
from snds.policy import Policy

__all__ = ["LOSS", "METRICS", "RunFolder"]

#: The loss history's file.
LOSS = "loss.json"
#: The evaluation's file.
METRICS = "metrics.json"


@dataclasses.dataclass(frozen=True)
class RunFolder:
    """A run folder (see the module's description).

    Attributes:
        path: The folder; it need not exist yet.
    """

    path: Path

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))

    @property
    def checkpoint(self) -> Path:
        """Where a training in this folder keeps its checkpoint."""
        return self.path / CHECKPOINT

    @property
    def metrics_file(self) -> Path:
        """The evaluation's file, ``metrics.json``."""
        return self.path / METRICS

    @property
    def loss_file(self) -> Path:
        """The loss history's file, ``loss.json``."""
        return self.path / LOSS

    def prepare(self, *, resume: bool = False) -> None:
        """Makes the folder ready for a training: refuses a file in its place, removes the
        temporaries of a killed write and, unless ``resume``, the checkpoint of an earlier
        training.

        Raises:
            ConfigError: ``path`` is a file.
        """
        if self.path.exists() and not self.path.is_dir():
            raise ConfigError(f"--out {self.path}: is a file, not a directory")
        remove_temporaries(self.path)
        if not resume:
            self.checkpoint.unlink(missing_ok=True)

    def save(self, policy: Policy, result: TrainResult | None = None, *, record: dict) -> None:
        """Writes a trained model, removing the results of any earlier model first.

        Arguments:
            policy: The model; written from a CPU copy, the policy itself stays on its device.
            result: What the training did: its loss history goes to ``loss.json``, the rest
                to ``model.json`` as ``train_result``. None: ``record`` has what there is.
            record: JSON-ready records for ``model.json`` (``data``, ``split``, ``train``...).
        """
        if policy.center.device.type != "cpu":
            policy = copy.deepcopy(policy).to("cpu")
        self.clear_results()
        record = dict(record)
        if result is not None:
            record["train_result"] = {
                k: v for k, v in dataclasses.asdict(result).items() if k != "history"
            }
        save_model(policy, self.path, extra=record)
        if result is not None:
            write_json(self.loss_file, {"history": result.history})

    def clear_results(self) -> None:
        """Removes ``metrics.json`` and ``loss.json``, which belong to the model before."""
        for path in (self.metrics_file, self.loss_file):
            path.unlink(missing_ok=True)

    def write_metrics(self, metrics: dict) -> None:
        """Writes ``metrics.json`` (NumPy values become plain JSON)."""
        write_json(self.metrics_file, to_jsonable(metrics))

    def finish(self) -> None:
        """Marks the training complete: removes its checkpoint."""
        self.checkpoint.unlink(missing_ok=True)

    def load(self) -> tuple[Policy, dict]:
        """The model and its ``model.json`` record (:func:`snds.models.load_model`)."""
        return load_model(self.path)

    def read_config(self) -> dict:
        """The ``model.json`` record: architecture, data, split, training settings."""
        return read_description(self.path)

    def read_metrics(self) -> dict | None:
        """The last evaluation, or None if there is none."""
        return json.loads(self.metrics_file.read_text()) if self.metrics_file.is_file() else None

    def read_history(self) -> list[float] | None:
        """The training loss history, or None without ``loss.json``."""
        if not self.loss_file.is_file():
            return None
        return json.loads(self.loss_file.read_text()).get("history")

    @staticmethod
    def model_files(policy: Policy, record: dict) -> dict[str, bytes]:
        """The files :meth:`save` would write for a model without a loss history, as bytes
        by name: for a process that trains where it cannot write the folder."""
        with tempfile.TemporaryDirectory() as folder:
            RunFolder(Path(folder)).save(policy, record=record)
            return {name: (Path(folder) / name).read_bytes() for name in (WEIGHTS, DESCRIPTION)}

    def write_files(self, files: dict[str, bytes]) -> None:
        """Writes files of :meth:`model_files`, results of an earlier model removed first;
        the weights before the description that names their hash."""
        self.clear_results()
        for name in sorted(files, key=lambda name: name != WEIGHTS):
            content = files[name]
            atomic_write(self.path / name, lambda tmp, content=content: tmp.write_bytes(content))
