"""Calls for tests/test_parallel.py to run in spawned worker processes.

A module of its own that imports neither snds nor torch, so that a worker starts in a
fraction of a second: a spawned worker imports the module of the function it runs.
"""

from __future__ import annotations

import time
from pathlib import Path


def power(base: int, exponent: int) -> int:
    """``base ** exponent``, slowest for the first calls so that they finish out of order."""
    time.sleep(0.05 * max(0, 3 - base))
    return base**exponent


def fail_first(directory: str, index: int, seconds: float) -> int:
    """Raises at once for index 0; otherwise waits, then leaves a file named by the index."""
    if index == 0:
        raise ValueError("call 0 fails")
    time.sleep(seconds)
    (Path(directory) / str(index)).touch()
    return index
