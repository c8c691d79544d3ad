"""The image set update computes once what every view shares: the sheet's control embedding is
reused outside the cells the slot reaches, with the images of the full computation; every batch,
the last partial one included, runs the same compiled programs; a batch is written while the
next one computes."""

import jax
import numpy as np
import pytest

from signerf_jax.diffusion import controlnet as controlnet_lib
from signerf_jax.diffusion import guidance as guidance_lib
from signerf_jax.diffusion import pipeline as pipeline_lib
from signerf_jax.diffusion import sampler
from signerf_jax.editing import crops, generation
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.editing import update

# pylint: disable-next=unused-import  (generator: the module's fixture)
from test_update import LAYOUT, generator, make_sheet, make_views, take


def keys_of(indices) -> np.ndarray:
  return np.stack([generation.view_key(0, int(index)) for index in indices])


def slot_inputs(views, sheet_rgb, sheet_control):
  """The views' tiles in the sheet's slot: (image, control, mask), unpadded."""
  tiles = [crops.crop_to_tiles(array, views.boxes, LAYOUT.tile_height, LAYOUT.tile_width,
                               fill_value=fill)
           for array, fill in ((views.images, update.TILE_FILL_COLOR),
                               (views.controls[..., None], 0.0), (views.masks[..., None], 0.0))]
  return sheet_lib.slot_update_inputs(sheet_rgb, sheet_control, *tiles, layout=LAYOUT)


def full_computation(generator, views, keys):
  """The update of a batch as it was computed before the sheet was prepared once: nothing
  reused (the sampler embeds each view's whole control image itself, as `pipeline.generate`
  without an embedding does), nothing padded; (edited, slots) as numpy arrays."""
  image, control, mask = slot_inputs(views, *make_sheet())
  generated = pipeline_lib.generate(generator.pipeline, generator.prompt, image, mask, control,
                                    key=keys, options=generator.options)
  slots = sheet_lib.slot_tiles(generated, LAYOUT)
  return (np.asarray(crops.paste_tiles(views.images, slots, views.boxes, views.masks)),
          np.asarray(slots))


def test_the_update_with_the_sheet_computed_once_gives_the_images_of_the_full_computation(
    generator):
  views, keys = make_views(3), keys_of(range(3))
  sheet = update.SlotSheet.prepare(generator, *make_sheet())
  edited, slots = update.dispatch_update(generator, sheet, LAYOUT, views, keys)
  expected_edited, expected_slots = full_computation(generator, views, keys)
  # The batch is padded to four views and the embedding's cells around the slot are convolved
  # on a window: XLA may round the same sums differently (~1e-6 here).
  np.testing.assert_allclose(np.asarray(slots), expected_slots, rtol=0, atol=1e-5)
  np.testing.assert_allclose(np.asarray(edited), expected_edited, rtol=0, atol=1e-5)
  # The control embedding matters: a sheet whose embedding is another control's paints else.
  other_control = np.zeros_like(make_sheet()[1])
  wrong = update.SlotSheet(sheet.rgb, sheet.control,
                           generator.control_embedding(other_control[None]))
  wrong_slots = np.asarray(update.dispatch_update(generator, wrong, LAYOUT, views, keys)[1])
  assert np.abs(wrong_slots - expected_slots).max() > 1e-2


def test_the_slot_embedding_recomputes_exactly_the_cells_the_slot_reaches(generator,
                                                                          monkeypatch):
  """Each view's embedding from the sheet's: equal to embedding its whole control; the sheet's
  own embedding differs from it around the slot (so the recomputed cells are needed); and with
  a receptive field one latent cell short, the reuse would be wrong, which this test sees."""
  sheet = update.SlotSheet.prepare(generator, *make_sheet())
  control = slot_inputs(make_views(4), sheet.rgb, sheet.control)[1]
  full = np.asarray(generator.control_embedding(control))
  models = generator.pipeline.models
  reused = lambda: np.asarray(controlnet_lib.embed_conditioning_region(
      models.controlnet, models.controlnet_params, sheet.control_embedding,
      guidance_lib.control_image(control, models.controlnet.config.conditioning_channels),
      LAYOUT.slot_region))
  np.testing.assert_allclose(np.asarray(generator.control_embedding(
      control, sheet.control_embedding, LAYOUT.slot_region)), full, rtol=0, atol=1e-5)
  np.testing.assert_allclose(reused(), full, rtol=0, atol=1e-5)
  changed = np.abs(full - np.asarray(sheet.control_embedding)).max(axis=(0, 3)) > 1e-4
  factor = generator.latent_factor
  top, left, height, width = LAYOUT.slot_region
  slot_cells = np.zeros_like(changed)
  slot_cells[top // factor:(top + height) // factor, left // factor:(left + width) // factor] = 1
  assert changed[slot_cells == 0].any()  # The embedding reaches past the slot's own cells.
  radius = controlnet_lib.conditioning_radius
  monkeypatch.setattr(controlnet_lib, "conditioning_radius",
                      lambda config: radius(config) - factor)
  assert np.abs(reused() - full).max() > 1e-3


def test_batches_of_every_size_and_sheets_run_the_programs_the_first_batch_compiled(generator):
  """The last batch of an update is padded to the others' size; the reference sheets (and
  re-rolls) go through the same sampler as the update's batches."""
  edit_batch = update.batch_editor(generator, LAYOUT, "sheet", *make_sheet())
  views = make_views(8)
  edited, _ = edit_batch(take(views, slice(0, 4)), keys_of(range(4)))
  programs = (crops.crop_to_tiles, crops.paste_tiles, sheet_lib.slot_update_inputs,
              sheet_lib.slot_tiles, pipeline_lib.control_embedding,
              sampler.program(generator.pipeline.models), sampler.draw_noise)
  compiled_count = lambda: [program._cache_size()  # pylint: disable=protected-access
                            for program in programs]
  compiled = compiled_count()
  for batch in (slice(4, 5), slice(5, 8), slice(4, 6), slice(0, 4)):
    indices = np.arange(8)[batch]
    jax.block_until_ready(edit_batch(take(views, batch), keys_of(indices)))
  rgb, control = make_sheet()
  inputs = generation.SheetInputs(rgb, control, (control > 0.5).astype(np.float32), LAYOUT)
  recipes = [generation.SheetRecipe.parse(text) for text in ("0", "3/1@2")]
  generation.generate_sheets(generator, inputs, recipes)
  assert compiled_count() == compiled
  # Views 0..3 again: the same images, bit for bit.
  np.testing.assert_array_equal(np.asarray(edit_batch(take(views, slice(0, 4)),
                                                      keys_of(range(4)))[0]), np.asarray(edited))


def test_the_batches_before_a_failing_one_are_written(generator, tmp_path):
  """A batch is written while the next one is computed; if that one fails, the one before is
  still written before the error goes on."""
  views = make_views(6)
  edit_batch = update.batch_editor(generator, LAYOUT, "sheet", *make_sheet())

  def load_views(indices):
    if indices[0] >= 4:
      raise OSError("the disk went away")
    return take(views, indices)

  written = []
  with pytest.raises(OSError, match="went away"):
    update.run_update(generator, edit_batch, np.arange(6), load_views, tmp_path, seed=0,
                      progress=False, on_view_written=written.append)
  assert written == [0, 1, 2, 3]
  assert sorted(path.name for path in (tmp_path / "images").glob("*.png")) == [
      f"frame_{index:05d}.png" for index in range(4)]
