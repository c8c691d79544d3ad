"""Step 6, the image set update: every dataset view, in the empty slot of the fixed reference
sheet, inpainted so that the sheet's appearance carries over (paper, "Image Set Update").

For a batch of views (`SlotViews`: full-resolution images, masks, control depth and the box each
tile is cut from):
  1. each view is cut into a tile (`crops.crop_to_tiles`: the whole frame, letterboxed, or a crop
     around the selection) and placed in the sheet's slot (`sheet.slot_update_inputs`, vmapped
     over the batch); only the slot is masked;
  2. the batch is inpainted in one call, sharded over the devices along "views"
     (`generation.Generator`);
  3. the slot is cut out of each generated sheet and pasted back into the full-resolution image
     through the (soft) mask (`crops.paste_tiles`): pixels outside the mask stay bit for bit.

`run_update` drives this over all views whose mask is not empty. Batches are consecutive chunks
of those views, so every run forms the same batches; each finished view is written atomically
(its generated tile, then the edited image, which marks it done), and a restarted run skips the
views already written and recomputes only the batches that still hold unwritten views. With the
per-view keys of `generation.view_key`, a resumed update writes exactly the images an
uninterrupted one does.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import tqdm

from signerf_jax import camera as camera_lib
from signerf_jax import files
from signerf_jax.editing import crops
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.editing.generation import Generator, view_key
from signerf_jax.editing.project import frame_name
from signerf_jax.errors import InputError

IMAGES_FOLDER, TILES_FOLDER = "images", "tiles"
TILE_FILL_COLOR = 0.5  # Tile pixels outside the source image: neutral grey, never masked.


@dataclasses.dataclass(frozen=True)
class SlotViews:
  """A batch of dataset views at full resolution, [n, ...].

  Attributes:
    images: [n, H, W, 3] float32 in [0, 1], what goes into the slot.
    masks: [n, H, W] float32 in [0, 1], the inpainting masks.
    controls: [n, H, W] float32 in [0, 1], the normalised control depth.
    boxes: [n, 4] float32 crop boxes [x0, y0, width, height] the tiles are cut from.
  """

  images: np.ndarray
  masks: np.ndarray
  controls: np.ndarray
  boxes: np.ndarray


def tile_boxes(cameras: camera_lib.Cameras, layout: sheet_lib.SheetLayout, selection_points=None,
               margin: float = 0.15, max_upscale: float = 2.0) -> np.ndarray:
  """[N, 4] boxes the tiles of N views are cut from: whole frames (letterboxed to the tile's
  aspect) without `selection_points`, else crops around the selection's projection."""
  if selection_points is None:
    return np.asarray(crops.full_frame_boxes(cameras.num_cameras, cameras.height, cameras.width,
                                             layout.tile_height, layout.tile_width))
  return np.asarray(crops.selection_crop_boxes(
      cameras, jnp.asarray(selection_points, jnp.float32), layout.tile_height, layout.tile_width,
      margin, max_upscale))


def update_batch(generator: Generator, sheet_rgb, sheet_control, layout: sheet_lib.SheetLayout,
                 views: SlotViews, keys) -> tuple[np.ndarray, np.ndarray]:
  """Inpaints a batch of views in the sheet's slot and pastes the results back.

  Args:
    generator: the sharded generator (at most `batch_size` views).
    sheet_rgb: [SH, SW, 3] the generated reference sheet; sheet_control: [SH, SW, 1].
    layout: the sheet layout.
    views: the batch's views.
    keys: [n, 2] uint32 key data, one per view.
  Returns:
    edited: [n, H, W, 3] float32 full-resolution images; slots: [n, h, w, 3] the generated tiles.
  """
  height, width = layout.tile_height, layout.tile_width
  boxes = jnp.asarray(views.boxes, jnp.float32)
  tiles = [crops.crop_to_tiles(jnp.asarray(array, jnp.float32), boxes, height, width,
                               fill_value=fill)
           for array, fill in ((views.images, TILE_FILL_COLOR), (views.controls[..., None], 0.0),
                               (views.masks[..., None], 0.0))]
  # The vmapped slot assembly runs on the sharded batch, like the generation after it.
  image, control, mask = sheet_lib.slot_update_inputs(
      jnp.asarray(sheet_rgb, jnp.float32), jnp.asarray(sheet_control, jnp.float32),
      *(generator.shard(tile) for tile in tiles), layout=layout)
  generated = generator(image, mask, control, keys)
  slots = jax.vmap(lambda sheet: sheet_lib.disassemble(sheet, layout)[1])(generated)
  edited = crops.paste_tiles(jnp.asarray(views.images, jnp.float32), slots, boxes,
                             jnp.asarray(views.masks, jnp.float32))
  return np.asarray(edited), np.asarray(slots)


def edited_image_path(directory: str | os.PathLike, view_index: int) -> Path:
  """Where the update writes view `view_index`'s edited image (PNG) under `directory`."""
  return Path(directory) / IMAGES_FOLDER / f"{frame_name(view_index)}.png"


def independent_batch(generator: Generator, layout: sheet_lib.SheetLayout, views: SlotViews,
                      keys) -> tuple[np.ndarray, np.ndarray]:
  """Each view of a batch inpainted on its own (a single tile, no sheet), pasted back through its
  mask: the paper's baseline, whose views disagree with each other.

  Args and returns as `update_batch`, without the sheet.
  """
  height, width = layout.tile_height, layout.tile_width
  boxes = jnp.asarray(views.boxes, jnp.float32)
  image, control, mask = (
      crops.crop_to_tiles(jnp.asarray(array, jnp.float32), boxes, height, width, fill_value=fill)
      for array, fill in ((views.images, TILE_FILL_COLOR), (views.controls[..., None], 0.0),
                          (views.masks[..., None], 0.0)))
  tiles = generator(image, mask, control, keys)
  edited = crops.paste_tiles(jnp.asarray(views.images, jnp.float32), tiles, boxes,
                             jnp.asarray(views.masks, jnp.float32))
  return np.asarray(edited), np.asarray(tiles)


# How a batch of views is edited: (views, keys [n, 2]) -> (edited images, generated tiles).
EditBatch = Callable[[SlotViews, np.ndarray], tuple[np.ndarray, np.ndarray]]


def batch_editor(generator: Generator, layout: sheet_lib.SheetLayout, propagation: str,
                 sheet_rgb=None, sheet_control=None) -> EditBatch:
  """The `EditBatch` of a propagation mode: "sheet" (`update_batch`, through the sheet's slot)
  or "independent" (`independent_batch`)."""
  if propagation == "sheet":
    return functools.partial(update_batch, generator, sheet_rgb, sheet_control, layout)
  if propagation == "independent":
    return functools.partial(independent_batch, generator, layout)
  raise InputError(f"must be 'sheet' or 'independent', got {propagation!r}",
                   field="UpdateConfig.propagation")


def run_update(generator: Generator, edit_batch: EditBatch, view_indices: Sequence[int],
               load_views: Callable[[np.ndarray], SlotViews], directory: str | os.PathLike,
               seed: int, progress: bool = True,
               on_view_written: Callable[[int], None] = lambda view_index: None) -> dict:
  """The resumable image set update of `view_indices` (see the module docstring).

  Args:
    generator: the sharded generator (its batch size and devices).
    edit_batch: edits a batch of views (`batch_editor`).
    view_indices: the dataset views to edit (those whose mask is not empty), ascending.
    load_views: indices [n] -> their `SlotViews`.
    directory: receives images/frame_NNNNN.png (edited views) and tiles/frame_NNNNN.png.
    seed: the edit seed (view i uses `view_key(seed, i)`).
    progress: show a progress bar.
    on_view_written: called with each view index once its image is written.
  Returns:
    {"edited": views written by this call, "resumed": views found already written,
     "batches": batches computed, "batch_size", "devices"}.
  """
  view_indices = np.asarray(view_indices, np.int64)
  batch_size = generator.batch_size
  batches = [view_indices[start:start + batch_size]
             for start in range(0, len(view_indices), batch_size)]
  done = lambda index: edited_image_path(directory, int(index)).is_file()
  resumed = int(sum(done(index) for index in view_indices))
  bar = tqdm.tqdm(total=len(view_indices), initial=resumed, unit="view", disable=not progress,
                  desc="image set update", dynamic_ncols=True)
  edited_count, computed = 0, 0
  for batch in batches:
    todo = [int(index) for index in batch if not done(index)]
    if not todo:
      continue
    keys = np.stack([view_key(seed, int(index)) for index in batch])
    edited, slots = edit_batch(load_views(batch), keys)
    computed += 1
    for index, image, slot in zip(batch, edited, slots):
      if int(index) not in todo:
        continue
      files.write_image(Path(directory) / TILES_FOLDER / f"{frame_name(int(index))}.png", slot)
      files.write_image(edited_image_path(directory, int(index)), image)
      edited_count += 1
      bar.update(1)
      on_view_written(int(index))
  bar.close()
  return {"edited": edited_count, "resumed": resumed, "batches": computed,
          "batch_size": batch_size, "devices": generator.mesh.size}
