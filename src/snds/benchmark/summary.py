"""The summary table of a sweep: mean and spread over seeds per motion and method."""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np

from snds.benchmark.tasks import Task
from snds.methods import METHODS

__all__ = ["PAPER_SNDS_MSE", "row_groups", "summarise"]

#: SNDS velocity MSE (paper scale) in the paper's Fig. 4, for comparison in summaries.
PAPER_SNDS_MSE: dict[str, float] = {
    "Sine": 0.0018,
    "PShape": 0.0016,
    "Worm": 0.0031,
    "GShape": 0.0024,
    "NShape": 0.0016,
    "DoubleBendedLine": 0.0028,
    "CShape": 0.0014,
    "Angle": 0.0012,
}


def _label(row: dict) -> str:
    """The row's task in tables and figures (:attr:`Task.label`)."""
    return Task.from_row(row).label


def row_groups(rows: Sequence[dict]) -> Iterator[tuple[str, str, list[dict]]]:
    """(motion label, method, rows) in the order they first appear; the label is
    :attr:`Task.label` (the motion or file name, "-se3" for poses)."""
    keys: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        keys.setdefault((_label(row), row["method"]), []).append(row)
    for (motion, method), group in keys.items():
        yield motion, method, group


def _angle(group: list[dict], stat) -> str:
    if all(r.get("final_angle_error") is None for r in group):
        return "-"
    return stat(group, "final_angle_error", ".3g")


def summarise(rows: Sequence[dict]) -> str:
    """A Markdown table of mean ± std (over seeds) per motion and method.

    Errors are given to 3 significant digits (one-demonstration MSEs are below 1e-4). The
    "shortened" column is the mean fraction of stability rollouts in which the guarded Euler
    step had to shorten a step (where plain Euler at the data's step would not decrease V);
    "n/a" for methods without a Lyapunov function, which take plain steps. Where some rows
    are SE(3) tasks, a last column gives their orientation error at the end of the rollouts
    from the demonstrations' starts (radians; "-" for position tasks).
    """

    def stat(group: list[dict], key: str, fmt: str) -> str:
        values = np.array([r.get(key) for r in group], dtype=float)
        values = values[np.isfinite(values)]
        # Rows of older sweeps may lack a field (train CPU s before it was recorded).
        if len(values) == 0:
            return "n/a"
        more = f" ({len(values)} runs)" if len(values) < len(group) else ""
        if len(values) == 1:
            # One run has no spread to show: "± 0" would claim one.
            return f"{values[0]:{fmt}}{more}"
        return f"{values.mean():{fmt}} ± {values.std():{fmt}}{more}"

    poses = any(r.get("final_angle_error") is not None for r in rows)
    lines = [
        "| motion | method | runs | velocity MSE (paper scale) | paper's SNDS MSE "
        "| DTW (paper scale) | train s | train CPU s | converged | decrease violations "
        "| shortened |" + (" final angle (rad) |" if poses else ""),
        "|---|---|---|---|---|---|---|---|---|---|---|" + ("---|" if poses else ""),
    ]
    total = 0
    for motion, method, group in row_groups(rows):
        violations = sum(int(r["decrease_violations"]) for r in group)
        total += violations
        checked = METHODS[method].has_lyapunov if method in METHODS else True
        lines.append(
            f"| {motion} | {method} | {len(group)} | {stat(group, 'velocity_mse_paper', '.3g')} "
            f"| {PAPER_SNDS_MSE[motion] if motion in PAPER_SNDS_MSE and method == 'snds' else '-'} "
            f"| {stat(group, 'dtw_paper', '.3g')} | {stat(group, 'train_seconds', '.1f')} "
            f"| {stat(group, 'train_cpu_seconds', '.1f')} "
            f"| {stat(group, 'converged_fraction', '.3f')} "
            f"(min {min(r['converged_fraction'] for r in group):.3f}) "
            f"| {violations if checked else 'n/a (no V)'} "
            f"| {stat(group, 'shortened_fraction', '.2f') if checked else 'n/a'} |"
            + (f" {_angle(group, stat)} |" if poses else "")
        )
    lines += [
        "",
        f"Total decrease violations: {total}.",
        "",
        "Mean ± standard deviation over the runs (seeds) of each row; one run: its value. "
        "Paper's SNDS MSE: the paper's Fig. 4, on the snds rows. Converged: the fraction of "
        "the stability check's random starts that arrived at the target (worst run in "
        "brackets). Shortened: the fraction of those rollouts in which the guarded Euler step "
        "had to shorten a step, where plain Euler at the data's step would not have decreased "
        "V (n/a: a method without V takes plain steps).",
    ]
    return "\n".join(lines) + "\n"
