"""Compiling a C export (:mod:`snds.export.c`) and running it from Python, to check it.

:func:`compile_shared` builds the source with the system's C compiler as strict C99
(``-std=c99 -Wall -Werror -O2``) into a shared library; :class:`CPolicy` calls its functions
through :mod:`ctypes`, a batch of states one state at a time as a controller would;
:func:`verify_c` compares both precisions with the library (:func:`snds.export.compare`).
"""

from __future__ import annotations

import ctypes
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import torch

from snds.errors import CExportError
from snds.export.comparison import Check, compare
from snds.policy import Policy

__all__ = ["CFLAGS", "CPolicy", "compile_shared", "compiler", "verify_c"]

#: The flags every check compiles with: strict C99, every warning an error.
CFLAGS = ("-std=c99", "-pedantic", "-Wall", "-Wextra", "-Werror", "-O2")
#: The tolerance of the float build against the library in float32, relative to
#: max(|velocity|, top speed), as :data:`snds.export.TOLERANCE` for float32 exports.
FLOAT_TOLERANCE = 3e-4
#: The tolerance of the double build against the library in float64 (what makes ``snds
#: export --format c`` refuse a file), a margin of 100x over the largest difference measured
#: at any distance out to 1000 extents, 7.5e-13 (docs/robots-and-export.md); the tests hold
#: the double build to 1e-12.
DOUBLE_TOLERANCE = 1e-10


def compiler() -> str | None:
    """The C compiler: ``$CC``, else gcc or cc on the PATH; None if there is none."""
    for name in (os.environ.get("CC"), "gcc", "cc"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def compile_shared(header: str | Path, library: str | Path) -> Path:
    """Compiles the source beside ``header`` into the shared library ``library``.

    Raises:
        CExportError: Without a compiler, or with its first error lines.
    """
    header, library = Path(header), Path(library)
    cc = compiler()
    if cc is None:
        raise CExportError("no C compiler found (gcc or cc, or set CC) to check the C export")
    command = [
        cc,
        *CFLAGS,
        "-shared",
        "-fPIC",
        str(header.with_suffix(".c")),
        "-o",
        str(library),
        "-lm",
    ]
    result = subprocess.run(command, capture_output=True, text=True, check=False)
    if result.returncode != 0:
        first = "; ".join(result.stderr.strip().splitlines()[:3])
        raise CExportError(f"{header.with_suffix('.c')}: does not compile ({first})")
    return library


class CPolicy:
    """The functions of a compiled C export, on NumPy arrays.

    Arguments:
        library: The shared library (:func:`compile_shared`).
        states: Numbers per state row (the header's STATE_DIM).
        velocities: Numbers per velocity row (VELOCITY_DIM).
        prefix: The export's prefix.
    """

    def __init__(
        self, library: str | Path, *, states: int, velocities: int, prefix: str = "snds"
    ) -> None:
        self.lib = ctypes.CDLL(str(library))
        self.states, self.velocities, self.prefix = states, velocities, prefix
        for suffix, real in (("", ctypes.c_double), ("_f", ctypes.c_float)):
            pointer = ctypes.POINTER(real)
            policy = getattr(self.lib, f"{prefix}_policy{suffix}")
            policy.argtypes, policy.restype = [pointer, pointer], ctypes.c_int
            value = getattr(self.lib, f"{prefix}_lyapunov{suffix}")
            value.argtypes, value.restype = [pointer], real
            step = getattr(self.lib, f"{prefix}_step{suffix}")
            step.argtypes = [pointer, real, real, pointer, pointer]
            step.restype = real

    @staticmethod
    def _rows(x: np.ndarray, dtype: type, width: int) -> np.ndarray:
        x = np.ascontiguousarray(np.asarray(x, dtype=dtype))
        if x.ndim != 2 or x.shape[1] != width:
            raise ValueError(f"states must have shape (B, {width}), got {x.shape}")
        return x

    @staticmethod
    def _suffix(dtype: type) -> tuple[str, type]:
        return ("", ctypes.c_double) if np.dtype(dtype) == np.float64 else ("_f", ctypes.c_float)

    def stepper(self):
        """A function (state (states,), dt, max_speed) -> command (velocities,) of the double
        step for one state at a time, on buffers made once (a control loop's call)."""
        state = np.zeros(self.states)
        command, reached = np.zeros(self.velocities), np.zeros(self.states)
        pointer = ctypes.POINTER(ctypes.c_double)
        function = getattr(self.lib, f"{self.prefix}_step")
        arguments = [p.ctypes.data_as(pointer) for p in (state, command, reached)]

        def step(x: np.ndarray, dt: float, max_speed: float) -> np.ndarray:
            state[:] = x
            function(arguments[0], dt, max_speed, arguments[1], arguments[2])
            return command.copy()

        return step

    def policy(self, x: np.ndarray, dtype: type = np.float64) -> np.ndarray:
        """Velocities (B, velocities) at states (B, states), one call per state."""
        suffix, real = self._suffix(dtype)
        x = self._rows(x, dtype, self.states)
        out = np.zeros((len(x), self.velocities), dtype=dtype)
        function = getattr(self.lib, f"{self.prefix}_policy{suffix}")
        pointer = ctypes.POINTER(real)
        for row, result in zip(x, out, strict=True):
            function(row.ctypes.data_as(pointer), result.ctypes.data_as(pointer))
        return out

    def lyapunov(self, x: np.ndarray, dtype: type = np.float64) -> np.ndarray:
        """V (B,) at states (B, states)."""
        suffix, real = self._suffix(dtype)
        x = self._rows(x, dtype, self.states)
        function = getattr(self.lib, f"{self.prefix}_lyapunov{suffix}")
        pointer = ctypes.POINTER(real)
        return np.array([function(row.ctypes.data_as(pointer)) for row in x], dtype=dtype)

    def step(
        self, x: np.ndarray, dt: float, max_speed: float = 0.0, dtype: type = np.float64
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The guarded step of each state: commands (B, velocities), steps h (B,) and the
        states reached (B, states)."""
        suffix, real = self._suffix(dtype)
        x = self._rows(x, dtype, self.states)
        function = getattr(self.lib, f"{self.prefix}_step{suffix}")
        pointer = ctypes.POINTER(real)
        commands = np.zeros((len(x), self.velocities), dtype=dtype)
        reached = np.zeros_like(x)
        steps = np.zeros(len(x), dtype=dtype)
        for i, row in enumerate(x):
            steps[i] = function(
                row.ctypes.data_as(pointer),
                dt,
                max_speed,
                commands[i].ctypes.data_as(pointer),
                reached[i].ctypes.data_as(pointer),
            )
        return commands, steps, reached


def load_c(
    header: str | Path, policy: Policy, library: str | Path, *, prefix: str = "snds"
) -> CPolicy:
    """Compiles a C export into ``library`` and loads it."""
    compile_shared(header, library)
    space = policy.space
    return CPolicy(library, states=space.dim, velocities=space.tangent_dim, prefix=prefix)


def verify_c(
    header: str | Path,
    policy: Policy,
    *,
    samples: int = 10_000,
    seed: int = 0,
    prefix: str = "snds",
) -> list[Check]:
    """Compiles a C export and compares its double and float functions with the library
    (double: :data:`DOUBLE_TOLERANCE`, float: :data:`FLOAT_TOLERANCE` or the float32
    library's own rounding, as a float32 ONNX file).

    Returns:
        The double check, then the float one.
    """
    with tempfile.TemporaryDirectory(prefix="snds-c-") as folder:
        compiled = load_c(header, policy, Path(folder) / "policy.so", prefix=prefix)
        return [
            compare(
                lambda x, d=dtype: compiled.policy(x, d),
                policy,
                path=header,
                dtype=torch_dtype,
                samples=samples,
                seed=seed,
                tolerance=tolerance,
            )
            for dtype, torch_dtype, tolerance in (
                (np.float64, torch.float64, DOUBLE_TOLERANCE),
                (np.float32, torch.float32, FLOAT_TOLERANCE),
            )
        ]
