import jax
import numpy as np
import pytest

from signerf_jax.editing import sheet
from signerf_jax.errors import InputError

LAYOUTS = [
    sheet.SheetLayout(tile_height=36, tile_width=44),  # 2 x 3, slot bottom-right, padded
    sheet.SheetLayout(rows=3, columns=2, slot_row=0, slot_column=0, tile_height=40,
                      tile_width=24),  # already multiples of 8
    sheet.SheetLayout(rows=1, columns=2, slot_row=0, slot_column=1, tile_height=13,
                      tile_width=9),
]


def random_tiles(layout, count, channels, seed=0):
  rng = np.random.default_rng(seed)
  return rng.random((count, layout.tile_height, layout.tile_width, channels)).astype(np.float32)


@pytest.mark.parametrize("layout", LAYOUTS, ids=str)
@pytest.mark.parametrize("channels", [1, 3])
def test_assemble_then_disassemble_is_the_identity(layout, channels):
  tiles = random_tiles(layout, layout.num_tiles, channels)
  slot = random_tiles(layout, 1, channels, seed=1)[0]
  assembled = sheet.assemble(tiles, slot, layout)
  assert assembled.shape[0] % 8 == 0 and assembled.shape[1] % 8 == 0
  assert assembled.shape[:2] == layout.sheet_shape
  recovered_tiles, recovered_slot = sheet.disassemble(assembled, layout)
  np.testing.assert_array_equal(recovered_tiles, tiles)
  np.testing.assert_array_equal(recovered_slot, slot)


def test_tiles_go_in_row_major_order_around_the_slot_and_padding_is_bottom_right():
  layout = LAYOUTS[0]  # 2 x 3, tiles 36 x 44 in 40 x 48 cells
  tiles = np.arange(5, dtype=np.float32)[:, None, None, None] * np.ones((5, 36, 44, 1), np.float32)
  slot = np.full((36, 44, 1), 9.0, np.float32)
  image = np.asarray(sheet.assemble(tiles, slot, layout))[..., 0]
  np.testing.assert_array_equal(image[::40, ::48], [[0, 1, 2], [3, 4, 9]])
  assert layout.slot_offset == (40, 96)
  mask = np.asarray(sheet.assemble(np.ones_like(tiles), slot, layout, is_mask=True))[..., 0]
  assert mask[:36, :44].all() and not mask[36:40].any() and not mask[:, 44:48].any()
  np.testing.assert_array_equal(image[36:40, 48:92], 1.0)  # images repeat their last row


def test_reference_sheet_leaves_the_slot_empty():
  layout = LAYOUTS[0]
  rgb, control = random_tiles(layout, 5, 3), random_tiles(layout, 5, 1, seed=2)
  mask = np.ones((5, 36, 44, 1), np.float32)
  sheets = sheet.reference_sheet_inputs(rgb, control, mask, layout)
  slots = [np.asarray(sheet.disassemble(image, layout)[1]) for image in sheets]
  np.testing.assert_array_equal(slots[0], sheet.EMPTY_SLOT_COLOR)
  np.testing.assert_array_equal(slots[1], 0.0)
  np.testing.assert_array_equal(slots[2], 0.0)
  np.testing.assert_array_equal(sheet.disassemble(sheets[2], layout)[0], mask)


def slot_update_batch(layout, count, seed):
  rng = np.random.default_rng(seed)
  shape = (count, layout.tile_height, layout.tile_width)
  return (rng.random(shape + (3,), np.float32), rng.random(shape + (3,), np.float32),
          (rng.random(shape + (1,)) > 0.5).astype(np.float32))


def test_slot_update_is_a_vmapped_python_loop_with_only_the_slot_masked():
  layout = LAYOUTS[0]
  rng = np.random.default_rng(3)
  sheet_rgb = rng.random(layout.sheet_shape + (3,), np.float32)
  sheet_control = rng.random(layout.sheet_shape + (3,), np.float32)
  views = slot_update_batch(layout, 4, seed=4)
  batched = sheet.slot_update_inputs(sheet_rgb, sheet_control, *views, layout=layout)
  for index in range(4):
    single = sheet.slot_update_inputs(sheet_rgb, sheet_control,
                                      *(view[index:index + 1] for view in views), layout=layout)
    for batch_output, single_output in zip(batched, single):
      np.testing.assert_array_equal(batch_output[index], single_output[0])
    # The loop's meaning, spelled out: each view in the slot, the rest of the sheet unchanged.
    rgb_tiles, rgb_slot = sheet.disassemble(batched[0][index], layout)
    np.testing.assert_array_equal(rgb_tiles, sheet.disassemble(sheet_rgb, layout)[0])
    np.testing.assert_array_equal(rgb_slot, views[0][index])
    mask_tiles, mask_slot = sheet.disassemble(batched[2][index], layout)
    np.testing.assert_array_equal(mask_tiles, 0.0)
    np.testing.assert_array_equal(mask_slot, views[2][index])
  row, column = layout.slot_offset
  outside = np.ones(layout.sheet_shape, bool)
  outside[row:row + layout.tile_height, column:column + layout.tile_width] = False
  assert not np.asarray(batched[2])[:, outside].any()


def test_slot_update_does_not_recompile_between_batches():
  layout = LAYOUTS[1]
  sheet_rgb = np.zeros(layout.sheet_shape + (3,), np.float32)
  sheet_control = np.zeros(layout.sheet_shape + (3,), np.float32)
  outputs = sheet.slot_update_inputs(sheet_rgb, sheet_control, *slot_update_batch(layout, 2, 5),
                                     layout=layout)
  jax.block_until_ready(outputs)
  compiled = sheet.slot_update_inputs._cache_size()
  for seed in (6, 7):
    outputs = sheet.slot_update_inputs(sheet_rgb + seed, sheet_control,
                                       *slot_update_batch(layout, 2, seed), layout=layout)
    jax.block_until_ready(outputs)
  assert sheet.slot_update_inputs._cache_size() == compiled


def test_layout_validation():
  with pytest.raises(InputError, match="outside"):
    sheet.SheetLayout(slot_row=2)
  with pytest.raises(InputError, match="no room"):
    sheet.SheetLayout(rows=1, columns=1)
  layout = LAYOUTS[0]
  with pytest.raises(InputError, match="tiles"):
    sheet.assemble(random_tiles(layout, 4, 3), random_tiles(layout, 1, 3)[0], layout)
