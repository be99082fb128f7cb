"""Independent calls of one function, run here, on a local process pool or on a Dask cluster.

The one way the library and the benchmarks run many trainings side by side: each call is a
picklable top-level function and a tuple of its positional arguments, and each result comes
back with the index of its call as soon as it is ready. :func:`torch_threads` sets how many
threads torch may use inside one call (one, for the small networks here).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, TypeVar

import torch

from snds.errors import ConfigError, SNDSError

__all__ = ["starmap_unordered", "torch_threads"]

R = TypeVar("R")


def starmap_unordered(
    function: Callable[..., R],
    arguments: Iterable[tuple[Any, ...]],
    *,
    jobs: int | None = None,
    scheduler: str | None = None,
    keys: Sequence[str] | None = None,
) -> Iterator[tuple[int, R]]:
    """Calls ``function(*args)`` for each tuple of ``arguments``, side by side.

    Yields ``(index, result)`` in the order the calls finish, ``index`` being the position
    of the call's arguments in ``arguments``; sort on it for the order of submission. With
    ``jobs == 1`` the calls run one after the other in this process, in order and without
    starting a process. Otherwise they run on a pool of ``min(jobs, calls)`` processes
    started with "spawn" (forking a process whose torch has started threads can deadlock),
    or, with ``scheduler``, on that Dask cluster as tasks that are never taken from its cache
    (``pure=False``: running a training again must train again).

    When a call raises, or the caller stops iterating (an exception of its own, a
    ``KeyboardInterrupt``), the calls not yet started are cancelled and the exception goes
    on; calls already running on the local pool finish first, since a process cannot be
    stopped halfway safely.

    Arguments:
        function: A top-level function, so that a worker process can import it (a
            :func:`functools.partial` of one is fine, for keyword arguments shared by all
            calls).
        arguments: One tuple of positional arguments per call; each must pickle.
        jobs: Local worker processes (default: all cores; 1 runs in this process). Ignored
            with ``scheduler``, whose cluster decides.
        scheduler: A Dask scheduler address such as ``tcp://host:8786`` (needs
            ``pip install snds[cluster]``).
        keys: Unique Dask task names, one per call (default: Dask's own); they name the calls
            on the cluster's dashboard and nowhere else.

    Returns:
        An iterator of ``(index, result)``; the calls start when it is first advanced.

    Raises:
        ConfigError: ``jobs`` below 1, or ``keys`` not one distinct name per call.
        SNDSError: ``scheduler`` given but Dask not installed.
    """
    calls = list(arguments)
    if jobs is None:
        jobs = os.cpu_count() or 1
    if jobs < 1:
        raise ConfigError(f"jobs must be at least 1, got {jobs}")
    if keys is not None:
        keys = list(keys)
        if len(keys) != len(calls) or len(set(keys)) != len(keys):
            raise ConfigError(
                f"keys must name each of the {len(calls)} calls once, got {len(keys)} keys "
                f"({len(set(keys))} distinct)"
            )
    if scheduler is not None:
        # An optional extra: checked here, so that its absence shows before any call.
        try:
            import dask.distributed  # noqa: F401
        except ImportError:
            raise SNDSError("--scheduler needs Dask: pip install snds[cluster]") from None
        return _on_dask(function, calls, scheduler, keys)
    if jobs == 1:
        return _here(function, calls)
    return _on_pool(function, calls, min(jobs, len(calls)))


@contextmanager
def torch_threads(count: int = 1) -> Iterator[None]:
    """Runs a block (or, as a decorator, a function) with ``count`` torch CPU threads, then
    restores the number before it.

    The networks of this library are small and a rollout evaluates them on a handful of
    states per step, thousands of times: each call is a few microseconds of arithmetic, and
    with several OpenMP threads each also waits for the others to wake. Where other work
    holds the cores (runs side by side, a shared machine) the waits dominate: an SDS-EF
    rollout of the 7 LASA Sine starts (2,098 Euler steps) took 29-65 s on two threads against
    1.7-2.8 s on one on a loaded 2-core machine (``benchmarks/README.md``, Smoothness).

    Arguments:
        count: Threads inside the block, at least 1.

    Raises:
        ConfigError: ``count`` below 1.
    """
    if count < 1:
        raise ConfigError(f"torch threads must be at least 1, got {count}")
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _here(function: Callable[..., R], calls: list[tuple[Any, ...]]) -> Iterator[tuple[int, R]]:
    # One worker gains nothing from a process: run here and skip its start-up.
    for index, args in enumerate(calls):
        yield index, function(*args)


def _on_pool(
    function: Callable[..., R], calls: list[tuple[Any, ...]], workers: int
) -> Iterator[tuple[int, R]]:
    if not calls:
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
        futures = {pool.submit(function, *args): i for i, args in enumerate(calls)}
        try:
            for future in as_completed(futures):
                yield futures[future], future.result()
        except BaseException:
            # Also GeneratorExit: a caller that stops reading wants no more calls run.
            for future in futures:
                future.cancel()
            raise


def _on_dask(
    function: Callable[..., R],
    calls: list[tuple[Any, ...]],
    scheduler: str,
    keys: list[str] | None,
) -> Iterator[tuple[int, R]]:
    from dask.distributed import Client, as_completed

    with Client(scheduler) as client:
        futures = [
            client.submit(function, *args, pure=False, key=keys[i] if keys else None)
            for i, args in enumerate(calls)
        ]
        index = {future.key: i for i, future in enumerate(futures)}
        try:
            for future in as_completed(futures):
                yield index[future.key], future.result()
        except BaseException:
            client.cancel(futures)
            raise
