"""One NeRF training step: the settings (`TrainConfig`), the state it carries (`TrainState`),
the optimiser and its schedule, and the jit-compiled step over a donated state (the loss, the
gradients, the update, the occupancy grid's refresh). `training_run` runs these steps.

Each step's randomness is `fold_in(state.key, state.step)`, so nothing depends on how a run was
split into bursts or resumed.

A model with an edit region trains only on the pixels whose rays cross the region (`RegionRays`):
elsewhere it renders the frozen original exactly, so those pixels have no gradient, and spending
the batch on them would waste most of it (an object filling a tenth of the frames leaves nine
tenths of a uniform batch idle). The original's render around the region is computed once for
each of these rays, so a step evaluates the trained field alone.

Training is data-parallel over a device mesh (default: every device, `parallel.device_mesh`):
each step's ray batch is split over the devices, the state and the images are replicated, and
GSPMD all-reduces the gradients. The batch is the same for any device count, and so are the
results (to float tolerance). With the occupancy sampler, each device evaluates only its own
rays' samples when the device count divides `Capacity.sample_groups`.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax.sharding import Mesh

from signerf_jax import camera, parallel, validation
from signerf_jax.data.dataset import Dataset
from signerf_jax.errors import InputError
from signerf_jax.nerf import losses
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf.encoding import level_weights_at
from signerf_jax.validation import NonNegativeFloat, NonNegativeInt, PositiveFloat, PositiveInt


@dataclasses.dataclass(frozen=True)
class TrainConfig(validation.CheckedFields):
  """Optimisation settings (gin: `TrainConfig.<field>`, scoped per run in an edit).

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
    opacity_entropy_weight: weight of a prior pushing each ray's opacity towards 0 or 1
      (`losses.opacity_entropy`; for a model with an edit region, the opacity of the trained
      field inside the region): against the haze a field fitted to views that disagree becomes.
    checkpoint_every_steps, checkpoint_every_seconds: checkpoint when either is reached.
    seed: PRNG seed of the run.
  """

  steps: PositiveInt = 5000
  max_seconds: PositiveFloat | None = None
  learning_rate: PositiveFloat = 1e-2
  pose_learning_rate: NonNegativeFloat = 6e-4
  final_learning_rate: PositiveFloat = 1e-3
  warmup_steps: NonNegativeInt = 50
  gradient_clip_norm: PositiveFloat = 1.0
  adam_eps: PositiveFloat = 1e-15
  occupancy_update_every: PositiveInt = 16
  occupancy_warmup_steps: NonNegativeInt = 32
  interlevel_loss_weight: NonNegativeFloat = 1.0
  distortion_loss_weight: NonNegativeFloat = 0.002
  opacity_entropy_weight: NonNegativeFloat = 0.0
  checkpoint_every_steps: PositiveInt = 1000
  checkpoint_every_seconds: PositiveFloat = 120.0
  seed: NonNegativeInt = 0


@struct.dataclass
class TrainState:
  """Everything a step reads and writes (donated to the step, so updated in place)."""

  step: jax.Array  # int32 scalar
  variables: dict[str, Any]
  optimizer_state: optax.OptState
  key: jax.Array  # the run's base key; step keys are fold_in(key, step)


@struct.dataclass
class RegionRays:
  """The training pixels whose rays cross a model's edit region, with the frozen original's
  render around the region on each (`with_region_rays`).

  Attributes:
    pixels: [P] int32 flat indices into the images' [N, H, W].
    surroundings: `nerf_model.RegionSurroundings` of shape [P].
  """

  pixels: jax.Array
  surroundings: nerf_model.RegionSurroundings


@struct.dataclass
class TrainingData:
  """Training images on device (not donated; the same every step).

  Attributes:
    images: [N, H, W, 3] float32.
    cameras: N cameras.
    pixel_weights: [N, H, W] float32 per-pixel loss weights (1 = normal, 0 = ignore).
    alphas: None or [N, H, W] float32 opacity of RGBA images (`Dataset.alphas`).
    region: for a model with an edit region, the only pixels a step samples (`RegionRays`).
  """

  images: jax.Array
  cameras: camera.Cameras
  pixel_weights: jax.Array
  alphas: jax.Array | None = None
  region: RegionRays | None = None

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


def _pixel_rays(model: nerf_model.NerfModel, variables, cameras: camera.Cameras,
                image_shape: tuple[int, int, int], flat_pixels) -> camera.Rays:
  """The rays through `flat_pixels` [C] (indices into [N, H, W]) as the original NeRF saw them
  (its pose corrections applied)."""
  index, row, column = jnp.unravel_index(flat_pixels, image_shape)
  rays = camera.pixel_rays(cameras, index, column + 0.5, row + 0.5)
  if model.capacity.pose_refinement:
    rays = camera.refine_rays(rays, variables["original"]["params"][nerf_model.POSE_ADJUSTMENTS])
  return rays


@functools.partial(jax.jit, static_argnums=(0, 3))
def _crossing_chunk(model, variables, cameras, image_shape, flat_pixels):
  return nerf_model.crosses_region(
      model, _pixel_rays(model, variables, cameras, image_shape, flat_pixels))


@functools.partial(jax.jit, static_argnums=(0, 3))
def _surroundings_chunk(model, variables, cameras, image_shape, flat_pixels):
  return nerf_model.region_surroundings(
      model, variables, _pixel_rays(model, variables, cameras, image_shape, flat_pixels))


def _in_chunks(function, flat_pixels: np.ndarray, chunk_size: int):
  """`function(chunk)` over fixed-size chunks of `flat_pixels` [P] (the last one padded, so one
  compilation serves all), concatenated into numpy arrays [P, ...]."""
  outputs = []
  for start in range(0, len(flat_pixels), chunk_size):
    chunk = flat_pixels[start:start + chunk_size]
    result = function(np.pad(chunk, (0, chunk_size - len(chunk)), mode="edge"))
    outputs.append(jax.tree.map(lambda array: np.asarray(array)[:len(chunk)], result))
  return jax.tree.map(lambda *arrays: np.concatenate(arrays), *outputs)


def with_region_rays(data: TrainingData, model: nerf_model.NerfModel, variables,
                     chunk_size: int = 8192) -> TrainingData:
  """`data` with its `RegionRays` when `model` has an edit region (`variables` hold the
  original's): every pixel of non-zero weight whose ray crosses the region, with the original's
  render around the region (the only rays rendered: a box test finds them first)."""
  if model.edit_region is None or data.region is not None:
    return data
  image_shape = tuple(data.pixel_weights.shape)
  weighted = np.flatnonzero(np.asarray(data.pixel_weights).reshape(-1) > 0).astype(np.int32)
  inputs = (model, variables, data.cameras, image_shape)
  crossing = (_in_chunks(functools.partial(_crossing_chunk, *inputs), weighted, 16 * chunk_size)
              if len(weighted) else np.zeros(0, bool))
  pixels = weighted[crossing]
  if not len(pixels):
    raise InputError(f"no training pixel sees the edit region {model.edit_region}",
                     field="edit_region")
  surroundings = _in_chunks(functools.partial(_surroundings_chunk, *inputs), pixels, chunk_size)
  return data.replace(region=RegionRays(jnp.asarray(pixels), jax.tree.map(jnp.asarray,
                                                                          surroundings)))


def sample_rays(key, data: TrainingData, batch_size: int):
  """A uniform random batch of training pixels' rays: over every pixel, or over the region's.

  Returns:
    rays: Rays [batch_size].
    pixels: (camera_index, row, column), each [batch_size] int32.
    surroundings: the region's `RegionSurroundings` [batch_size], or None.
  """
  if data.region is None:
    rays, pixels = camera.random_rays(key, data.cameras, batch_size)
    return rays, pixels, None
  choice = jax.random.randint(key, (batch_size,), 0, data.region.pixels.shape[0])
  pixels = jnp.unravel_index(data.region.pixels[choice], data.pixel_weights.shape)
  rays = camera.pixel_rays(data.cameras, pixels[0], pixels[2] + 0.5, pixels[1] + 0.5)
  return rays, pixels, jax.tree.map(lambda array: array[choice], data.region.surroundings)


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
  rays, (index, row, column), surroundings = sample_rays(ray_key, data,
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
    rays, target, pixel_weight, background, surroundings = jax.lax.with_sharding_constraint(
        (rays, target, pixel_weight, background, surroundings), parallel.batch_sharded(mesh))
  if model.capacity.coarse_to_fine > 0:
    state = state.replace(variables={**state.variables, "level_weights": level_weights_at(
        model.capacity.num_levels, progress, model.capacity.coarse_to_fine)})

  def loss_fn(params):
    refined = rays
    if model.capacity.pose_refinement:
      refined = camera.refine_rays(rays, params[nerf_model.POSE_ADJUSTMENTS])
    outputs, aux = nerf_model.render_rays(model, {**state.variables, "params": params}, refined,
                                          render_key, training=True, background=background,
                                          surroundings=surroundings)
    ray_weights = pixel_weight * outputs["ray_complete"]
    mse = losses.weighted_mse(outputs["rgb"], target, ray_weights)
    loss = mse + config.distortion_loss_weight * losses.distortion_loss(
        aux["edges"], aux["weights"], model.scene.extent, ray_weights)
    if aux["proposals"]:
      loss = loss + config.interlevel_loss_weight * losses.interlevel_loss(
          aux["edges"], aux["weights"], aux["proposals"], ray_weights)
    statistics = {"mse": mse, "samples": aux["samples_evaluated"],
                  "complete_fraction": jnp.mean(outputs["ray_complete"])}
    loss = add_opacity_entropy(config, loss, aux["weights"], ray_weights, statistics)
    statistics["loss"] = loss
    return loss, statistics

  gradients, statistics = jax.grad(loss_fn, has_aux=True)(state.variables["params"])
  variables, optimizer_state = apply_gradients(config, state, gradients, progress)
  statistics["learning_rate"] = learning_rate(config, state.step, progress)
  statistics["psnr"] = -10.0 * jnp.log10(jnp.maximum(statistics.pop("mse"), 1e-10))
  return TrainState(state.step + 1, variables, optimizer_state, state.key), statistics


def add_opacity_entropy(config: TrainConfig, loss, weights, ray_weights, statistics):
  """loss + the opacity prior (`TrainConfig.opacity_entropy_weight`), recorded in statistics
  when it is on. weights: [R, N] compositing weights; ray_weights: [R]."""
  if config.opacity_entropy_weight == 0:
    return loss
  statistics["opacity_entropy"] = losses.opacity_entropy(weights, ray_weights)
  return loss + config.opacity_entropy_weight * statistics["opacity_entropy"]


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
