r"""Export of a policy for a real-time controller, and the check that it computes the same.

The exported graph is the policy's own ``forward``: user positions in, user velocities out,
with the Lyapunov gradient written analytically (:meth:`snds.nn.Lyapunov.value_and_grad`),
so no autograd is needed or traced. For an SE(3) :class:`~snds.se3.PosePolicy` (space
:class:`~snds.spaces.SE3`) a state is a pose (x, y, z, qx, qy, qz, qw; user units and a unit
quaternion), and the output the twist (linear velocity in user units per second, then
the world-frame angular velocity in rad/s) out, with the log map of the orientation and the
left Jacobian of SO(3) in the graph, so a controller needs no quaternion maths of its own.
What an export takes and returns, asked of the policy's space, and how its check samples
it, is its :class:`Signature`.
Two formats:

- ONNX (:func:`export_onnx`), run by onnxruntime from any language; the file carries the
  target, the state dimension, the speed scale and what its input and output are in its
  metadata.
- ``torch.export`` (:func:`export_pt2`), a ``.pt2`` archive: the graph as JSON and the
  weights as raw bytes (no pickle for plain tensors), loaded by :func:`torch.export.load`.

:func:`verify` runs an exported file on random states, from near the target to 1000x the
demonstrations' extent (for poses: with orientations uniform on SO(3)), and compares it with
the library evaluated in the same precision. :func:`export_c` writes a policy as
dependency-free C99.

The package, by concern: :mod:`~snds.export.graph` (what is traced, its signature and
random states), :mod:`~snds.export.fused` (the default policy as one fused graph),
:mod:`~snds.export.onnx_ops` (translations to ONNX), :mod:`~snds.export.writers` (the
files), :mod:`~snds.export.runtime` (running them), :mod:`~snds.export.comparison` (the
check), and the C export: :mod:`~snds.export.c` with its generators
(:mod:`~snds.export.c_source`, :mod:`~snds.export.c_lyapunov`, :mod:`~snds.export.c_space`)
and :mod:`~snds.export.c_check`, which compiles and checks it.
"""

from snds.errors import CExportError, ExportError
from snds.export.c import export_c
from snds.export.comparison import DATA_BOX, ROUNDING_SLACK, TOLERANCE, Check, compare, verify
from snds.export.graph import STATE_RADII, Signature, random_states, signature
from snds.export.runtime import (
    MIN_ROWS_PER_THREAD,
    OnnxPolicy,
    load_onnx,
    load_pt2,
    refused_entries,
)
from snds.export.writers import BATCH_NAME, FORMATS, INPUT_NAME, export_onnx, export_pt2

#: The name this check had before it refused more than pickles (kept for callers).
pickled_entries = refused_entries

__all__ = [
    "BATCH_NAME",
    "DATA_BOX",
    "FORMATS",
    "INPUT_NAME",
    "MIN_ROWS_PER_THREAD",
    "ROUNDING_SLACK",
    "STATE_RADII",
    "TOLERANCE",
    "CExportError",
    "Check",
    "ExportError",
    "OnnxPolicy",
    "Signature",
    "compare",
    "export_c",
    "export_onnx",
    "export_pt2",
    "load_onnx",
    "load_pt2",
    "pickled_entries",
    "random_states",
    "refused_entries",
    "signature",
    "verify",
]
