"""Tiles cut from full-resolution views: crops around the selection, and pasting edits back.

The paper puts whole frames, downscaled, into the sheet, and lists the lost resolution as a
limitation. Here a tile may instead be a crop around the selection's projected bounding box,
so the selection covers far more of the tile (docs/results.md);
the edited tile is then pasted back into the full-resolution image through the mask.

A crop box is [x0, y0, width, height] in (continuous) pixels of the source image; tile pixel
(row i, column j) samples the source at (x0 + (j + 1/2) width / tile_width,
y0 + (i + 1/2) height / tile_height). Boxes have the tile's aspect ratio, so nothing is stretched.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from signerf_jax import camera as camera_lib


def full_frame_boxes(num_views: int, height: int, width: int, tile_height: int,
                     tile_width: int) -> jax.Array:
  """[N, 4] boxes holding the whole frame at the tile's aspect, centred (letterboxed)."""
  aspect = tile_width / tile_height
  box_width = max(width, height * aspect)
  box_height = box_width / aspect
  box = jnp.array([(width - box_width) / 2, (height - box_height) / 2, box_width, box_height],
                  jnp.float32)
  return jnp.broadcast_to(box, (num_views, 4))


@functools.partial(jax.jit, static_argnames=("tile_height", "tile_width"))
def selection_crop_boxes(cameras: camera_lib.Cameras, points, tile_height: int, tile_width: int,
                         margin: float = 0.15, max_upscale: float = 2.0) -> jax.Array:
  """Crop boxes around the selection's projected bounding box, one per camera.

  The box is the projected bounding box of `points`, grown to the tile's aspect ratio, widened by
  `margin` of its size on every side, and at least tile / `max_upscale` pixels (so a tiny
  selection is not blown up beyond that). It is then shifted to lie inside the image where it
  fits; where it is larger than the image it stays centred and the overhang is padding. A camera
  for which some point is behind it gets the full frame.

  Args:
    cameras: N cameras (H x W).
    points: [K, 3] points spanning the selection (box corners, proxy vertices).
    tile_height, tile_width: the tile size the crops are resized to.
    margin: extra context on each side, as a fraction of the box size.
    max_upscale: the largest magnification from source pixels to tile pixels.
  Returns:
    [N, 4] float32 boxes [x0, y0, width, height].
  """
  aspect = tile_width / tile_height
  pixels, depth = camera_lib.project(cameras, points)  # [N, K, 2], [N, K]
  low, high = pixels.min(axis=1), pixels.max(axis=1)
  center = (low + high) / 2
  extent = high - low
  box_width = jnp.maximum(extent[:, 0], extent[:, 1] * aspect) * (1 + 2 * margin)
  box_width = jnp.maximum(box_width, tile_width / max_upscale)
  size = jnp.stack([box_width, box_width / aspect], -1)
  limits = jnp.array([cameras.width, cameras.height], jnp.float32)
  corner = center - size / 2
  fits = size <= limits
  corner = jnp.where(fits, jnp.clip(corner, 0.0, limits - size), (limits - size) / 2)
  boxes = jnp.concatenate([corner, size], -1)
  full = full_frame_boxes(cameras.num_cameras, cameras.height, cameras.width, tile_height,
                          tile_width)
  return jnp.where(jnp.all(depth > 0, axis=1)[:, None], boxes, full)


def _sample_positions(box_start, box_size, target_size: int):
  """Source coordinates of the target pixel centres along one axis, [target_size]."""
  return box_start + (jnp.arange(target_size) + 0.5) * box_size / target_size


def _crop_one(image, box, tile_height: int, tile_width: int, fill_value):
  height, width = image.shape[:2]
  scale = jnp.array([tile_height / box[3], tile_width / box[2]])
  translation = -jnp.array([box[1], box[0]]) * scale
  tile = jax.image.scale_and_translate(image, (tile_height, tile_width, image.shape[2]), (0, 1),
                                       scale, translation, "linear", antialias=True)
  rows = _sample_positions(box[1], box[3], tile_height)
  columns = _sample_positions(box[0], box[2], tile_width)
  inside = (((rows >= 0) & (rows < height))[:, None]
            & ((columns >= 0) & (columns < width))[None, :])
  return jnp.where(inside[..., None], tile, fill_value)


@functools.partial(jax.jit, static_argnames=("tile_height", "tile_width"))
def crop_to_tiles(images, boxes, tile_height: int, tile_width: int, fill_value=0.5) -> jax.Array:
  """Resamples the part of each image inside its box to a tile (antialiased bilinear).

  Args:
    images: [N, H, W, C] float32.
    boxes: [N, 4] crop boxes [x0, y0, width, height] in pixels.
    tile_height, tile_width: output size.
    fill_value: value of tile pixels whose centre falls outside the image.
  Returns:
    [N, tile_height, tile_width, C] float32.
  """
  crop = lambda image, box: _crop_one(image, box, tile_height, tile_width, fill_value)
  return jax.vmap(crop)(images, boxes)


def _paste_one(image, tile, box, mask):
  height, width = image.shape[:2]
  tile_height, tile_width = tile.shape[:2]
  scale = jnp.array([box[3] / tile_height, box[2] / tile_width])
  translation = jnp.array([box[1], box[0]])
  resampled = jax.image.scale_and_translate(tile, image.shape, (0, 1), scale, translation,
                                            "linear", antialias=True)
  rows = jnp.arange(height) + 0.5
  columns = jnp.arange(width) + 0.5
  inside = (((rows >= box[1]) & (rows < box[1] + box[3]))[:, None]
            & ((columns >= box[0]) & (columns < box[0] + box[2]))[None, :])
  weight = jnp.where(inside, jnp.reshape(mask, (height, width)), 0.0)[..., None]
  return jnp.where(weight > 0, image * (1 - weight) + resampled * weight, image)


@jax.jit
def paste_tiles(images, tiles, boxes, masks) -> jax.Array:
  """Pastes edited tiles back into their full-resolution images through the masks.

  Only pixels with mask > 0 inside the crop change: out = (1 - m) image + m tile_resampled.
  Everywhere else the result is the original pixels, bit for bit.

  Args:
    images: [N, H, W, C] float32 originals.
    tiles: [N, h, w, C] edited tiles cut from `images` with `boxes`.
    boxes: [N, 4] the crop boxes the tiles were made with.
    masks: [N, H, W] or [N, H, W, 1] blend weights in [0, 1] at full resolution.
  Returns:
    [N, H, W, C] float32.
  """
  return jax.vmap(_paste_one)(images, tiles, boxes, masks)
