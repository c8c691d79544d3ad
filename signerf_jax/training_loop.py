"""The one training loop every trainer runs (the NeRF, its fine-tuning, the shipped model's
stages): steps until a step count or a time budget, a progress bar, checkpoints every so many
steps or seconds and at the end, and a divergence guard.

The caller owns the state and passes two callbacks, each given the training seconds so far (a
schedule may follow them): `advance(seconds)` runs one step and returns its statistics (scalars,
possibly still on the device), `save(seconds)` checkpoints the current state. The
guard reads the loss every `sync_every` steps and always before a checkpoint: a loss that is no
longer finite stops the run with `TrainingDiverged` before the state reaches the checkpoint, so
the last good checkpoint survives and a resumed run starts from it.

Ctrl-C (SIGINT) and SIGTERM stop the loop after the step under way: it checkpoints the steps
since the last checkpoint and raises `TrainingInterrupted`, which names the step reached and
where it was saved (`signerf` reports it in one line and exits with 130 / 143). While the loop
runs in the main thread it handles both signals itself, so a signal never lands inside a step
(whose state and step count would then disagree) or inside a checkpoint write; a second signal
during a step stops it at once (a step that hangs), still checkpointing the steps completed
before it. SIGTERM is handled only when a handler is installed for it (`signerf` installs one
raising `Terminated`): otherwise it keeps its default, killing the process.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import signal
import threading
import time
import types
from typing import Any, Callable, Iterator, Mapping

import tqdm

from signerf_jax.errors import InputError


class TrainingDiverged(InputError):
  """The loss stopped being finite; the checkpoint before it is kept."""


class Terminated(BaseException):
  """SIGTERM arrived: what `signerf`'s SIGTERM handler raises, as Python's SIGINT handler raises
  KeyboardInterrupt (a BaseException too, so no `except Exception` on the way swallows it)."""


# The signals that stop a run, and the exception each raises outside the loop.
STOP_SIGNALS = {signal.SIGINT: KeyboardInterrupt, signal.SIGTERM: Terminated}


def signal_of(error: BaseException) -> signal.Signals:
  """The signal whose exception `error` is (KeyboardInterrupt: SIGINT, Terminated: SIGTERM)."""
  return signal.SIGTERM if isinstance(error, Terminated) else signal.SIGINT


class TrainingInterrupted(BaseException):
  """A signal stopped the training loop; the steps it completed are checkpointed.

  Attributes:
    step: the step reached (the checkpoint's, when `saved`).
    signum: the signal (SIGINT or SIGTERM); `exit_code` is the shell's 128 + signum.
    where: the run (its directory, for a loop with checkpoints).
    saved: whether a checkpoint holds the state at `step` (False: the loop has no checkpoints,
      or was stopped before its first step of a run with none).
  """

  def __init__(self, step: int, signum: int, where: str, saved: bool):
    self.step, self.signum, self.where, self.saved = step, signal.Signals(signum), where, saved
    outcome = (f"; checkpoint saved in {where}; run the same command to resume" if saved
               else ", which no checkpoint holds")
    super().__init__(f"interrupted at step {step}{outcome}")

  @property
  def exit_code(self) -> int:
    return 128 + int(self.signum)


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


class _StopSignals:
  """While active, SIGINT and SIGTERM ask the loop to stop after the step under way instead of
  raising wherever the main thread happens to be. A second one inside `interruptible` (a step)
  raises at once, as without the loop, so a step that hangs can still be stopped; anywhere
  else (reading the statistics, a checkpoint write) it waits too, so a checkpoint is never cut
  between its renames nor the final one skipped.

  Installed only from the main thread (the only one Python runs handlers in, and the only one
  allowed to set them), and for a signal only when its handler is a Python function (SIGINT's
  default raises KeyboardInterrupt; SIGTERM's is the one `signerf` installs): a signal that is
  ignored, or left to kill the process, keeps doing that.

  Attributes:
    signum: the first signal received (None: none).
  """

  def __init__(self):
    self.signum: int | None = None
    self._interruptible = False
    self._previous: dict[int, Any] = {}

  def __enter__(self) -> "_StopSignals":
    if threading.current_thread() is threading.main_thread():
      for signum in STOP_SIGNALS:
        if callable(signal.getsignal(signum)):
          self._previous[signum] = signal.signal(signum, self._handle)
    return self

  def __exit__(self, *exception_info) -> None:
    for signum, handler in self._previous.items():
      signal.signal(signum, handler)

  def _handle(self, signum: int, frame: types.FrameType | None) -> None:
    if self.signum is None or not self._interruptible:
      self.signum = self.signum or signum
      return
    self._previous[signum](signum, frame)

  @contextlib.contextmanager
  def interruptible(self) -> Iterator[None]:
    """Inside, a signal after the first raises (the handler in place before the loop's)."""
    self._interruptible = True
    try:
      yield
    finally:
      self._interruptible = False


def _budget_left(budget: LoopBudget, step: int, seconds_trained: float) -> bool:
  """Whether another step may start: below the step count, the deadline and the time budget."""
  return (step < budget.until_step and time.monotonic() < budget.deadline
          and (budget.max_seconds is None or seconds_trained < budget.max_seconds))


def _show_progress(bar: tqdm.tqdm, step: int, budget: LoopBudget, smoothed_loss: float | None,
                   seconds_trained: float, statistics: dict[str, float]) -> None:
  """Advances the progress bar; every 10 steps it shows the smoothed loss, seconds and PSNR."""
  bar.update(1)
  if (step % 10 == 0 or step == budget.until_step) and smoothed_loss is not None:
    shown = {"loss": f"{smoothed_loss:.4f}", "seconds": f"{seconds_trained:.0f}"}
    if "psnr" in statistics:
      shown["psnr"] = f"{statistics['psnr']:.2f}"
    bar.set_postfix(shown)


def run_loop(advance: Callable[[float], Mapping[str, Any]],
             save: Callable[[float], None] | None,
             budget: LoopBudget, *, step: int, seconds_trained: float = 0.0,
             where: str | os.PathLike = "training", hint: str = "a lower learning rate",
             description: str | None = None, progress: bool = True) -> LoopResult:
  """Runs `advance` until the budget is spent, checkpointing with `save`.

  Args:
    advance: runs one step (given the training seconds before it) and returns its statistics,
      with a scalar "loss"; it updates its state whole or not at all (a KeyboardInterrupt or
      Terminated it raises means the step did not run).
    save: checkpoints the current state (given the training seconds); None: no checkpoints.
    budget: when to stop and checkpoint.
    step, seconds_trained: what was done before (a resumed run's steps and training seconds).
    where, hint, description: the run and the remedy named in a divergence error; the progress
      bar's label.
  Returns: the step reached, the training seconds and the last statistics.
  Raises:
    TrainingDiverged: the loss stopped being finite (the last good checkpoint is kept).
    TrainingInterrupted: SIGINT or SIGTERM (or `advance` raised KeyboardInterrupt or
      Terminated); the steps completed are checkpointed first.
  """
  where, statistics, pending = os.fspath(where), {}, None
  first_step, smoothed_loss = step, None
  last_checkpoint_step, last_checkpoint_time = step, time.perf_counter()
  bar = tqdm.tqdm(total=budget.until_step, initial=step, disable=not progress, unit="step",
                  desc=description, dynamic_ncols=True)
  with _StopSignals() as stop:
    try:
      while stop.signum is None and _budget_left(budget, step, seconds_trained):
        started = time.perf_counter()
        with stop.interruptible():
          pending = advance(seconds_trained)
        step += 1
        if step % budget.sync_every == 0 or step == budget.until_step:
          statistics, pending = _read(pending, step, where, hint), None
          smoothed_loss = statistics["loss"] if smoothed_loss is None else (
              0.9 * smoothed_loss + 0.1 * statistics["loss"])
        seconds_trained += time.perf_counter() - started
        _show_progress(bar, step, budget, smoothed_loss, seconds_trained, statistics)
        if save is not None and _checkpoint_due(budget, step - last_checkpoint_step,
                                                time.perf_counter() - last_checkpoint_time):
          if pending is not None:
            statistics, pending = _read(pending, step, where, hint), None
          save(seconds_trained)
          last_checkpoint_step, last_checkpoint_time = step, time.perf_counter()
    except tuple(STOP_SIGNALS.values()) as error:  # A second signal, or raised by `advance`.
      stop.signum = stop.signum or signal_of(error)
    finally:
      bar.close()
    statistics = statistics if pending is None else _read(pending, step, where, hint)
    # A run that ends saves if it stepped; one interrupted, if it stepped since its last save.
    if save is not None and step > (first_step if stop.signum is None else last_checkpoint_step):
      save(seconds_trained)
      last_checkpoint_step = step
    signum = stop.signum  # Also one that arrived during the final checkpoint.
  if signum is not None:
    raise TrainingInterrupted(step, signum, where,
                              saved=save is not None and last_checkpoint_step == step > 0)
  return LoopResult(step, seconds_trained, statistics)
