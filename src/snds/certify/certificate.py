"""The certificate file: what was proven, for which model, rate and precision.

``certificate.json`` records the model's weights hash, the step, the precision, the box, the
excluded ball, every proven cell (dyadic level and index) with its bounds, and the cells left
open or refuted (with the counterexamples). :func:`certify` runs the search at the data's
step and bisects for the largest certified step; :func:`certified_rate` reads the rate an
export may record.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np
import torch

from snds.certify.model import PolicyModel
from snds.certify.search import Search, prove
from snds.errors import CertificateError
from snds.io import atomic_write
from snds.policy import Policy

__all__ = [
    "FORMAT",
    "CertificateError",
    "VerifyConfig",
    "certified_rate",
    "certify",
    "content_digest",
    "covers_box",
    "read_certificate",
    "write_certificate",
]

#: The file format's name and version.
FORMAT = "snds-certificate/1"
#: Relative error allowed to a deployed float64 step (its rounding is ~1e-13 relative).
ETA = {"float64": 1e-6, "float32": 1e-3}


@dataclass(frozen=True, kw_only=True)
class VerifyConfig:
    """Settings of :func:`certify`.

    Attributes:
        box_factor: Half-width of the box in extents (3: the stability check's box).
        radius_factor: Excluded ball's radius in extents.
        dtype: "float64" or "float32": the controller's precision.
        eta: Relative error allowed to a deployed step (None: :data:`ETA` of ``dtype``).
        max_level: Deepest dyadic level of a cell.
        budget: Most cells bounded per search.
        start_size: Largest side of the first cells, in extents (the first level is the
            coarsest whose cells are no wider; at least level 3). No wider either than 1.5
            radians of the nominal field's fastest Fourier feature: its bounds are useless on
            wider cells, which would only be bounded to be split.
    """

    box_factor: float = 3.0
    radius_factor: float = 1e-3
    dtype: str = "float64"
    eta: float | None = None
    max_level: int = 16
    budget: int = 200_000
    start_size: float = 0.1


def _cells(rows: np.ndarray) -> list[list[int]]:
    return rows.astype(int).tolist()


def certify(
    policy: Policy,
    *,
    dt: float,
    weights_sha256: str,
    config: VerifyConfig = VerifyConfig(),
    sampled_safe_dt: float | None = None,
) -> dict:
    """Proves one step of ``dt`` seconds over the box by branch and bound.

    If every cell is proven, the certificate is for ``dt``. If not, and no cell is refuted,
    each bounded cell still proves every step up to its own largest one; the smallest of these
    is proven over the whole box, and the certificate is for that step (``dt`` in the file;
    ``requested_dt``, ``requested_status`` and ``requested_proven_fraction`` say how the
    requested step fared).

    Returns:
        The certificate (JSON-ready dict).
    """
    cpu, wall = time.process_time(), time.perf_counter()
    model = PolicyModel.from_policy(policy)
    dtype = {"float64": torch.float64, "float32": torch.float32}[config.dtype]
    eta = ETA[config.dtype] if config.eta is None else config.eta
    scale = float(policy.normalization.extent) / model.length
    half, radius = config.box_factor * scale, config.radius_factor * scale

    fastest = float(np.abs(model.fourier).sum(0).max())
    first = min(config.start_size * scale, 1.5 / fastest)

    def search(step: float, start: np.ndarray | None = None) -> Search:
        return prove(
            model,
            policy,
            half_width=half,
            dt=step,
            radius=radius,
            eta=eta,
            dtype=dtype,
            max_level=config.max_level,
            budget=config.budget,
            start=start,
            start_level=max(3, math.ceil(math.log2(2 * half / first))),
        )

    result = search(dt)
    step = dt / model.time
    cells, table = result.proven, result.bounds
    certified = dt if result.complete else 0.0
    if not result.complete and not len(result.refuted):
        # Every bounded cell proves every step up to its own largest step: the smallest of
        # them is proven over the whole box (minus the ball), with the same cells.
        smallest = result.largest_step()
        if smallest > 0:
            step = smallest
            certified = smallest * model.time
            cells = np.concatenate([result.proven, result.open])
            table = np.concatenate([result.bounds, result.open_bounds])
    if certified > 0 and certified != dt:
        a_lo, speed, grad_hi, quadratic = table[:, 0], table[:, 1], table[:, 2], table[:, 3]
        gain = step * a_lo * (1 - 1e-15)
        loss = (step * eta * grad_hi * speed + 0.5 * step**2 * quadratic) * (1 + 1e-12)
        table = table.copy()
        table[:, 4] = gain - loss
    proven_here = certified > 0
    rows = (
        [c + b for c, b in zip(_cells(cells), table.tolist())]
        if proven_here
        else [c + b for c, b in zip(_cells(result.proven), result.bounds.tolist())]
    )
    open_rows = [] if proven_here else _cells(result.open)
    return {
        "format": FORMAT,
        "weights_sha256": weights_sha256,
        "dtype": config.dtype,
        "eta": eta,
        "dt": certified if proven_here else dt,
        "rate_hz": 1.0 / (certified if proven_here else dt),
        "requested_dt": dt,
        "requested_status": "proven"
        if result.complete
        else ("refuted" if len(result.refuted) else "open"),
        "requested_proven_fraction": _volume(result.proven, model.dim),
        "time_scale": model.time,
        "length_scale": model.length,
        "target": [float(c) for c in policy.target],
        "box_half_width": half,
        "box_factor": config.box_factor,
        "excluded_radius": radius,
        "excluded_radius_user": radius * model.length,
        "excluded_fraction_of_extent": config.radius_factor,
        "proven": rows,
        "bounds_columns": [
            "descent_lo",
            "speed",
            "grad_hi",
            "quadratic",
            "decrease",
            "largest_step",
        ],
        "excluded": _cells(result.excluded),
        "open": open_rows,
        "refuted": _cells(result.refuted),
        "counterexamples": [vars(c) for c in result.counterexamples[:20]],
        "status": "proven" if proven_here else ("refuted" if len(result.refuted) else "open"),
        "proven_fraction": 1.0 - _volume(result.excluded, model.dim)
        if proven_here
        else (_volume(result.proven, model.dim)),
        "largest_certified_dt": certified,
        "sampled_largest_safe_dt": sampled_safe_dt,
        "cells_bounded": result.evaluated,
        "cells_never_bounded": result.unbounded,
        "cpu_seconds": time.process_time() - cpu,
        "wall_seconds": time.perf_counter() - wall,
    }


def _partition(result: Search) -> np.ndarray:
    return np.concatenate([result.proven, result.excluded])


def _volume(cells: np.ndarray, n: int) -> float:
    return float(sum(2.0 ** (-n * int(level)) for level in cells[:, 0]))


def covers_box(cells: list[list[int]], n: int) -> bool:
    """Whether dyadic cells (level, index...) tile the box exactly: each inside it, no two
    overlapping (no cell is another's ancestor or a duplicate) and volumes adding up to 1."""
    seen: set[tuple[int, ...]] = set()
    total = Fraction(0)
    for cell in cells:
        level, index = int(cell[0]), tuple(int(i) for i in cell[1 : n + 1])
        if level < 0 or any(not 0 <= i < 2**level for i in index):
            return False
        key = (level, *index)
        if key in seen:
            return False
        seen.add(key)
        total += Fraction(1, 2 ** (n * level))
    if total != 1:
        return False
    for level, *index in seen:
        for up in range(1, level + 1):
            if (level - up, *(i >> up for i in index)) in seen:
                return False
    return True


def read_certificate(path: str | Path) -> dict:
    """Reads ``certificate.json``; one clear line on a malformed file."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise CertificateError(f"{path}: not a readable JSON certificate ({error})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise CertificateError(f"{path}: not a {FORMAT} file (field 'format')")
    return data


def content_digest(certificate: dict) -> str:
    """sha256 of the certificate's content without its own ``content_sha256`` field: an edit
    of the file after it was written changes it (a deliberate edit that recomputes it is
    caught by the re-check's own proof instead)."""
    body = {k: v for k, v in certificate.items() if k != "content_sha256"}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def write_certificate(path: str | Path, certificate: dict) -> Path:
    """Writes the certificate atomically, with its content digest."""
    path = Path(path)
    certificate = {**certificate, "content_sha256": content_digest(certificate)}
    text = json.dumps(certificate, indent=1)
    atomic_write(path, lambda tmp: tmp.write_text(text))
    return path


def certified_rate(path: str | Path) -> float | None:
    """The lowest control rate (Hz) that ``certificate.json`` proves over its whole box, or
    None if it proves none: what an export records as the rate at and above which the guarded
    step is not needed. A proof at step h holds for every shorter step (each cell's condition
    is monotone in h), so every faster rate is covered too. Re-check the file first
    (``snds verify --check``)."""
    data = read_certificate(path)
    return 1.0 / float(data["dt"]) if data.get("status") == "proven" else None
