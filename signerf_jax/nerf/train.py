"""Training: a jit-compiled step over a donated `TrainState`, checkpointed and resumable.

A run directory holds:
  config.gin          every gin binding in force
  model.json          scene geometry, capacity and where the data came from
  checkpoint.msgpack  the latest TrainState plus step / seconds trained
A resumed run continues exactly as an uninterrupted one: each step's randomness is
`fold_in(state.key, state.step)`, so nothing depends on how the run was split.

Training is data-parallel over a device mesh (default: every device, `parallel.device_mesh`):
each step's ray batch is split over the devices, the state and the images are replicated, and
GSPMD all-reduces the gradients. The batch is the same for any device count, and so are the
results (to float tolerance). With the occupancy sampler, each device evaluates only its own
rays' samples when the device count divides `Capacity.sample_groups`.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from pathlib import Path
from typing import Any, Callable

import gin
import jax
import jax.numpy as jnp
import numpy as np
import optax
import tqdm
from flax import struct
from jax.sharding import Mesh

from signerf_jax import camera, configs, files, parallel
from signerf_jax.data.dataset import Dataset
from signerf_jax.errors import InputError
from signerf_jax.nerf import checkpoint, losses
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf.capacity import Capacity, SceneInfo, derive_capacity
from signerf_jax.nerf.encoding import level_weights_at

MODEL_FILE = "model.json"


@gin.configurable
@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """Optimisation settings.

  Attributes:
    steps: training steps (the learning-rate schedule spans them).
    max_seconds: wall-clock training time budget (None = no limit): training stops there, and
      the learning-rate schedule spans it (`Trainer.progress`).
    learning_rate: peak Adam learning rate (after a linear warm-up).
    pose_learning_rate: peak learning rate of the pose corrections (`Capacity.pose_refinement`;
      same schedule).
    final_learning_rate: learning rate at the end of the schedule (exponential decay).
    warmup_steps: linear warm-up length.
    gradient_clip_norm: global-norm gradient clipping.
    adam_eps: Adam's epsilon (tiny, as instant-NGP: most table rows see tiny gradients).
    occupancy_update_every: steps between occupancy-grid refreshes.
    occupancy_warmup_steps: steps before the first refresh (every cell is sampled until then).
      Pruning an untrained field removes cells at random, and a pruned cell gets no samples, so
      no gradient to become dense where the scene needs it.
    interlevel_loss_weight: weight of the proposal loss.
    distortion_loss_weight: weight of mip-NeRF 360's distortion loss (crisper surfaces).
    checkpoint_every_steps, checkpoint_every_seconds: checkpoint when either is reached.
    seed: PRNG seed of the run.
  """

  steps: int = 5000
  max_seconds: float | None = None
  learning_rate: float = 1e-2
  pose_learning_rate: float = 6e-4
  final_learning_rate: float = 1e-3
  warmup_steps: int = 50
  gradient_clip_norm: float = 1.0
  adam_eps: float = 1e-15
  occupancy_update_every: int = 16
  occupancy_warmup_steps: int = 32
  interlevel_loss_weight: float = 1.0
  distortion_loss_weight: float = 0.002
  checkpoint_every_steps: int = 1000
  checkpoint_every_seconds: float = 120.0
  seed: int = 0


@struct.dataclass
class TrainState:
  """Everything a step reads and writes (donated to the step, so updated in place)."""

  step: jax.Array  # int32 scalar
  variables: dict[str, Any]
  optimizer_state: optax.OptState
  key: jax.Array  # the run's base key; step keys are fold_in(key, step)


@struct.dataclass
class TrainingData:
  """Training images on device (not donated; the same every step).

  Attributes:
    images: [N, H, W, 3] float32.
    cameras: N cameras.
    pixel_weights: [N, H, W] float32 per-pixel loss weights (1 = normal, 0 = ignore).
    alphas: None or [N, H, W] float32 opacity of RGBA images (`Dataset.alphas`).
  """

  images: jax.Array
  cameras: camera.Cameras
  pixel_weights: jax.Array
  alphas: jax.Array | None = None

  @classmethod
  def from_dataset(cls, dataset: Dataset, pixel_weights=None) -> "TrainingData":
    weights = np.ones(dataset.images.shape[:3], np.float32)
    if dataset.masks is not None:
      weights = weights * dataset.masks
    if pixel_weights is not None:
      pixel_weights = np.asarray(pixel_weights, np.float32)
      if pixel_weights.shape != weights.shape:
        raise InputError(f"pixel weights have shape {pixel_weights.shape}, the images "
                         f"{weights.shape}", dataset.root or None, "pixel_weights")
      weights = weights * pixel_weights
    alphas = None if dataset.alphas is None else jnp.asarray(dataset.alphas, jnp.float32)
    return cls(jnp.asarray(dataset.images, jnp.float32),
               jax.tree.map(jnp.asarray, dataset.cameras), jnp.asarray(weights), alphas)


def make_optimizer(config: TrainConfig) -> optax.GradientTransformation:
  """Gradient clipping and Adam's scaling; the step applies `learning_rate` itself, because the
  schedule follows training progress, which a time budget measures in seconds, not steps."""
  return optax.chain(optax.clip_by_global_norm(config.gradient_clip_norm),
                     optax.scale_by_adam(b1=0.9, b2=0.99, eps=config.adam_eps))


def learning_rate(config: TrainConfig, step, progress):
  """The learning rate at `step` and `progress` (traced scalars).

  A linear warm-up from 1% over `warmup_steps`, times an exponential decay from
  `learning_rate` to `final_learning_rate` as progress goes from 0 to 1.

  Args:
    step: int32 steps done.
    progress: float32 in [0, 1], the larger of steps / config.steps and seconds trained /
      config.max_seconds (`Trainer.progress`): with a time budget the schedule spans it.
  """
  warmup = jnp.clip((step + 1) / max(config.warmup_steps, 1), 0.01, 1.0)
  ratio = config.final_learning_rate / config.learning_rate
  return config.learning_rate * warmup * ratio**jnp.clip(progress, 0.0, 1.0)


def apply_gradients(config: TrainConfig, state: TrainState, gradients, progress
                    ) -> tuple[dict[str, Any], optax.OptState]:
  """The parameters after one optimiser step on `gradients`, and the new optimiser state."""
  params = state.variables["params"]
  updates, optimizer_state = make_optimizer(config).update(gradients, state.optimizer_state,
                                                           params)
  rate = learning_rate(config, state.step, progress)
  rates = {name: rate * (config.pose_learning_rate / config.learning_rate
                         if name == nerf_model.POSE_ADJUSTMENTS else 1.0) for name in params}
  params = {name: jax.tree.map(lambda param, update: param - rates[name] * update,
                               params[name], updates[name]) for name in params}
  return {**state.variables, "params": params}, optimizer_state


def init_state(model: nerf_model.NerfModel, config: TrainConfig, init_variables=None
               ) -> TrainState:
  """A fresh state, or one starting from `init_variables` with a new optimizer.

  `init_variables` may hold "params" (fine-tuning starts from them) and, for an edit region,
  "original" (the frozen original scene); what it lacks is freshly initialised. Fine-tuning
  starts from an empty occupancy grid (all cells sampled until the warm-up ends): edited images
  may put content where the old scene was empty, and the old grid would never sample it.
  """
  key = jax.random.PRNGKey(config.seed)
  init_key, run_key = jax.random.split(key)
  variables = nerf_model.init_variables(model, init_key)
  if init_variables is not None:
    given = {name: jax.tree.map(jnp.asarray, init_variables[name])
             for name in ("params", "original") if name in init_variables}
    if "original" in given and model.edit_region is None:
      raise InputError("original-scene variables given for a model without an edit region",
                       field="init_variables")
    variables = {**variables, **given}
  optimizer_state = make_optimizer(config).init(variables["params"])
  return TrainState(jnp.int32(0), variables, optimizer_state, run_key)


def train_step(model: nerf_model.NerfModel, config: TrainConfig, state: TrainState,
               data: TrainingData, progress, mesh: Mesh | None = None
               ) -> tuple[TrainState, dict[str, jax.Array]]:
  """One optimisation step (pure; `make_train_step` jits it with the state donated).

  With a `mesh`, the rays are split over its devices (the batch must divide evenly).
  `progress` (float32 scalar in [0, 1]) places the step in the schedule (`learning_rate`).

  Returns:
    the new state and scalar statistics: loss, psnr (of the batch), complete_fraction (rays
    that fit the sample budget), samples (network evaluations), learning_rate.
  """
  ray_key, render_key, background_key = jax.random.split(
      jax.random.fold_in(state.key, state.step), 3)
  rays, (index, row, column) = camera.random_rays(ray_key, data.cameras,
                                                  model.capacity.rays_per_batch)
  target = data.images[index, row, column]
  pixel_weight = data.pixel_weights[index, row, column]
  background = None
  if data.alphas is not None and model.background is not None:
    # instant-NGP's random backgrounds: where the photo is transparent the target takes a new
    # colour each step, so empty space must stay empty. With the constant background alone,
    # density of that colour in front of it would fit the photos equally well (floaters that
    # hide the object in other views: the sparse-view failure).
    background = jax.random.uniform(background_key, target.shape)
    transparency = (1.0 - data.alphas[index, row, column])[:, None]
    target = target + transparency * (background - model.background)
  if mesh is not None:
    rays, target, pixel_weight, background = jax.lax.with_sharding_constraint(
        (rays, target, pixel_weight, background), parallel.batch_sharded(mesh))
  if model.capacity.coarse_to_fine > 0:
    state = state.replace(variables={**state.variables, "level_weights": level_weights_at(
        model.capacity.num_levels, progress, model.capacity.coarse_to_fine)})

  def loss_fn(params):
    refined = rays
    if model.capacity.pose_refinement:
      refined = camera.refine_rays(rays, params[nerf_model.POSE_ADJUSTMENTS])
    outputs, aux = nerf_model.render_rays(model, {**state.variables, "params": params}, refined,
                                          render_key, training=True, background=background)
    ray_weights = pixel_weight * outputs["ray_complete"]
    mse = losses.weighted_mse(outputs["rgb"], target, ray_weights)
    loss = mse + config.distortion_loss_weight * losses.distortion_loss(
        aux["edges"], aux["weights"], model.scene.extent, ray_weights)
    if aux["proposals"]:
      loss = loss + config.interlevel_loss_weight * losses.interlevel_loss(
          aux["edges"], aux["weights"], aux["proposals"], ray_weights)
    statistics = {"loss": loss, "mse": mse, "samples": aux["samples_evaluated"],
                  "complete_fraction": jnp.mean(outputs["ray_complete"])}
    return loss, statistics

  gradients, statistics = jax.grad(loss_fn, has_aux=True)(state.variables["params"])
  variables, optimizer_state = apply_gradients(config, state, gradients, progress)
  statistics["learning_rate"] = learning_rate(config, state.step, progress)
  statistics["psnr"] = -10.0 * jnp.log10(jnp.maximum(statistics.pop("mse"), 1e-10))
  return TrainState(state.step + 1, variables, optimizer_state, state.key), statistics


def occupancy_step(model: nerf_model.NerfModel, config: TrainConfig, state: TrainState
                   ) -> TrainState:
  """Refreshes the occupancy grid (due every `occupancy_update_every` steps after warm-up).

  A separate jitted function called between steps: inside the step, a `lax.cond` around it made
  every step ~10x slower on CPU (XLA copies the operands of both branches).
  """
  key = jax.random.fold_in(jax.random.fold_in(state.key, state.step), 1)
  update_index = state.step // config.occupancy_update_every
  variables = nerf_model.update_occupancy(model, state.variables, key, update_index)
  return state.replace(variables=variables)


@functools.lru_cache(maxsize=8)
def _jitted_steps(model: nerf_model.NerfModel, config: TrainConfig, mesh: Mesh):
  """The jitted step and occupancy refresh, shared by every Trainer of one (model, config,
  mesh), so that resuming or restarting a run in the same process compiles nothing new.

  State and data are replicated over the mesh, in and out.
  """
  replicated = parallel.replicated(mesh)
  step_fn = jax.jit(lambda state, data, progress: train_step(model, config, state, data,
                                                            progress, mesh),
                    donate_argnums=0, in_shardings=replicated, out_shardings=replicated)
  occupancy_fn = jax.jit(lambda state: occupancy_step(model, config, state), donate_argnums=0,
                         in_shardings=replicated, out_shardings=replicated)
  return step_fn, occupancy_fn


def make_train_step(model: nerf_model.NerfModel, config: TrainConfig, mesh: Mesh
                    ) -> Callable[[TrainState, TrainingData, jax.Array],
                                  tuple[TrainState, dict]]:
  """One training step for this model and config, data-parallel over `mesh`: the occupancy
  refresh when it is due, then `train_step`; both jitted with the state donated."""
  parallel.check_divisible(model.capacity.rays_per_batch, mesh, "Capacity.rays_per_batch")
  step_fn, occupancy_fn = _jitted_steps(model, config, mesh)
  if model.capacity.sampler != "occupancy":
    return step_fn

  def step_with_occupancy(state: TrainState, data: TrainingData, progress):
    step = int(state.step)
    if step >= config.occupancy_warmup_steps and step % config.occupancy_update_every == 0:
      state = occupancy_fn(state)
    return step_fn(state, data, progress)

  return step_with_occupancy


@dataclasses.dataclass
class Trainer:
  """A training run in memory: the model, its jitted step and the state, advanced in bursts.

  `train` below is the usual entry point; benchmarks use a Trainer directly to evaluate between
  bursts without recompiling. `mesh` is the devices the steps run on (None: all of them).
  """

  model: nerf_model.NerfModel
  config: TrainConfig
  data: TrainingData
  state: TrainState
  seconds_trained: float = 0.0
  samples_trained: float = 0.0
  last_statistics: dict[str, float] = dataclasses.field(default_factory=dict)
  mesh: Mesh | None = None

  def __post_init__(self):
    self.mesh = parallel.device_mesh() if self.mesh is None else self.mesh
    self._step_fn = make_train_step(self.model, self.config, self.mesh)
    # Placed once: the step would otherwise copy the images to every device at each call.
    self.data, self.state = parallel.replicate((self.data, self.state), self.mesh)

  @property
  def step(self) -> int:
    return int(self.state.step)

  @property
  def progress(self) -> float:
    """How far through its schedule the run is, in [0, 1]: the larger of the steps done over
    `config.steps` and the seconds trained over `config.max_seconds` (when set)."""
    fractions = [self.step / max(self.config.steps, 1)]
    if self.config.max_seconds:
      fractions.append(self.seconds_trained / self.config.max_seconds)
    return min(1.0, max(fractions))

  def run(self, *, until_step: int | None = None, until_seconds: float | None = None,
          run_dir: str | os.PathLike | None = None, progress: bool = True) -> dict[str, float]:
    """Trains until `until_step` (default: config.steps) or `until_seconds` of total training
    time, checkpointing into `run_dir` (if given) periodically and at the end.

    Returns:
      the last step's statistics (floats).
    """
    until_step = self.config.steps if until_step is None else until_step
    limit = until_seconds if until_seconds is not None else self.config.max_seconds
    statistics: dict[str, float] = {}
    last_checkpoint_step, last_checkpoint_time = self.step, time.perf_counter()
    bar = tqdm.tqdm(total=until_step, initial=self.step, disable=not progress, unit="step",
                    dynamic_ncols=True)
    smoothed_loss = None
    while self.step < until_step and (limit is None or self.seconds_trained < limit):
      started = time.perf_counter()
      self.state, step_statistics = self._step_fn(self.state, self.data,
                                                  jnp.float32(self.progress))
      loss = float(step_statistics["loss"])  # Blocks, so the time below is the step's.
      self.seconds_trained += time.perf_counter() - started
      smoothed_loss = loss if smoothed_loss is None else 0.9 * smoothed_loss + 0.1 * loss
      statistics = {name: float(value) for name, value in step_statistics.items()}
      self.samples_trained += statistics["samples"]
      bar.update(1)
      if self.step % 10 == 0 or self.step == until_step:
        bar.set_postfix(loss=f"{smoothed_loss:.4f}", psnr=f"{statistics['psnr']:.2f}",
                        seconds=f"{self.seconds_trained:.0f}")
      if run_dir is not None and (
          self.step - last_checkpoint_step >= self.config.checkpoint_every_steps or
          time.perf_counter() - last_checkpoint_time >= self.config.checkpoint_every_seconds):
        self.save(run_dir)
        last_checkpoint_step, last_checkpoint_time = self.step, time.perf_counter()
    bar.close()
    if run_dir is not None:
      self.save(run_dir)
    self.last_statistics = statistics or self.last_statistics
    return self.last_statistics

  def save(self, run_dir: str | os.PathLike) -> None:
    checkpoint.save(run_dir, self.state, {"step": self.step,
                                          "seconds_trained": self.seconds_trained,
                                          "samples_trained": self.samples_trained})

  def restore(self, run_dir: str | os.PathLike) -> None:
    """Continues from the checkpoint in `run_dir` (state, seconds and samples trained)."""
    state, metadata = checkpoint.restore(run_dir, self.state)
    # Placed like the fresh state: host arrays would make the first step compile again.
    self.state = parallel.replicate(state, self.mesh)
    self.seconds_trained = float(metadata.get("seconds_trained", 0.0))
    self.samples_trained = float(metadata.get("samples_trained", 0.0))


def write_model_file(run_dir: str | os.PathLike, model: nerf_model.NerfModel,
                     dataset: Dataset, data_options: dict[str, Any] | None = None) -> None:
  files.write_json(Path(run_dir) / MODEL_FILE, {
      "scene": dataclasses.asdict(model.scene),
      "capacity": dataclasses.asdict(model.capacity),
      "edit_region": model.edit_region,
      "dataset": dataset.summary(),
      "data_options": dict(data_options or {}),
  })


def read_model_file(run_dir: str | os.PathLike) -> tuple[nerf_model.NerfModel, dict[str, Any]]:
  """The model of a run and the rest of model.json (dataset summary, data options)."""
  path = Path(run_dir) / MODEL_FILE
  description = files.read_json(path)
  try:
    model = nerf_model.NerfModel(SceneInfo.from_json(description["scene"]),
                                 Capacity.from_json(description["capacity"]),
                                 description.get("edit_region"))
  except (KeyError, TypeError, ValueError, InputError) as error:
    raise InputError(f"malformed model description ({error})", path) from None
  return model, description


def build_model(dataset: Dataset, capacity: Capacity | None = None) -> nerf_model.NerfModel:
  """The model for a dataset, with capacity derived from it unless given."""
  scene = SceneInfo.from_dataset(dataset)
  return nerf_model.NerfModel(scene, capacity or derive_capacity(scene))


def make_trainer(dataset: Dataset, *, model: nerf_model.NerfModel | None = None,
                 config: TrainConfig | None = None, init_variables=None,
                 pixel_weights=None, mesh: Mesh | None = None) -> Trainer:
  """A Trainer at step 0 (fresh, or fine-tuning from `init_variables`), data-parallel over
  `mesh` (default: all devices)."""
  config = config or TrainConfig()
  model = model or build_model(dataset)
  return Trainer(model, config, TrainingData.from_dataset(dataset, pixel_weights),
                 init_state(model, config, init_variables), mesh=mesh)


def train(dataset: Dataset, run_dir: str | os.PathLike, *, init_variables=None,
          steps: int | None = None, max_seconds: float | None = None, pixel_weights=None,
          model: nerf_model.NerfModel | None = None, config: TrainConfig | None = None,
          data_options: dict[str, Any] | None = None, progress: bool = True) -> Trainer:
  """Trains (or resumes, if `run_dir` has a checkpoint) a NeRF on `dataset`.

  Args:
    dataset: training views.
    run_dir: where config.gin, model.json and the checkpoint go.
    init_variables: start from these variables (fine-tuning; e.g. `load_run(...).variables`);
      the model must then be the one they belong to (pass `model`).
    steps, max_seconds: override TrainConfig.steps / max_seconds.
    pixel_weights: optional [N, H, W] per-pixel loss weights (multiplied with dataset.masks).
    model: the architecture (default: derived from the dataset).
    config: training settings (default: gin-configured TrainConfig()).
    data_options: how the data was loaded (root, downscale, ...), recorded for `signerf eval`.
    progress: show a progress bar.
  Returns:
    the Trainer after training (model, state, seconds_trained).
  """
  config = config or TrainConfig()
  overrides = {name: value for name, value in (("steps", steps), ("max_seconds", max_seconds))
               if value is not None}
  config = dataclasses.replace(config, **overrides)
  run_dir = Path(run_dir)
  if checkpoint.has_checkpoint(run_dir):
    saved_model, _ = read_model_file(run_dir)
    if model is not None and model != saved_model:
      raise InputError("the run directory holds a different model", run_dir / MODEL_FILE)
    model = saved_model
  trainer = make_trainer(dataset, model=model, config=config, init_variables=init_variables,
                         pixel_weights=pixel_weights)
  run_dir.mkdir(parents=True, exist_ok=True)
  configs.save_gin_config(run_dir)
  if checkpoint.has_checkpoint(run_dir):
    trainer.restore(run_dir)
  else:
    write_model_file(run_dir, trainer.model, dataset, data_options)
  trainer.run(run_dir=run_dir, progress=progress)
  return trainer
