"""The page (``snds app``): time from a stroke added after training to the refined field on
screen.

Three strokes (the first three LASA Sine demonstrations, every 5th sample, as
benchmarks/app.py opens them) are opened in the page in headless Chromium and trained with
the page's defaults (``snds train``'s). Then, one after the other, the next three Sine
demonstrations are added as strokes at their own clock (``sndsApp.addStroke``, the path a
finished mouse stroke takes), each refining the policy on screen
(``POST /api/jobs/{id}/refine``); for each, the page's own clock gives the time from the
stroke added to the refined field drawn, and the worker reports its CPU seconds.

    python benchmarks/app_refine.py      # a few minutes; table into benchmarks/README.md

Writes ``benchmarks/results/app-refine.json`` and (without ``--no-readme``) the
``app-refine`` block of ``benchmarks/README.md``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
from _runner import cpu_name, write_readme_section

from snds.app.headless import launch
from snds.app.strokes import csv_text, parse_strokes
from snds.data import load_lasa

HERE = Path(__file__).resolve().parent
COMMAND = "python benchmarks/app_refine.py"


def strokes(first: int, count: int) -> list[list[list[float]]]:
    """LASA Sine demonstrations first..first+count-1, every 5th sample, as [x, y, t]."""
    demos = load_lasa("Sine").select(range(first, first + count))
    return [np.column_stack([d.positions[::5], d.times[::5]]).tolist() for d in demos]


def start_server() -> tuple[subprocess.Popen, str]:
    """``snds app`` in a process of its own, on a free port; its process and URL."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    process = subprocess.Popen(
        [sys.executable, "-m", "snds", "--quiet", "app", "--port", str(port)]
    )
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while True:
        try:
            urllib.request.urlopen(f"{url}/api/health", timeout=5).read()
            return process, url
        except OSError:
            if time.monotonic() > deadline or process.poll() is not None:
                raise RuntimeError("snds app did not start") from None
            time.sleep(0.2)


def measure(url: str, added: int) -> dict:
    """Trains on 3 strokes in the page, then adds ``added`` strokes one by one."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = launch(playwright)
        page = browser.new_page(viewport={"width": 1240, "height": 800})
        page.goto(url)
        csv = csv_text(parse_strokes({"strokes": strokes(0, 3)})).encode()
        page.set_input_files(
            "#upload", files=[{"name": "sine.csv", "mimeType": "text/csv", "buffer": csv}]
        )
        page.wait_for_function("sndsApp.strokes.length === 3")
        page.click("#train")
        page.wait_for_function("sndsApp.drawn.snds", timeout=1_800_000, polling=100)
        status = page.evaluate("sndsApp.jobs.snds.status")
        train = {k: status[k] for k in ("step", "saved_after", "saved_cpu_seconds") if k in status}
        rows = []
        for stroke in strokes(3, added):
            before = page.evaluate("sndsApp.jobs.snds.id")
            page.evaluate("s => sndsApp.addStroke(s)", stroke)
            state = page.evaluate("document.body.dataset.state")
            page.wait_for_function(
                f"sndsApp.jobs.snds.id !== {json.dumps(before)} && sndsApp.timings.refine.drawn",
                timeout=600_000,
                polling=20,
            )
            timing = page.evaluate("sndsApp.timings.refine")
            # The next stroke comes as soon as the field is shown (as a user's would), which
            # stops this one's stability check; the last one's check is waited for.
            status = page.evaluate("sndsApp.jobs.snds.status")
            rows.append(
                {
                    "strokes": page.evaluate("sndsApp.strokes.length"),
                    "state_after_stroke": state,
                    "stroke_to_field_seconds": (timing["drawn"] - timing["added"]) / 1e3,
                    "saved_after_seconds": status["saved_after"],
                    "saved_cpu_seconds": status["saved_cpu_seconds"],
                }
            )
            print(json.dumps(rows[-1]), flush=True)
        page.wait_for_function(
            "sndsApp.jobs.snds.status.state === 'done'", timeout=1_800_000, polling=100
        )
        metrics = page.evaluate("sndsApp.jobs.snds.status.metrics")
        browser.close()
    stability = metrics["stability"]
    last = {
        "train_seconds": metrics["train_seconds"],
        "converged": stability["converged_fraction"],
        "violations": stability["decrease_violations"],
        "rollouts": stability["rollouts"],
    }
    return {"train": train, "refinements": rows, "last": last}


def table(record: dict) -> str:
    rows = record["refinements"]
    lines = [
        "| strokes | stroke to refined field on screen, s | refinement job until saved, s "
        "| worker CPU s until saved |",
        "|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| 3 + {row['strokes'] - 3} | {row['stroke_to_field_seconds']:.2f} "
            f"| {row['saved_after_seconds']:.2f} | {row['saved_cpu_seconds']:.2f} |"
        )
    median = float(np.median([r["stroke_to_field_seconds"] for r in rows]))
    last = record["last"]
    lines.append(f"| median | {median:.2f} | | |")
    lines.append(
        f"\nThe last refinement's check: {last['converged']:.3f} of {last['rollouts']} random "
        f"starts arrived, {last['violations']} decrease violations; its optimiser took "
        f"{last['train_seconds']:.2f} s."
    )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--added", type=int, default=3, help="strokes added one by one")
    parser.add_argument("--no-readme", action="store_true")
    args = parser.parse_args()
    load = os.getloadavg()
    process, url = start_server()
    try:
        record = measure(url, args.added)
    finally:
        process.terminate()
        process.wait(timeout=30)
    record["meta"] = {
        "date": datetime.date.today().isoformat(),
        "cpu": cpu_name(),
        "cores": os.cpu_count(),
        "load_average_before": load,
        "load_average_after": os.getloadavg(),
        "command": COMMAND,
    }
    out = HERE / "results"
    out.mkdir(exist_ok=True)
    (out / "app-refine.json").write_text(json.dumps(record, indent=2) + "\n")
    text = table(record)
    print(text)
    if not args.no_readme:
        after = record["meta"]["load_average_after"][0]
        header = (
            f"`{COMMAND}` ({record['meta']['cpu']}, {os.cpu_count()} cores; 1-minute load "
            f"average {load[0]:.1f} before and {after:.1f} after: the machine was shared, "
            "so these are upper figures)"
        )
        write_readme_section("app-refine", header + "\n\n" + text)


if __name__ == "__main__":
    main()
