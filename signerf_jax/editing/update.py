"""Step 6, the image set update: every dataset view, in the empty slot of the fixed reference
sheet, inpainted so that the sheet's appearance carries over (paper, "Image Set Update").

What does not change from view to view is computed once per update (`SlotSheet`): the sheet on
the devices and the ControlNet's embedding of its control (the prompt's embeddings are the
generator's, encoded when it is loaded). For a batch of views (`SlotViews`: full-resolution
images, masks, control depth and the box each tile is cut from), padded to the generator's batch
size so that every batch, the last included, runs the same compiled programs:
  1. each view is cut into a tile (`crops.crop_to_tiles`: the whole frame, letterboxed, or a crop
     around the selection) and placed in the sheet's slot (`sheet.slot_update_inputs`, vmapped
     over the batch); only the slot is masked, and only the control embedding's cells the slot
     reaches are recomputed (`controlnet.embed_conditioning_region`);
  2. the batch is inpainted in one call, sharded over the devices along "views"
     (`generation.Generator`);
  3. the slot is cut out of each generated sheet and pasted back into the full-resolution image
     through the (soft) mask (`crops.paste_tiles`): pixels outside the mask stay bit for bit.

`run_update` drives this over all views whose mask is not empty. Batches are consecutive chunks
of those views, so every run forms the same batches; each finished view is written atomically
(its generated tile, then the edited image, which marks it done), and a restarted run skips the
views already written and recomputes only the batches that still hold unwritten views. With the
per-view keys of `generation.view_key`, a resumed update writes exactly the images an
uninterrupted one does. A batch is written while the next one is computed (JAX dispatches it
asynchronously), so the PNG encoding and disk writes cost no sampling time.
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
from signerf_jax import distributed, files, parallel
from signerf_jax.editing import crops
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.editing.generation import Generator, view_key
from signerf_jax.editing.project import frame_name
from signerf_jax.errors import InputError

IMAGES_FOLDER, TILES_FOLDER = "images", "tiles"
TILE_FILL_COLOR = 0.5  # Tile pixels outside the source image: neutral grey, never masked.


@dataclasses.dataclass(frozen=True)
class SlotViews:
  """A batch of dataset views at full resolution, [n, ...] (host arrays; `padded_tiles` makes a
  padded copy on the devices).

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


@dataclasses.dataclass(frozen=True)
class SlotSheet:
  """The generated reference sheet as every batch of an update reads it (made once per update).

  Attributes:
    rgb: [SH, SW, 3] float32 the sheet, on every device of the generator's mesh.
    control: [SH, SW, C] float32 its control, likewise.
    control_embedding: [1, SH / f, SW / f, E] the ControlNet's embedding of `control` (f the
      latent factor); a view's differs only in the cells its slot reaches.
  """

  rgb: jax.Array
  control: jax.Array
  control_embedding: jax.Array

  @classmethod
  def prepare(cls, generator: Generator, sheet_rgb, sheet_control) -> "SlotSheet":
    """From the sheet [SH, SW, 3] and its control [SH, SW, C] (host or device arrays); the
    embedding by the program that embeds the generator's batches (no compilation of its own)."""
    rgb, control = (jax.device_put(jnp.asarray(array, jnp.float32),
                                   parallel.replicated(generator.mesh))
                    for array in (sheet_rgb, sheet_control))
    embedding = generator.control_embedding(generator.shard(control[None]))[:1]
    return cls(rgb, control, jax.device_put(embedding, parallel.replicated(generator.mesh)))


def padded_tiles(generator: Generator, views: SlotViews, layout: sheet_lib.SheetLayout):
  """(the views padded to the generator's batch size B and sharded like its inputs, their tiles
  (image [B, h, w, 3], control [B, h, w, 1], mask [B, h, w, 1]))."""
  padded = SlotViews(*(generator.shard(getattr(views, field.name))
                       for field in dataclasses.fields(SlotViews)))
  tiles = tuple(crops.crop_to_tiles(array, padded.boxes, layout.tile_height, layout.tile_width,
                                    fill_value=fill)
                for array, fill in ((padded.images, TILE_FILL_COLOR),
                                    (padded.controls[..., None], 0.0),
                                    (padded.masks[..., None], 0.0)))
  return padded, tiles


def update_batch(generator: Generator, sheet_rgb, sheet_control, layout: sheet_lib.SheetLayout,
                 views: SlotViews, keys) -> tuple[np.ndarray, np.ndarray]:
  """Inpaints a batch of views in the sheet's slot and pastes the results back (the sheet made
  ready for this batch alone; an update makes it ready once: `batch_editor`).

  Args:
    generator: the sharded generator (at most `batch_size` views).
    sheet_rgb: [SH, SW, 3] the generated reference sheet; sheet_control: [SH, SW, 1].
    layout: the sheet layout.
    views: the batch's n views.
    keys: [n, 2] uint32 key data, one per view.
  Returns:
    edited: [n, H, W, 3] float32 full-resolution images; slots: [n, h, w, 3] the generated tiles.
  """
  sheet = SlotSheet.prepare(generator, sheet_rgb, sheet_control)
  return distributed.to_host(dispatch_update(generator, sheet, layout, views, keys))


def dispatch_update(generator: Generator, sheet: SlotSheet, layout: sheet_lib.SheetLayout,
                    views: SlotViews, keys) -> tuple[jax.Array, jax.Array]:
  """`update_batch` with the sheet made ready (`SlotSheet.prepare`), returned as soon as it is
  dispatched: the same (edited, slots), which JAX computes asynchronously (reading them waits).
  """
  padded, tiles = padded_tiles(generator, views, layout)
  image, control, mask = sheet_lib.slot_update_inputs(sheet.rgb, sheet.control, *tiles,
                                                      layout=layout)
  embedding = generator.control_embedding(control, sheet.control_embedding, layout.slot_region)
  generated = generator.dispatch(image, mask, control, keys, embedding)
  slots = sheet_lib.slot_tiles(generated, layout)
  edited = crops.paste_tiles(padded.images, slots, padded.boxes, padded.masks)
  return edited[:len(keys)], slots[:len(keys)]


def edited_image_path(directory: str | os.PathLike, view_index: int) -> Path:
  """Where the update writes view `view_index`'s edited image (PNG) under `directory`."""
  return Path(directory) / IMAGES_FOLDER / f"{frame_name(view_index)}.png"


def independent_batch(generator: Generator, layout: sheet_lib.SheetLayout, views: SlotViews,
                      keys) -> tuple[np.ndarray, np.ndarray]:
  """Each view of a batch inpainted on its own (a single tile, no sheet), pasted back through its
  mask: the paper's baseline, whose views disagree with each other.

  Args and returns as `update_batch`, without the sheet.
  """
  return distributed.to_host(dispatch_independent(generator, layout, views, keys))


def dispatch_independent(generator: Generator, layout: sheet_lib.SheetLayout, views: SlotViews,
                         keys) -> tuple[jax.Array, jax.Array]:
  """`independent_batch`, returned as soon as it is dispatched (as `dispatch_update`)."""
  padded, (image, control, mask) = padded_tiles(generator, views, layout)
  tiles = generator.dispatch(image, mask, control, keys)
  edited = crops.paste_tiles(padded.images, tiles, padded.boxes, padded.masks)
  return edited[:len(keys)], tiles[:len(keys)]


# How a batch of views is edited: (views, keys [n, 2]) -> (edited images, generated tiles), both
# dispatched (`dispatch_update`).
EditBatch = Callable[[SlotViews, np.ndarray], tuple[jax.Array, jax.Array]]


def batch_editor(generator: Generator, layout: sheet_lib.SheetLayout, propagation: str,
                 sheet_rgb=None, sheet_control=None) -> EditBatch:
  """The `EditBatch` of a propagation mode: "sheet" (`update_batch`, through the slot of the sheet
  [SH, SW, 3] with control [SH, SW, C], made ready once here) or "independent"
  (`independent_batch`)."""
  if propagation == "sheet":
    return functools.partial(dispatch_update, generator,
                             SlotSheet.prepare(generator, sheet_rgb, sheet_control), layout)
  if propagation == "independent":
    return functools.partial(dispatch_independent, generator, layout)
  raise InputError(f"must be 'sheet' or 'independent', got {propagation!r}",
                   field="UpdateConfig.propagation")


def _write_views(directory: Path, batch: np.ndarray, todo: set[int], edited, slots,
                 on_view_written: Callable[[int], None]) -> int:
  """Writes the tiles and images of a batch's views in `todo` (waiting for them to be
  computed); calls `on_view_written` after each; returns how many were written."""
  # Gathered from every process when the batch is spread over several.
  edited, slots = distributed.to_host((edited, slots))
  for index, image, slot in zip(batch, edited, slots):
    if int(index) in todo:
      files.write_image(directory / TILES_FOLDER / f"{frame_name(int(index))}.png", slot)
      files.write_image(edited_image_path(directory, int(index)), image)
      on_view_written(int(index))
  return len(todo)


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
  view_indices, directory = np.asarray(view_indices, np.int64), Path(directory)
  batch_size = generator.batch_size
  batches = [view_indices[start:start + batch_size]
             for start in range(0, len(view_indices), batch_size)]
  done = lambda index: edited_image_path(directory, int(index)).is_file()
  resumed = int(sum(done(index) for index in view_indices))
  bar = tqdm.tqdm(total=len(view_indices), initial=resumed, unit="view", disable=not progress,
                  desc="image set update", dynamic_ncols=True)

  def written(view_index: int) -> None:
    bar.update(1)
    on_view_written(view_index)

  edited_count, computed, pending = 0, 0, None  # pending: the batch dispatched last, unwritten.
  for batch in batches:
    todo = {int(index) for index in batch if not done(index)}
    if not todo:
      continue
    keys = np.stack([view_key(seed, int(index)) for index in batch])
    try:
      dispatched = (batch, todo, *edit_batch(load_views(batch), keys))
      computed += 1
    finally:  # While this batch computes (or when it failed), the one before is written.
      if pending is not None:
        edited_count += _write_views(directory, *pending, written)
        pending = None
    pending = dispatched
  if pending is not None:
    edited_count += _write_views(directory, *pending, written)
  bar.close()
  return {"edited": edited_count, "resumed": resumed, "batches": computed,
          "batch_size": batch_size, "devices": generator.mesh.size}
