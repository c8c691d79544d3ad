"""The loop of one training stage of the default model: its state, train step and checkpoints.

A stage (`stages`) trains its parameters with its loss (`losses`) and settings (`stage_settings`)
in a `TrainState`: step, parameters, their moving average, optimizer state and every metric so
far. `run_stage` runs the compiled train step (`make_train_step`) from the stage's checkpoint
until it is finished or the run's budget is spent (`training_loop.run_loop`).

Determinism and resuming: a step's batch comes from `training_data.step_rng(seed, stage, step)`
and its random numbers from `fold_in(key(seed), step)`, so a step does the same work whenever
it runs. A checkpoint (`save_checkpoint`) is the whole `TrainState`, written by `checkpoints`
(msgpack, no pickle; atomic and checksummed); a resumed run is the uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any, Callable

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from signerf_jax import checkpoints, training_loop
from signerf_jax.default_model.losses import LossFunction, Params
from signerf_jax.default_model.stage_settings import StageSettings
from signerf_jax.errors import InputError


@struct.dataclass
class TrainState:
  """Everything a stage's training carries from step to step (and checkpoints).

  Attributes:
    step: () int32, steps done.
    params: the trained parameters.
    ema_params: their exponential moving average.
    opt_state: the optimizer state.
    history: {metric: [num_steps] float32}, each step's value (NaN for steps not run yet).
    wall_seconds: () float32, training time up to this state (counted at checkpoints).
  """

  step: jax.Array
  params: Params
  ema_params: Params
  opt_state: Any
  history: dict[str, jax.Array]
  wall_seconds: jax.Array


def init_state(params: Params, settings: StageSettings, metric_names) -> TrainState:
  """The state before the first step: `params` and their average, a fresh optimizer state and
  a NaN history of `settings.num_steps` steps for each of `metric_names`."""
  # Copies: the train step donates both trees, which must share no buffer with each other or
  # with the caller's arrays.
  return TrainState(step=jnp.zeros((), jnp.int32), params=jax.tree.map(jnp.array, params),
                    ema_params=jax.tree.map(jnp.array, params),
                    opt_state=settings.optimizer().init(params),
                    history={name: jnp.full((settings.num_steps,), jnp.nan, jnp.float32)
                             for name in metric_names},
                    wall_seconds=jnp.zeros((), jnp.float32))


@functools.lru_cache(maxsize=4)
def make_train_step(loss_fn: LossFunction, settings: StageSettings):
  """A compiled `(state, frozen, batch) -> state` step of `loss_fn(params, frozen, batch, key)`.

  Cached, so runs of a stage with the same loss function and settings share one compilation.
  """
  optimizer = settings.optimizer()
  base_key = jax.random.key(settings.seed)

  def train_step(state: TrainState, frozen: Params, batch: Any) -> TrainState:
    key = jax.random.fold_in(base_key, state.step)
    (loss, metrics), gradients = jax.value_and_grad(loss_fn, has_aux=True)(
        state.params, frozen, batch, key)
    updates, opt_state = optimizer.update(gradients, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)
    step = state.step.astype(jnp.float32)
    decay = jnp.minimum(settings.ema_decay, (1.0 + step) / (10.0 + step))
    ema_params = jax.tree.map(lambda average, new: decay * average + (1.0 - decay) * new,
                              state.ema_params, params)
    metrics = {**metrics, "loss": loss, "gradient_norm": optax.tree.norm(gradients)}
    history = {name: values.at[state.step].set(metrics[name])
               for name, values in state.history.items()}
    return state.replace(step=state.step + 1, params=params, ema_params=ema_params,
                         opt_state=opt_state, history=history)

  return jax.jit(train_step, donate_argnums=0)


def save_checkpoint(directory: str | os.PathLike, state: TrainState) -> None:
  """Writes the whole state to `directory` (`checkpoints.save`: atomic, checksummed)."""
  checkpoints.save(directory, state, {"step": int(state.step)})


def restore_checkpoint(directory: str | os.PathLike, template: TrainState) -> TrainState:
  """The state saved in `directory`, in the structure of `template` (a fresh `init_state`)."""
  state_dict, _ = checkpoints.read(directory)
  path = checkpoints.checkpoint_path(directory)
  try:
    restored = flax.serialization.from_state_dict(template, state_dict)
  except (ValueError, KeyError, TypeError) as error:
    raise InputError(f"not a checkpoint of this stage and configuration ({error})", path) from None
  shapes = lambda tree: jax.tree.map(np.shape, tree)
  if (not isinstance(restored.history, dict) or set(restored.history) != set(template.history)
      or shapes(restored.replace(history={})) != shapes(template.replace(history={}))):
    raise InputError("checkpoint shapes differ from this configuration's", path)
  # The stage's num_steps may have changed since: raised, the history gets NaN for the new steps
  # and training extends from the checkpoint; lowered, the steps done keep their metrics (the
  # stage counts as finished).
  length = max(template.history["loss"].shape[0], int(restored.step))
  restored = restored.replace(history={
      name: np.concatenate([np.asarray(values)[:length],
                            np.full(max(length - len(values), 0), np.nan, np.float32)])
      for name, values in restored.history.items()})
  return jax.tree.map(jnp.asarray, restored)


def stage_finished(directory: str | os.PathLike, settings: StageSettings) -> bool:
  """Whether `directory` holds a checkpoint of all `settings.num_steps` steps."""
  if not checkpoints.has_checkpoint(directory):
    return False
  return int(checkpoints.read(directory)[1]["step"]) >= settings.num_steps


@dataclasses.dataclass(frozen=True)
class RunBudget:
  """When a run stops (then it checkpoints and returns; a later run resumes).

  Attributes:
    deadline: `time.monotonic()` value after which no new step starts.
    max_steps: most steps a stage runs in this run (None: no limit).
    checkpoint_seconds: wall time between checkpoints.
    progress: show progress bars.
  """

  deadline: float = float("inf")
  max_steps: int | None = None
  checkpoint_seconds: float = 300.0
  progress: bool = True


def run_stage(name: str, directory: str | os.PathLike, settings: StageSettings,
              initial_params: Callable[[], Params], frozen: Params, loss_fn: LossFunction,
              make_batch: Callable[[int], Any], metric_names, budget: RunBudget) -> TrainState:
  """Trains one stage from its checkpoint in `directory` (or from scratch) until it is finished
  or the budget's deadline passes; checkpoints along the way and at the end
  (`training_loop.run_loop`: a diverged stage stops with TrainingDiverged, its last good
  checkpoint kept).

  Args:
    name: the stage's name (progress bar).
    initial_params: builds the starting parameters (called only without a checkpoint).
    make_batch: step -> that step's batch.
    metric_names: what the loss function reports (plus "loss" and "gradient_norm").
  Returns:
    The state reached (`int(state.step) == settings.num_steps` when finished).
  """
  template = init_state(initial_params(), settings, metric_names)
  state = (restore_checkpoint(directory, template) if checkpoints.has_checkpoint(directory)
           else template)
  train_step = make_train_step(loss_fn, settings)
  first_step, first_seconds = int(state.step), float(state.wall_seconds)
  step = first_step  # Counted here: reading state.step would wait for the device every step.

  def advance(seconds: float) -> dict[str, jax.Array]:
    del seconds  # The schedule follows steps.
    nonlocal state, step
    state = train_step(state, frozen, make_batch(step))
    step += 1
    return {"loss": state.history["loss"][step - 1]}

  def save(seconds: float) -> None:
    nonlocal state
    state = state.replace(wall_seconds=jnp.float32(first_seconds + seconds))
    save_checkpoint(directory, state)

  last_step = settings.num_steps if budget.max_steps is None else min(
      settings.num_steps, first_step + budget.max_steps)
  training_loop.run_loop(
      advance, save, training_loop.LoopBudget(
          until_step=last_step, deadline=budget.deadline,
          checkpoint_every_seconds=budget.checkpoint_seconds, sync_every=10),
      step=first_step, where=directory, hint=f"a lower {name}_stage.learning_rate",
      description=f"training {name}", progress=budget.progress)
  return state
