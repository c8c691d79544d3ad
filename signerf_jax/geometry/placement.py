"""Where a picked pixel lands in the scene, and the surface around it: the support a proxy
stands on; and the box around what rectangles drawn in two views see (`editing.place` turns
either into a selection).

The NeRF's median termination depth along the pixel's ray gives the point; the surface around it
is a plane fitted to the points of a window of pixels around it, robust to the window reaching
past the support's edge (onto the object behind, or the background): RANSAC over point triples
with a threshold relative to the distance from the camera, then a least-squares refit to the
inliers.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from signerf_jax import camera as camera_lib
from signerf_jax.errors import InputError

# Inlier threshold of the plane fit, as a fraction of the point's distance from the camera: the
# NeRF's depth error grows with distance.
RELATIVE_THRESHOLD = 0.01
RANSAC_ITERATIONS = 256
# Grid cells per side when intersecting viewing frusta (`frusta_box`).
FRUSTA_GRID = 96


@dataclasses.dataclass(frozen=True)
class Plane:
  """A plane fitted to surface points.

  Attributes:
    point: [3] float64 on the plane (the picked point projected onto it).
    normal: [3] float64 unit normal.
    inlier_fraction: the share of the window's points within the threshold.
    rms_distance: root-mean-square distance of the inliers to the plane (scene units).
  """

  point: np.ndarray
  normal: np.ndarray
  inlier_fraction: float
  rms_distance: float


def _plane_through(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """(centroid, unit normal) of the least-squares plane through [K >= 3, 3] points."""
  centroid = points.mean(axis=0)
  _, _, right = np.linalg.svd(points - centroid)
  return centroid, right[-1]


def fit_plane(points, picked, threshold: float, seed: int = 0,
              iterations: int = RANSAC_ITERATIONS) -> Plane:
  """Fits a plane to `points`, robust to outliers, and projects `picked` onto it.

  Args:
    points: [K, 3] surface points (non-finite rows are dropped).
    picked: [3] the point the plane should support.
    threshold: inlier distance (scene units).
    seed: seeds the RANSAC triples (the fit is deterministic in it).
  Returns:
    the plane; its normal's sign is arbitrary (`orient` it).
  Raises:
    InputError (field "pixel") with fewer than 3 usable points or none off a line.
  """
  points = np.asarray(points, np.float64).reshape(-1, 3)
  points = points[np.all(np.isfinite(points), axis=1)]
  if len(points) < 3:
    raise InputError(f"only {len(points)} surface points around the pixel: pick a pixel on a "
                     "surface the NeRF has learned", field="pixel")
  rng = np.random.default_rng(seed)
  best_inliers, best_count = None, -1
  for _ in range(iterations):
    first, second, third = points[rng.choice(len(points), 3, replace=False)]
    normal = np.cross(second - first, third - first)
    length = np.linalg.norm(normal)
    if length < 1e-12:
      continue
    inliers = np.abs((points - first) @ (normal / length)) < threshold
    if inliers.sum() > best_count:
      best_inliers, best_count = inliers, int(inliers.sum())
  if best_inliers is None or best_count < 3:
    raise InputError("the surface points around the pixel lie on a line: pick a pixel inside a "
                     "surface", field="pixel")
  centroid, normal = _plane_through(points[best_inliers])
  distances = (points[best_inliers] - centroid) @ normal
  picked = np.asarray(picked, np.float64)
  return Plane(point=picked - ((picked - centroid) @ normal) * normal, normal=normal,
               inlier_fraction=best_count / len(points),
               rms_distance=float(np.sqrt(np.mean(distances**2))))


def orient(plane: Plane, towards) -> Plane:
  """The plane with its normal on the side of the point `towards` ([3], e.g. the camera)."""
  side = float((np.asarray(towards, np.float64) - plane.point) @ plane.normal)
  return plane if side >= 0 else dataclasses.replace(plane, normal=-plane.normal)


def window_pixels(x: float, y: float, width: int, height: int, radius: int
                  ) -> tuple[np.ndarray, np.ndarray]:
  """Pixel-centre coordinates ([K] x, [K] y) of the square window of `radius` around pixel
  (x, y), clipped to the image, the picked position itself first."""
  columns = np.arange(max(int(x) - radius, 0), min(int(x) + radius + 1, width)) + 0.5
  rows = np.arange(max(int(y) - radius, 0), min(int(y) + radius + 1, height)) + 0.5
  grid_x, grid_y = np.meshgrid(columns, rows)
  return (np.concatenate([[x], grid_x.ravel()]).astype(np.float32),
          np.concatenate([[y], grid_y.ravel()]).astype(np.float32))


def frusta_box(cameras: camera_lib.Cameras, rectangles, bounds,
               resolution: int = FRUSTA_GRID) -> np.ndarray:
  """The axis-aligned box around what every rectangle sees: the intersection of their viewing
  frusta inside `bounds`, sampled on a grid (two views from different directions triangulate
  the object; nearly parallel views leave the box long along their common direction).

  Args:
    cameras: one camera per rectangle.
    rectangles: [V, 4] (x0, y0, x1, y1) pixel rectangles, one per camera.
    bounds: [2, 3] the region to search (the scene's, scene units).
    resolution: grid cells per side.
  Returns:
    [2, 3] float64 (min, max) corners, scene units (grown by half a grid cell).
  Raises:
    InputError (field "rectangle"): fewer than two rectangles, an empty one, or frusta that do
    not meet inside `bounds`.
  """
  rectangles = np.asarray(rectangles, np.float64).reshape(-1, 4)
  if len(rectangles) < 2 or len(rectangles) != cameras.num_cameras:
    raise InputError(f"needs one rectangle in each of at least two views, got "
                     f"{len(rectangles)}", field="rectangle")
  low, high = np.minimum(rectangles[:, :2], rectangles[:, 2:]), np.maximum(
      rectangles[:, :2], rectangles[:, 2:])
  if np.any(high - low <= 0):
    raise InputError("a rectangle has no area", field="rectangle")
  lower, upper = np.asarray(bounds, np.float64)
  cell = (upper - lower) / resolution
  steps = (np.arange(resolution) + 0.5)[:, None] * cell
  grid = np.stack(np.meshgrid(*(lower[axis] + steps[:, axis] for axis in range(3)),
                              indexing="ij"), -1).reshape(-1, 3)
  pixels, z_depth = camera_lib.project(cameras, grid)
  pixels, z_depth = np.asarray(pixels), np.asarray(z_depth)
  seen = np.all((z_depth > 0) & np.all((pixels >= low[:, None]) & (pixels <= high[:, None]),
                                       axis=-1), axis=0)
  if not seen.any():
    raise InputError("the rectangles' views do not meet inside the scene: draw them around the "
                     "same object", field="rectangle")
  return np.stack([grid[seen].min(0) - cell / 2, grid[seen].max(0) + cell / 2])
