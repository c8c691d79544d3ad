"""The training loop: stops at its step count or budget, checkpoints by steps and at the end,
stops a diverged run before its state reaches a checkpoint, and on SIGINT / SIGTERM checkpoints
the steps done and reports the step."""

import math
import signal
import time

import numpy as np
import pytest

from signerf_jax import training_loop
from signerf_jax.training_loop import LoopBudget, TrainingDiverged, TrainingInterrupted


class FakeRun:
  """A state that counts steps; its loss turns `bad` (nan or inf) from step `bad_from` on."""

  def __init__(self, bad_from=None, bad=math.nan):
    self.step, self.saved = 0, []
    self.bad_from, self.bad = bad_from, bad

  def advance(self, seconds):
    assert seconds >= 0
    self.step += 1
    diverged = self.bad_from is not None and self.step >= self.bad_from
    # Device scalars, as a jitted step returns them.
    return {"loss": np.float32(self.bad if diverged else 1.0 / self.step), "psnr": np.float32(20)}

  def save(self, seconds):
    assert seconds >= 0
    self.saved.append(self.step)


def test_runs_to_its_step_count_and_checkpoints_by_steps_and_at_the_end():
  run = FakeRun()
  result = training_loop.run_loop(run.advance, run.save,
                                  LoopBudget(until_step=10, checkpoint_every_steps=4),
                                  step=0, progress=False)
  assert (result.step, run.step) == (10, 10)
  assert run.saved == [4, 8, 10]
  assert result.statistics["loss"] == pytest.approx(0.1)


def test_a_resumed_run_continues_from_its_step_and_seconds():
  run = FakeRun()
  run.step = 7
  result = training_loop.run_loop(run.advance, run.save, LoopBudget(until_step=9), step=7,
                                  seconds_trained=100.0, progress=False)
  assert result.step == 9 and result.seconds_trained >= 100.0
  assert run.saved == [9]


@pytest.mark.parametrize("budget", [LoopBudget(until_step=5, max_seconds=10.0),
                                    LoopBudget(until_step=5, deadline=time.monotonic() - 1)],
                         ids=["seconds_spent", "deadline_passed"])
def test_a_spent_time_budget_runs_no_step_and_writes_nothing(budget):
  run = FakeRun()
  result = training_loop.run_loop(run.advance, run.save, budget, step=0, seconds_trained=10.0,
                                  progress=False)
  assert result.step == 0 and run.step == 0 and run.saved == []


@pytest.mark.parametrize("bad", [math.nan, math.inf])
@pytest.mark.parametrize("sync_every", [1, 5])
def test_a_diverged_run_stops_before_its_state_is_checkpointed(bad, sync_every):
  run = FakeRun(bad_from=4, bad=bad)
  with pytest.raises(TrainingDiverged, match="after step [45].*last checkpoint is kept") as error:
    training_loop.run_loop(run.advance, run.save,
                           LoopBudget(until_step=20, checkpoint_every_steps=3,
                                      sync_every=sync_every),
                           step=0, where="runs/lego", progress=False)
  assert run.saved == [3]  # The checkpoint at step 3 (finite loss) only.
  assert error.value.path == "runs/lego" and error.value.field == "loss"


def test_statistics_read_every_few_steps_are_still_read_at_the_end():
  run = FakeRun()
  result = training_loop.run_loop(run.advance, None, LoopBudget(until_step=7, sync_every=5),
                                  step=0, progress=False)
  assert result.statistics["loss"] == pytest.approx(1 / 7)


class InterruptedRun(FakeRun):
  """A FakeRun whose step `at` raises `error` before changing its state (what a Ctrl-C inside
  the step raises), or whose steps and saves send themselves signals (`signals_in_step`,
  `signals_in_save`: {step: [signals]})."""

  def __init__(self, at=None, error=KeyboardInterrupt, signals_in_step=None,
               signals_in_save=None):
    super().__init__()
    self.at, self.error = at, error
    self.signals_in_step, self.signals_in_save = signals_in_step or {}, signals_in_save or {}

  def advance(self, seconds):
    if self.step + 1 == self.at:
      raise self.error()
    for signum in self.signals_in_step.get(self.step + 1, ()):
      signal.raise_signal(signum)  # Handled before the next bytecode, inside the step.
    return super().advance(seconds)

  def save(self, seconds):
    for signum in self.signals_in_save.get(self.step, ()):
      signal.raise_signal(signum)
    super().save(seconds)


@pytest.fixture
def sigterm_raises_terminated():
  """SIGTERM raises Terminated, as under `signerf` (cli.main installs that handler)."""
  def raise_terminated(signum, frame):
    raise training_loop.Terminated()
  previous = signal.signal(signal.SIGTERM, raise_terminated)
  yield
  signal.signal(signal.SIGTERM, previous)


@pytest.mark.parametrize("error,exit_code", [(KeyboardInterrupt, 130),
                                             (training_loop.Terminated, 143)])
def test_an_interrupted_step_checkpoints_the_steps_before_it_and_reports_their_count(error,
                                                                                    exit_code):
  run = InterruptedRun(at=7, error=error)
  with pytest.raises(TrainingInterrupted) as interrupted:
    training_loop.run_loop(run.advance, run.save,
                           LoopBudget(until_step=20, checkpoint_every_steps=4),
                           step=0, where="runs/lego", progress=False)
  assert run.step == 6 and run.saved == [4, 6]  # Steps 5 and 6 were not lost.
  assert interrupted.value.step == 6 and interrupted.value.saved
  assert interrupted.value.exit_code == exit_code
  assert str(interrupted.value) == ("interrupted at step 6; checkpoint saved in runs/lego; run "
                                    "the same command to resume")


def test_an_interrupt_right_after_a_checkpoint_writes_no_other():
  run = InterruptedRun(at=5)
  with pytest.raises(TrainingInterrupted) as interrupted:
    training_loop.run_loop(run.advance, run.save,
                           LoopBudget(until_step=20, checkpoint_every_steps=4), step=0,
                           progress=False)
  assert run.saved == [4] and interrupted.value.step == 4 and interrupted.value.saved


def test_an_interrupt_before_the_first_step_of_a_fresh_run_saves_nothing():
  run = InterruptedRun(at=1)
  with pytest.raises(TrainingInterrupted, match="at step 0, which no checkpoint holds") as error:
    training_loop.run_loop(run.advance, run.save, LoopBudget(until_step=20), step=0,
                           progress=False)
  assert run.saved == [] and not error.value.saved


def test_an_interrupted_loop_without_checkpoints_reports_its_step():
  run = InterruptedRun(at=4)
  with pytest.raises(TrainingInterrupted, match="at step 3, which no checkpoint holds"):
    training_loop.run_loop(run.advance, None, LoopBudget(until_step=20), step=0, progress=False)


@pytest.mark.parametrize("signum,exit_code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_during_a_step_lets_it_finish_then_checkpoints_it(sigterm_raises_terminated,
                                                                  signum, exit_code):
  # Raised inside the step, a KeyboardInterrupt would leave a state and a step count that
  # disagree (the NeRF trainer assigns its state, then reads the statistics): the loop takes
  # the signal and stops after the step.
  run = InterruptedRun(signals_in_step={3: [signum]})
  with pytest.raises(TrainingInterrupted) as interrupted:
    training_loop.run_loop(run.advance, run.save, LoopBudget(until_step=20), step=0,
                           progress=False)
  assert run.step == 3 and run.saved == [3]
  assert interrupted.value.step == 3 and interrupted.value.exit_code == exit_code
  assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # Restored.


def test_a_second_signal_stops_a_step_at_once_and_keeps_the_steps_before_it():
  run = InterruptedRun(signals_in_step={3: [signal.SIGINT, signal.SIGINT]})
  with pytest.raises(TrainingInterrupted) as interrupted:
    training_loop.run_loop(run.advance, run.save, LoopBudget(until_step=20), step=0,
                           progress=False)
  assert run.step == 2 and run.saved == [2] and interrupted.value.step == 2


def test_signals_during_a_checkpoint_write_wait_until_it_is_written(sigterm_raises_terminated):
  # Two signals (the second would stop a step at once) inside the periodic checkpoint at step
  # 4: the write completes, then the run stops.
  run = InterruptedRun(signals_in_save={4: [signal.SIGTERM, signal.SIGINT]})
  with pytest.raises(TrainingInterrupted) as interrupted:
    training_loop.run_loop(run.advance, run.save,
                           LoopBudget(until_step=20, checkpoint_every_steps=4), step=0,
                           progress=False)
  assert run.saved == [4] and interrupted.value.step == 4
  assert interrupted.value.exit_code == 143


def test_a_signal_during_the_final_checkpoint_is_reported_after_it():
  run = InterruptedRun(signals_in_save={5: [signal.SIGINT, signal.SIGINT]})
  with pytest.raises(TrainingInterrupted) as interrupted:
    training_loop.run_loop(run.advance, run.save, LoopBudget(until_step=5), step=0,
                           progress=False)
  assert run.saved == [5] and interrupted.value.step == 5 and interrupted.value.saved


def test_sigterm_keeps_its_default_without_a_handler_and_handlers_are_restored():
  seen = []

  def advance(seconds):
    seen.append((signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)))
    return {"loss": 1.0}

  assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
  training_loop.run_loop(advance, None, LoopBudget(until_step=2), step=0, progress=False)
  sigint_handler, sigterm_handler = seen[0]
  assert sigint_handler is not signal.default_int_handler  # The loop's, during the steps.
  assert sigterm_handler == signal.SIG_DFL  # A SIGTERM still kills a library caller.
  assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
  assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
