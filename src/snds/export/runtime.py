"""Running an export: ONNX in onnxruntime (:class:`OnnxPolicy`) and ``.pt2`` archives in
torch (:func:`load_pt2`), the latter only if every entry is what :func:`export_pt2` writes.
"""

from __future__ import annotations

import json
import re
import threading
import zipfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch

from snds.errors import ExportError

__all__ = ["MIN_ROWS_PER_THREAD", "OnnxPolicy", "load_onnx", "load_pt2", "refused_entries"]

#: Rows per thread below which :class:`OnnxPolicy` runs a batch whole: handing a chunk to a
#: thread costs tens of microseconds.
MIN_ROWS_PER_THREAD = 1024


class OnnxPolicy:
    """An exported policy in onnxruntime, as a function of NumPy positions (B, n).

    Two paths, both with one-thread sessions:

    * **One state per call** (the control loop) runs on input and output buffers bound to
      the session once (onnxruntime's IO binding): the state is copied in, the velocity
      copied out, and nothing else is allocated or converted, which saves ``session.run``'s
      own conversions on every call (docs/design.md).
    * **Batches** of at least ``threads x`` :data:`MIN_ROWS_PER_THREAD` states are split into
      ``threads`` contiguous chunks that run at the same time on the one session
      (onnxruntime releases the GIL and lets several threads run a session). The graph is
      mostly small element-wise operations, which onnxruntime's own intra-op threads do not
      split: with them, two threads took 10.7 ms on 10,000 states of the compact network
      where one took 11.6.

    Arguments:
        path: The ``.onnx`` file.
        threads: Threads for large batches (1: every call on the caller's thread).

    Raises:
        ExportError: Without onnxruntime, or for a file it cannot load.
    """

    def __init__(self, path: str | Path, *, threads: int = 1) -> None:
        try:
            import onnxruntime as ort
        except ImportError as error:
            raise ExportError(
                "running ONNX needs onnxruntime: pip install 'snds[export]'"
            ) from error
        if threads < 1:
            raise ExportError(f"threads must be >= 1, got {threads}")
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        try:
            self.session = ort.InferenceSession(
                str(path), options, providers=["CPUExecutionProvider"]
            )
        except Exception as error:  # onnxruntime raises its own exception types
            raise ExportError(f"{path}: not a loadable ONNX model ({error})") from error
        first = self.session.get_inputs()[0]
        self.input_name = first.name
        self.dtype = np.float64 if first.type == "tensor(double)" else np.float32
        self.threads = threads
        self._pool = None
        self._lock = threading.Lock()
        self._bound: tuple | None = None

    def _bind(self, width: int):
        """Binds a one-row input buffer and its output buffer to the session, once."""
        import onnxruntime as ort

        x = np.zeros((1, width), dtype=self.dtype)
        y = self._run(x)
        binding = self.session.io_binding()
        binding.bind_ortvalue_input(self.input_name, ort.OrtValue.ortvalue_from_numpy(x))
        output = self.session.get_outputs()[0].name
        binding.bind_ortvalue_output(output, ort.OrtValue.ortvalue_from_numpy(y))
        self._bound = (x, y, binding)
        return self._bound

    def _run(self, x: np.ndarray) -> np.ndarray:
        return self.session.run(None, {self.input_name: x})[0]

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Velocities (B, m) at positions (B, n), in the file's precision."""
        x = np.asarray(x, dtype=self.dtype)
        if x.ndim == 2 and x.shape[0] == 1:
            with self._lock:
                bound = self._bound
                if bound is None or bound[0].shape != x.shape:
                    bound = self._bind(x.shape[1])
                buffer, out, binding = bound
                np.copyto(buffer, x)
                self.session.run_with_iobinding(binding)
                return out.copy()
        if self.threads == 1 or x.ndim != 2 or len(x) < self.threads * MIN_ROWS_PER_THREAD:
            return self._run(x)
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="snds-onnx")
        chunks = np.array_split(np.ascontiguousarray(x), self.threads)
        return np.concatenate(list(self._pool.map(self._run, chunks)))


def load_onnx(path: str | Path, *, threads: int = 1) -> OnnxPolicy:
    """An onnxruntime session of an exported policy, as a function of NumPy positions.

    Arguments:
        path: The ``.onnx`` file.
        threads: Threads for large batches (see :class:`OnnxPolicy`).

    Returns:
        A function from positions (B, n) to velocities (B, n) (a pose file: poses (B, 7) to
        twists (B, 6)), in the file's precision.
    """
    return OnnxPolicy(path, threads=threads)


def load_pt2(path: str | Path) -> Callable[[np.ndarray], np.ndarray]:
    """A ``.pt2`` export as a function of NumPy positions (B, n) -> velocities (B, n).

    :func:`torch.export.load` would unpickle what an archive stores pickled (a tensor
    subclass, sample inputs, a custom object); an snds export holds none of that, and this
    refuses any file with an entry that :func:`export_pt2` does not write
    (:func:`refused_entries`).

    Raises:
        ExportError: For a file that is not such an archive.
    """
    path = Path(path)
    refused = refused_entries(path)
    if refused:
        raise ExportError(
            f"{path}: holds {refused[0]}, which an snds export does not write "
            "(it could hold pickled data); refused"
        )
    module = torch.export.load(str(path)).module()
    dtype = next(iter(module.state_dict().values())).dtype

    @torch.no_grad()
    def run(x: np.ndarray) -> np.ndarray:
        # A copy: the caller's array may be read-only, which torch cannot wrap.
        return module(torch.tensor(np.asarray(x), dtype=dtype)).numpy()

    return run


#: The entries of a ``.pt2`` archive that :func:`snds.export.export_pt2` writes, under the
#: archive's top folder, as patterns (``torch.export.save``'s layout). ``kind`` says how each
#: is read: ``raw``, bytes torch copies into a tensor; ``json``, a JSON document;
#: ``config``, a JSON document that says, per tensor, how its raw bytes are stored;
#: ``empty``, a file of length 0 (the sample inputs, which :func:`export_pt2` removes).
ARCHIVE_ENTRIES: tuple[tuple[str, str], ...] = (
    (r"archive_format|archive_version|byteorder|\.data/version|\.data/serialization_id", "raw"),
    (r"models/[A-Za-z0-9_]+\.json", "json"),
    (r"data/(weights|constants)/[A-Za-z0-9_]+_(weights|constants)_config\.json", "config"),
    (r"data/(weights|constants)/[A-Za-z0-9_]+", "raw"),
    (r"data/sample_inputs/[A-Za-z0-9_]+\.pt", "empty"),
)


def refused_entries(path: str | Path) -> list[str]:
    """Entries of a ``.pt2`` archive that :func:`load_pt2` refuses (an snds export: none).

    An entry is refused unless it is what :func:`snds.export.export_pt2` writes
    (:data:`ARCHIVE_ENTRIES`), so a change of ``torch.export``'s layout is refused rather
    than read: a name that no pattern matches; sample inputs that are not empty (they are
    stored by ``torch.save``, a pickle); a tensor that its config does not state, with
    ``"use_pickle": false``, to be stored as raw bytes; and raw bytes that no config names.

    Raises:
        ExportError: If the file is not a zip archive or a config is not JSON.
    """
    try:
        with zipfile.ZipFile(path) as archive:
            entries = {info.filename: info for info in archive.infolist() if not info.is_dir()}
            roots = {name.split("/", 1)[0] for name in entries}
            refused, raw_tensors, stated = [], set(), set()
            for name, info in entries.items():
                root, _, inner = name.partition("/")
                kind = next(
                    (kind for pattern, kind in ARCHIVE_ENTRIES if re.fullmatch(pattern, inner)),
                    None,
                )
                if kind is None or len(roots) != 1:
                    refused.append(name)
                elif kind == "empty" and info.file_size:
                    refused.append(name)
                elif kind == "config":
                    folder = name.rpartition("/")[0]
                    for key, entry in json.loads(archive.read(name)).get("config", {}).items():
                        if not isinstance(entry, dict) or entry.get("use_pickle") is not False:
                            refused.append(f"{name}:{key}")
                        else:
                            stated.add(f"{folder}/{entry.get('path_name')}")
                elif kind == "raw" and inner.startswith("data/"):
                    raw_tensors.add(name)
    except (zipfile.BadZipFile, OSError, json.JSONDecodeError, AttributeError) as error:
        raise ExportError(f"{path}: not a .pt2 archive ({error})") from error
    return refused + sorted(raw_tensors - stated)
