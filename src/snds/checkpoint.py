"""The state of a fit between two steps, and its checkpoint file.

A checkpoint holds the whole optimisation state in one safetensors file (tensors: weights,
the last good weights, Adam's moments, the generator, the loss history), with the scalars,
settings and identity as JSON in its header, so one atomic rename writes it all. A fit that
finds one continues from it bit for bit (:func:`snds.train.fit`); one of other settings,
architecture or data is refused.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

from snds.errors import CheckpointError
from snds.io import atomic_write
from snds.losses import Samples
from snds.policy import Policy

__all__ = [
    "CHECKPOINT",
    "CHECKPOINT_VERSION",
    "FitState",
    "TrainResult",
    "fit_identity",
    "restore_checkpoint",
    "save_checkpoint",
]


@dataclass
class TrainResult:
    """What :func:`snds.train.fit` did.

    Attributes:
        history: The loss at every step.
        seconds: Wall time of the optimisation.
        steps: Steps taken.
        restarts: Restarts after a NaN or diverging loss.
        stopped: Why training ended ("steps", "plateau", "time" or "callback").
    """

    history: list[float] = field(default_factory=list)
    seconds: float = 0.0
    steps: int = 0
    restarts: int = 0
    stopped: str = "steps"


CHECKPOINT_VERSION = 1
#: The checkpoint's name in a model directory (``snds train --resume`` looks for it there).
CHECKPOINT = "checkpoint.safetensors"
_RECORD = "snds_checkpoint"


@dataclass
class FitState:
    """Everything of a fit that changes from step to step, besides weights and optimiser.

    Attributes:
        good: The last good weights, which a diverged step restores.
        result: The result so far.
        step: The step being taken.
        best: The best smoothed loss.
        smoothed: The smoothed loss.
        since_best: Steps since the smoothed loss last improved enough.
        lr_scale: The learning rate's factor (halved at each restart).
        finished: Whether the fit has ended.
    """

    good: dict[str, torch.Tensor]
    result: TrainResult = field(default_factory=TrainResult)
    step: int = 0
    best: float = math.inf
    smoothed: float = math.inf
    since_best: int = 0
    lr_scale: float = 1.0
    finished: bool = False


def fit_identity(policy: Policy, config: Any, samples: Samples) -> dict:
    """What must be the same for a checkpoint to continue a fit: settings (``config``, a
    :class:`~snds.train.TrainConfig`), model, data."""
    digest = hashlib.sha256()
    for tensor in samples.tensors().values():
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    digest.update(str(samples.tracked).encode())
    identity = {
        "train": config.to_dict(),
        "kind": policy.kind,
        "dim": policy.dim,
        "policy": policy.config.to_dict(),
        "normalization": policy.normalization.to_dict(),
        "data_sha256": digest.hexdigest(),
    }
    # As it reads back from the file (tuples become lists), so the two compare equal.
    return json.loads(json.dumps(identity))


def save_checkpoint(
    path: Path,
    state: FitState,
    identity: dict,
    policy: Policy,
    optimizer: torch.optim.Optimizer,
    generator: torch.Generator,
) -> None:
    """Writes the state of a fit atomically; safetensors and JSON only."""
    tensors = {f"policy.{k}": v for k, v in policy.state_dict().items()}
    tensors |= {f"good.{k}": v for k, v in state.good.items()}
    optimizer_state = optimizer.state_dict()
    for index, entries in optimizer_state["state"].items():
        tensors |= {f"optimizer.{index}.{k}": v for k, v in entries.items()}
    tensors["generator"] = generator.get_state()
    tensors["history"] = torch.tensor(state.result.history, dtype=torch.float64)
    tensors = {k: v.detach().cpu().contiguous() for k, v in tensors.items()}
    result = {k: v for k, v in asdict(state.result).items() if k != "history"}
    record = {
        "version": CHECKPOINT_VERSION,
        "identity": identity,
        "step": state.step,
        "best": state.best,
        "smoothed": state.smoothed,
        "since_best": state.since_best,
        "lr_scale": state.lr_scale,
        "finished": state.finished,
        "result": result,
        "optimizer_groups": optimizer_state["param_groups"],
    }
    metadata = {_RECORD: json.dumps(record)}
    atomic_write(path, lambda tmp: save_file(tensors, str(tmp), metadata=metadata))


def restore_checkpoint(
    path: Path,
    identity: dict,
    policy: Policy,
    optimizer: torch.optim.Optimizer,
    generator: torch.Generator,
) -> FitState:
    """Loads a checkpoint into ``policy``, ``optimizer`` and ``generator``; the rest returned."""
    try:
        with safe_open(str(path), framework="pt") as file:
            record = json.loads((file.metadata() or {})[_RECORD])
        tensors = load_file(str(path))
        if record.get("version") != CHECKPOINT_VERSION:
            raise CheckpointError(
                f"{path}: checkpoint version {record.get('version')!r}, this snds reads "
                f"{CHECKPOINT_VERSION}"
            )
        if record["identity"] != identity:
            theirs, ours = record["identity"], identity
            differ = [k for k in ours if theirs.get(k) != ours[k]]
            details = [
                f"{k}.{f}: {theirs[k].get(f)!r} -> {ours[k][f]!r}"
                for k in differ
                if isinstance(ours[k], dict) and isinstance(theirs.get(k), dict)
                for f in ours[k]
                if theirs[k].get(f) != ours[k][f]
            ]
            names = {
                "train": "train settings",
                "kind": "method",
                "dim": "dimension",
                "policy": "architecture",
                "normalization": "normalisation",
                "data_sha256": "training data",
            }
            raise CheckpointError(
                f"{path}: made with other {', '.join(names.get(k, k) for k in differ)} "
                f"({'; '.join(details[:3]) or 'the training data differ'}); "
                "train without resuming, or with the same arguments"
            )

        def part(prefix: str) -> dict[str, torch.Tensor]:
            return {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}

        policy.load_state_dict(part("policy."))
        entries: dict[int, dict[str, torch.Tensor]] = {}
        for key, tensor in part("optimizer.").items():
            index, name = key.split(".", 1)
            entries.setdefault(int(index), {})[name] = tensor
        optimizer.load_state_dict({"state": entries, "param_groups": record["optimizer_groups"]})
        generator.set_state(tensors["generator"])
        history = tensors["history"].tolist()
        state = FitState(
            good={k: v.to(policy.center.device) for k, v in part("good.").items()},
            result=TrainResult(history=history, **record["result"]),
            step=int(record["step"]),
            best=float(record["best"]),
            smoothed=float(record["smoothed"]),
            since_best=int(record["since_best"]),
            lr_scale=float(record["lr_scale"]),
            finished=bool(record["finished"]),
        )
    except CheckpointError:
        raise
    # A damaged file can fail in the reader (SafetensorError, OSError), in the JSON, or in a
    # missing or misshapen entry (KeyError, TypeError, ValueError, RuntimeError from torch).
    except (SafetensorError, OSError, KeyError, TypeError, ValueError, RuntimeError) as error:
        raise CheckpointError(f"{path}: corrupted checkpoint ({error})") from error
    return state
