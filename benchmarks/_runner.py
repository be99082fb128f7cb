"""What every benchmark script shares: its options, seeds and threads, the machine it ran on,
its result files and its table in ``benchmarks/README.md``.

A script builds its parser with :func:`parser` (the common options ``--seeds``, ``--threads``,
``--no-readme``, and where it takes them ``--jobs``, ``--set KEY=VALUE`` and ``--tag``), calls
:func:`set_threads`, records :func:`machine` beside its rows with :func:`write_results`, and
puts its table, headed by :func:`machine_line`, between its markers of the README with
:func:`write_readme_section`. Rerunning a script replaces its block and nothing else.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import datetime
import json
import os
import platform
import resource
import subprocess
from collections.abc import Iterable, Sequence
from pathlib import Path

__all__ = [
    "DATA",
    "HERE",
    "README",
    "RESULTS",
    "children_cpu",
    "commit",
    "cpu_name",
    "machine",
    "machine_line",
    "markdown_table",
    "parse_pairs",
    "parse_value",
    "parser",
    "set_threads",
    "shrink_png",
    "split_overrides",
    "write_readme_section",
    "write_results",
]

HERE = Path(__file__).resolve().parent
README = HERE / "README.md"
RESULTS = HERE / "results"
#: The real recordings beyond LASA (../shared/data, beside the checkout; see its README).
DATA = HERE.parent.parent / "shared" / "data"


def parser(
    doc: str | None,
    *,
    seeds: int | None = None,
    threads: bool = True,
    jobs: bool = False,
    overrides: bool = False,
    tag: bool = False,
) -> argparse.ArgumentParser:
    """The script's parser with the options every script shares.

    Arguments:
        doc: The script's docstring: its first line is the description, the rest the epilog.
        seeds: Adds ``--seeds N`` (seeds 0 .. N-1) with this default.
        threads: Adds ``--threads`` (torch threads per run, default 1).
        jobs: Adds ``--jobs`` (runs side by side; default all cores).
        overrides: Adds ``--set KEY=VALUE ...`` (see :func:`parse_pairs`).
        tag: Adds ``--tag`` (a suffix of the result files and of the README block).
    """
    first, _, rest = (doc or "").strip().partition("\n")
    out = argparse.ArgumentParser(
        description=first,
        epilog=rest.strip() or None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    if seeds is not None:
        out.add_argument("--seeds", type=int, default=seeds, help="seeds 0 .. N-1")
    if threads:
        out.add_argument("--threads", type=int, default=1, help="torch threads per run")
    if jobs:
        out.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="runs side by side")
    if overrides:
        out.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="overrides")
    if tag:
        out.add_argument("--tag", default="", help="suffix of the result files and README block")
    out.add_argument("--no-readme", action="store_true", help="leave benchmarks/README.md as is")
    return out


def set_threads(threads: int) -> None:
    """Sets torch's intra-op threads (one by default: two on a busy 2-core machine crawl)."""
    import torch

    torch.set_num_threads(threads)


def cpu_name() -> str:
    """The processor's model name (from /proc/cpuinfo where there is one)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown processor"


def commit() -> str:
    """The checkout's commit (short hash), with "+changes" if ``src/`` differs from it."""

    def git(*argv: str) -> str:
        return subprocess.run(
            ["git", *argv], cwd=HERE, capture_output=True, text=True, check=False
        ).stdout.strip()

    head = git("rev-parse", "--short", "HEAD") or "unknown"
    return head + ("+changes" if git("status", "--porcelain", "--", "../src") else "")


def machine(*, threads: int = 1, jobs: int = 1) -> dict:
    """Where and how a run was measured: date, commit, CPU model, cores, threads, load."""
    import torch

    return {
        "date": datetime.date.today().isoformat(),
        "commit": commit(),
        "cpu": cpu_name(),
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "torch": torch.__version__,
        "threads": threads,
        "jobs": jobs,
        "load_average": list(os.getloadavg()),
    }


def machine_line(meta: dict) -> str:
    """One sentence for above a table: when, at which commit, on what, how loaded."""
    load = meta.get("load_average")
    together = "one run at a time" if meta.get("jobs", 1) == 1 else f"{meta['jobs']} runs at once"
    where = f"{meta['cpu']} ({meta['cores']} cores)" if "cpu" in meta else meta.get("machine", "?")
    return (
        f"Measured {meta.get('date', '?')} at {meta.get('commit', '?')} on {where}, "
        f"{together}, {meta.get('threads', 1)} torch "
        f"thread(s) each" + (f", load average {load[0]:.1f}" if load else "") + "."
    )


def write_results(
    name: str, rows: Sequence[dict], meta: dict, *, folder: Path = RESULTS, with_csv: bool = True
) -> Path:
    """Writes ``folder/name.json`` (``{"meta": ..., "rows": ...}``) and (``with_csv``)
    ``name.csv``, each through a temporary file and a rename."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.json"
    _replace(path, json.dumps({"meta": meta, "rows": list(rows)}, indent=1) + "\n")
    if rows and with_csv:
        fields = list(dict.fromkeys(key for row in rows for key in row))
        tmp = path.with_suffix(".csv.tmp")
        with open(tmp, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=fields)
            writer.writeheader()
            writer.writerows(rows)
        os.replace(tmp, path.with_suffix(".csv"))
    return path


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    """A Markdown table; cells are written with ``str``."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def write_readme_section(tag: str, body: str, readme: Path = README) -> None:
    """Replaces the block of ``tag`` (or appends it), through a temporary file and a rename."""
    text = readme.read_text() if readme.exists() else "# Benchmarks\n"
    begin, end = f"<!-- {tag}:begin -->", f"<!-- {tag}:end -->"
    block = f"{begin}\n{body}\n{end}"
    if begin in text and end in text:
        text = text[: text.index(begin)] + block + text[text.index(end) + len(end) :]
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    _replace(readme, text)


def _replace(path: Path, text: str) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def children_cpu() -> float:
    """CPU seconds of the finished child processes (a subprocess's training, say)."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def parse_value(text: str) -> object:
    """A value as JSON where it parses (``0.1``, ``[64, 64]``, ``true``), else the string."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def parse_pairs(pairs: Iterable[str]) -> dict[str, object]:
    """``["KEY=VALUE", ...]`` -> ``{key: value}`` (values by :func:`parse_value`).

    Raises:
        SystemExit: For an item without ``=`` or without a key.
    """
    overrides: dict[str, object] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise SystemExit(f"{pair!r} is not KEY=VALUE")
        overrides[key] = parse_value(value)
    return overrides


def split_overrides(overrides: dict[str, object]) -> tuple[dict[str, object], dict[str, object]]:
    """(the fields of :class:`~snds.policy.PolicyConfig`, the rest: the training's)."""
    from snds.policy import PolicyConfig

    policy_fields = {field.name for field in dataclasses.fields(PolicyConfig)}
    policy = {k: v for k, v in overrides.items() if k in policy_fields}
    return policy, {k: v for k, v in overrides.items() if k not in policy_fields}


def shrink_png(path: Path, colors: int = 64) -> None:
    """Rewrites a committed figure with a palette of ``colors`` (a 3-5x smaller file)."""
    from PIL import Image

    with Image.open(path) as image:
        small = image.convert("RGB").quantize(colors=colors, method=Image.Quantize.MEDIANCUT)
    tmp = path.with_suffix(".tmp.png")
    small.save(tmp, optimize=True)
    os.replace(tmp, path)
