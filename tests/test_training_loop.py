"""The training loop: stops at its step count or budget, checkpoints by steps and at the end,
and stops a diverged run before its state reaches a checkpoint."""

import math
import time

import numpy as np
import pytest

from signerf_jax import training_loop
from signerf_jax.training_loop import LoopBudget, TrainingDiverged


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
