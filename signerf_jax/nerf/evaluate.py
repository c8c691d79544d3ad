"""Evaluation of a trained model on held-out views: PSNR, SSIM, LPIPS (given its weights),
near-camera floaters, depth error (where the dataset has ground truth) and the generalisation
gap to the training views; and loading a finished run back from its directory."""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import jax
import numpy as np

from signerf_jax import checkpoints
from signerf_jax.data.dataset import Dataset
from signerf_jax.errors import InputError
from signerf_jax.metrics import depth_consistency
from signerf_jax.metrics import image as image_metrics
from signerf_jax.metrics import lpips
from signerf_jax.nerf import render, train, training_run
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf.scene_info import camera_distances

# Near-camera floaters: render weight nearer than this fraction of the scene radius.
NEAR_CAMERA_FRACTION = 0.05
# Training views rendered for the train-view PSNR (evenly spaced; rendering all is slow).
TRAIN_VIEWS_EVALUATED = 16


@dataclasses.dataclass
class TrainedRun:
  """A run directory loaded back: everything needed to render or fine-tune.

  Attributes:
    model: the static architecture.
    variables: {"params", optional "occupancy"} (see `nerf.model`).
    step, seconds_trained: progress when the checkpoint was written.
    description: model.json (scene, capacity, dataset summary, data options).
  """

  model: nerf_model.NerfModel
  variables: dict[str, Any]
  step: int
  seconds_trained: float
  description: dict[str, Any]


def load_run(run_dir: str | os.PathLike) -> TrainedRun:
  """Loads the model and the latest checkpoint of a run directory."""
  model, description = training_run.read_model_file(run_dir)
  # Only the structure is needed: tracing the initialisation is seconds faster than running it.
  template = jax.eval_shape(lambda: train.init_state(model, train.TrainConfig()))
  state, metadata = checkpoints.restore(run_dir, template, train.upgrade_state_dict)
  return TrainedRun(model, state.variables, int(metadata.get("step", int(state.step))),
                    float(metadata.get("seconds_trained", 0.0)), description)


def scene_radius(model: nerf_model.NerfModel, cameras) -> float:
  """The cameras' median distance to the centre of the modelled region (scene units): the
  scale near-camera floaters are measured against."""
  return float(np.median(camera_distances(model.scene.bounds, cameras)))


def evaluate(model: nerf_model.NerfModel, variables, dataset: Dataset,
             chunk_size: int = render.DEFAULT_CHUNK_SIZE, lpips_params=None,
             near_camera_fraction: float = NEAR_CAMERA_FRACTION,
             supersampling: int | None = None
             ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
  """Renders every view of `dataset` and compares it with the images (and depths).

  Args:
    lpips_params: VGG-LPIPS weights (`metrics.lpips.load_lpips_params`); None reports no LPIPS.
    near_camera_fraction: floaters are render weight nearer to the camera than this fraction of
      `scene_radius`.
    supersampling: rays per pixel side, averaged (`render.render_cameras`; None: the model's
      `Capacity.pixel_samples`).
  Returns:
    metrics: psnr, ssim, lpips (means over views; psnr of each view, then averaged, as NeRF
      papers do; lpips None without weights), depth_mae and depth_rmse (z-depth, scene units,
      over pixels with ground truth > 0; None without ground truth), near_camera_weight (the
      share of all render weight nearer than near_camera_fraction * scene_radius to the
      camera: near-camera floaters), num_views, supersampling (the rays per pixel side used),
      depth_consistency (the share of the rendered surface whose median depth the nearest other
      view agrees with, `metrics.depth_consistency`: a depth measure without ground truth;
      None for one view).
    renders: `render.render_cameras`' outputs for the views.
  """
  near_distance = near_camera_fraction * scene_radius(model, dataset.cameras)
  if supersampling is None:
    supersampling = model.capacity.pixel_samples
  renders = render.render_cameras(model, variables, dataset.cameras, chunk_size, near_distance,
                                  supersampling=supersampling, settings=render.HELD_OUT)
  psnrs = [float(image_metrics.psnr_jit(renders["rgb"][i], dataset.images[i]))
           for i in range(dataset.num_images)]
  ssims = [float(image_metrics.ssim_jit(renders["rgb"][i], dataset.images[i]))
           for i in range(dataset.num_images)]
  lpips_values = None if lpips_params is None else [
      float(lpips.lpips_distance(lpips_params, renders["rgb"][i:i + 1],
                                 dataset.images[i:i + 1])[0])
      for i in range(dataset.num_images)]
  metrics: dict[str, Any] = {
      "psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims)),
      "lpips": None if lpips_values is None else float(np.mean(lpips_values)),
      "depth_mae": None, "depth_rmse": None,
      "near_camera_weight": float(np.sum(renders["near_weight"]) /
                                  max(np.sum(renders["accumulation"]), 1e-12)),
      "num_views": dataset.num_images, "supersampling": supersampling,
      "depth_consistency": _depth_consistency(dataset.cameras, renders)}
  if dataset.depths is not None:
    known = dataset.depths > 0
    if not np.any(known):
      raise InputError("ground-truth depth maps are all zero (unknown)", dataset.root or None,
                       "depths")
    error = renders["depth"][known] - dataset.depths[known]
    metrics["depth_mae"] = float(np.mean(np.abs(error)))
    metrics["depth_rmse"] = float(np.sqrt(np.mean(error**2)))
  return metrics, renders


def _depth_consistency(cameras, renders) -> float | None:
  """The share of the views' rendered surface their nearest neighbour agrees with
  (`metrics.depth_consistency`, on the median depth); None for a single view."""
  if cameras.num_cameras < 2:
    return None
  return depth_consistency.depth_consistency(cameras, renders["median_depth"],
                                             renders["accumulation"])["consistent_fraction"]


def training_views(dataset: Dataset, count: int = TRAIN_VIEWS_EVALUATED) -> Dataset:
  """At most `count` of the training views, evenly spaced: what the train-view PSNR uses."""
  if dataset.num_images <= count:
    return dataset
  return dataset.subset(np.round(np.linspace(0, dataset.num_images - 1, count)).astype(int))


def generalisation_report(model: nerf_model.NerfModel, variables, held_out: Dataset,
                          training: Dataset, chunk_size: int = render.DEFAULT_CHUNK_SIZE,
                          lpips_params=None, renders_dir: str | os.PathLike | None = None,
                          supersampling: int | None = None
                          ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
  """Held-out metrics, train-view metrics and the gap between them.

  Args:
    held_out: the held-out views (never trained on).
    training: the training views (`training_views` of them are rendered).
    renders_dir: if given, the held-out renders go there (`render.write_renders`: colour,
      depth as EXR and as a picture, accumulation).
    supersampling: rays per pixel side, averaged (`render.render_cameras`), for both.
  Returns:
    {"held_out": metrics, "train": metrics, "generalisation_gap_db": train - held-out PSNR,
     "appearance": what held-out views use for the per-image appearance code}, and the
    held-out renders (`render.render_cameras`).
  """
  held_out_metrics, renders = evaluate(model, variables, held_out, chunk_size, lpips_params,
                                       supersampling=supersampling)
  train_metrics, _ = evaluate(model, variables, training_views(training), chunk_size,
                              lpips_params, supersampling=supersampling)
  if renders_dir is not None:
    render.write_renders(renders_dir, held_out.image_names, renders)
  return {
      "held_out": held_out_metrics,
      "train": train_metrics,
      "generalisation_gap_db": train_metrics["psnr"] - held_out_metrics["psnr"],
      "appearance": ("held-out views use the mean of the training views' appearance codes"
                     if model.capacity.appearance_embedding else "no appearance codes"),
  }, renders
