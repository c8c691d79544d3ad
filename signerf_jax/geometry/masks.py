"""Inpainting masks in image space: dilation, feathering, and which views have any mask at all.

Dilation radii are given in pixels at a reference resolution (`REFERENCE_SIZE` on the image's
longer side) and scaled with the actual image, so one setting means the same margin around the
selection for a 512-pixel tile and a 2048-pixel dataset image.

Both operations come from one exact, capped Euclidean distance transform: the distance from every
pixel centre to the nearest masked pixel centre. A row pass finds, per row, the nearest masked
column on either side (running max/min of indices); a column pass takes the minimum of
dy^2 + dx^2 over the 2R + 1 row offsets within the cap R (Felzenszwalb and Huttenlocher's
separable scheme with the second pass done by brute force, which is cheap for the radii used).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax.errors import InputError

REFERENCE_SIZE = 512


def scaled_radius(radius: float, height: int, width: int,
                  reference_size: int = REFERENCE_SIZE) -> float:
  """`radius` pixels at `reference_size` on the longer side, in pixels of an H x W image."""
  return float(radius) * max(height, width) / reference_size


def distance_to_mask(mask: jax.Array, max_distance: int) -> jax.Array:
  """Euclidean distance (pixels) from each pixel to the nearest masked pixel, capped.

  Args:
    mask: [..., H, W] bool (or anything where nonzero = masked).
    max_distance: the cap R (static); farther pixels get R + 1.
  Returns:
    [..., H, W] float32: 0 on the mask, exact distances up to R, R + 1 beyond.
  """
  mask = mask.astype(bool)
  width = mask.shape[-1]
  far = max_distance + 1
  columns = jnp.arange(width, dtype=jnp.int32)
  # Row pass: horizontal distance to the nearest masked pixel in the same row.
  left = jax.lax.cummax(jnp.where(mask, columns, -2 * width), axis=mask.ndim - 1)
  right = jax.lax.cummin(jnp.where(mask, columns, 3 * width), axis=mask.ndim - 1, reverse=True)
  horizontal = jnp.minimum(columns - left, right - columns).astype(jnp.float32)
  horizontal_squared = jnp.minimum(horizontal, far)**2
  # Column pass: combine rows within the cap.
  padded = jnp.pad(horizontal_squared, [(0, 0)] * (mask.ndim - 2) + [(max_distance,) * 2, (0, 0)],
                   constant_values=far**2)
  height, row_axis = mask.shape[-2], mask.ndim - 2

  def add_row_offset(step, best):  # step 0 .. 2R is the row offset step - R.
    shifted = jax.lax.dynamic_slice_in_dim(padded, step, height, axis=row_axis)
    return jnp.minimum(best, shifted + ((step - max_distance)**2).astype(jnp.float32))

  best = jax.lax.fori_loop(0, 2 * max_distance + 1, add_row_offset,
                           jnp.full(mask.shape, far**2, jnp.float32))
  return jnp.minimum(jnp.sqrt(best), far)


@functools.partial(jax.jit, static_argnames=("radius", "feather", "reference_size"))
def dilate_and_feather(mask: jax.Array, radius: float = 0.0, feather: float = 0.0,
                       reference_size: int = REFERENCE_SIZE) -> jax.Array:
  """Grows a mask by a disc and optionally gives it a soft edge.

  Args:
    mask: [..., H, W] bool or {0, 1} (nonzero = masked).
    radius: dilation radius in pixels at `reference_size` (static); a pixel joins the mask when
      its centre is within the scaled radius of a masked pixel centre.
    feather: width of the soft edge outside the dilated mask, in pixels at `reference_size`
      (static); the mask falls linearly from 1 at the dilated edge to 0 at `feather` beyond it.
    reference_size: the longer image side the radii refer to.
  Returns:
    [..., H, W] float32 in [0, 1]: exactly 1 on the dilated mask, exactly 0 beyond the feather.
  """
  if radius < 0 or feather < 0:
    raise InputError(f"radius and feather must be >= 0, got {radius}, {feather}",
                     field="mask_dilation")
  height, width = mask.shape[-2:]
  radius_px = scaled_radius(radius, height, width, reference_size)
  feather_px = scaled_radius(feather, height, width, reference_size)
  if radius_px == 0 and feather_px == 0:
    return mask.astype(bool).astype(jnp.float32)
  distance = distance_to_mask(mask, int(math.ceil(radius_px + feather_px)))
  if feather_px == 0:
    return (distance <= radius_px).astype(jnp.float32)
  return jnp.clip((radius_px + feather_px - distance) / feather_px, 0.0, 1.0)


def views_with_empty_masks(masks, min_pixels: int = 1) -> np.ndarray:
  """Indices of the views whose mask has fewer than `min_pixels` nonzero pixels.

  No diffusion is run for these views: the selection is not visible in them.

  Args:
    masks: [N, H, W] (or [N, H, W, 1]) mask per view.
  Returns:
    [K] int64 view indices, ascending.
  Raises:
    InputError: no view shows the selection at all.
  """
  counts = np.asarray(jnp.sum(jnp.asarray(masks).reshape(len(masks), -1) > 0, axis=1))
  empty = np.flatnonzero(counts < min_pixels)
  if len(empty) == len(counts):
    raise InputError(f"the selection is not visible in any of the {len(counts)} views (no view "
                     f"has {min_pixels} or more mask pixels): move or enlarge the selection",
                     field="selection")
  return empty
