"""An edit's NeRF trainings in a process of their own, which keeps the memory XLA frees.

glibc's allocator is set once per process (`signerf_jax.allocator`): keeping freed memory makes
a NeRF training step faster (more steps in a time budget), and the diffusion sampler, the
renders and the compilations of the other stages slower (the one malloc arena they contend
for). An edit does both, so on a CPU its commands leave their own process's allocator alone
and run each stage that trains a NeRF (the original, the fine-tune) in a child process that
keeps freed memory (`training_runner`). The child starts afresh (`spawn`: a fork would inherit
the parent's arenas and threads), runs the stage from the edit directory and the settings under
the parent's claim of the directory (`ownership.joined`), and sends back its summary line or
what stopped it. A signal to the parent (Ctrl-C, or SIGINT /
SIGTERM sent to it alone) is passed on to the child, which checkpoints the steps it completed;
the parent then stops as the child did.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import traceback
from pathlib import Path
from typing import Any

import jax

from signerf_jax import allocator, cli, ownership, training_loop
from signerf_jax.editing import stages
from signerf_jax.editing.project import EditDirectory
from signerf_jax.errors import InputError


def training_runner() -> stages.RunTraining | None:
  """`run_in_training_process` where a child process would keep freed memory and this one does
  not (a CPU, glibc, SIGNERF_KEEP_FREED_MEMORY not 0), in a run of one process (in a run of
  several under `jax.distributed`, every process must take part in each training); else None:
  the trainings run in this process."""
  if allocator.keeps_freed_memory() or not allocator.can_keep_freed_memory():
    return None
  return run_in_training_process if jax.process_count() == 1 else None


def run_in_training_process(stage: stages.Stage, context: stages.EditContext) -> str:
  """Runs `stage` (one that trains a NeRF) in a child process keeping freed memory; returns its
  summary line.

  Raises:
    InputError: the stage found bad input.
    TrainingInterrupted: a signal stopped the training (its steps are checkpointed).
    KeyboardInterrupt, Terminated: a signal stopped the child outside the training loop.
    RuntimeError: the child failed otherwise, or ended without a word.
  """
  spawn = multiprocessing.get_context("spawn")
  receiver, sender = spawn.Pipe(duplex=False)
  child = spawn.Process(
      target=_run_child, name=f"signerf {stage.name}",
      args=(sender, stage.name, str(context.directory.root), context.settings,
            dict(context.keys), context.stages_to_run, context.progress))
  child.start()
  sender.close()  # The child holds the only writing end: once it has ended, `recv` returns.
  stopped_by = _wait(child)
  ownership.refresh(context.directory.root)  # What the child wrote is the edit's.
  try:
    outcome = receiver.recv()
  except EOFError:  # It ended without a word: killed (out of memory?), or Python failed.
    outcome = ("ended", child.exitcode)
  finally:
    receiver.close()
  context.forget_nerf(stage.trains_nerf)  # The child trained it again.
  return _result(stage, outcome, stopped_by)


def _wait(child: multiprocessing.Process) -> BaseException | None:
  """Waits for `child` to end, passing on the signals this process receives meanwhile; returns
  the exception of the first (None: none)."""
  stopped_by = None
  while True:
    try:
      child.join()
      return stopped_by
    except tuple(training_loop.STOP_SIGNALS.values()) as error:
      stopped_by = stopped_by or error
      if child.pid is not None and child.exitcode is None:
        os.kill(child.pid, training_loop.signal_of(error))


def _result(stage: stages.Stage, outcome: tuple[Any, ...], stopped_by: BaseException | None
            ) -> str:
  """The summary the child sent, or what stopped it raised here."""
  kind, *details = outcome
  if kind == "done" and stopped_by is None:
    return details[0]
  if kind == "interrupted":
    raise training_loop.TrainingInterrupted(*details)
  if kind == "input_error":
    raise InputError(*details)
  if stopped_by is not None:
    raise stopped_by
  if kind == "signal":
    raise training_loop.STOP_SIGNALS[details[0]]()
  if kind == "failed":
    raise RuntimeError(f"the {stage.name} stage's training process failed:\n{details[0]}")
  code = details[0]
  how = (f"was killed by {signal.Signals(-code).name}" if code is not None and code < 0 else
         f"ended with exit code {code}")
  raise RuntimeError(f"the {stage.name} stage's training process {how} before it finished; "
                     "run the same command to resume from its last checkpoint")


def _run_child(sender, stage_name: str, directory: str, settings, keys, stages_to_run,
               progress: bool) -> None:
  """The child: keeps freed memory, runs the stage and sends ("done", summary), or what stopped
  it: ("interrupted", step, signum, where, saved), ("input_error", problem, path, field),
  ("signal", signum) or ("failed", traceback)."""
  allocator.keep_freed_memory()  # Before JAX starts its backend, and so its threads.
  signal.signal(signal.SIGTERM, cli.raise_terminated)
  try:
    cli.use_compilation_cache()
    context = stages.EditContext(EditDirectory(Path(directory)), settings, progress, keys,
                                 stages_to_run)
    stage = {stage.name: stage for stage in stages.pipeline_stages(settings)}[stage_name]
    with ownership.joined(directory):  # The parent's claim: it waits meanwhile.
      outcome = ("done", stage.run(context))
  except training_loop.TrainingInterrupted as interruption:
    outcome = ("interrupted", interruption.step, int(interruption.signum), interruption.where,
               interruption.saved)
  except InputError as error:
    outcome = ("input_error", error.problem, error.path, error.field)
  except tuple(training_loop.STOP_SIGNALS.values()) as error:
    outcome = ("signal", training_loop.signal_of(error))
  except Exception:  # pylint: disable=broad-except  (reported by the parent)
    outcome = ("failed", traceback.format_exc())
  sender.send(outcome)
  sender.close()
