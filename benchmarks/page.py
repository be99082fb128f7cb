"""The page (``snds app``): time from "train" to the field on screen, and responsiveness.

Three strokes of 200 points (the first three LASA Sine demonstrations, every 5th sample:
hand-drawn data at their own clock) are opened in the page in headless Chromium (Debian's
``chromium``, driven by Playwright), and "Train" is clicked with the page's defaults, which
are ``snds train``'s. Measured:

* the time from the click to the field drawn on the canvas (the page's own clock), and to
  the end of the job (the stability check's numbers shown);
* while the job trains: the latency of ``GET /api/health`` and the page's longest gap between
  two animation frames; while a second default job trains, the latency of the requests the
  page makes on a finished model (``/field`` on its 72 x 54 grid, ``/rollout`` of one piece of
  1 s of motion, as the page asks for them while it plays the previous one);
  the same requests on an idle server for comparison;
* CPU seconds beside wall seconds: the worker's (reported by it), the server process's
  (``/proc``).

    python benchmarks/page.py      # a few minutes; table into benchmarks/README.md

Without Chromium the time to the field is measured through the API as the page makes its
requests (train, stream until the model is saved, the field), without drawing. Writes
``benchmarks/results/page.json`` and (without ``--no-readme``) the ``page`` block of
``benchmarks/README.md``.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
from _runner import RESULTS, machine, machine_line, parser, write_readme_section

from snds.app.headless import available, launch
from snds.app.strokes import csv_text, parse_strokes
from snds.data import load_lasa
from snds.io import write_json

FIELD = {"bounds": [-100.0, 100.0, -75.0, 75.0], "size": [72, 54]}
# Records the gaps between animation frames on the page, to see whether it stays fluid.
FRAME_GAPS = """() => {
  window.frameGaps = [];
  let last = performance.now();
  const tick = (now) => {
    window.frameGaps.push(now - last);
    last = now;
    requestAnimationFrame(tick);
  };
  requestAnimationFrame(tick);
}"""


def _strokes() -> dict:
    demos = load_lasa("Sine").first(3)
    raw = [np.column_stack([d.positions[::5], d.times[::5]]).tolist() for d in demos]
    return parse_strokes({"strokes": raw}).to_dict()


def _request(url: str, body: dict | None = None, method: str | None = None) -> tuple[dict, float]:
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(url, data=data, method=method)
    if data is not None:
        request.add_header("Content-Type", "application/json")
    start = time.perf_counter()
    with urllib.request.urlopen(request, timeout=120) as answer:
        payload = json.loads(answer.read())
    return payload, time.perf_counter() - start


def _cpu(pid: int) -> float:
    """CPU seconds of a process and its waited-for children (``/proc/PID/stat``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = sum(int(fields[k]) for k in (11, 12, 13, 14))
    return ticks / os.sysconf("SC_CLK_TCK")


def _summary(seconds: list[float]) -> dict:
    values = 1e3 * np.asarray(seconds)
    return {
        "count": len(values),
        "median_ms": float(np.median(values)),
        "p95_ms": float(np.percentile(values, 95)),
        "max_ms": float(values.max()),
    }


class Server:
    """``snds app`` in a process of its own, on a free port."""

    def __init__(self) -> None:
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            port = probe.getsockname()[1]
        self.url = f"http://127.0.0.1:{port}"
        self.process = subprocess.Popen(
            [sys.executable, "-m", "snds", "--quiet", "app", "--port", str(port)]
        )
        deadline = time.monotonic() + 60
        while True:
            try:
                _request(f"{self.url}/api/health")
                break
            except OSError:
                if time.monotonic() > deadline or self.process.poll() is not None:
                    raise RuntimeError("snds app did not start") from None
                time.sleep(0.2)

    def api(self, path: str, body: dict | None = None, method: str | None = None):
        return _request(f"{self.url}{path}", body, method)

    def wait(self, job: str, states: set[str]) -> dict:
        while True:
            status, _ = self.api(f"/api/jobs/{job}")
            if status["state"] in states:
                return status
            time.sleep(0.1)

    def stop(self) -> None:
        self.process.terminate()
        self.process.wait(timeout=30)


def _poll_health(server: Server, until: threading.Event, out: list[float]) -> None:
    while not until.is_set():
        out.append(server.api("/api/health")[1])
        time.sleep(0.2)


def _train_in_browser(server: Server, strokes: dict) -> dict:
    """Opens the strokes in the page, clicks Train and times it on the page's clock."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = launch(playwright)
        page = browser.new_page(viewport={"width": 1240, "height": 800})
        page.goto(server.url)
        csv = csv_text(parse_strokes(strokes)).encode()
        page.set_input_files(
            "#upload", files=[{"name": "sine.csv", "mimeType": "text/csv", "buffer": csv}]
        )
        page.wait_for_function("sndsApp.strokes.length === 3")
        page.evaluate(FRAME_GAPS)
        health: list[float] = []
        trained = threading.Event()
        poller = threading.Thread(target=_poll_health, args=(server, trained, health))
        before = _cpu(server.process.pid)
        page.click("#train")
        poller.start()
        page.wait_for_function("sndsApp.drawn.snds", timeout=1_800_000, polling=50)
        trained.set()
        poller.join()
        page.wait_for_function(
            "sndsApp.jobs.snds.status.state === 'done'", timeout=1_800_000, polling=100
        )
        timings = page.evaluate("sndsApp.timings.snds")
        layer_ms = page.evaluate("sndsApp.jobs.snds.layerMs")
        gaps = page.evaluate("window.frameGaps")
        job = page.evaluate("sndsApp.jobs.snds.id")
        status, _ = server.api(f"/api/jobs/{job}")
        browser.close()
    return {
        "via": "page (headless Chromium)",
        "job": job,
        "click_to_field_seconds": (timings["drawn"] - timings["clicked"]) / 1e3,
        "status": status,
        "server_cpu_seconds": _cpu(server.process.pid) - before,
        "draw_field_ms": layer_ms,
        "health_while_training": _summary(health),
        "frame_gap_ms_while_training": {
            "median": float(np.median(gaps)),
            "max": float(np.max(gaps)),
        },
    }


def _train_through_the_api(server: Server, strokes: dict) -> dict:
    """The page's requests without the page: train, stream until saved, the field."""
    health: list[float] = []
    trained = threading.Event()
    poller = threading.Thread(target=_poll_health, args=(server, trained, health))
    before = _cpu(server.process.pid)
    start = time.perf_counter()
    status, _ = server.api("/api/train", strokes)
    poller.start()
    server.wait(status["id"], {"checking", "done", "error"})
    server.api(f"/api/jobs/{status['id']}/field", FIELD)
    seconds = time.perf_counter() - start
    trained.set()
    poller.join()
    final = server.wait(status["id"], {"done", "error"})
    return {
        "via": "API (no browser)",
        "job": status["id"],
        "click_to_field_seconds": seconds,
        "status": final,
        "server_cpu_seconds": _cpu(server.process.pid) - before,
        "health_while_training": _summary(health),
    }


def _requests(
    server: Server, job: str, count: int, *, while_training: str | None = None
) -> dict[str, list[float]]:
    """Latencies of the page's requests on a finished model (a rollout piece of 1 s of
    motion, as the page asks for them), ``count`` rounds or until ``while_training`` stops
    training."""
    times: dict[str, list[float]] = {"health": [], "field": [], "rollout": []}
    for _ in range(count):
        if while_training and server.api(f"/api/jobs/{while_training}")[0]["state"] != "training":
            break
        times["health"].append(server.api("/api/health")[1])
        times["field"].append(server.api(f"/api/jobs/{job}/field", FIELD)[1])
        piece = {"start": [-90, 70], "duration": 1.0}
        times["rollout"].append(server.api(f"/api/jobs/{job}/rollout", piece)[1])
    return times


def main() -> None:
    options = parser(__doc__, threads=False)
    options.add_argument("--no-browser", action="store_true", help="measure through the API")
    args = options.parse_args()
    strokes = _strokes()
    server = Server()
    try:
        browser = available() and not args.no_browser
        first = (
            _train_in_browser(server, strokes)
            if browser
            else _train_through_the_api(server, strokes)
        )
        job = first["job"]
        idle = _requests(server, job, 10)
        # A second default job (another seed), timed on the first job's model while it trains.
        second, _ = server.api("/api/train", {**strokes, "settings": {"seed": 1}})
        server.wait(second["id"], {"training"})
        time.sleep(1.0)
        busy = _requests(server, job, 10, while_training=second["id"])
        server.api(f"/api/jobs/{second['id']}", method="DELETE")
    finally:
        server.stop()
    status = first["status"]
    stability = status["metrics"]["stability"]
    record = {
        **machine(),
        "strokes": "LASA Sine demonstrations 0-2, every 5th sample: 3 x 200 points",
        "settings": "snds train's defaults (the page's)",
        **{k: v for k, v in first.items() if k != "status"},
        "train_steps": status["total"],
        "saved_after_seconds": status["saved_after"],
        "job_seconds": status["seconds"],
        "worker_cpu_seconds": status["worker_cpu_seconds"],
        "saved_cpu_seconds": status.get("saved_cpu_seconds"),
        "train_seconds": status["metrics"]["train_seconds"],
        "converged_fraction": stability["converged_fraction"],
        "decrease_violations": stability["decrease_violations"],
        "idle": {k: _summary(v) for k, v in idle.items()},
        "while_training": {k: _summary(v) for k, v in busy.items()},
    }
    write_json(RESULTS / "page.json", record)
    print(json.dumps(record, indent=2))
    if not args.no_readme:
        write_readme_section("page", _table(record))


def _table(r: dict) -> str:
    idle, busy = r["idle"], r["while_training"]
    rows = [
        f"{machine_line(r)} {r['strokes']}, {r['settings']} ({r['train_steps']} steps), "
        f"measured {r['via']}, `python benchmarks/page.py`.",
        "",
        "| from the click on Train | wall s | worker CPU s |",
        "|---|---|---|",
        f"| model saved (training: {r['train_seconds']:.1f} s) | "
        f"{r['saved_after_seconds']:.1f} | {_seconds(r.get('saved_cpu_seconds'))} |",
        f"| field drawn on the page | {r['click_to_field_seconds']:.1f} | |",
        f"| stability check shown (converged {r['converged_fraction']:.3f}, "
        f"{r['decrease_violations']} violations) | {r['job_seconds']:.1f} | "
        f"{r['worker_cpu_seconds']:.1f} (server: {r['server_cpu_seconds']:.1f}) |",
        "",
        "| request (ms, median / p95 / max) | idle | while a job trains |",
        "|---|---|---|",
        f"| `GET /api/health` | {_ms(idle['health'])} | {_ms(busy['health'])} |",
        f"| `POST /field` (72 x 54) | {_ms(idle['field'])} | {_ms(busy['field'])} |",
        f"| `POST /rollout` (1 s of motion) | {_ms(idle['rollout'])} | {_ms(busy['rollout'])} |",
    ]
    if "frame_gap_ms_while_training" in r:
        gaps = r["frame_gap_ms_while_training"]
        rows += [
            "",
            "While the first job trained, `/api/health` answered in "
            f"{_ms(r['health_while_training'])} ms and the page's animation frames came "
            f"every {gaps['median']:.0f} ms (longest gap {gaps['max']:.0f} ms); drawing the "
            f"field (V's contours and the streamlines) took {r['draw_field_ms']:.0f} ms.",
        ]
    return "\n".join(rows)


def _seconds(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def _ms(summary: dict) -> str:
    return f"{summary['median_ms']:.0f} / {summary['p95_ms']:.0f} / {summary['max_ms']:.0f}"


if __name__ == "__main__":
    main()
