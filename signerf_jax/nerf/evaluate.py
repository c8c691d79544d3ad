"""Evaluation of a trained model on held-out views: PSNR, SSIM and (where the dataset has ground
truth) depth error; and loading a finished run back from its directory."""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import numpy as np

from signerf_jax.data.dataset import Dataset
from signerf_jax.errors import InputError
from signerf_jax.metrics import image as image_metrics
from signerf_jax.nerf import checkpoint, render, train
from signerf_jax.nerf import model as nerf_model


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
  model, description = train.read_model_file(run_dir)
  config = train.TrainConfig()
  template = train.init_state(model, config)
  state, metadata = checkpoint.restore(run_dir, template)
  return TrainedRun(model, state.variables, int(metadata.get("step", int(state.step))),
                    float(metadata.get("seconds_trained", 0.0)), description)


def evaluate(model: nerf_model.NerfModel, variables, dataset: Dataset,
             chunk_size: int = 4096) -> tuple[dict[str, float], dict[str, np.ndarray]]:
  """Renders every view of `dataset` and compares it with the images (and depths).

  Returns:
    metrics: psnr, ssim (means over views; psnr of each view, then averaged, as NeRF papers do),
      depth_mae and depth_rmse (z-depth, scene units, over pixels with ground truth > 0; None
      without ground truth), num_views.
    renders: `render.render_cameras`' outputs for the views.
  """
  renders = render.render_cameras(model, variables, dataset.cameras, chunk_size)
  psnrs = [float(image_metrics.psnr_jit(renders["rgb"][i], dataset.images[i]))
           for i in range(dataset.num_images)]
  ssims = [float(image_metrics.ssim_jit(renders["rgb"][i], dataset.images[i]))
           for i in range(dataset.num_images)]
  metrics: dict[str, Any] = {"psnr": float(np.mean(psnrs)), "ssim": float(np.mean(ssims)),
                             "depth_mae": None, "depth_rmse": None,
                             "num_views": dataset.num_images}
  if dataset.depths is not None:
    known = dataset.depths > 0
    if not np.any(known):
      raise InputError("ground-truth depth maps are all zero (unknown)", dataset.root or None,
                       "depths")
    error = renders["depth"][known] - dataset.depths[known]
    metrics["depth_mae"] = float(np.mean(np.abs(error)))
    metrics["depth_rmse"] = float(np.sqrt(np.mean(error**2)))
  return metrics, renders
