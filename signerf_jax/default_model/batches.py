"""Model inputs from the default model's data: inpainting masks, control depth and sheets.

Inputs of the inpainting UNet + ControlNet, per single view or per sheet (all float32, images in
[0, 1]): image [.., 3], mask [.., 1], masked_image = image * (1 - mask) [.., 3], control
[.., 1] (normalised inverse depth, near = 1, far = 0) and object [.., 1] (the visible silhouette:
training weighs the masked ground apart from the masked object). Because every mask kind covers
the whole visible object and the renderer casts no shadows, the masked image equals the object-free
`background_rgb` times (1 - mask): the model never sees the object it is to paint.

Mask kinds (`mask_kinds(dilation_radii)`), from exact to coarse:
  "silhouette"    the visible silhouette: it shows the exact shape, so the base UNet could read
                  the shape off the mask and the ControlNet would not be needed; use it little;
  "dilated_<r>"   the silhouette grown by r pixels (the stored `dilated_silhouettes`): a blob
                  with the object's rough outline, like the pipeline's dilated proxy masks;
  "box"           the silhouette's bounding box grown by BOX_MARGIN of its size on each side
                  (at least MIN_BOX_MARGIN_PIXELS): only position and extent, the shape must
                  come from the control depth.
Training picks a kind per sample (`inpainting_masks` takes per-sample indices into the kinds).

Sheet modes (views in the stored order: tiles in grid order skipping the slot, then the slot):
  "all_views"        every cell holds its view and its mask (the model learns that the tiles of
                     one sheet share an appearance);
  "reference_sheet"  as the pipeline generates the reference sheet: tiles masked, the slot empty
                     (grey, control 0, mask 0; `sheet.reference_sheet_inputs`);
  "slot_update"      as the image set update: the tiles show the object unmasked (standing in for
                     a generated sheet) and only the slot view is masked, so the model learns to
                     copy the tiles' appearance into the slot.
Tokenising captions (and dropping them for classifier-free guidance) is left to the training.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.errors import InputError
from signerf_jax.geometry import control_depth

BOX_MARGIN = 0.15
MIN_BOX_MARGIN_PIXELS = 2
SHEET_MODES = ("all_views", "reference_sheet", "slot_update")


def mask_kinds(dilation_radii) -> tuple[str, ...]:
  """The mask kind names for a dataset's dilation radii (its manifest's `dilation_radii`)."""
  return ("silhouette", *(f"dilated_{radius}" for radius in dilation_radii), "box")


def box_masks(boxes: np.ndarray, height: int, width: int) -> np.ndarray:
  """[..., H, W] float32 masks of the [..., 4] boxes [x0, y0, x1, y1), grown by the margin."""
  boxes = np.asarray(boxes, np.float32)
  size = boxes[..., 2:] - boxes[..., :2]
  margin = np.maximum(BOX_MARGIN * size, MIN_BOX_MARGIN_PIXELS)
  low, high = boxes[..., :2] - margin, boxes[..., 2:] + margin
  columns, rows = np.arange(width) + 0.5, np.arange(height) + 0.5
  inside_x = (columns >= low[..., None, 0:1]) & (columns <= high[..., None, 0:1])
  inside_y = (rows[:, None] >= low[..., None, None, 1]) & (rows[:, None] <= high[..., None, None, 1])
  return (inside_x & inside_y).astype(np.float32)


def candidate_masks(arrays: dict[str, np.ndarray]) -> np.ndarray:
  """[S, V, K, H, W] float32: every mask kind (in `mask_kinds` order) for every view."""
  silhouette = arrays["silhouette"][:, :, None]
  height, width = silhouette.shape[-2:]
  boxes = box_masks(arrays["boxes"], height, width)[:, :, None]
  return np.concatenate([silhouette, arrays["dilated_silhouettes"], boxes], 2).astype(np.float32)


def inpainting_masks(arrays: dict[str, np.ndarray], kind_indices) -> np.ndarray:
  """[S, V, H, W] the mask kind `kind_indices[s]` ([S] ints into `mask_kinds`) of each sample."""
  candidates = candidate_masks(arrays)
  kind_indices = np.asarray(kind_indices)
  if kind_indices.shape != candidates.shape[:1] or not np.all(
      (kind_indices >= 0) & (kind_indices < candidates.shape[2])):
    raise InputError(f"need one kind index in [0, {candidates.shape[2]}) per sample, got "
                     f"{kind_indices.tolist()}", field="kind_indices")
  return candidates[np.arange(len(candidates)), :, kind_indices]


def control(arrays: dict[str, np.ndarray]) -> jax.Array:
  """[S, V, H, W] control depth, each view normalised over its stored `control_near_far`."""
  depth = jnp.asarray(arrays["depth"], jnp.float32)
  near_far = jnp.asarray(arrays["control_near_far"])
  flat = lambda array: array.reshape((-1,) + array.shape[2:])
  normalised = control_depth.normalize_control_depth(flat(depth), flat(near_far[..., 0]),
                                                     flat(near_far[..., 1]))
  return normalised.reshape(depth.shape)


def _inputs(image, mask, control_map, object_pixels) -> dict[str, jax.Array]:
  return {"image": image, "mask": mask, "masked_image": image * (1.0 - mask),
          "control": control_map, "object": object_pixels}


def _silhouettes(arrays: dict[str, np.ndarray]) -> jax.Array:
  """[S, V, H, W, 1] float32 visible silhouettes."""
  return (jnp.asarray(arrays["silhouette"]) > 0).astype(jnp.float32)[..., None]


def single_view_inputs(arrays: dict[str, np.ndarray], masks) -> dict[str, jax.Array]:
  """Inputs [S, H, W, C] of single-view samples (V = 1) with their [S, 1, H, W] masks."""
  if arrays["rgb"].shape[1] != 1:
    raise InputError(f"single views have 1 view per sample, got {arrays['rgb'].shape[1]}",
                     field="rgb")
  image = jnp.asarray(arrays["rgb"][:, 0], jnp.float32) / 255.0
  return _inputs(image, jnp.asarray(masks)[:, 0, ..., None], control(arrays)[:, 0, ..., None],
                 _silhouettes(arrays)[:, 0])


@functools.partial(jax.jit, static_argnames=("layout", "mode"))
def _sheet(rgb, mask, control_map, silhouette, layout: sheet_lib.SheetLayout, mode: str):
  """One sample's views [V, h, w, C] -> (image, mask, control, object) sheets."""
  tiles = lambda views: views[:layout.num_tiles]
  assemble = lambda views, is_mask=False: sheet_lib.assemble(tiles(views), views[-1], layout,
                                                            is_mask=is_mask)
  # Every view's silhouette, whatever the mode: it only matters where the mask is.
  object_sheet = assemble(silhouette, True)
  if mode == "reference_sheet":
    image, control_sheet, mask_sheet = sheet_lib.reference_sheet_inputs(
        tiles(rgb), tiles(control_map), tiles(mask), layout)
    return image, mask_sheet, control_sheet, object_sheet
  if mode == "slot_update":
    mask = mask.at[:layout.num_tiles].set(0.0)
  return assemble(rgb), assemble(mask, True), assemble(control_map), object_sheet


def sheet_inputs(arrays: dict[str, np.ndarray], masks, layout: sheet_lib.SheetLayout,
                 mode: str = "all_views") -> dict[str, jax.Array]:
  """Inputs [S, sheet_height, sheet_width, C] of sheet samples with their [S, V, H, W] masks.

  Args:
    arrays: a batch of sheet samples (V = layout.num_tiles + 1 views).
    masks: [S, V, H, W] inpainting masks (`inpainting_masks`).
    layout: the sheet layout; its tiles must be the views' size.
    mode: one of SHEET_MODES (module docstring).
  """
  if mode not in SHEET_MODES:
    raise InputError(f"must be one of {SHEET_MODES}, got {mode!r}", field="mode")
  num_views, height, width = arrays["rgb"].shape[1:4]
  if (num_views, height, width) != (layout.num_tiles + 1, layout.tile_height, layout.tile_width):
    raise InputError(f"the samples have {num_views} views of {height} x {width}; the layout takes "
                     f"{layout.num_tiles} tiles and a slot of {layout.tile_height} x "
                     f"{layout.tile_width}", field="layout")
  rgb = jnp.asarray(arrays["rgb"], jnp.float32) / 255.0
  image, mask, control_sheet, object_sheet = jax.vmap(
      functools.partial(_sheet, layout=layout, mode=mode))(
          rgb, jnp.asarray(masks, jnp.float32)[..., None], control(arrays)[..., None],
          _silhouettes(arrays))
  return _inputs(image, mask, control_sheet, object_sheet)
