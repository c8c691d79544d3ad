"""Does a reference sheet carry shape to its slot? (Beside the gates; issue 19.)

Gate 3 shows that the slot update takes its colour from the sheet. This asks the same of shape,
which decides whether a sheet can make an edited NeRF more solid than independent edits. Each
eval sheet's held-out view (stored last) is inpainted, with one key per sample for all three:
  * "alone": as a single tile;
  * "true_views": in the slot of a sheet whose tiles are the true renders of the same object
    from the sheet's other views (more shape than any generated sheet can show);
  * "other_object": in the slot of a sheet of the next sample's true renders (another object);
under each `CONDITIONS` entry: its box mask (the shape given by the control depth alone, none at
ControlNet scale 0) or the pipeline's proxy mask, at a ControlNet scale. The slot's object
(`generated_objects.segment_objects`) is compared with its true silhouette by IoU, paired per
sample: a sheet that carries shape raises it from "alone" to "true_views"; that the slot reads
the sheet at all shows as a fall from "true_views" to "other_object".
"""

from __future__ import annotations

import numpy as np

from signerf_jax.default_model import generated_objects
from signerf_jax.default_model.evaluation import FULL_SCALE, EvaluationSettings
from signerf_jax.default_model.evaluation_generation import (CallTimer, ViewInputs,
                                                             evaluation_key,
                                                             generate_with_captions,
                                                             pipeline_proxy_masks, round_trip,
                                                             with_scale)
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.editing.generation import Generator, SheetInputs
from signerf_jax.metrics import silhouettes as silhouettes_lib
from signerf_jax.metrics import solidity

# (masks, ControlNet scale): box masks with the control off and on; the pipeline's proxy masks
# at the scale it runs at.
CONDITIONS = (("box", 0.0), ("box", FULL_SCALE), ("proxy", FULL_SCALE))


def true_view_sheets(sheets: ViewInputs, layout: sheet_lib.SheetLayout) -> list[SheetInputs]:
  """Per sample of `sheets` ([S, M + 1, ...]: the M tile views, then the slot view), the sheet
  of its M true renders and their control depth, nothing masked."""
  tiles = layout.num_tiles
  return [SheetInputs.from_tiles(truth[:tiles], controls[:tiles],
                                 np.zeros_like(masks[:tiles]), layout)
          for truth, controls, masks in zip(sheets.truth, sheets.controls, sheets.masks)]


def slot_in_true_view_sheets(sheets: ViewInputs, layout: sheet_lib.SheetLayout,
                             true_sheets: list[SheetInputs], sources: np.ndarray,
                             slot_masks: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Slot-update inputs whose sheets hold true renders instead of generated tiles.

  Args:
    sheets: [S, M + 1, ...] sheet samples (the M tile views, then the slot view).
    true_sheets: `true_view_sheets(sheets, layout)`.
    sources: [S] sample i's slot view goes into sample sources[i]'s true-view sheet.
    slot_masks: [S, H, W] the slot views' inpainting masks.
  Returns:
    (rgb [S, SH, SW, 3], control [S, SH, SW, 1], mask [S, SH, SW, 1]); the mask is zero on the
    tiles (`sheet.slot_update_inputs`).
  """
  tiles = layout.num_tiles
  parts = [sheet_lib.slot_update_inputs(
      true_sheets[source].rgb, true_sheets[source].control, sheets.background[index, tiles][None],
      sheets.controls[index, tiles][None, ..., None], slot_masks[index][None, ..., None],
      layout=layout) for index, source in enumerate(sources)]
  return tuple(np.concatenate([np.asarray(part[position]) for part in parts])
               for position in range(3))


def shape_transfer_measures(ious: dict[str, np.ndarray]) -> dict:
  """The mean IoU of each source ("alone", "true_views", "other_object": [S] IoUs each), what the
  true views add over "alone" and what another object's views take from them."""
  true_views = ious["true_views"]
  return {"mean_iou": {source: float(np.mean(values)) for source, values in ious.items()},
          "added_by_true_views": solidity.paired_difference(true_views, ious["alone"]),
          "lost_to_other_object": solidity.paired_difference(true_views, ious["other_object"])}


def evaluate_shape_transfer(single_generator: Generator, sheet_generator: Generator,
                            sheets: ViewInputs, layout: sheet_lib.SheetLayout,
                            settings: EvaluationSettings, timer: CallTimer
                            ) -> tuple[dict, dict]:
  """The measure of the module docstring.

  Args:
    single_generator, sheet_generator: the single views' and the sheets' generators.
    sheets: sheet samples ([S, M + 1, ...], S >= 2).
  Returns:
    ({"sheets": S, "conditions": [per `CONDITIONS` entry: masks, ControlNet scale and
      `shape_transfer_measures`]},
     {"conditions": CONDITIONS, "slots": [per condition: {source: [S, H, W, 3]}]}).
  """
  tiles, count = layout.num_tiles, len(sheets.captions)
  background, silhouettes = sheets.background[:, tiles], sheets.silhouettes[:, tiles]
  reference = round_trip(single_generator, background)
  masks = {"box": sheets.masks[:, tiles], "proxy": pipeline_proxy_masks(silhouettes, settings)}
  keys = np.stack([evaluation_key(settings.seed, "shape_transfer", index)
                   for index in range(count)])
  sources = {"true_views": np.arange(count), "other_object": np.roll(np.arange(count), -1)}
  true_sheets = true_view_sheets(sheets, layout)  # The same sheets under every condition.
  measures, slots = [], []
  for mask_kind, scale in CONDITIONS:
    slot_masks = masks[mask_kind]
    generated = {"alone": generate_with_captions(
        with_scale(single_generator, scale), sheets.captions, background, slot_masks,
        sheets.controls[:, tiles], keys, timer, "single_view")}
    for source, order in sources.items():
      image, control, mask = slot_in_true_view_sheets(sheets, layout, true_sheets, order,
                                                      slot_masks)
      made = generate_with_captions(with_scale(sheet_generator, scale), sheets.captions, image,
                                    mask, control, keys, timer, "slot_update")
      generated[source] = np.stack([np.asarray(sheet_lib.disassemble(one, layout)[1])
                                    for one in made])
    ious = {source: silhouettes_lib.silhouette_iou(generated_objects.segment_objects(
        images, reference, slot_masks, settings.difference_threshold,
        settings.min_component_pixels), silhouettes) for source, images in generated.items()}
    measures.append({"masks": mask_kind, "controlnet_scale": scale,
                     **shape_transfer_measures(ious)})
    slots.append(generated)
  return {"sheets": count, "conditions": measures}, {"conditions": CONDITIONS, "slots": slots}
