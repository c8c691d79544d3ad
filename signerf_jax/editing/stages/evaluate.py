"""The evaluate stage: what the edit did, measured and shown.

  background     the paper's PSNR/SSIM between original and edited NeRF renders outside the
                 selection, at held-out cameras;
  adherence      whether the edited images and renders show the prompt's colour, and (proxy
                 selections) the proxy's silhouette;
  consistency    camera-verified correspondences of the sheet-propagated edit against
                 independent per-view edits (same prompt, settings and seed for every view, as
                 the paper's comparison), with the independent edits' cost;
  CLIP           directional similarity (when CLIP weights are given);
  figures        before/after renders, the sheet, the independent edits, an orbit video.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np
import tqdm

from signerf_jax import files
from signerf_jax.clip import similarity as clip_similarity
from signerf_jax.editing import conditioning as conditioning_lib
from signerf_jax.editing import evaluation, figures, generation
from signerf_jax.editing import update as update_lib
from signerf_jax.editing.config import as_json
from signerf_jax.editing.stages import nerf_consistency
from signerf_jax.editing.stages.context import EditContext, evenly_spaced
from signerf_jax.editing.stages.inputs import VIEWS_PER_CHUNK
from signerf_jax.editing.stages.propagation import EditedViews, edited_views
from signerf_jax.metrics import background
from signerf_jax.nerf import camera_paths, edit_region_render, render

BEFORE_AFTER_VIEWS = 4
# Columns of the independent-edits figure.
FIGURE_VIEWS = 6


def evaluation_settings(context: EditContext) -> dict[str, Any]:
  """The evaluate stage's key: the evaluation, consistency and NeRF-consistency settings and the
  generation."""
  return {"evaluation": as_json(context.settings.evaluation),
          "consistency": as_json(context.settings.consistency),
          "nerf_consistency": as_json(context.settings.nerf_consistency),
          "generation": context.generation_key(1)}


def _held_out_conditioning(context: EditContext, nerf) -> conditioning_lib.Conditioning:
  """The original NeRF's renders, selections and masks at the held-out cameras."""
  return conditioning_lib.condition_in_chunks(nerf.model, nerf.variables, context.eval_cameras,
                                              context.selection, context.settings.selection,
                                              VIEWS_PER_CHUNK)


def _adherence(context: EditContext, views: EditedViews, before, after) -> dict[str, Any]:
  """Prompt colour (and proxy shape) adherence of the image set and the NeRF renders."""
  prompt, conditioned = context.settings.edit.prompt, views.conditioning
  metrics = {"prompt_color_adherence": {
      "image_set": evaluation.prompt_color_adherence(prompt, views.edited, conditioned.selected),
      "nerf_renders": evaluation.prompt_color_adherence(prompt, after, before.selected)}}
  if context.selection.kind == "proxy":
    metrics["shape_iou"] = {
        "image_set": evaluation.shape_adherence(views.originals, views.edited,
                                                conditioned.selected, conditioned.mask),
        "nerf_renders": evaluation.shape_adherence(before.render, after, before.selected,
                                                   before.mask)}
  return metrics


def _consistency(context: EditContext, edited_views: EditedViews) -> dict[str, Any]:
  """Independent per-view edits of some edited views, against the sheet-propagated ones."""
  chosen = evenly_spaced(np.arange(edited_views.cameras.num_cameras),
                         context.settings.evaluation.independent_views)
  cameras, conditioned = edited_views.cameras.take(chosen), edited_views.conditioning
  edited = edited_views.edited[chosen]
  views = update_lib.SlotViews(edited_views.originals[chosen], conditioned.mask[chosen],
                               conditioned.control[chosen], context.tile_boxes(cameras))
  keys = np.repeat(generation.seed_key(context.settings.edit.seed)[None], len(chosen), axis=0)
  start = time.perf_counter()
  # A few batches at a size nothing else samples: Winograd's convolutions would add more
  # compilation than these calls earn back (`layers.winograd_convolutions`).
  generator = dataclasses.replace(context.generator(1), winograd_convolutions=False)
  independent = evaluation.independent_edits(generator, context.layout, views, keys)
  seconds = time.perf_counter() - start
  consistency = evaluation.consistency_comparison(
      {"original": views.images, "sheet_propagated": edited, "independent": independent},
      cameras, conditioned.mask[chosen] > 0, context.settings.consistency)
  shown = min(FIGURE_VIEWS, len(chosen))
  files.write_image(context.directory.path("evaluation", "independent_edits.png"),
                    figures.image_grid([list(views.images[:shown]), list(edited[:shown]),
                                        list(independent[:shown])],
                                       [["original"] * shown, ["sheet propagated"] * shown,
                                        ["independent"] * shown]))
  # Their cost against the sheet propagation's (the ablations' quality against time).
  return {"independent_edits": {"views": len(chosen), "seconds": seconds},
          "consistency": consistency}


def _clip_similarity(context: EditContext, originals, edited, before, after) -> dict[str, float]:
  model = clip_similarity.load_clip_model(context.settings.evaluation.clip_model)
  captions = (context.settings.evaluation.source_caption, context.settings.edit.prompt)
  return {
      "image": float(np.mean(clip_similarity.clip_directional_similarity(
          model, originals, edited, *captions))),
      "nerf": float(np.mean(clip_similarity.clip_directional_similarity(
          model, before.render, after, *captions)))}


def _figures(context: EditContext, iteration: int, nerfs, before, after) -> list:
  """Before/after at the held-out cameras showing the most of the selection, the sheet, and an
  orbit video; returns their paths."""
  directory, config = context.directory.path("evaluation"), context.settings.evaluation
  shown = np.argsort(-np.count_nonzero(before.selected.reshape(len(after), -1), axis=1),
                     kind="stable")[:BEFORE_AFTER_VIEWS]
  files.write_image(directory / "before_after.png", figures.image_grid(
      [[before.render[index] for index in shown], [after[index] for index in shown]],
      [["before"] * len(shown), ["after"] * len(shown)]))
  sheet_png = context.directory.path("sheet", "sheet.png", iteration=iteration)
  files.write_bytes(directory / "sheet.png", sheet_png.read_bytes())
  outputs = [directory / "before_after.png", directory / "sheet.png"]
  if config.video_frames:
    path = camera_paths.orbit_cameras(nerfs[1].model, context.dataset.cameras, config.video_frames)
    original = render.render_cameras(nerfs[0].model, nerfs[0].variables, path)["rgb"]
    edited = edit_region_render.render_over_original(nerfs[1].model, nerfs[1].variables, path,
                                                     original)
    frames = np.concatenate([original, edited], axis=2)
    outputs.append(render.write_video(directory / "before_after.mp4", frames, config.video_fps))
  return outputs


def evaluate_edit(context: EditContext) -> str:
  """Measures the edit at the held-out cameras (background preservation, adherence, independent
  edits, CLIP, the edited NeRF's fit, solidity and correspondences, as configured), writes
  evaluation/metrics.json and the figures and video; returns the summary line."""
  start = time.perf_counter()
  config = context.settings.evaluation
  measure_nerf = context.settings.nerf_consistency.enabled
  parts = (["held-out renders", "adherence"] + ["independent edits"] * bool(
      config.independent_views) + ["CLIP"] * bool(config.clip_model)
           + ["fit, solidity, correspondences"] * measure_nerf + ["figures"])
  bar = tqdm.tqdm(total=len(parts), desc="evaluate", unit="part", disable=not context.progress,
                  dynamic_ncols=True, postfix=parts[0])

  def part_done():
    bar.update()
    bar.set_postfix_str(parts[min(bar.n, len(parts) - 1)])

  iteration = 2 if context.settings.edit.second_iteration else 1
  original, edited_nerf = context.nerf(0), context.nerf(iteration)
  before = _held_out_conditioning(context, original)
  # Outside the edit region's pixels the edited NeRF renders what the original does.
  after = edit_region_render.render_over_original(edited_nerf.model, edited_nerf.variables,
                                                  context.eval_cameras, before.render)
  part_done()
  metrics: dict[str, Any] = {"prompt": context.settings.edit.prompt,
                             "num_eval_views": context.eval_cameras.num_cameras}
  metrics["background"] = background.background_preservation(before.render, after,
                                                              before.mask > 0)
  # The views the NeRF learned the edit from, before and after it.
  views = edited_views(context, iteration)
  metrics.update(_adherence(context, views, before, after))
  part_done()
  if config.independent_views:
    metrics.update(_consistency(context, views))
    part_done()
  if config.clip_model:
    metrics["clip_directional_similarity"] = _clip_similarity(context, views.originals,
                                                              views.edited, before, after)
    part_done()
  if measure_nerf:
    metrics["nerf_consistency"] = nerf_consistency.measure(
        context, views, original, edited_nerf, before.selected,
        context.settings.nerf_consistency)
    part_done()
  outputs = _figures(context, iteration, (original, edited_nerf), before, after)
  part_done()
  bar.close()
  # This stage's own seconds too: the stage record is written only after it returns.
  metrics["stage_seconds"] = {**context.directory.stage_seconds(),
                              "evaluate": time.perf_counter() - start}
  metrics_path = context.directory.path("evaluation", "metrics.json")
  files.write_json(metrics_path, metrics)
  bg = metrics["background"]
  return (f"background PSNR {bg['psnr_paper']:.2f} dB / SSIM {bg['ssim_paper']:.3f} (paper's "
          f"masked images; background only: {bg['psnr_background']:.2f} dB) on "
          f"{context.eval_cameras.num_cameras} held-out views: "
          f"{', '.join(map(str, [metrics_path, *outputs]))}")
