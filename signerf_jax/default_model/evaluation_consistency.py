"""Colour consistency of sheets, independent views and slot updates (gate 3 of `evaluation`).

On sheets whose caption names no colour, so that the model picks one: the M tile views are
generated as one reference sheet (the slot empty, as the pipeline makes it), each alone (a single
tile with its own key), and the held-out view (stored last) in the slot of the fixed generated
sheet (`sheet.slot_update_inputs`). Each generated object's dominant and mean colour
(`generated_objects.object_colors`) is then compared over pairs of views: among the sheet's
tiles, among the independent views, and between the slot and each tile.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from signerf_jax.default_model import generated_objects
from signerf_jax.default_model import samples
from signerf_jax.default_model.evaluation import FULL_SCALE, EvaluationSettings
from signerf_jax.default_model.evaluation_generation import (CallTimer, ViewInputs,
                                                             evaluation_key,
                                                             generate_with_captions, round_trip,
                                                             with_scale)
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.editing.generation import Generator, SheetInputs


def _keys(seed: int, purpose: str, count: int, views: Sequence[int]) -> np.ndarray:
  """[count * len(views), 2] key data of the `views` of each of `count` sheets, sheet by sheet."""
  return np.stack([evaluation_key(seed, purpose, index, view)
                   for index in range(count) for view in views])


def _flat(array: np.ndarray) -> np.ndarray:
  """[S, V, ...] -> [S * V, ...]."""
  return array.reshape((-1,) + array.shape[2:])


def _generate_sheets(generator: Generator, sheets: ViewInputs, layout: sheet_lib.SheetLayout,
                     seed: int, timer: CallTimer) -> tuple[list[SheetInputs], np.ndarray]:
  """The reference sheets: each sheet's M tile views assembled with the slot empty ([S] inputs)
  and generated ([S, SH, SW, 3])."""
  tiles = layout.num_tiles
  inputs = [SheetInputs.from_tiles(sheets.background[index, :tiles],
                                   sheets.controls[index, :tiles], sheets.masks[index, :tiles],
                                   layout) for index in range(len(sheets.captions))]
  stacked = lambda name: np.stack([getattr(one, name) for one in inputs])
  generated = generate_with_captions(
      generator, sheets.captions, stacked("rgb"), stacked("mask"), stacked("control"),
      _keys(seed, "sheet", len(inputs), [0]), timer, "sheet")
  return inputs, generated


def _generate_slot_updates(generator: Generator, sheets: ViewInputs,
                           layout: sheet_lib.SheetLayout, inputs: list[SheetInputs],
                           generated: np.ndarray, seed: int, timer: CallTimer) -> np.ndarray:
  """[S, SH, SW, 3]: each sheet's slot view (stored last) inpainted in the slot of its fixed
  generated sheet (`generated`, made from `inputs`), nothing else inpainted."""
  tiles = layout.num_tiles
  in_slot = [sheet_lib.slot_update_inputs(
      sheet, one.control, sheets.background[index, tiles][None],
      sheets.controls[index, tiles][None, ..., None], sheets.masks[index, tiles][None, ..., None],
      layout=layout) for index, (sheet, one) in enumerate(zip(generated, inputs))]
  image, control, mask = (np.concatenate([part[position] for part in in_slot])
                          for position in range(3))
  return generate_with_captions(generator, sheets.captions, image, mask, control,
                                _keys(seed, "slot", len(in_slot), [0]), timer, "slot_update")


def _generate_independent(single_generator: Generator, sheets: ViewInputs, tiles: int, seed: int,
                          timer: CallTimer) -> np.ndarray:
  """[S, M, H, W, 3]: the M tile views of each sheet, each generated alone with its own key."""
  return generate_with_captions(
      single_generator, [text for text in sheets.captions for _ in range(tiles)],
      _flat(sheets.background[:, :tiles]), _flat(sheets.masks[:, :tiles]),
      _flat(sheets.controls[:, :tiles]), _keys(seed, "independent", len(sheets.captions),
                                               range(tiles)),
      timer, "single_view").reshape(sheets.background[:, :tiles].shape)


def _sheet_object_colors(images: np.ndarray, reference: np.ndarray, masks: np.ndarray,
                         settings: EvaluationSettings) -> tuple[list[list], np.ndarray]:
  """(names [S][V], mean colours [S, V, 3]) of the objects in generated views [S, V, H, W, 3],
  inpainted under `masks` [S, V, H, W] over views whose VAE round trip is `reference`."""
  count, views = images.shape[:2]
  objects = generated_objects.segment_objects(_flat(images), _flat(reference), _flat(masks),
                                              settings.difference_threshold,
                                              settings.min_component_pixels)
  names, means = generated_objects.object_colors(_flat(images), objects)
  return ([names[index * views:(index + 1) * views] for index in range(count)],
          means.reshape(count, views, 3))


def _agreement_measures(names: dict[str, list[list]], means: dict[str, np.ndarray]) -> dict:
  """Per kind of generation ("sheet", "independent", "slot_update": [S][V] colour names and
  [S, V, 3] mean colours), the mean over sheets of the colour agreement and of the mean RGB
  distance (the slot against the sheet's tiles, the others among themselves), and the count
  of views without an object."""
  count = len(names["sheet"])
  against = lambda name, index: names["sheet"][index] if name == "slot_update" else None
  against_means = lambda name, index: means["sheet"][index] if name == "slot_update" else None
  return {
      "agreement": {name: float(np.mean([
          generated_objects.color_agreement(names[name][index], against(name, index))
          for index in range(count)])) for name in names},
      "mean_rgb_distance": {name: float(np.nanmean([generated_objects.mean_color_distance(
          means[name][index], against_means(name, index)) for index in range(count)]))
                            for name in means},
      "no_object_found": {name: int(sum(color is None for row in names[name] for color in row))
                          for name in names},
  }


def evaluate_consistency(generator: Generator, single_generator: Generator, sheets: ViewInputs,
                         layout: sheet_lib.SheetLayout, settings: EvaluationSettings,
                         timer: CallTimer) -> tuple[dict, dict]:
  """Colour agreement of sheet tiles, independent views and slot updates (module docstring).

  Args:
    generator: the sheets' and slot updates' generator (`settings.sheets_per_device`).
    single_generator: the independent views' generator.
    sheets: sheet samples ([S, M + 1, ...]: the M tile views, then the slot view).
    layout: the sheets' layout (M tiles of the views' size).
  Returns:
    (the measures, {"sheet_inputs": [S] SheetInputs, "sheets": [S, SH, SW, 3] generated
     sheets, "slot_updates": [S, SH, SW, 3], "independent": [S, M, H, W, 3]}).
  """
  tiles = layout.num_tiles
  generator, single_generator = (with_scale(one, FULL_SCALE)
                                 for one in (generator, single_generator))
  reference = round_trip(generator, sheets.background)
  inputs, generated = _generate_sheets(generator, sheets, layout, settings.seed, timer)
  updated = _generate_slot_updates(generator, sheets, layout, inputs, generated, settings.seed,
                                   timer)
  independent = _generate_independent(single_generator, sheets, tiles, settings.seed, timer)
  generated_tiles = np.stack([sheet_lib.disassemble(sheet, layout)[0] for sheet in generated])
  slots = np.stack([sheet_lib.disassemble(sheet, layout)[1] for sheet in updated])
  names, means = {}, {}
  for name, images, views in (("sheet", generated_tiles, list(range(tiles))),
                              ("independent", independent, list(range(tiles))),
                              ("slot_update", slots[:, None], [tiles])):
    names[name], means[name] = _sheet_object_colors(images, reference[:, views],
                                                    sheets.masks[:, views], settings)
  return {
      "sheets": len(sheets.captions), "controlnet_scale": FULL_SCALE,
      "slot_crop_views": int(np.sum(sheets.view_kinds[:, tiles]
                                    == samples.VIEW_KINDS.index("crop"))),
      **_agreement_measures(names, means),
  }, {"sheet_inputs": inputs, "sheets": generated, "slot_updates": updated,
      "independent": independent}
