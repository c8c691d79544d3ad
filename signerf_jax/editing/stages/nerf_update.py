"""The finetune stage (paper, Sec. 3 step 7): the NeRF learns the edited dataset, fine-tuned from
the original (the paper's choice for edits) or retrained from scratch (its choice for inserted
objects); with an edit region only inside the selection's grown box, over the frozen original
NeRF elsewhere (`FinetuneConfig.edit_region`)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from signerf_jax.data import load_dataset
from signerf_jax.editing import finetune
from signerf_jax.editing.config import as_json, training_key
from signerf_jax.editing.stages.context import EditContext
from signerf_jax.nerf import training_run


def update_method(context: EditContext, iteration: int) -> str:
  """"finetune" or "retrain"; a second iteration always fine-tunes the edited NeRF."""
  if iteration > 1:
    return "finetune"
  if context.settings.edit.nerf_update != "auto":
    return context.settings.edit.nerf_update
  return "retrain" if context.settings.selection.kind == "proxy" else "finetune"


def finetune_settings(context: EditContext, iteration: int) -> dict[str, Any]:
  """The finetune stage's key: the method (retrain or fine-tune), its losses and training (and
  capacity when retraining)."""
  method = update_method(context, iteration)
  settings = {"method": method, "losses": as_json(context.settings.finetune),
              "train": training_key(context.settings.training[method])}
  if context.settings.edit.replay:  # Only when set, as the original training's key.
    settings["replay"] = context.settings.edit.replay
  if method == "retrain":
    settings["capacity"] = as_json(context.settings.capacity)
  return settings


def _start(context: EditContext, iteration: int):
  """(model, initial variables, description of the region) the update starts from."""
  start = context.nerf(iteration - 1)
  model, variables = start.model, start.variables
  config = context.settings.finetune
  if config.edit_region and model.edit_region is None:
    model = dataclasses.replace(model, edit_region=context.selection.grown_bounds(
        config.region_margin))
    variables = {"params": start.variables["params"], "original": start.variables}
  region = "" if model.edit_region is None else (
      ", inside the box " + " .. ".join(str(np.round(corner, 3).tolist())
                                        for corner in model.edit_region) +
      " only (the original NeRF elsewhere)")
  return model, variables, region


def update_nerf(context: EditContext, iteration: int = 1) -> str:
  """Step 7: trains the edited NeRF on the iteration's edited dataset, retraining a new field
  inside the edit region or fine-tuning the previous NeRF (`update_method`), into edited/; returns
  the summary line."""
  method = update_method(context, iteration)
  dataset_dir = context.directory.path("dataset", iteration=iteration)
  edited = load_dataset(dataset_dir, split="all")
  run_dir = context.directory.path("edited", iteration=iteration)
  data_options = {"root": str(dataset_dir.resolve()), "downscale": 1}
  config = context.settings.training[method]
  replay_progress = context.replayed_schedule(run_dir)
  model, variables, region = _start(context, iteration)
  if method == "retrain":
    # A new field (over the original one outside the edit region); without an edit region a
    # new NeRF built for the edited dataset, as for any dataset.
    kept = {"original": variables["original"]} if model.edit_region is not None else None
    if kept:
      model = dataclasses.replace(
          model, region_view_dependence=context.settings.finetune.region_view_dependence)
    trainer = training_run.train(edited, run_dir, config=config, data_options=data_options,
                                 model=model if kept else None, init_variables=kept,
                                 capacity_rules=context.settings.capacity,
                                 progress=context.progress, replay_progress=replay_progress)
    how = "retrained from scratch"
  else:
    losses_config = context.settings.finetune
    losses = finetune.FinetuneLosses(
        lpips_weight=losses_config.lpips_weight if losses_config.lpips_weights else 0.0,
        patch_size=losses_config.patch_size)
    trainer = finetune.finetune(
        edited, run_dir, model=model, init_variables=variables, config=config,
        loss_settings=losses, lpips_params=finetune.load_lpips(losses_config.lpips_weights),
        edited_bounds=model.edit_region or context.selection.bounds, data_options=data_options,
        progress=context.progress, replay_progress=replay_progress)
    how = ("fine-tuned from the " + ("original" if iteration == 1 else "edited") +
           " NeRF (L1" + (" + LPIPS)" if losses.uses_lpips else ")"))
  context.forget_nerf(iteration)
  return (f"{how}{region}: {trainer.step} steps ({trainer.seconds_trained:.0f} s), last batch "
          f"{trainer.last_statistics.get('psnr', float('nan')):.2f} dB: {run_dir}")
