"""snds.parallel: the same results as a plain map, however the calls run; a failure stops
the calls not yet started."""

from __future__ import annotations

import importlib.util
import operator
import sys

import pytest
import torch
from _parallel_calls import fail_first, power

from snds.errors import ConfigError, SNDSError
from snds.parallel import starmap_unordered, torch_threads

CALLS = [(base, exponent) for base in range(6) for exponent in (2, 3)]


@pytest.mark.parametrize("jobs", [1, 2])
def test_results_are_those_of_a_plain_map(jobs: int) -> None:
    # GIVEN calls whose first ones are the slowest (on two workers they finish out of order)
    # WHEN they run through the helper
    results = list(starmap_unordered(power, CALLS, jobs=jobs))
    # THEN each index comes once, with the result of its own arguments
    assert sorted(i for i, _ in results) == list(range(len(CALLS)))
    assert dict(results) == {i: base**exponent for i, (base, exponent) in enumerate(CALLS)}


def test_one_job_runs_here_in_order() -> None:
    # A lambda cannot pickle: only a run in this process can call it.
    assert list(starmap_unordered(lambda x: -x, [(1,), (2,)], jobs=1)) == [(0, -1), (1, -2)]


def test_no_calls_start_no_pool() -> None:
    assert list(starmap_unordered(operator.mul, [], jobs=2)) == []


@pytest.mark.parametrize("jobs", [1, 2])
def test_a_failure_propagates_and_cancels_the_calls_not_started(jobs: int, tmp_path) -> None:
    # GIVEN 20 calls of 0.3 s each, the first of which fails at once
    calls = [(str(tmp_path), i, 0.3) for i in range(20)]
    # WHEN they run
    with pytest.raises(ValueError, match="call 0 fails"):
        for _ in starmap_unordered(fail_first, calls, jobs=jobs):
            pass
    # THEN the calls not yet handed to a worker never ran: in this process none did; on a
    # pool the two running and the three queued ahead of them, about 5 (all 19 without the
    # cancel, since the pool waits for its calls before the exception leaves)
    assert len(list(tmp_path.iterdir())) < (1 if jobs == 1 else 10)


def test_stopping_early_cancels_the_rest(tmp_path) -> None:
    calls = [(str(tmp_path), i, 0.3) for i in range(1, 21)]
    for _ in starmap_unordered(fail_first, calls, jobs=2):
        break  # the generator closes here, as it would on an exception in the loop
    # About 6 ran (the first, the two running after it, three queued); all 20 without the cancel.
    assert len(list(tmp_path.iterdir())) < 10


@pytest.mark.parametrize("jobs", [0, -1])
def test_jobs_below_one_are_refused_at_the_call(jobs: int) -> None:
    with pytest.raises(ConfigError, match="jobs must be at least 1"):
        starmap_unordered(operator.mul, CALLS, jobs=jobs)


@pytest.mark.parametrize("keys", [["a"], ["a", "a"]])
def test_keys_must_name_each_call_once(keys: list[str]) -> None:
    with pytest.raises(ConfigError, match="keys must name each of the 2 calls once"):
        starmap_unordered(operator.mul, [(1, 2), (3, 4)], scheduler="tcp://x:1", keys=keys)


def test_scheduler_without_dask_says_how_to_install_it(monkeypatch) -> None:
    # None in sys.modules makes an import fail as if the package were absent.
    monkeypatch.setitem(sys.modules, "dask.distributed", None)
    with pytest.raises(SNDSError, match=r"pip install snds\[cluster\]"):
        starmap_unordered(operator.mul, CALLS, scheduler="tcp://127.0.0.1:8786")


@pytest.mark.skipif(importlib.util.find_spec("dask") is None, reason="needs snds[cluster]")
def test_a_dask_cluster_gives_the_same_results() -> None:
    from dask.distributed import LocalCluster

    # One worker thread in this process: the cluster starts in about a second.
    with LocalCluster(n_workers=1, processes=False, dashboard_address=None) as cluster:
        keys = [f"power-{a}-{b}" for a, b in CALLS]
        results = dict(
            starmap_unordered(power, CALLS, scheduler=cluster.scheduler_address, keys=keys)
        )
        assert results == {i: base**exponent for i, (base, exponent) in enumerate(CALLS)}
        # pure=False: the same calls again run again rather than come from a cache.
        again = starmap_unordered(
            operator.mul, [(2, 3), (2, 3)], scheduler=cluster.scheduler_address
        )
        assert sorted(again) == [(0, 6), (1, 6)]


@pytest.mark.skipif(importlib.util.find_spec("dask") is None, reason="needs snds[cluster]")
def test_a_failure_on_dask_propagates() -> None:
    from dask.distributed import LocalCluster

    with LocalCluster(n_workers=1, processes=False, dashboard_address=None) as cluster:
        calls = [(".", 0, 0.0)]
        with pytest.raises(ValueError, match="call 0 fails"):
            list(starmap_unordered(fail_first, calls, scheduler=cluster.scheduler_address))


def test_torch_threads_sets_the_count_inside_and_restores_it_after_an_error() -> None:
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with pytest.raises(RuntimeError, match="inside"), torch_threads(1):
            assert torch.get_num_threads() == 1
            raise RuntimeError("inside")
        assert torch.get_num_threads() == 2

        @torch_threads(1)
        def threads() -> int:
            return torch.get_num_threads()

        assert (threads(), threads(), torch.get_num_threads()) == (1, 1, 2)
        with pytest.raises(ConfigError, match="at least 1"), torch_threads(0):
            pass
    finally:
        torch.set_num_threads(before)
