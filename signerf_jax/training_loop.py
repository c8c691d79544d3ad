"""The one training loop every trainer runs (the NeRF, its fine-tuning, the shipped model's
stages): steps until a step count or a time budget, a progress bar, checkpoints every so many
steps or seconds and at the end, and a divergence guard.

The caller owns the state and passes two callbacks, each given the training seconds so far (a
schedule may follow them): `advance(seconds)` runs one step and returns its statistics (scalars,
possibly still on the device), `save(seconds)` checkpoints the current state. The
guard reads the loss every `sync_every` steps and always before a checkpoint: a loss that is no
longer finite stops the run with `TrainingDiverged` before the state reaches the checkpoint, so
the last good checkpoint survives and a resumed run starts from it.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from typing import Any, Callable, Mapping

import tqdm

from signerf_jax.errors import InputError


class TrainingDiverged(InputError):
  """The loss stopped being finite; the checkpoint before it is kept."""


@dataclasses.dataclass(frozen=True)
class LoopBudget:
  """When the loop stops and when it checkpoints.

  Attributes:
    until_step: the step count to reach.
    max_seconds: training seconds (summed over resumed runs, checkpoint writes excluded) after
      which no step starts; None: no limit.
    deadline: `time.monotonic()` after which no step starts (this process's wall-clock limit).
    checkpoint_every_steps, checkpoint_every_seconds: checkpoint when either has passed since
      the last checkpoint (None: never by that measure).
    sync_every: read the statistics (blocking on the device) every this many steps; 1 makes
      each step's time exact, which a time budget that drives the schedule needs.
  """

  until_step: int
  max_seconds: float | None = None
  deadline: float = math.inf
  checkpoint_every_steps: int | None = None
  checkpoint_every_seconds: float | None = None
  sync_every: int = 1


@dataclasses.dataclass(frozen=True)
class LoopResult:
  """What a loop run did: the step reached, the training seconds (with earlier runs'), and the
  last statistics read (floats)."""

  step: int
  seconds_trained: float
  statistics: dict[str, float]


def _read(statistics: Mapping[str, Any], step: int, where: str, hint: str) -> dict[str, float]:
  """The statistics as floats; raises TrainingDiverged unless the loss is finite."""
  values = {name: float(value) for name, value in statistics.items()}
  if not math.isfinite(values["loss"]):
    raise TrainingDiverged(
        f"the loss is {values['loss']} after step {step}: training diverged; the last "
        f"checkpoint is kept (resume from it with {hint})", where, "loss")
  return values


def _checkpoint_due(budget: LoopBudget, steps_since: int, seconds_since: float) -> bool:
  return bool((budget.checkpoint_every_steps and steps_since >= budget.checkpoint_every_steps) or
              (budget.checkpoint_every_seconds and seconds_since
               >= budget.checkpoint_every_seconds))


def run_loop(advance: Callable[[float], Mapping[str, Any]],
             save: Callable[[float], None] | None,
             budget: LoopBudget, *, step: int, seconds_trained: float = 0.0,
             where: str | os.PathLike = "training", hint: str = "a lower learning rate",
             description: str | None = None, progress: bool = True) -> LoopResult:
  """Runs `advance` until the budget is spent, checkpointing with `save`.

  Args:
    advance: runs one step (given the training seconds before it); returns its statistics,
      with a scalar "loss".
    save: writes a checkpoint of the current state (given the training seconds; None: no
      checkpoints).
    budget: when to stop and checkpoint.
    step: the steps done before (a resumed run's).
    seconds_trained: the training seconds done before.
    where, hint: name the run and the remedy in a divergence error.
    description: the progress bar's label.
  Returns:
    The step reached, the training seconds and the last statistics.
  Raises:
    TrainingDiverged: the loss stopped being finite (nothing after the last good checkpoint is
      saved).
  """
  where = os.fspath(where)
  statistics: dict[str, float] = {}
  pending: Mapping[str, Any] | None = None
  first_step, smoothed_loss = step, None
  last_checkpoint_step, last_checkpoint_time = step, time.perf_counter()
  bar = tqdm.tqdm(total=budget.until_step, initial=step, disable=not progress, unit="step",
                  desc=description, dynamic_ncols=True)
  while (step < budget.until_step and time.monotonic() < budget.deadline
         and (budget.max_seconds is None or seconds_trained < budget.max_seconds)):
    started = time.perf_counter()
    pending = advance(seconds_trained)
    step += 1
    if step % budget.sync_every == 0 or step == budget.until_step:
      statistics, pending = _read(pending, step, where, hint), None
      loss = statistics["loss"]
      smoothed_loss = loss if smoothed_loss is None else 0.9 * smoothed_loss + 0.1 * loss
    seconds_trained += time.perf_counter() - started
    bar.update(1)
    if (step % 10 == 0 or step == budget.until_step) and smoothed_loss is not None:
      shown = {"loss": f"{smoothed_loss:.4f}", "seconds": f"{seconds_trained:.0f}"}
      if "psnr" in statistics:
        shown["psnr"] = f"{statistics['psnr']:.2f}"
      bar.set_postfix(shown)
    if save is not None and _checkpoint_due(budget, step - last_checkpoint_step,
                                            time.perf_counter() - last_checkpoint_time):
      if pending is not None:
        statistics, pending = _read(pending, step, where, hint), None
      save(seconds_trained)
      last_checkpoint_step, last_checkpoint_time = step, time.perf_counter()
  bar.close()
  if pending is not None:
    statistics = _read(pending, step, where, hint)
  if save is not None and step > first_step:
    save(seconds_trained)
  return LoopResult(step, seconds_trained, statistics)
