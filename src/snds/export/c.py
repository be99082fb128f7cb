r"""A policy as dependency-free C99: ``snds export --format c``.

:func:`export_c` writes a header and a source file (``policy.h``, ``policy.c``) that compute,
for one state at a time and with no allocation, no global mutable state and nothing but
``<math.h>``:

- ``snds_policy(state, velocity)``: :math:`\pi(x)`, what the ONNX export computes (user
  positions in, velocities out; a pose model: pose (7) in, twist (6) out; a model with a
  phase: positions then phase in, velocity then phase rate out);
- ``snds_lyapunov(state)``: :math:`V` in model coordinates;
- ``snds_step(state, dt, max_speed, command, next)``: the guarded step of
  :func:`snds.rollout.safe_velocity`: the velocity scaled down to ``max_speed`` (the
  positions' speed, user units/s; 0: none), its step shortened by halving until V decreases
  enough, the command to hold for the period (the velocity times h / dt) and the state
  reached; it returns h.

each in ``double`` and, with the suffix ``_f``, ``float`` (weights rounded once to float).

The forward pass is the library's, state by state: the normalisation (a pose's log map and
scales), the nominal network with its Fourier features, minus :math:`f(0)`; V through the
warp's coupling layers and the ICNN in its Bregman form; the decay rate (with the data
kernel on the anchors); the projection; the unit of speed (a pose's left Jacobian). The
values at the target, :math:`f(0)`, :math:`\phi(0)`, :math:`g(0)` and :math:`\nabla g(0)`, are
computed by the library in float64 and stored (the library evaluates them with every batch).
A state exactly at the target gets velocity 0.

:mod:`snds.export.c_check` compiles the files and compares them with the library.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import torch

from snds.errors import CExportError
from snds.export.c_source import Generator
from snds.export.graph import policy_copy
from snds.io import atomic_write
from snds.nn.lyapunov import Lyapunov, WarpedLyapunov
from snds.phase import StartRule
from snds.policy import Policy, StablePolicy
from snds.se3 import PosePolicy

__all__ = ["DEFAULT_RATE", "CExportError", "export_c"]

#: The control rate (Hz) whose period is the files' ``SNDS_DT`` unless another is given.
DEFAULT_RATE = 500.0


def _check_policy(policy: Policy) -> StablePolicy:
    if type(policy) not in (StablePolicy, PosePolicy):
        raise CExportError(
            f"the C export writes SNDS policies (positions, poses, a phase); this model is "
            f"{policy.method!r} ({type(policy).__name__}): export it as ONNX"
        )
    if not policy.stable:
        raise CExportError(
            "the C export needs the policy's Lyapunov function (the guarded step uses it); "
            "an unconstrained (bc) model exports as ONNX"
        )
    lyapunov = policy.lyapunov
    if isinstance(lyapunov, WarpedLyapunov):
        if any(layer.affine for layer in lyapunov.warp.layers):
            raise CExportError("the C export writes additive coupling layers only")
        lyapunov = lyapunov.convex
    if not isinstance(lyapunov, Lyapunov):
        raise CExportError(f"the C export cannot write a V of type {type(lyapunov).__name__}")
    return policy


def _c_name(prefix: str) -> str:
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]{0,30}", prefix):
        raise CExportError(
            f"the C prefix {prefix!r} is not a C identifier (letters, digits, _; at most 31)"
        )
    return prefix


def export_c(
    policy: Policy,
    path: str | Path,
    *,
    rate: float = DEFAULT_RATE,
    max_speed: float | None = None,
    prefix: str = "snds",
    start_rule: StartRule | None = None,
) -> Path:
    """Writes a policy as C99: ``path`` (the header, ``.h``) and the source beside it (``.c``).

    Arguments:
        policy: An SNDS policy (positions, poses or a phase); it is copied, not changed.
        path: The header to write; the source gets the same name with ``.c``.
        rate: The control rate (Hz) whose period is the header's ``<PREFIX>_DT``.
        max_speed: The speed limit written as ``<PREFIX>_MAX_SPEED`` (user units of the
            positions per second; None: 0, no limit), what a loop passes to the step.
        prefix: Prefix of every public name (functions ``prefix_policy``, macros
            ``PREFIX_*``).
        start_rule: A model with a phase: how a new start gets its phase
            (:func:`snds.phase.start_rule`), for ``prefix_start_state``, which gives the
            library's :func:`snds.phase.start_state`.

    Returns:
        The header's path.

    Raises:
        CExportError: For a policy it cannot write or a bad option.
    """
    _check_policy(policy)
    prefix = _c_name(prefix)
    if not (math.isfinite(rate) and rate > 0):
        raise CExportError(f"the control rate must be a positive number of Hz, got {rate}")
    if max_speed is not None and not (math.isfinite(max_speed) and max_speed > 0):
        raise CExportError(f"--max-speed must be a positive number, got {max_speed}")
    exact = policy_copy(policy, torch.float64)
    path = Path(path)
    if path.suffix != ".h":
        raise CExportError(f"{path}: the C export's file is the header, ending in .h")
    if start_rule is not None:
        references = np.asarray(start_rule.references, dtype=np.float64)
        if (
            not policy.space.phase_dim
            or references.ndim != 2
            or references.shape[1] != policy.space.dim
            or not np.isfinite(references).all()
            or not start_rule.reach >= 0
        ):
            raise CExportError(
                f"a start rule is for a model with a phase: finite references of shape (K, "
                f"{policy.space.dim}); got {references.shape}"
            )
    generator = Generator(exact, prefix=prefix, start_rule=start_rule)
    header, source = generator.header(rate=rate, max_speed=max_speed or 0.0), generator.source()
    source = source.replace('#include "HEADER"', f'#include "{path.name}"')
    atomic_write(path.with_suffix(".c"), lambda tmp: tmp.write_text(source))
    atomic_write(path, lambda tmp: tmp.write_text(header))
    return path
