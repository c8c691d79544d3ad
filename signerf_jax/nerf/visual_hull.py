"""The visual hull of an RGBA capture: the occupancy-grid cells its photos allow to hold anything.

Where a training photo is transparent, its ray passes through empty space all the way: any cell
such a ray crosses is empty. The hull is what is left: the cells every photo that sees them
shows in front of something opaque, and at least one photo sees. Random backgrounds
(`training_data.step_batch`) teach the field the same thing ray by ray, but only where a step's
rays happen to go and only as far as the field can resolve; carving the grid (`occupancy.carve`)
makes it exact from the first step, so no sample is spent and no floater can grow outside the
hull. Few views carve loosely (a sparse capture's hull is a rough polyhedron around the object),
so this is a bound on the geometry, not a shape.

A cell is judged by its bounding sphere: a photo calls it empty only when no opaque pixel lies
within the sphere's projection (the projected radius rounded up, plus a pixel of margin for the
silhouettes that downscaling blurs), and only when the whole projection is inside the frame.
"""

from __future__ import annotations

from typing import Callable

import cv2
import jax.numpy as jnp
import numpy as np

from signerf_jax import camera

# A pixel whose alpha exceeds this is opaque enough to hold something (8-bit alphas step by
# 0.004; a downscaled silhouette's edge pixels keep a fraction of the object).
OPAQUE_ALPHA = 0.01
# Cells projecting larger than this many pixels (radius) are not judged by that photo: the
# dilation would cover most of a small image, and such cells sit close to the camera, where the
# other photos judge them.
MAX_FOOTPRINT_PIXELS = 16


def hull_cells(cameras: camera.Cameras, alphas, resolution: int,
               from_unit_cube: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
  """The cells of a `resolution`^3 grid over the unit cube that lie in the photos' visual hull.

  Args:
    cameras: the N training cameras (scene units).
    alphas: [N, H, W] float32 opacity of the training photos in [0, 1].
    resolution: R, the grid's cells per side.
    from_unit_cube: unit-cube points [..., 3] -> scene points [..., 3] (the model's, bounded:
      an affine map, so a cell's corners bound it).
  Returns:
    [R, R, R] bool: True where no photo shows the cell empty and at least one photo sees it.
  """
  alphas = np.asarray(alphas, np.float32)
  centres_unit = (np.stack(np.meshgrid(*[np.arange(resolution)] * 3, indexing="ij"), -1)
                  .reshape(-1, 3) + 0.5) / resolution
  centres = np.asarray(from_unit_cube(centres_unit), np.float32)
  cell_size = np.asarray(from_unit_cube(np.ones(3) / resolution)) - np.asarray(
      from_unit_cube(np.zeros(3)))
  radius = 0.5 * float(np.linalg.norm(cell_size))
  shown_empty = np.zeros(len(centres), bool)
  seen = np.zeros(len(centres), bool)
  for view in range(cameras.num_cameras):
    seen_here, judged, pixels, footprint = _footprints(cameras.take(np.array([view])), centres,
                                                       radius)
    opaque = _dilated_opacity(alphas[view] > OPAQUE_ALPHA, footprint[judged])
    columns, rows = np.floor(pixels[judged]).astype(np.int32).T
    opaque_near = opaque[footprint[judged], rows, columns]
    seen |= seen_here
    shown_empty[np.flatnonzero(judged)[~opaque_near]] = True
  return (seen & ~shown_empty).reshape((resolution,) * 3)


def _footprints(view: camera.Cameras, centres, radius: float):
  """For one camera and the cells' `centres` [P, 3] (bounding spheres of `radius`): which cells
  it sees ([P] bool: the centre in front of it and inside its frame), which it can judge ([P]
  bool: the sphere in front of it, its projection whole inside the frame and no larger than
  MAX_FOOTPRINT_PIXELS), the centres' pixels [P, 2] and the footprints' radii [P] int32 (whole
  pixels: the projected radius rounded up, plus one)."""
  pixels, z_depth = camera.project(view, jnp.asarray(centres))
  pixels, z_depth = np.asarray(pixels[0]), np.asarray(z_depth[0])
  focal = float(max(view.fx[0], view.fy[0]))
  in_front = z_depth > radius
  projected = np.where(in_front, radius * focal / np.where(in_front, z_depth, 1.0), np.inf)
  footprint = np.ceil(np.minimum(projected, MAX_FOOTPRINT_PIXELS + 1)).astype(np.int32) + 1

  def inside(margin):
    return ((pixels[:, 0] - margin >= 0) & (pixels[:, 0] + margin <= view.width)
            & (pixels[:, 1] - margin >= 0) & (pixels[:, 1] + margin <= view.height))

  seen = (z_depth > 0) & inside(0)
  judged = in_front & (projected <= MAX_FOOTPRINT_PIXELS) & inside(footprint)
  return seen, judged, pixels, footprint


def _dilated_opacity(opaque, footprints) -> np.ndarray:
  """[F + 1, H, W] bool: `opaque` [H, W] dilated by a square of each radius 0..F, F the largest
  of `footprints` (a pixel is True when an opaque pixel lies within that many rows and
  columns)."""
  largest = int(footprints.max(initial=0))
  mask = opaque.astype(np.uint8)
  return np.stack([cv2.dilate(mask, np.ones((2 * size + 1,) * 2, np.uint8)) > 0
                   for size in range(largest + 1)])
