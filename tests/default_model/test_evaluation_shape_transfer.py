"""Whether a sheet carries shape to its slot, on constructed sheets and a stand-in generator."""

import numpy as np
import pytest

from signerf_jax.default_model import evaluation, evaluation_generation
from signerf_jax.default_model import evaluation_shape_transfer as shape_transfer
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.errors import InputError

SIZE = 16
LAYOUT = sheet_lib.SheetLayout(rows=1, columns=3, tile_height=SIZE, tile_width=SIZE)
RED = (0.8, 0.1, 0.08)
# Each sample's object: a square at a place of its own, the same in all of its views (a
# turntable of a sphere), so a sheet of its true views shows the slot's silhouette exactly.
SQUARES = [(slice(2, 8), slice(2, 8)), (slice(8, 14), slice(8, 14)), (slice(3, 9), slice(8, 14))]


def constructed_sheets() -> evaluation_generation.ViewInputs:
  """Three samples of 2 tile views and a slot view on a grey striped ground, box masks."""
  views = LAYOUT.num_tiles + 1
  stripes = 0.35 + 0.3 * (np.arange(SIZE) // 3 % 2)
  ground = np.repeat(np.broadcast_to(stripes[None, :, None], (SIZE, SIZE, 1)), 3, -1)
  background = np.broadcast_to(ground, (len(SQUARES), views, SIZE, SIZE, 3)).astype(np.float32)
  silhouettes = np.zeros((len(SQUARES), views, SIZE, SIZE), bool)
  for index, (rows, columns) in enumerate(SQUARES):
    silhouettes[index, :, rows, columns] = True
  truth = np.where(silhouettes[..., None], np.float32(RED), background)
  masks = np.zeros(silhouettes.shape, np.float32)
  masks[..., 1:15, 1:15] = 1.0
  return evaluation_generation.ViewInputs(
      background=background, masks=masks, controls=silhouettes.astype(np.float32),
      silhouettes=silhouettes, truth=truth, view_kinds=np.zeros((len(SQUARES), views), np.int64),
      captions=["an object"] * len(SQUARES))


def copying_generator(generator, captions, image, mask, control, keys, timer, task):
  """Stands in for `generate_with_captions`: a single view comes back as it went in (nothing
  made); a sheet's slot takes the first tile's pixels where it is masked (a model that copies
  the sheet's shape)."""
  mask = np.asarray(mask).reshape(np.shape(image)[:3])
  if np.shape(image)[1:3] == (SIZE, SIZE):
    return np.asarray(image)
  outputs = []
  for sheet, sheet_mask in zip(image, mask):
    tiles, slot = (np.asarray(part) for part in sheet_lib.disassemble(sheet, LAYOUT))
    slot_mask = np.asarray(sheet_lib.disassemble(sheet_mask[..., None], LAYOUT)[1])
    slot = np.where(slot_mask >= 0.5, tiles[0], slot)
    outputs.append(np.asarray(sheet_lib.assemble(tiles, slot, LAYOUT)))
  return np.stack(outputs)


def test_slot_in_true_view_sheets_puts_each_view_among_the_chosen_samples_tiles():
  sheets = constructed_sheets()
  sources = np.array([2, 0, 1])
  slot_masks = sheets.masks[:, LAYOUT.num_tiles] * 0.5
  rgb, control, mask = shape_transfer.slot_in_true_view_sheets(
      sheets, LAYOUT, shape_transfer.true_view_sheets(sheets, LAYOUT), sources, slot_masks)
  for index, source in enumerate(sources):
    tiles, slot = sheet_lib.disassemble(rgb[index], LAYOUT)
    np.testing.assert_allclose(tiles, sheets.truth[source, :LAYOUT.num_tiles])
    np.testing.assert_allclose(slot, sheets.background[index, LAYOUT.num_tiles])
    control_tiles, control_slot = sheet_lib.disassemble(control[index], LAYOUT)
    np.testing.assert_allclose(control_tiles[..., 0], sheets.controls[source, :LAYOUT.num_tiles])
    np.testing.assert_allclose(control_slot[..., 0], sheets.controls[index, LAYOUT.num_tiles])
    mask_tiles, mask_slot = sheet_lib.disassemble(mask[index], LAYOUT)
    assert not np.any(mask_tiles)  # Only the slot is inpainted.
    np.testing.assert_allclose(mask_slot[..., 0], slot_masks[index])


def test_a_sheet_that_carries_shape_is_told_apart(monkeypatch):
  """With a model that copies the sheet's shape: the true views' sheet gives the slot its exact
  silhouette, another object's sheet its shape, a single view none (nothing generated)."""
  monkeypatch.setattr(shape_transfer, "generate_with_captions", copying_generator)
  monkeypatch.setattr(shape_transfer, "round_trip", lambda generator, images: images)
  monkeypatch.setattr(shape_transfer, "with_scale", lambda generator, scale: generator)
  measures, images = shape_transfer.evaluate_shape_transfer(
      None, None, constructed_sheets(), LAYOUT, evaluation.EvaluationSettings(),
      evaluation_generation.CallTimer())
  assert measures["sheets"] == len(SQUARES)
  assert [(one["masks"], one["controlnet_scale"]) for one in measures["conditions"]] == list(
      shape_transfer.CONDITIONS)
  box = measures["conditions"][0]
  assert box["mean_iou"]["true_views"] == 1.0
  assert box["mean_iou"]["alone"] == 0.0
  assert 0.0 < box["mean_iou"]["other_object"] < 0.5  # The squares overlap a little or not.
  assert box["added_by_true_views"]["mean"] == 1.0
  assert box["added_by_true_views"]["significant"]
  assert box["lost_to_other_object"]["significant"]
  slot_true_views = images["slots"][0]["true_views"]
  assert slot_true_views.shape == (len(SQUARES), SIZE, SIZE, 3)


def test_settings_need_two_shape_transfer_sheets():
  with pytest.raises(InputError) as error:
    evaluation.EvaluationSettings(shape_transfer_sheets=1)
  assert error.value.field == "default_model_evaluation.shape_transfer_sheets"
