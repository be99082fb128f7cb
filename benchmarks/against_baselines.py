"""SNDS rows of one sweep against the baselines' rows of another: issue 21's counts.

For each motion, SNDS's mean DTW and velocity MSE (paper scale) over its seeds against the
best mean of the published stable methods of the other sweep (SDS-EF, LPV-DS, SEDS), with
SNDS's worst converged fraction and its decrease violations. BC, SNDS's own network without
the projection, is shown beside them as the unconstrained control, not counted as a
baseline: it has no stability guarantee and reaches the target from a few percent of random
starts at most, so it is not a method a user would pick instead.

Writes the table to ``benchmarks/README.md`` (block ``snds-vs-baselines``) and
the figures beside the SNDS rows (``against-baselines.json``).

    python benchmarks/against_baselines.py benchmarks/results/data-rate/paper8-snds-0.1.jsonl \\
        benchmarks/results/sweeps/paper8/results.jsonl
    python benchmarks/against_baselines.py benchmarks/results/sweeps/paper8-demos1/results.jsonl \\
        --section snds-vs-baselines-demos1   # one sweep holding every method
"""

from __future__ import annotations

import argparse
import json
import statistics
from collections import defaultdict
from pathlib import Path

from _readme import write_readme_section

from snds.benchmark import MOTION_GROUPS

#: The published stable methods a user would pick instead of SNDS.
BASELINES = ("sdsef", "lpvds", "seds")
#: SNDS's network without the projection: the unconstrained control.
CONTROL = "bc"


def _rows(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def _mean(rows: list[dict], key: str) -> float:
    return statistics.fmean(row[key] for row in rows)


def _sd(rows: list[dict], key: str) -> float:
    """The sample standard deviation over seeds (0 for a single run)."""
    return statistics.stdev(row[key] for row in rows) if len(rows) > 1 else 0.0


def _order(motion: str) -> tuple[int, str]:
    """The paper's order of its motions (its Fig. 4), then the rest by name."""
    paper = MOTION_GROUPS["paper8"] + MOTION_GROUPS["multi"]
    return (paper.index(motion), "") if motion in paper else (len(paper), motion)


def compare(snds_rows: list[dict], base_rows: list[dict]) -> list[dict]:
    """One record per motion of the SNDS rows, in the paper's order."""
    base: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for row in base_rows:
        base[(row["motion"], row["method"])].append(row)
    ours: dict[str, list[dict]] = defaultdict(list)
    for row in snds_rows:
        if row["method"] == "snds":
            ours[row["motion"]].append(row)
    records = []
    for motion, rows in sorted(ours.items(), key=lambda item: _order(item[0])):
        methods = [m for m in BASELINES if base[(motion, m)]]
        if not methods:
            continue  # no baseline has run on this motion yet
        dtw = {m: _mean(base[(motion, m)], "dtw_paper") for m in methods}
        mse = {m: _mean(base[(motion, m)], "velocity_mse_paper") for m in methods}
        best_dtw, best_mse = min(dtw, key=dtw.get), min(mse, key=mse.get)
        control = base[(motion, CONTROL)]
        records.append(
            {
                "motion": motion,
                "runs": len(rows),
                "dtw": _mean(rows, "dtw_paper"),
                "dtw_sd": _sd(rows, "dtw_paper"),
                "best_baseline_dtw": dtw[best_dtw],
                "best_baseline_dtw_sd": _sd(base[(motion, best_dtw)], "dtw_paper"),
                "best_dtw_method": best_dtw,
                "mse": _mean(rows, "velocity_mse_paper"),
                "best_baseline_mse": mse[best_mse],
                "best_mse_method": best_mse,
                "control_dtw": _mean(control, "dtw_paper") if control else None,
                "control_mse": _mean(control, "velocity_mse_paper") if control else None,
                "control_converged": (
                    min(row["converged_fraction"] for row in control) if control else None
                ),
                "min_converged": min(row["converged_fraction"] for row in rows),
                "violations": sum(row["decrease_violations"] for row in rows),
                "median_train_seconds": statistics.median(row["train_seconds"] for row in rows),
                "median_train_cpu_seconds": statistics.median(
                    row["train_cpu_seconds"] for row in rows
                ),
            }
        )
    return records


def _cell(value: float | None, spec: str) -> str:
    return "n/a" if value is None else format(value, spec)


def table(records: list[dict], snds_path: Path, base_path: Path) -> str:
    lines = [
        f"SNDS rows `{snds_path.name}` against the baselines of `{base_path.parent.name}` "
        "(means over seeds, paper scale, DTW's standard deviation over seeds in brackets; "
        "baselines: SDS-EF, LPV-DS, SEDS; **bold**: SNDS below every baseline). BC, the "
        "unconstrained control, is not counted.",
        "",
        "| motion | runs | SNDS DTW | best baseline DTW | SNDS MSE | best baseline MSE "
        "| SNDS converged (min) | violations | BC DTW | BC MSE | BC converged (min) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        dtw = f"{r['dtw']:.3f}"
        mse = f"{r['mse']:.3g}"
        lines.append(
            f"| {r['motion']} | {r['runs']} "
            f"| {f'**{dtw}**' if r['dtw'] < r['best_baseline_dtw'] else dtw} ({r['dtw_sd']:.3f}) "
            f"| {r['best_dtw_method']} {r['best_baseline_dtw']:.3f} "
            f"({r['best_baseline_dtw_sd']:.3f}) "
            f"| {f'**{mse}**' if r['mse'] < r['best_baseline_mse'] else mse} "
            f"| {r['best_mse_method']} {r['best_baseline_mse']:.3g} "
            f"| {r['min_converged']:.3f} | {r['violations']} "
            f"| {_cell(r['control_dtw'], '.3f')} | {_cell(r['control_mse'], '.3g')} "
            f"| {_cell(r['control_converged'], '.3f')} |"
        )
    dtw_ahead = sum(r["dtw"] < r["best_baseline_dtw"] for r in records)
    mse_ahead = sum(r["mse"] < r["best_baseline_mse"] for r in records)
    lines += ["", f"DTW ahead on {dtw_ahead} of {len(records)}, MSE on {mse_ahead}."]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("snds", type=Path, help="results.jsonl with the SNDS rows")
    parser.add_argument(
        "baselines",
        type=Path,
        nargs="?",
        help="results.jsonl with the baselines' rows (default: the SNDS file, one sweep)",
    )
    parser.add_argument("--section", default="snds-vs-baselines", help="README block to write")
    parser.add_argument("--no-readme", action="store_true")
    args = parser.parse_args()
    baselines = args.baselines or args.snds
    records = compare(_rows(args.snds), _rows(baselines))
    out = args.snds.with_name("against-baselines.json")
    out.write_text(json.dumps(records, indent=1) + "\n")
    body = table(records, args.snds, baselines)
    print(body)
    if not args.no_readme:
        write_readme_section(args.section, body)


if __name__ == "__main__":
    main()
