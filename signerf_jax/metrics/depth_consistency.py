"""Multi-view depth consistency: does a NeRF's depth agree between views where no ground-truth
depth exists (real captures)?

The geometric check of multi-view stereo fusion (as COLMAP's and MVSNet's): a pixel of view A is
lifted to 3D by A's rendered depth, projected into a neighbouring view B, lifted again by B's
depth at the pixel it lands on, and projected back into A. The pixel is consistent when it comes
back within `pixel_tolerance` pixels of where it started and at a depth within
`relative_depth_tolerance` of A's. A NeRF whose surfaces are where the photos say agrees with
itself from every camera; fog and floaters, fitted to each training view separately, put a
pixel's depth where its neighbour's view does not. Pixels the neighbour cannot see (outside its
frame, transparent there, or hidden behind something nearer) fail the check too, so views close
together measure geometry rather than occlusion: each view is checked against its nearest
neighbour.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax import camera as camera_lib
from signerf_jax.errors import InputError
from signerf_jax.metrics import consistency

# COLMAP's stereo fusion defaults (max_reproj_error 2 px, max_depth_error 0.01).
PIXEL_TOLERANCE = 2.0
RELATIVE_DEPTH_TOLERANCE = 0.01
# A pixel has a surface to check when at least this much of its ray's light is absorbed.
OPACITY_THRESHOLD = 0.5


def _lift(cameras: camera_lib.Cameras, index: int, z_depth, rows, columns):
  """[..., 3] world points at z-depth `z_depth` [...] through pixel centres (rows, columns)."""
  rays = camera_lib.pixel_rays(cameras, jnp.full(rows.shape, index, jnp.int32),
                               columns + 0.5, rows + 0.5)
  distance = z_depth / jnp.maximum(rays.cos_to_optical_axis, 1e-6)
  return rays.origins + rays.directions * distance[..., None]


def _lookup(image, pixels):
  """(values, inside): `image` [H, W] at the pixel containing each of `pixels` [..., 2] (x, y),
  and whether that pixel is inside the frame."""
  height, width = image.shape
  column, row = jnp.floor(pixels[..., 0]), jnp.floor(pixels[..., 1])
  inside = (column >= 0) & (column < width) & (row >= 0) & (row < height)
  row = jnp.clip(row, 0, height - 1).astype(jnp.int32)
  column = jnp.clip(column, 0, width - 1).astype(jnp.int32)
  return image[row, column], inside


@jax.jit
def _consistent_pixels(pair: camera_lib.Cameras, depths, opacities, pixel_tolerance,
                       relative_depth_tolerance):
  """(consistent, checked): [H, W] bool of view 0 of `pair` (2 cameras); `depths`, `opacities`
  [2, H, W]. `checked`: pixels with a surface (opacity over OPACITY_THRESHOLD, depth > 0)."""
  height, width = depths.shape[1:]
  rows, columns = jnp.meshgrid(jnp.arange(height, dtype=jnp.float32),
                               jnp.arange(width, dtype=jnp.float32), indexing="ij")
  surface = (opacities >= OPACITY_THRESHOLD) & (depths > 0) & jnp.isfinite(depths)
  points = _lift(pair, 0, depths[0], rows, columns)
  pixels_in_b, depth_in_b = camera_lib.project(pair.take([1]), points)
  pixels_in_b, depth_in_b = pixels_in_b[0], depth_in_b[0]
  depth_b, inside = _lookup(depths[1], pixels_in_b)
  surface_b, _ = _lookup(surface[1], pixels_in_b)
  # B's surface at the pixel A's point lands on, lifted and projected back into A.
  points_b = _lift(pair, 1, depth_b, jnp.floor(pixels_in_b[..., 1]),
                   jnp.floor(pixels_in_b[..., 0]))
  pixels_back, depth_back = camera_lib.project(pair.take([0]), points_b)
  centres = jnp.stack([columns + 0.5, rows + 0.5], axis=-1)
  reprojection_error = jnp.linalg.norm(pixels_back[0] - centres, axis=-1)
  depth_error = jnp.abs(depth_back[0] - depths[0]) / jnp.maximum(depths[0], 1e-12)
  checked = surface[0]
  consistent = (checked & inside & surface_b & (depth_in_b > 0)
                & (reprojection_error <= pixel_tolerance)
                & (depth_error <= relative_depth_tolerance))
  return consistent, checked


def nearest_views(cameras: camera_lib.Cameras) -> np.ndarray:
  """[N] int: for each camera the index of the nearest other camera (by centre distance)."""
  if cameras.num_cameras < 2:
    raise InputError(f"needs at least 2 views, got {cameras.num_cameras}",
                     field="cameras")
  return consistency.nearest_cameras(cameras, 1)[:, 0]


def depth_consistency(cameras: camera_lib.Cameras, depths, opacities,
                      pixel_tolerance: float = PIXEL_TOLERANCE,
                      relative_depth_tolerance: float = RELATIVE_DEPTH_TOLERANCE
                      ) -> dict[str, Any]:
  """How much of each view's rendered surface its nearest neighbour view agrees with.

  Args:
    cameras: N >= 2 cameras of one image size.
    depths: [N, H, W] rendered z-depth (scene units; a NeRF's median depth, which fog does not
      pull towards the camera as the mean does).
    opacities: [N, H, W] accumulated opacity in [0, 1]: pixels below OPACITY_THRESHOLD have no
      surface to check (the background of an object capture).
    pixel_tolerance: pixels a point may land away from where it started, after the round trip.
    relative_depth_tolerance: its depth's largest difference, as a fraction of the depth.
  Returns:
    consistent_fraction: consistent pixels over all views' pixels with a surface (0 when no
      view has one); per_view: each view's fraction (None without a surface); surface_fraction:
      the share of all pixels with a surface; neighbours: each view's neighbour; the tolerances.
  """
  depths = np.asarray(depths, np.float32)
  opacities = np.asarray(opacities, np.float32)
  expected = (cameras.num_cameras, cameras.height, cameras.width)
  for name, array in (("depths", depths), ("opacities", opacities)):
    if array.shape != expected:
      raise InputError(f"must have shape {expected} (views, height, width), got {array.shape}",
                       field=name)
  neighbours = nearest_views(cameras)
  consistent_counts, checked_counts = [], []
  for view, neighbour in enumerate(neighbours):
    pair = np.array([view, neighbour])
    consistent, checked = _consistent_pixels(
        cameras.take(pair), depths[pair], opacities[pair], jnp.float32(pixel_tolerance),
        jnp.float32(relative_depth_tolerance))
    consistent_counts.append(int(np.count_nonzero(consistent)))
    checked_counts.append(int(np.count_nonzero(checked)))
  total_checked = sum(checked_counts)
  return {
      "consistent_fraction": sum(consistent_counts) / total_checked if total_checked else 0.0,
      "per_view": [count / checked if checked else None
                   for count, checked in zip(consistent_counts, checked_counts)],
      "surface_fraction": total_checked / float(np.prod(expected)),
      "neighbours": neighbours.tolist(),
      "pixel_tolerance": pixel_tolerance,
      "relative_depth_tolerance": relative_depth_tolerance,
  }
