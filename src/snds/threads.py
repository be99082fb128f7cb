"""How many torch CPU threads the library's work runs on when the user does not say.

The networks are small (a few hundred thousand multiply-adds per state): a training step on a
batch of 512 states, or a rollout step on a few hundred, is a few milliseconds of arithmetic
split into many small kernels, and with several OpenMP threads each kernel also waits for
the others to wake. ``benchmarks/threads.py`` measures 1 against 2 threads for a fit, an
evaluation and the stability check (``benchmarks/results/threads.json``); :func:`fastest_threads`
returns the count that won for work of that size.
"""

from __future__ import annotations

from typing import Any

__all__ = ["fastest_threads"]


def fastest_threads(work: Any = None) -> int:
    """The torch thread count that measured fastest for ``work`` (a
    :class:`~snds.train.TrainConfig`, a :class:`~snds.stability.CheckConfig`, or None for an
    evaluation): one, for every size the library runs (``benchmarks/threads.py``)."""
    return 1
