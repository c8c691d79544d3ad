"""One NeRF training step: the settings (`TrainConfig`), the state it carries (`TrainState`),
the optimiser and its schedule, and the jit-compiled step over a donated state (the loss, the
gradients, the update, the occupancy grid's refresh). `training_run` runs these steps.

Each step's randomness is `fold_in(state.key, state.step)`, so nothing depends on how a run was
split into bursts or resumed.

The images a step trains on and how it draws its batch of rays from them: `training_data`.

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

from signerf_jax import parallel, validation
from signerf_jax.errors import InputError
from signerf_jax.nerf import keypoint_depth, losses, photo_consistency, training_data
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf.capture_choices import capture_default
from signerf_jax.nerf.encoding import level_weights_at
from signerf_jax.nerf.training_data import TrainingData
from signerf_jax.validation import NonNegativeFloat, NonNegativeInt, PositiveFloat, PositiveInt


@dataclasses.dataclass(frozen=True)
class TrainConfig(validation.CheckedFields):
  """Optimisation settings (gin: `TrainConfig.<field>`, scoped per run in an edit).

  Attributes:
    steps: training steps (the learning-rate schedule spans them).
    max_seconds: wall-clock training time budget (None = no limit): training stops there, and
      the learning-rate schedule spans it (`Trainer.progress`).
    learning_rate, final_learning_rate: peak Adam learning rate (after a linear warm-up) and
      the rate at the end of the schedule (exponential decay). None: the capture chooses
      (`capture_choices.with_capture_choices`): SPARSE_OBJECT_LEARNING_RATES for a sparse capture
      of an object on a constant background, LEARNING_RATES otherwise (`capture_default`).
    warmup_steps: linear warm-up length.
    gradient_clip_norm: global-norm gradient clipping.
    adam_eps: Adam's epsilon (tiny, as instant-NGP: most table rows see tiny gradients).
    occupancy_update_every: steps between occupancy-grid refreshes.
    occupancy_warmup_steps: steps before the first refresh (every cell is sampled until then).
      Pruning an untrained field removes cells at random, and a pruned cell gets no samples, so
      no gradient to become dense where the scene needs it.
    interlevel_loss_weight: weight of the proposal loss.
    distortion_loss_weight: weight of mip-NeRF 360's distortion loss (crisper surfaces). None:
      the capture chooses (`capture_choices.with_capture_choices`): SPARSE_DISTORTION_LOSS_WEIGHT
      for a sparse capture of a scene with a background, SPARSE_OBJECT_DISTORTION_LOSS_WEIGHT
      for one of an object on a constant background, DISTORTION_LOSS_WEIGHT otherwise.
    opacity_entropy_weight: weight of a prior pushing each ray's opacity towards 0 or 1
      (`losses.opacity_entropy`; for a model with an edit region, the opacity of the trained
      field inside the region): against the haze a field fitted to views that disagree becomes.
    keypoint_depth_weight: weight of the depth error at triangulated keypoints of the
      training views (`keypoint_depth`, `losses.disparity_error`; models without an edit
      region): depth the photos fix where the photometric loss alone does not find it. None:
      the capture chooses (`capture_choices.with_capture_choices`): SPARSE_KEYPOINT_DEPTH_WEIGHT
      for a sparse capture of a scene with a background, 0 otherwise.
    keypoint_rays: keypoint rays each step.
    photo_consistency_weight: weight of the colour disagreement of each training ray's samples
      with its neighbouring training views (`photo_consistency`; models without an edit
      region): it moves weight from floaters to where the other photos agree. None: the
      capture chooses (`capture_choices.with_capture_choices`): SPARSE_PHOTO_CONSISTENCY_WEIGHT
      for a sparse capture of a scene with a background, 0 otherwise.
    photo_consistency_neighbours: the nearest training views (by camera position) compared.
    photo_consistency_truncation: the largest disagreement a sample counts (mean absolute
      RGB difference in [0, 1]): occlusion and reflections cost no more.
    visual_hull: carve the occupancy grid to the visual hull of the photos' alpha
      (`visual_hull`): cells some transparent pixel's ray crosses stay empty from the first
      step. None: the capture chooses (`capture_choices.with_capture_choices`): photos with alpha
      carve a model with an occupancy grid (and no edit region); False never carves.
    checkpoint_every_steps, checkpoint_every_seconds: checkpoint when either is reached.
    seed: PRNG seed of the run.
  """

  steps: PositiveInt = 5000
  max_seconds: PositiveFloat | None = None
  learning_rate: PositiveFloat | None = None
  final_learning_rate: PositiveFloat | None = None
  warmup_steps: NonNegativeInt = 50
  gradient_clip_norm: PositiveFloat = 1.0
  adam_eps: PositiveFloat = 1e-15
  occupancy_update_every: PositiveInt = 16
  occupancy_warmup_steps: NonNegativeInt = 32
  interlevel_loss_weight: NonNegativeFloat = 1.0
  distortion_loss_weight: NonNegativeFloat | None = None
  opacity_entropy_weight: NonNegativeFloat = 0.0
  keypoint_depth_weight: NonNegativeFloat | None = None
  keypoint_rays: PositiveInt = 256
  photo_consistency_weight: NonNegativeFloat | None = None
  photo_consistency_neighbours: PositiveInt = 4
  photo_consistency_truncation: PositiveFloat = 0.25
  visual_hull: bool | None = None
  checkpoint_every_steps: PositiveInt = 1000
  checkpoint_every_seconds: PositiveFloat = 120.0
  seed: NonNegativeInt = 0


@struct.dataclass
class TrainState:
  """Everything a step reads and writes (donated to the step, so updated in place)."""

  step: jax.Array  # int32 scalar
  variables: dict[str, Any]
  optimizer_state: optax.OptState  # `make_optimizer`'s
  key: jax.Array  # the run's base key; step keys are fold_in(key, step)


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
  peak = capture_default(config, "learning_rate")
  ratio = capture_default(config, "final_learning_rate") / peak
  return peak * warmup * ratio**jnp.clip(progress, 0.0, 1.0)


@dataclasses.dataclass(frozen=True)
class ProgressSchedule:
  """`learning_rate` as an optax stateful schedule (`optax.schedules.StatefulSchedule`): its
  state is the int32 count of updates done (the step), and every update passes the step's
  `progress`. Progress is an input, not a function of the count, because a time budget
  measures it in seconds."""

  config: TrainConfig

  def init(self) -> jax.Array:
    return jnp.zeros([], jnp.int32)

  def update(self, count, **extra_args) -> jax.Array:
    del extra_args
    return optax.safe_increment(count)

  def __call__(self, count, progress=0.0, **extra_args) -> jax.Array:
    del extra_args
    return learning_rate(self.config, count, progress)


def make_optimizer(config: TrainConfig) -> optax.GradientTransformationExtraArgs:
  """Global-norm clipping, Adam's scaling, then the scheduled learning rate (`ProgressSchedule`,
  injected so the state records the rate of the last update). Each update takes the step's
  progress: `update(gradients, state, params, progress=...)`."""
  return optax.chain(
      optax.clip_by_global_norm(config.gradient_clip_norm),
      optax.scale_by_adam(b1=0.9, b2=0.99, eps=config.adam_eps),
      optax.inject_hyperparams(optax.scale_by_learning_rate)(
          learning_rate=ProgressSchedule(config)))


def last_learning_rate(optimizer_state: optax.OptState) -> jax.Array:
  """The float32 learning rate `make_optimizer`'s last update applied."""
  return optimizer_state[-1].hyperparams["learning_rate"]


def upgrade_state_dict(state_dict: dict[str, Any]) -> dict[str, Any]:
  """A checkpoint's state dict (`checkpoints.read`) in the current layout: checkpoints written
  before the learning rate was part of the optimizer hold only clipping's and Adam's states;
  the schedule's state is their update count (the rate is recomputed at the next update)."""
  optimizer_state = state_dict["optimizer_state"]
  if set(optimizer_state) != {"0", "1"}:
    return state_dict
  count = optimizer_state["1"]["count"]
  schedule = {"count": count, "hyperparams": {"learning_rate": np.float32(0.0)},
              "hyperparams_states": {"learning_rate": count}, "inner_state": {}}
  return {**state_dict, "optimizer_state": {**optimizer_state, "2": schedule}}


def apply_gradients(config: TrainConfig, state: TrainState, gradients, progress
                    ) -> tuple[dict[str, Any], optax.OptState]:
  """The variables after one optimiser step on `gradients` at `progress` (float32 scalar in
  [0, 1]; `learning_rate`), and the new optimiser state."""
  params = state.variables["params"]
  updates, optimizer_state = make_optimizer(config).update(
      gradients, state.optimizer_state, params, progress=progress)
  return {**state.variables, "params": optax.apply_updates(params, updates)}, optimizer_state


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
  ray_key, render_key, background_key, keypoint_key = jax.random.split(
      jax.random.fold_in(state.key, state.step), 4)
  rays, target, pixel_weight, background, surroundings, rays_per_pixel = training_data.step_batch(
      model, data, ray_key, background_key)
  seen = rays.shape[0]
  keypoint_distances = None
  if config.keypoint_depth_weight and data.keypoints is not None and surroundings is None:
    rays, background, keypoint_distances = _with_keypoint_rays(model, config, data, keypoint_key,
                                                               rays, background)
  if mesh is not None:
    rays, target, pixel_weight, background, surroundings = jax.lax.with_sharding_constraint(
        (rays, target, pixel_weight, background, surroundings), parallel.batch_sharded(mesh))
  if model.capacity.coarse_to_fine > 0:
    state = state.replace(variables={**state.variables, "level_weights": level_weights_at(
        model.capacity.num_levels, progress, model.capacity.coarse_to_fine)})

  def loss_fn(params):
    outputs, aux = nerf_model.render_rays(model, {**state.variables, "params": params}, rays,
                                          render_key, training=True, background=background,
                                          surroundings=surroundings)
    keypoint_depth_error = None
    if keypoint_distances is not None:
      outputs, aux, keypoint_depth_error = _split_keypoint_rays(model, seen, keypoint_distances,
                                                                outputs, aux)
    ray_weights = jnp.repeat(pixel_weight, rays_per_pixel) * outputs["ray_complete"]
    pixel_rgb = outputs["rgb"].reshape(-1, rays_per_pixel, 3).mean(axis=1)
    pixel_complete = outputs["ray_complete"].reshape(-1, rays_per_pixel).all(axis=1)
    mse = losses.weighted_mse(pixel_rgb, target, pixel_weight * pixel_complete)
    loss = mse + capture_default(config, "distortion_loss_weight") * losses.distortion_loss(
        aux, model.scene.extent, ray_weights)
    if aux["proposals"]:
      loss = loss + config.interlevel_loss_weight * losses.interlevel_loss(
          aux["edges"], aux["weights"], aux["proposals"], ray_weights)
    statistics = {"mse": mse, "samples": aux["samples_evaluated"],
                  "complete_fraction": jnp.mean(outputs["ray_complete"])}
    loss = add_opacity_entropy(config, loss, aux["weights"], ray_weights, statistics)
    loss = add_photo_consistency(config, data, loss, aux, rays, seen, ray_weights, statistics)
    if keypoint_depth_error is not None:
      statistics["keypoint_depth"] = keypoint_depth_error
      loss = loss + config.keypoint_depth_weight * keypoint_depth_error
    statistics["loss"] = loss
    return loss, statistics

  gradients, statistics = jax.grad(loss_fn, has_aux=True)(state.variables["params"])
  variables, optimizer_state = apply_gradients(config, state, gradients, progress)
  statistics["learning_rate"] = last_learning_rate(optimizer_state)
  statistics["psnr"] = -10.0 * jnp.log10(jnp.maximum(statistics.pop("mse"), 1e-10))
  return TrainState(state.step + 1, variables, optimizer_state, state.key), statistics


def _with_keypoint_rays(model: nerf_model.NerfModel, config: TrainConfig, data: TrainingData,
                        key, rays, background):
  """The batch's rays [R] followed by `config.keypoint_rays` rays through keypoints
  (`keypoint_depth.sample_rays`), their backgrounds (None, or [R, 3] followed by the model's
  constant background) and the keypoints' distances [K]. The keypoint rays have no colour
  target, only their depth."""
  keypoint_rays, distances = keypoint_depth.sample_rays(key, data.keypoints, data.cameras,
                                                        config.keypoint_rays)
  rays = jax.tree.map(lambda *parts: jnp.concatenate(parts), rays, keypoint_rays)
  if background is not None:
    background = jnp.concatenate([background, jnp.broadcast_to(
        jnp.asarray(model.background, background.dtype), (config.keypoint_rays, 3))])
  return rays, background, distances


def _split_keypoint_rays(model: nerf_model.NerfModel, seen: int, distances, outputs, aux):
  """`render_rays`' outputs and aux of the batch's first `seen` rays, and the keypoint rays'
  (the rest) `losses.disparity_error` against their known `distances` [K]."""
  keypoints = slice(seen, None)
  error = losses.disparity_error(
      aux["edges"][keypoints], aux["weights"][keypoints], distances,
      model.scene.camera_distance, outputs["ray_complete"][keypoints].astype(jnp.float32))
  # Packed samples are not split by ray: the losses read the batch's from the dense weights.
  per_ray = {name: value for name, value in aux.items()
             if name not in ("samples_evaluated", "packed")}
  outputs, per_ray = jax.tree.map(lambda array: array[:seen], (outputs, per_ray))
  return outputs, {**per_ray, "samples_evaluated": aux["samples_evaluated"]}, error


def add_opacity_entropy(config: TrainConfig, loss, weights, ray_weights, statistics):
  """loss + the opacity prior (`TrainConfig.opacity_entropy_weight`), recorded in statistics
  when it is on. weights: [R, N] compositing weights; ray_weights: [R]."""
  if config.opacity_entropy_weight == 0:
    return loss
  statistics["opacity_entropy"] = losses.opacity_entropy(weights, ray_weights)
  return loss + config.opacity_entropy_weight * statistics["opacity_entropy"]


def add_photo_consistency(config: TrainConfig, data: TrainingData, loss, aux, rays, seen: int,
                          ray_weights, statistics):
  """loss + the samples' colour disagreement with the neighbouring views
  (`TrainConfig.photo_consistency_weight`), recorded in statistics, when it is on (and the
  model has no edit region). aux: `render_rays`' of the batch's first `seen` `rays` (the
  pixels'; keypoint rays follow them); ray_weights: [seen]."""
  if (not config.photo_consistency_weight or data.neighbour_views is None
      or data.region is not None):
    return loss
  statistics["photo_consistency"] = photo_consistency.sample_disagreement(
      aux["edges"], aux["weights"], jax.tree.map(lambda array: array[:seen], rays), data.images,
      data.cameras, data.neighbour_views, ray_weights, config.photo_consistency_truncation)
  return loss + config.photo_consistency_weight * statistics["photo_consistency"]


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
