"""Saving and loading models: safetensors weights plus a JSON description, never pickle.

A model directory holds ``model.safetensors`` (the tensors) and ``model.json`` (format
version, library version, architecture, normalisation, target, train config and the data it
was trained on). Loading reads only these two plain formats, so a file we did not write can
at worst be refused, never execute code.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

from snds._version import __version__
from snds.data.demonstrations import Normalization
from snds.errors import DataError, ModelFileError
from snds.io import atomic_write, write_json
from snds.methods import POLICY_KINDS
from snds.policy import Policy

__all__ = [
    "DESCRIPTION",
    "FORMAT_VERSION",
    "WEIGHTS",
    "load_model",
    "read_description",
    "save_model",
]

#: Version of the model directory layout; a newer one is refused, not guessed at.
FORMAT_VERSION = 1
WEIGHTS = "model.safetensors"
DESCRIPTION = "model.json"


def save_model(policy: Policy, directory: Path, *, extra: dict | None = None) -> None:
    """Saves a policy of any method as ``model.safetensors`` + ``model.json`` in ``directory``.

    Arguments:
        policy: The policy.
        directory: The model directory (created if needed).
        extra: More JSON-ready records for ``model.json`` (train config, data source, ...).
    """
    directory = Path(directory)
    tensors = {k: v.detach().cpu().contiguous() for k, v in policy.state_dict().items()}
    description = {
        "format_version": FORMAT_VERSION,
        "library": "snds",
        "library_version": __version__,
        "kind": policy.kind,
        "method": policy.method,
        "dim": policy.dim,
        "dtype": str(next(iter(tensors.values())).dtype).removeprefix("torch."),
        "policy": policy.config.to_dict(),
        "normalization": policy.normalization.to_dict(),
        "target": policy.normalization.center.tolist(),
        **(extra or {}),
    }
    digest: list[str] = []

    def write_weights(tmp: Path) -> None:
        save_file(tensors, str(tmp))
        digest.append(_sha256(tmp))

    # Weights first, then the description that names their hash: a save interrupted between
    # the two renames leaves a pair that load_model refuses, never a silent mismatch.
    atomic_write(directory / WEIGHTS, write_weights)
    write_json(directory / DESCRIPTION, {**description, "weights_sha256": digest[0]})


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def read_description(directory: Path) -> dict:
    """Reads and validates ``model.json`` of a model directory."""
    path = Path(directory) / DESCRIPTION
    if not path.is_file():
        raise ModelFileError(f"{path}: missing (is {directory} a model directory?)")
    try:
        description = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ModelFileError(f"{path}: corrupted JSON ({error})") from error
    if not isinstance(description, dict) or description.get("library") != "snds":
        raise ModelFileError(f"{path}: not an snds model description")
    version = description.get("format_version")
    if not isinstance(version, int):
        raise ModelFileError(f"{path}: no integer format_version")
    if version > FORMAT_VERSION:
        raise ModelFileError(
            f"{path}: format version {version} is newer than this snds reads "
            f"({FORMAT_VERSION}); upgrade snds"
        )
    for key in ("dim", "policy", "normalization"):
        if key not in description:
            raise ModelFileError(f"{path}: missing field {key!r}")
    return description


def load_model(directory: Path) -> tuple[Policy, dict]:
    """Loads a policy saved by :func:`save_model`, of the class its ``kind`` names.

    Arguments:
        directory: The model directory.

    Returns:
        The policy (in eval mode, in the dtype it was saved in) and the ``model.json`` record.
    """
    directory = Path(directory)
    description = read_description(directory)
    # Files of format 1 written before baselines existed carry no kind: an SNDS/BC policy.
    kind = description.get("kind", "stable")
    if not isinstance(kind, str) or kind not in POLICY_KINDS:
        raise ModelFileError(
            f"{directory / DESCRIPTION}: unknown policy kind {kind!r}; this snds reads "
            f"{', '.join(POLICY_KINDS)}"
        )
    cls = POLICY_KINDS[kind]
    # Built on the meta device first (no memory): a crafted model.json asking for huge layers
    # is refused by the shape check below before anything is allocated.
    shapes = _described_shapes(directory / DESCRIPTION, cls, description)
    weights = directory / WEIGHTS
    if not weights.is_file():
        raise ModelFileError(f"{weights}: missing")
    try:
        with safe_open(str(weights), framework="pt") as header:
            found = {name: tuple(header.get_slice(name).get_shape()) for name in header.keys()}
    except (SafetensorError, OSError, ValueError) as error:
        raise ModelFileError(f"{weights}: corrupted safetensors file ({error})") from error
    _check_shapes(weights, shapes, found)
    recorded = description.get("weights_sha256")
    if recorded is not None and recorded != _sha256(weights):
        raise ModelFileError(
            f"{weights}: does not match {DESCRIPTION} (its hash differs: changed since, or a "
            "save was interrupted between the two files)"
        )
    policy = _build(directory / DESCRIPTION, cls, description)
    try:
        tensors = load_file(str(weights))
    except (SafetensorError, OSError, ValueError) as error:
        raise ModelFileError(f"{weights}: corrupted safetensors file ({error})") from error
    _check_tensors(weights, tensors)
    dtype = next(iter(tensors.values())).dtype
    policy.to(dtype)
    policy.load_state_dict(tensors)
    return policy.eval(), description


def _build(path: Path, cls: type[Policy], description: dict) -> Policy:
    """The policy ``description`` describes, with fresh weights; a ModelFileError if invalid."""
    try:
        fields = dict(description["policy"])
        for name, before in getattr(cls.config_class, "BEFORE_ADDED", {}).items():
            fields.setdefault(name, before)
        config = cls.config_class(**fields)
        normalization = Normalization.from_dict(description["normalization"])
        dim = description["dim"]
        # bool is an int to Python, and int("2") would accept text: only a true integer will do.
        if type(dim) is not int or dim < 1:
            raise ValueError(f"dim must be a positive integer, got {dim!r}")
        return cls(dim=dim, normalization=normalization, config=config)
    # A description we did not write can break a constructor anywhere: a wrong type
    # (TypeError), a bad value (ValueError, DataError), a negative width (RuntimeError).
    except (TypeError, ValueError, RuntimeError, KeyError, AttributeError, DataError) as error:
        # One line: torch's own messages list every overload on lines of their own.
        reason = (str(error).splitlines() or [type(error).__name__])[0]
        raise ModelFileError(f"{path}: invalid architecture ({reason})") from error


def _described_shapes(path: Path, cls: type[Policy], description: dict) -> dict[str, tuple]:
    """The tensor shapes of the described architecture, computed without allocating them."""
    with torch.device("meta"):
        policy = _build(path, cls, description)
    return {name: tuple(tensor.shape) for name, tensor in policy.state_dict().items()}


def _check_shapes(path: Path, expected: dict[str, tuple], found: dict[str, tuple]) -> None:
    missing = sorted(set(expected) - set(found))
    unexpected = sorted(set(found) - set(expected))
    if missing or unexpected:
        raise ModelFileError(
            f"{path}: tensors do not match the architecture (missing {missing[:3]}, "
            f"unexpected {unexpected[:3]})"
        )
    for name, shape in found.items():
        if shape != expected[name]:
            raise ModelFileError(
                f"{path}: tensor {name!r} has shape {shape}, the architecture needs "
                f"{expected[name]}"
            )


def _check_tensors(path: Path, found: dict[str, torch.Tensor]) -> None:
    for name, tensor in found.items():
        if not tensor.is_floating_point() or not bool(torch.isfinite(tensor).all()):
            raise ModelFileError(f"{path}: tensor {name!r} is not finite floating point")
