r"""An independent re-check of a certificate in Arb ball arithmetic (python-flint).

It shares no bound code with :mod:`snds.certify.bounds`: the networks are re-evaluated in
Arb's rigorous balls (its own rounding and its own proven enclosures of exp, log, sin and
cos) rather than NumPy intervals, the Taylor enclosures are formed as ball polynomials rather
than by Gershgorin on interval matrices, and the tiling and the excluded ball are checked in
exact rational arithmetic. Only the weights themselves (float numbers read from the model)
are shared. A cell the certificate lists as proven passes if these bounds prove the same
inequality (see :mod:`snds.certify.bounds`) for its step; the numbers the certificate
records for it must also be true of the model at the cell's centre, so an altered file is
rejected.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from fractions import Fraction

import numpy as np

from snds.certify.arb import ArbModel, flint_module, prove_cell, prove_split
from snds.certify.certificate import FORMAT, content_digest, covers_box
from snds.certify.model import PolicyModel
from snds.certify.reprove import Reprover
from snds.policy import Policy

__all__ = ["Recheck", "recheck"]


@dataclass(frozen=True)
class Recheck:
    """The re-check's verdict.

    Attributes:
        ok: Every check passed.
        checked: Proven cells re-proven.
        failures: One line per failed check (empty if ok).
        cpu_seconds: Time taken.
    """

    ok: bool
    checked: int
    failures: list[str]
    cpu_seconds: float


#: Cells that the NumPy re-check leaves unproven and Arb then tries, one by one.
_ARB_CELLS = 200


def _corners(cells: np.ndarray, half: float) -> tuple[np.ndarray, np.ndarray]:
    """Float boxes (K, n) holding the exact dyadic cells."""
    size = (2.0 * half) / 2.0 ** cells[:, :1].astype(np.float64)
    lo = -half + cells[:, 1:] * size
    hi = -half + (cells[:, 1:] + 1) * size
    slack = 4e-16 * half
    return np.nextafter(lo - slack, -np.inf), np.nextafter(hi + slack, np.inf)


def recheck(
    policy: Policy, certificate: dict, *, weights_sha256: str, max_failures: int = 10
) -> Recheck:
    """Re-proves every proven cell of a certificate and checks its tiling and header.

    Arguments:
        policy: The model the certificate is about.
        certificate: The certificate (as read by
            :func:`snds.certify.certificate.read_certificate`).
        weights_sha256: The model's weights hash, which must match the certificate's.
        max_failures: Stop after this many failed checks.
    """
    cpu = time.process_time()
    flint = flint_module()
    failures: list[str] = []
    if certificate.get("format") != FORMAT:
        return Recheck(False, 0, [f"not a {FORMAT} file"], 0.0)
    if certificate.get("content_sha256") != content_digest(certificate):
        failures.append("the file was altered after it was written (content_sha256 differs)")
    if certificate.get("weights_sha256") != weights_sha256:
        failures.append("the certificate is for other weights (weights_sha256 differs)")
    weights = PolicyModel.from_policy(policy)
    n = weights.dim
    old_prec = flint.ctx.prec
    flint.ctx.prec = 80
    try:
        model = ArbModel(flint, weights)
        half = float(certificate["box_half_width"])
        extent = float(policy.normalization.extent) / weights.length
        if half < float(certificate["box_factor"]) * extent * (1 - 1e-12):
            failures.append("the box is smaller than box_factor x the model's extent")
        if abs(float(certificate["time_scale"]) - weights.time) > 1e-12 * weights.time:
            failures.append("time_scale differs from the model's")
        step = float(certificate["dt"]) / weights.time
        eta = float(certificate["eta"])
        if not eta >= 0:
            failures.append("eta must be >= 0")
        proven = [row[: n + 1] for row in certificate["proven"]]
        everything = proven + certificate["excluded"] + certificate["open"] + certificate["refuted"]
        if not covers_box(everything, n):
            failures.append("the cells do not tile the box exactly")
        listed_status = certificate.get("status")
        complete = not certificate["open"] and not certificate["refuted"]
        if (listed_status == "proven") != complete:
            failures.append(f"status {listed_status!r} does not match the open and refuted cells")
        radius = Fraction(float(certificate["excluded_radius"]))
        half_q = Fraction(half)
        for cell in certificate["excluded"]:
            size = 2 * half_q / 2 ** int(cell[0])
            far = sum(
                max(abs(-half_q + i * size), abs(-half_q + (i + 1) * size)) ** 2 for i in cell[1:]
            )
            if far > radius**2:
                failures.append(f"excluded cell {cell} is not inside the excluded ball")
                break
        checked = 0
        rows = certificate["proven"]
        cells = np.array([row[: n + 1] for row in rows], dtype=np.int64).reshape(-1, n + 1)
        recorded = np.array([row[n + 1 : n + 6] for row in rows], dtype=np.float64).reshape(-1, 5)
        # First the NumPy Taylor models (snds.certify.reprove), all cells at once; a cell they
        # cannot prove gets Arb's balls, split twice, if there are few such cells.
        proven = np.zeros(len(cells), dtype=bool)
        a_center = np.zeros(len(cells))
        speed_center = np.zeros(len(cells))
        reprover = Reprover(weights)
        for begin in range(0, len(cells), 2048):
            part = cells[begin : begin + 2048]
            lo, hi = _corners(part, half)
            ok, a_c, speed_c = reprover.prove(lo, hi, step=step, eta=eta)
            proven[begin : begin + 2048] = ok
            a_center[begin : begin + 2048] = a_c
            speed_center[begin : begin + 2048] = speed_c
        # Second-order models for the cells first-order ones leave.
        again = np.flatnonzero(~proven)
        for begin in range(0, len(again), 1024):
            part = again[begin : begin + 1024]
            lo, hi = _corners(cells[part], half)
            proven[part] = reprover.prove(lo, hi, step=step, eta=eta, second=True)[0]
        stubborn = np.flatnonzero(~proven)
        for k in stubborn[:_ARB_CELLS]:
            cell = cells[k].tolist()
            proven[k] = prove_cell(model, cell, half, step, eta)[0] or prove_split(
                model, cell, half, step, eta, depth=2
            )
        for k in np.flatnonzero(~proven)[:max_failures]:
            failures.append(f"cell {cells[k].tolist()}: not proven by the re-check's bounds")
        checked = len(cells)
        a_rec, speed_rec, grad_rec, quad_rec, dec_rec = recorded.T
        false = (a_rec > a_center) | (speed_rec < speed_center) | (quad_rec < 0)
        for k in np.flatnonzero(false)[:max_failures]:
            failures.append(
                f"cell {cells[k].tolist()}: its recorded bounds are false at its centre"
            )
        claimed = step * a_rec - step * eta * grad_rec * speed_rec - 0.5 * step**2 * quad_rec
        wrong = (dec_rec > claimed * (1 + 1e-9) + 1e-300) | (dec_rec <= 0)
        for k in np.flatnonzero(wrong)[:max_failures]:
            failures.append(
                f"cell {cells[k].tolist()}: its recorded decrease does not follow its bounds"
            )
    finally:
        flint.ctx.prec = old_prec
    return Recheck(not failures, checked, failures, time.process_time() - cpu)
