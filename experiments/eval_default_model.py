"""The default model's quality gates (issue 5) on the held-out procedural data.

    python experiments/eval_default_model.py [--model DIR] [--data DIR] [--output JSON] \
        [--gin_file eval_default_model] [--gin_param 'default_model_evaluation.num_singles = 16']

Measures prompt adherence, shape adherence over ControlNet scales (in box masks, and in the
pipeline's proxy masks: whether the control steers the shape), colour consistency of sheets,
independent views and slot updates, whether a sheet carries shape to its slot (beside the gates),
and seconds per generation call
(`signerf_jax.default_model.evaluation`, whose docstring defines each measure), on the "eval"
split of the dataset. Writes
  * --output (default: default_model.json in --results DIR, default outputs/experiments/): the
    measures, pass/fail of each gate with its threshold, timings and the machine (CPU count, load
    average), and the full gin config beside it (.gin);
  * <output stem>_samples.png: single views (input, mask, control, generation per ControlNet
    scale, the object found at scale 1, the truth), sheets (input, mask, control, generated
    sheet, slot update, the same views generated independently) and shape transfer (one true
    view of the object, the slot view's input, its object made alone, in a sheet of the true
    views and in one of another object's, the truth; box masks at ControlNet scale 0).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import gin
import jax
import numpy as np

from signerf_jax import configs, files
from signerf_jax.default_model import (evaluation, evaluation_consistency,
                                       evaluation_generation, evaluation_shape_transfer,
                                       evaluation_singles, training_data)
from signerf_jax.diffusion import pipeline as pipeline_lib
from signerf_jax.diffusion.attention import AttentionOptions
from signerf_jax.editing import figures, generation
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.editing.config import DEFAULT_MODEL_DIR

sys.path.insert(0, str(Path(__file__).resolve().parent))
import plotting  # pylint: disable=wrong-import-position
from machine import code_version  # pylint: disable=wrong-import-position
import results_dir  # pylint: disable=wrong-import-position

REPOSITORY = Path(__file__).resolve().parent.parent
DEFAULT_DATA = REPOSITORY / "outputs" / "default_model_data"


def machine(load_at_start) -> dict:
  """CPUs, devices, the 1, 5 and 15 minute load averages at the start and now, the code's commit."""
  return {"cpu_count": os.cpu_count(), "usable_cpus": len(os.sched_getaffinity(0)),
          "load_average_at_start": list(load_at_start), "load_average_at_end": list(
              os.getloadavg()), "devices": [str(device) for device in jax.devices()],
          "jax": jax.__version__, **code_version()}


def samples_figure(singles: evaluation_generation.ViewInputs, single_images: dict,
                   sheets: evaluation_generation.ViewInputs, sheet_images: dict,
                   layout: sheet_lib.SheetLayout, settings: evaluation.EvaluationSettings
                   ) -> np.ndarray:
  """The figure of the module docstring, [H, W, 3] in [0, 1]."""
  full = list(settings.controlnet_scales).index(evaluation.FULL_SCALE)
  seen = lambda image, mask: image * (1 - mask[..., None]) + sheet_lib.EMPTY_SLOT_COLOR * mask[
      ..., None]
  rows, labels = [], []
  for index in range(min(settings.figure_singles, len(singles.captions))):
    mask = singles.masks[index, 0]
    rows.append([seen(singles.background[index, 0], mask), mask, singles.controls[index, 0],
                 *single_images["generated"][:, index],
                 single_images["objects"][full, index].astype(np.float32),
                 singles.truth[index, 0]])
    labels.append([singles.captions[index], "mask", "control",
                   *(f"scale {scale:g}" for scale in settings.controlnet_scales),
                   f"object at {evaluation.FULL_SCALE:g}", "truth"])
  grids = [figures.image_grid(rows, labels)]
  rows, labels = [], []
  empty_slot = np.full((layout.tile_height, layout.tile_width, 3), sheet_lib.EMPTY_SLOT_COLOR,
                       np.float32)
  for index in range(min(settings.figure_sheets, len(sheets.captions))):
    inputs = sheet_images["sheet_inputs"][index]
    rows.append([seen(inputs.rgb, inputs.mask[..., 0]), inputs.mask, inputs.control,
                 sheet_images["sheets"][index], sheet_images["slot_updates"][index],
                 np.asarray(sheet_lib.assemble(sheet_images["independent"][index], empty_slot,
                                               layout))])
    labels.append([sheets.captions[index], "mask", "control", "reference sheet", "slot update",
                   "independent views"])
  if rows:
    grids.append(figures.image_grid(rows, labels))
  return plotting.stacked(grids, gap=0)


def shape_transfer_figure(sheets: evaluation_generation.ViewInputs, transfer_images: dict,
                          layout: sheet_lib.SheetLayout, settings: evaluation.EvaluationSettings
                          ) -> np.ndarray:
  """The shape-transfer rows of the module docstring (the first condition), [H, W, 3]."""
  tiles, slots = layout.num_tiles, transfer_images["slots"][0]
  masks, scale = transfer_images["conditions"][0]
  rows, labels = [], []
  for index in range(min(settings.figure_sheets, len(sheets.captions))):
    mask = sheets.masks[index, tiles][..., None]
    rows.append([sheets.truth[index, 0],
                 sheets.background[index, tiles] * (1 - mask) + sheet_lib.EMPTY_SLOT_COLOR * mask,
                 slots["alone"][index], slots["true_views"][index],
                 slots["other_object"][index], sheets.truth[index, tiles]])
    labels.append(["a true view", f"{masks} mask, scale {scale:g}", "alone", "true views' sheet",
                   "other object's", "truth"])
  return figures.image_grid(rows, labels)


def print_summary(result: dict) -> None:
  prompt, shape = result["prompt_adherence"], result["shape_adherence"]
  consistency, timing, gates = result["consistency"], result["timing"], result["gates"]
  verdict = lambda name: "PASS" if gates[name]["passed"] else "FAIL"
  ious = ", ".join(f"{scale:g}: {iou:.3f}"
                   for scale, iou in zip(shape["controlnet_scales"], shape["mean_iou"]))
  print(f"prompt adherence  {verdict('prompt_adherence')}  {prompt['share']:.3f} of "
        f"{prompt['samples']} objects in the named colour (VAE ceiling "
        f"{prompt['vae_ceiling']:.3f}; >= {gates['prompt_adherence']['threshold']})")
  print(f"shape adherence   {verdict('shape_adherence')}  mean IoU by ControlNet scale {ious} "
        f"(ceiling {shape['segmentation_ceiling_iou']:.3f}; >= "
        f"{gates['shape_adherence']['threshold']} at 1, rising)")
  per_scale = lambda values: ", ".join(f"{value:.3f}" for value in values)
  print(f"  (not a gate)    pooled precision {per_scale(shape['pooled_precision'])}; recall "
        f"{per_scale(shape['pooled_recall'])}; masked ground changed "
        f"{per_scale(shape['changed_ground_share'])}")
  proxy = shape["with_proxy_masks"]
  print(f"  (not a gate)    with the pipeline's proxy masks: mean IoU "
        f"{per_scale(proxy['mean_iou'])} (ceiling {proxy['segmentation_ceiling_iou']:.3f}); "
        f"precision {per_scale(proxy['pooled_precision'])}; recall "
        f"{per_scale(proxy['pooled_recall'])}; found by the caption's hue (gate 4) "
        f"{per_scale(proxy['by_caption_hue']['mean_iou'])} (ceiling "
        f"{proxy['by_caption_hue']['segmentation_ceiling_iou']:.3f})")
  by_hue = shape["by_caption_hue"]
  print(f"  (not a gate)    found by the caption's hue ({by_hue['samples']} views): "
        + ", ".join(f"{scale:g}: {iou:.3f}" for scale, iou in
                    zip(shape["controlnet_scales"], by_hue["mean_iou"]))
        + f" (ceiling {by_hue['segmentation_ceiling_iou']:.3f})")
  control = gates["control_steers_shape"]
  print(f"control (proxy)   {verdict('control_steers_shape')}  in the proxy masks, found by the "
        f"caption's hue: IoU at 1 {control['by_caption_hue']['iou_at_full_scale']:.3f} (>= "
        f"{control['iou_threshold']}), rise from 0 "
        f"{control['by_caption_hue']['rise_from_scale_0']:.3f} (>= {control['rise_threshold']}); "
        f"by difference {control['by_difference']['iou_at_full_scale']:.3f}, rise "
        f"{control['by_difference']['rise_from_scale_0']:.3f}")
  agreement = consistency["agreement"]
  print(f"consistency       {verdict('consistency')}  colour agreement over "
        f"{consistency['sheets']} sheets: sheet {agreement['sheet']:.3f}, slot update "
        f"{agreement['slot_update']:.3f}, independent {agreement['independent']:.3f} (margin >= "
        f"{gates['consistency']['threshold']})")
  interval = lambda measure: f"[{measure['interval'][0]:+.3f}, {measure['interval'][1]:+.3f}]"
  for condition in result["shape_transfer"]["conditions"]:
    iou, added = condition["mean_iou"], condition["added_by_true_views"]
    lost = condition["lost_to_other_object"]
    print(f"  (not a gate)    shape transfer, {condition['masks']} masks at scale "
          f"{condition['controlnet_scale']:g}: slot IoU alone {iou['alone']:.3f}, in the true "
          f"views' sheet {iou['true_views']:.3f} ({added['mean']:+.3f} {interval(added)}), in "
          f"another object's {iou['other_object']:.3f} (true views {lost['mean']:+.3f} "
          f"{interval(lost)})")
  seconds = lambda task, field: timing.get(task, {}).get(field)
  show = lambda value: "n/a" if value is None else f"{value:.2f} s"
  print(f"timing            sheet {show(seconds('sheet', 'seconds_per_sample'))}, slot update "
        f"{show(seconds('slot_update', 'seconds_per_sample'))}, single view "
        f"{show(seconds('single_view', 'seconds_per_sample'))} per sample; compile sheet "
        f"{show(seconds('sheet', 'compile_seconds'))}, single view "
        f"{show(seconds('single_view', 'compile_seconds'))}")


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--model", default=str(DEFAULT_MODEL_DIR),
                      help="a diffusers ControlNet inpainting pipeline (default: the shipped model)")
  parser.add_argument("--data", default=str(DEFAULT_DATA),
                      help="the generated dataset (experiments/make_default_model_data.py)")
  results_dir.add_argument(parser)
  parser.add_argument("--output", metavar="JSON",
                      help="the json to write (default: DIR/default_model.json)")
  configs.add_gin_arguments(parser)
  args = parser.parse_args(argv)
  start = time.monotonic()
  load_at_start = os.getloadavg()
  configs.parse_gin(args.gin_file or ["eval_default_model"], args.gin_param)
  settings, thresholds = evaluation.EvaluationSettings(), evaluation.QualityGates()
  options = configs.build(pipeline_lib.GenerationOptions)

  data = training_data.load_split(args.data, "eval", keep=None, progress=False)
  single_indices, sheet_indices = evaluation_generation.select_samples(data.singles, data.sheets,
                                                                       settings)
  singles = evaluation_generation.ViewInputs.from_arrays(data.singles, single_indices)
  sheets = evaluation_generation.ViewInputs.from_arrays(data.sheets, sheet_indices)
  single_generator = generation.load_generator(
      args.model, "", "", "", "", options, settings.singles_per_device,
      attention=configs.build(AttentionOptions))
  sheet_generator = dataclasses.replace(single_generator,
                                        views_per_device=settings.sheets_per_device)
  load_seconds = time.monotonic() - start

  timer = evaluation_generation.CallTimer()
  single_measures, single_images = evaluation_singles.evaluate_singles(single_generator, singles,
                                                                       settings, timer)
  consistency, sheet_images = evaluation_consistency.evaluate_consistency(
      sheet_generator, single_generator, sheets, data.layout, settings, timer)
  transfer_sheets = evaluation_generation.ViewInputs.from_arrays(
      data.sheets, np.arange(min(settings.shape_transfer_sheets, len(data.sheets["caption"]))))
  shape_transfer, transfer_images = evaluation_shape_transfer.evaluate_shape_transfer(
      single_generator, sheet_generator, transfer_sheets, data.layout, settings, timer)
  shape = single_measures["shape_adherence"]
  gates = evaluation.quality_gates(single_measures["prompt_adherence"]["share"],
                                   shape["mean_iou"], shape["controlnet_scales"],
                                   consistency["agreement"], thresholds)
  proxy = shape["with_proxy_masks"]
  gates["control_steers_shape"] = evaluation.control_gate(
      proxy["by_caption_hue"]["mean_iou"], proxy["mean_iou"], shape["controlnet_scales"],
      thresholds)
  result = {
      "model": str(args.model), "data": str(args.data), "split": "eval", "gates": gates,
      **single_measures, "consistency": consistency, "shape_transfer": shape_transfer,
      "timing": {**timer.summary(), "loading_seconds": load_seconds,
                 "total_wall_seconds": time.monotonic() - start},
      "machine": machine(load_at_start),
      "settings": dataclasses.asdict(settings), "generation_options": dataclasses.asdict(options)}
  output = Path(args.output or args.results / "default_model.json")
  files.write_json(output, result)
  files.write_text(output.with_suffix(".gin"), gin.config_str())
  figure_path = output.with_name(f"{output.stem}_samples.png")
  files.write_image(figure_path, plotting.stacked([
      samples_figure(singles, single_images, sheets, sheet_images, data.layout, settings),
      shape_transfer_figure(transfer_sheets, transfer_images, data.layout, settings)],
      gap=0))
  print_summary(result)
  print(f"results in {output}, samples in {figure_path}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
