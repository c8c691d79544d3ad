"""Step 7, updating the NeRF with the edited images: fine-tuning or retraining.

The paper (appendix "Training") fine-tunes the original NeRF for edits, with re-initialised
optimisers and an LPIPS loss for consistency, and trains a new NeRF from scratch for inserted
objects. By default both update only an *edit region* (`FinetuneConfig.edit_region`, see
`nerf.model`): the selection's box, grown by a margin, rendered by the updated field over the
frozen original field everywhere else, so that what the edited views disagree on cannot become
floaters over the background. Retraining is ordinary `nerf.training_run.train` on the edited
dataset (a fresh field, inside the region when there is one). Fine-tuning starts from the original
parameters with a fresh optimiser state and occupancy grid (`train.init_state`) and minimises,
per step,

  L1(render, target) + distortion + interlevel [+ lpips_weight * LPIPS(render, target)]
      [+ TrainConfig.opacity_entropy_weight * binary entropy of each ray's opacity],

L1 because the edited images disagree a little between views (the NeRF should settle on their
median, not their mean). LPIPS compares image structure, so with LPIPS weights the step renders
`rays_per_batch / patch_size^2` square patches instead of scattered rays, and LPIPS sees each
patch as an image (`metrics.lpips`); rays that overflow the sample budget are replaced by their
targets there, so they add no error.

Occupancy grid (bounded scenes): pruning judges a cell by the density the field has there, and
a pruned cell gets no samples, so no gradient to become dense. Inserted content appears where
the original scene was empty, so the cells of the edited region (`region_cells`) are kept
unvisited, i.e. always sampled, throughout fine-tuning; elsewhere pruning works as usual.

`finetune` keeps `training_run.train`'s run-directory contract (model.json, a resumable
checkpoint), so `signerf render` and `signerf eval --run` work on the result.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax import camera, checkpoints, ownership
from signerf_jax.data.dataset import Dataset
from signerf_jax.errors import InputError
from signerf_jax.metrics import lpips
from signerf_jax.nerf import losses, occupancy, train, training_data, training_run
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf.capture_choices import capture_default


@dataclasses.dataclass(frozen=True)
class FinetuneLosses:
  """The static loss settings of a fine-tuning step.

  Attributes:
    lpips_weight: weight of the LPIPS term; 0 disables it (and patch rendering).
    patch_size: side of the rendered patches when LPIPS is on.
  """

  lpips_weight: float = 0.0
  patch_size: int = 32

  @property
  def uses_lpips(self) -> bool:
    return self.lpips_weight > 0


def weighted_l1(predicted, target, weights):
  """sum_r w_r |p_r - t_r|_1 / (3 sum_r w_r): mean absolute error over weighted rays [R, 3]."""
  absolute = jnp.sum(jnp.abs(predicted - target), axis=-1)
  return jnp.sum(weights * absolute) / jnp.maximum(3.0 * jnp.sum(weights), 1e-8)


def random_patches(key, cameras: camera.Cameras, count: int, size: int):
  """`count` random size x size pixel patches over all cameras.

  Returns:
    rays: Rays of shape [count, size, size].
    pixels: (camera_index, row, column), each [count, size, size] int32.
  """
  view_key, row_key, column_key = jax.random.split(key, 3)
  index = jax.random.randint(view_key, (count, 1, 1), 0, cameras.num_cameras)
  top = jax.random.randint(row_key, (count, 1, 1), 0, cameras.height - size + 1)
  left = jax.random.randint(column_key, (count, 1, 1), 0, cameras.width - size + 1)
  offsets = jnp.arange(size, dtype=jnp.int32)
  rows = jnp.broadcast_to(top + offsets[None, :, None], (count, size, size))
  columns = jnp.broadcast_to(left + offsets[None, None, :], (count, size, size))
  index = jnp.broadcast_to(index, (count, size, size))
  return camera.pixel_rays(cameras, index, columns + 0.5, rows + 0.5), (index, rows, columns)


def finetune_step(model: nerf_model.NerfModel, config: train.TrainConfig,
                  loss_settings: FinetuneLosses, state: train.TrainState,
                  data: training_data.TrainingData, progress, lpips_params
                  ) -> tuple[train.TrainState, dict]:
  """One fine-tuning step (pure; see the module docstring for the loss)."""
  ray_key, render_key = jax.random.split(jax.random.fold_in(state.key, state.step))
  if loss_settings.uses_lpips:
    size = loss_settings.patch_size
    count = max(1, model.capacity.rays_per_batch // size**2)
    rays, pixels = random_patches(ray_key, data.cameras, count, size)
    rays, pixels = rays.reshape(-1), tuple(array.reshape(-1) for array in pixels)
    surroundings = None  # A patch reaches beyond the region's pixels: rendered in full.
  else:
    rays, pixels, surroundings = training_data.sample_rays(ray_key, data,
                                                   model.capacity.rays_per_batch)
  target = data.images[pixels]
  pixel_weight = data.pixel_weights[pixels]

  def loss_fn(params):
    outputs, aux = nerf_model.render_rays(model, {**state.variables, "params": params}, rays,
                                          render_key, training=True, surroundings=surroundings)
    ray_weights = pixel_weight * outputs["ray_complete"]
    l1 = weighted_l1(outputs["rgb"], target, ray_weights)
    loss = l1 + capture_default(config, "distortion_loss_weight") * losses.distortion_loss(
        aux, model.scene.extent, ray_weights)
    if aux["proposals"]:
      loss = loss + config.interlevel_loss_weight * losses.interlevel_loss(
          aux["edges"], aux["weights"], aux["proposals"], ray_weights)
    statistics = {"l1": l1, "mse": losses.weighted_mse(outputs["rgb"], target, ray_weights),
                   "samples": aux["samples_evaluated"],
                   "complete_fraction": jnp.mean(outputs["ray_complete"])}
    loss = train.add_opacity_entropy(config, loss, aux["weights"], ray_weights, statistics)
    if loss_settings.uses_lpips:
      patches = (-1, loss_settings.patch_size, loss_settings.patch_size, 3)
      rendered = jnp.where(ray_weights[:, None] > 0, outputs["rgb"], target)
      perceptual = jnp.mean(lpips.lpips_distance(lpips_params, rendered.reshape(patches),
                                                 target.reshape(patches)))
      loss = loss + loss_settings.lpips_weight * perceptual
      statistics["lpips"] = perceptual
    statistics["loss"] = loss
    return loss, statistics

  gradients, statistics = jax.grad(loss_fn, has_aux=True)(state.variables["params"])
  variables, optimizer_state = train.apply_gradients(config, state, gradients, progress)
  statistics["psnr"] = -10.0 * jnp.log10(jnp.maximum(statistics.pop("mse"), 1e-10))
  return train.TrainState(state.step + 1, variables, optimizer_state, state.key), statistics


@functools.lru_cache(maxsize=8)
def _jitted_steps(model: nerf_model.NerfModel, config: train.TrainConfig,
                  loss_settings: FinetuneLosses):
  step_fn = jax.jit(lambda state, data, progress, lpips_params: finetune_step(
      model, config, loss_settings, state, data, progress, lpips_params), donate_argnums=0)
  occupancy_fn = jax.jit(lambda state: train.occupancy_step(model, config, state),
                         donate_argnums=0)
  return step_fn, occupancy_fn


def region_cells(model: nerf_model.NerfModel, bounds) -> jax.Array | None:
  """[R, R, R] bool occupancy cells overlapping the box `bounds` ([2, 3] scene units), or None
  for models without an occupancy grid."""
  if model.capacity.sampler != "occupancy":
    return None
  resolution = model.capacity.occupancy_resolution
  low, high = np.clip(np.asarray(model.to_unit_cube(np.asarray(bounds, np.float32))), 0, 1)
  edges = np.arange(resolution + 1) / resolution
  overlap = [(edges[1:] >= low[axis]) & (edges[:-1] <= high[axis]) for axis in range(3)]
  return jnp.asarray(overlap[0][:, None, None] & overlap[1][None, :, None]
                     & overlap[2][None, None, :])


@jax.jit
def _keep_sampled(state: train.TrainState, cells) -> train.TrainState:
  grid = jnp.where(cells, occupancy.UNVISITED, state.variables["occupancy"])
  return state.replace(variables={**state.variables, "occupancy": grid})


@dataclasses.dataclass
class FinetuneTrainer(training_run.Trainer):
  """`training_run.Trainer` with the fine-tuning step (same loop, checkpoints and progress).

  Attributes:
    loss_settings: LPIPS weight and patch size.
    lpips_params: the LPIPS network's parameters (when it is used).
    editable_cells: occupancy cells kept sampled (`region_cells`), or None.
  """

  loss_settings: FinetuneLosses = FinetuneLosses()
  lpips_params: Any = None
  editable_cells: jax.Array | None = None

  def __post_init__(self):
    super().__post_init__()  # The device mesh and the replicated data and state.
    step_fn, occupancy_fn = _jitted_steps(self.model, self.config, self.loss_settings)
    config, uses_occupancy = self.config, self.model.capacity.sampler == "occupancy"

    def step(state, data, progress):
      step_index = int(state.step)
      if (uses_occupancy and step_index >= config.occupancy_warmup_steps
          and step_index % config.occupancy_update_every == 0):
        state = occupancy_fn(state)
        if self.editable_cells is not None:
          state = _keep_sampled(state, self.editable_cells)
      return step_fn(state, data, progress, self.lpips_params)

    self._step_fn = step


def load_lpips(path: str) -> Any:
  """The LPIPS parameters of a weights file, or None for "" (no LPIPS)."""
  if not path:
    return None
  if not Path(path).is_file():
    raise InputError("LPIPS weights file not found", path, "FinetuneConfig.lpips_weights")
  return lpips.load_lpips_params(path)


def finetune(dataset: Dataset, run_dir: str | os.PathLike, *, model: nerf_model.NerfModel,
             init_variables, config: train.TrainConfig, loss_settings: FinetuneLosses,
             lpips_params=None, edited_bounds=None,
             data_options: dict[str, Any] | None = None,
             progress: bool = True, replay_progress=None) -> FinetuneTrainer:
  """Fine-tunes `init_variables` of `model` on `dataset` into `run_dir` (resumed if it holds a
  checkpoint); a fresh optimiser state, as the paper re-initialises its optimisers.

  Args:
    dataset: the edited training views.
    run_dir: the new run directory.
    model, init_variables: the NeRF to start from (`evaluate.load_run(...)`).
    config: steps, learning rates (gin scope `finetune/TrainConfig`).
    loss_settings: LPIPS weight and patch size.
    lpips_params: `load_lpips(...)` when `loss_settings.uses_lpips`.
    edited_bounds: [2, 3] box around the edited region, kept sampled (see the module docstring).
    data_options: how the data was loaded, recorded in model.json.
    replay_progress: [S] float32 progress per step to train with instead of `config`'s steps
      and time budget (`training_run.train`'s).
  """
  if loss_settings.uses_lpips:
    if lpips_params is None:
      raise InputError("an LPIPS weight needs LPIPS weights", field="FinetuneConfig.lpips_weights")
    size = loss_settings.patch_size
    if not lpips.MIN_IMAGE_SIZE <= size <= min(dataset.height, dataset.width):
      raise InputError(f"must be between {lpips.MIN_IMAGE_SIZE} and the image size "
                       f"{min(dataset.height, dataset.width)}, got {size}",
                       field="FinetuneConfig.patch_size")
  run_dir = Path(run_dir)
  if replay_progress is not None:
    config = dataclasses.replace(config, steps=len(replay_progress), max_seconds=None)
  trainer = FinetuneTrainer(model, config, training_data.TrainingData.from_dataset(dataset),
                            train.init_state(model, config, init_variables),
                            loss_settings=loss_settings, lpips_params=lpips_params,
                            editable_cells=None if edited_bounds is None
                            else region_cells(model, edited_bounds),
                            replay_progress=replay_progress)
  with ownership.claimed(run_dir, ownership.RUN, inputs=(("data", dataset.root),)):
    if checkpoints.has_checkpoint(run_dir):
      trainer.restore(run_dir)
    else:
      training_run.write_model_file(run_dir, model, dataset, data_options)
    trainer.run(run_dir=run_dir, progress=progress)
  return trainer
