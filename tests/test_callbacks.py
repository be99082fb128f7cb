"""Callbacks: every hook fires in the order of the fit's events, as often as they happen, and
a callback can stop a fit; fit and fit_many run them through one loop."""

from __future__ import annotations

import dataclasses

import pytest
import torch

import snds.train as train_module
from snds.batched import fit_many
from snds.callbacks import Callback
from snds.data import no_split
from snds.train import TrainConfig, fit

from conftest import SMALL, make_policy

TINY = TrainConfig(steps=12, batch_size=64, lr=1e-2, dtype="float64")


class Recorder(Callback):
    """Keeps every event it is given, as (hook, event)."""

    def __init__(self, stop_at: int | None = None) -> None:
        self.events: list[tuple[str, object]] = []
        self.stop_at = stop_at

    def on_step(self, event):
        self.events.append(("step", event))
        return event.step == self.stop_at

    def on_restart(self, event):
        self.events.append(("restart", event))

    def on_checkpoint(self, event):
        self.events.append(("checkpoint", event))

    def on_end(self, event):
        self.events.append(("end", event))

    def hooks(self) -> list[str]:
        return [hook for hook, _ in self.events]


def test_hooks_fire_in_order_with_the_right_counts(spiral, tmp_path):
    # GIVEN a 12-step fit that checkpoints every 5 steps
    recorder, checkpoint = Recorder(), tmp_path / "checkpoint.safetensors"
    policy = make_policy(spiral, SMALL)
    result = fit(
        policy,
        spiral,
        no_split(spiral),
        config=TINY,
        callbacks=[recorder],
        progress=False,
        checkpoint=checkpoint,
        checkpoint_every=5,
    )
    # THEN each step once, in order, a checkpoint before steps 5 and 10 and one at the end,
    # then the end
    expected = ["step"] * 5 + ["checkpoint"] + ["step"] * 5 + ["checkpoint"] + ["step"] * 2
    assert recorder.hooks() == [*expected, "checkpoint", "end"]
    steps = [event for hook, event in recorder.events if hook == "step"]
    assert [event.step for event in steps] == list(range(12))
    assert [event.loss for event in steps] == result.history
    assert all(event.total == 12 and event.fit == 0 and event.lr > 0 for event in steps)
    assert all(event.policy is policy for event in steps)
    saved = [event.steps for hook, event in recorder.events if hook == "checkpoint"]
    assert saved == [5, 10, 12]
    (_, end), *_ = [(h, e) for h, e in recorder.events if h == "end"]
    assert (end.steps, end.stopped, end.restarts) == (12, "steps", 0)

    # WHEN the finished fit is resumed from its checkpoint, it trains no more and ends at once
    again = Recorder()
    fit(
        make_policy(spiral, SMALL),
        spiral,
        no_split(spiral),
        config=TINY,
        callbacks=[again],
        progress=False,
        checkpoint=checkpoint,
    )
    assert again.hooks() == ["end"]


def test_a_callback_stops_the_fit_where_it_asks(spiral):
    recorder = Recorder(stop_at=4)
    policy = make_policy(spiral, SMALL)
    result = fit(
        policy, spiral, no_split(spiral), config=TINY, callbacks=[recorder], progress=False
    )
    assert (result.steps, result.stopped) == (5, "callback")
    assert recorder.hooks() == ["step"] * 5 + ["end"]
    assert recorder.events[-1][1].stopped == "callback"


def test_a_restart_is_reported_with_the_diverged_step(spiral, monkeypatch):
    # GIVEN a loss that is NaN at its 4th evaluation
    real, calls = train_module.step_loss, []

    def flaky(*args):
        calls.append(1)
        loss = real(*args)
        return loss * float("nan") if len(calls) == 4 else loss

    monkeypatch.setattr(train_module, "step_loss", flaky)
    recorder = Recorder()
    policy = make_policy(spiral, SMALL)
    fit(policy, spiral, no_split(spiral), config=TINY, callbacks=[recorder], progress=False)
    # THEN step 3 restarts (no step event for it) and the fit goes on to its last step
    restarts = [event for hook, event in recorder.events if hook == "restart"]
    assert [(e.step, e.restarts) for e in restarts] == [(3, 1)]
    assert recorder.hooks()[3] == "restart"
    steps = [event.step for hook, event in recorder.events if hook == "step"]
    assert steps == [0, 1, 2, *range(4, 12)]


def test_fit_many_reports_each_fit_and_matches_fit_through_the_shared_loop(spiral):
    # GIVEN one policy trained by fit and the same by fit_many (a stack of one), in float64
    config = dataclasses.replace(TINY, steps=20, lr=1e-3)
    alone, stacked = make_policy(spiral, SMALL), make_policy(spiral, SMALL)
    expected = fit(alone, spiral, no_split(spiral), config=config, progress=False)
    recorder = Recorder(stop_at=15)
    (result,) = fit_many(
        [stacked], [spiral], [no_split(spiral)], [config], callbacks=[recorder], progress=False
    )
    # THEN the callback stopped it after step 15, and up to there it is fit's, to the rounding
    # of a batched matrix product (tests/test_batched.py)
    assert (result.steps, result.stopped) == (16, "callback")
    assert recorder.hooks() == ["step"] * 16 + ["end"]
    assert result.history == pytest.approx(expected.history[:16], rel=1e-9, abs=0)


def test_fit_many_events_name_their_fit(spiral):
    configs = [dataclasses.replace(TINY, steps=6, seed=seed) for seed in range(2)]
    policies = [make_policy(spiral, SMALL, seed=seed) for seed in range(2)]
    recorder = Recorder()
    fit_many(policies, [spiral] * 2, [no_split(spiral)] * 2, configs, callbacks=[recorder])
    steps = [(e.step, e.fit) for hook, e in recorder.events if hook == "step"]
    assert steps == [(step, fit) for step in range(6) for fit in (0, 1)]
    assert [e.fit for hook, e in recorder.events if hook == "end"] == [0, 1]


def test_fit_restores_the_callers_thread_count(spiral):
    torch.set_num_threads(2)
    try:
        fit(make_policy(spiral, SMALL), spiral, no_split(spiral), config=TINY, progress=False)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(1)
