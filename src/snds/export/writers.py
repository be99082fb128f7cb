"""Writing an export: a ``.pt2`` archive (:func:`export_pt2`) or an ONNX file
(:func:`export_onnx`), each written whole or not at all (:func:`snds.io.atomic_write`).
"""

from __future__ import annotations

import contextlib
import json
import logging
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import torch

from snds.errors import ExportError
from snds.export.graph import check_dtype, signature, trace
from snds.export.onnx_ops import TRANSLATIONS
from snds.io import atomic_write
from snds.phase import StartRule
from snds.policy import Policy

__all__ = ["BATCH_NAME", "FORMATS", "INPUT_NAME", "export_onnx", "export_pt2", "quiet_exporter"]

#: The name of the ONNX input (a state per row) and of its batch dimension; the output is
#: :attr:`~snds.export.graph.Signature.output_name`.
INPUT_NAME = "state"
BATCH_NAME = "batch"


@contextlib.contextmanager
def quiet_exporter() -> Iterator[None]:
    """Silences the ONNX exporter's logging and torch's FutureWarnings while it runs."""
    # The ONNX exporter logs a warning per missing optional library (torchvision), and torch
    # warns about its own deprecated internals: neither is the user's business.
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)
            yield
    finally:
        logger.setLevel(level)


def export_pt2(policy: Policy, path: str | Path, *, dtype: torch.dtype = torch.float32) -> Path:
    """Exports a policy with ``torch.export`` to a ``.pt2`` archive.

    Arguments:
        policy: The policy; it is copied, not changed.
        path: The file to write.
        dtype: Precision of the graph, its input and its output.

    Returns:
        The path written. Its program maps positions (B, n) to velocities (B, n), user units
        (a pose policy: poses (B, 7) to twists (B, 6), see :class:`Signature`).
    """
    check_dtype(dtype)
    program = trace(policy, dtype)
    # Example inputs would be stored with torch.save, a pickle; the program needs none.
    program.example_inputs = None
    path = Path(path)

    def write(tmp: Path) -> None:
        # Through a file object: torch.export.save warns about a file name not ending in .pt2.
        with open(tmp, "wb") as handle:
            torch.export.save(program, handle)

    atomic_write(path, write)
    return path


def export_onnx(
    policy: Policy,
    path: str | Path,
    *,
    dtype: torch.dtype = torch.float32,
    start_rule: StartRule | None = None,
) -> Path:
    """Exports a policy to ONNX (opset 18), with a dynamic batch dimension.

    Arguments:
        policy: The policy; it is copied, not changed.
        path: The file to write.
        dtype: Precision of the graph, its input and its output.
        start_rule: How a model with a phase gives a new start its phase
            (:func:`snds.phase.start_rule`), written as ``snds.start_references`` (a JSON list
            of reference states) and ``snds.start_reach`` (user units): a new start takes the
            phase of the reference nearest to its position if within the reach, else 0.

    Returns:
        The path written. The graph maps ``x`` (B, n) to velocities (B, n), user units (a
        pose policy: poses (B, 7) to twists (B, 6), see :class:`Signature`); its metadata
        holds ``snds.dim``, ``snds.input`` and ``snds.output`` (what they are, in words),
        ``snds.target`` (a JSON list; a pose policy: position then quaternion),
        ``snds.extent`` (the demonstrations' largest distance from the target),
        ``snds.top_speed`` (user units per second), ``snds.dtype`` and ``snds.method``; a pose
        policy's also ``snds.angle_extent`` (radians) and ``snds.top_angular_speed`` (rad/s).
    """
    check_dtype(dtype)
    starts = {} if start_rule is None else _start_metadata(policy, start_rule)
    try:
        import onnx
    except ImportError as error:
        raise ExportError(
            "ONNX export needs onnx and onnxscript: pip install 'snds[export]'"
        ) from error
    program = trace(policy, dtype)
    kind = signature(policy)
    with quiet_exporter():
        onnx_program = torch.onnx.export(
            program,
            input_names=[INPUT_NAME],
            output_names=[kind.output_name],
            dynamo=True,
            optimize=True,
            verbose=False,
            custom_translation_table=TRANSLATIONS,
        )
    model = onnx_program.model_proto
    # The exporter names the batch dimension after its symbol (s77): a controller reads it.
    for value in [*model.graph.input, *model.graph.output]:
        value.type.tensor_type.shape.dim[0].dim_param = BATCH_NAME
    metadata = {
        **signature(policy).metadata(),
        "snds.dtype": str(dtype).removeprefix("torch."),
        "snds.method": policy.method,
        # A modulated policy (snds.obstacles) records its fixed obstacles.
        **getattr(policy, "export_metadata", dict)(),
        **starts,
    }
    for key, value in metadata.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    path = Path(path)
    atomic_write(path, lambda tmp: onnx.save(model, str(tmp)))
    return path


def _start_metadata(policy: Policy, rule: StartRule) -> dict[str, str]:
    """A start rule as ONNX metadata, or an error naming the shape."""
    references = np.asarray(rule.references, dtype=np.float64)
    dim = policy.space.dim
    if references.ndim != 2 or references.shape[1] != dim or not np.isfinite(references).all():
        raise ExportError(
            f"start references must be finite, of shape (K, {dim}); got {references.shape}"
        )
    return {
        "snds.start_references": json.dumps(references.tolist()),
        "snds.start_reach": repr(float(rule.reach)),
    }


#: ``snds export --format`` choices.
FORMATS: dict[str, Callable[..., Path]] = {"onnx": export_onnx, "pt2": export_pt2}
