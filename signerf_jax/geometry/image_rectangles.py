"""Where a region of the scene can appear in each camera's image, as pixel rectangles, so that
a NeRF is rendered only there (`nerf.render.render_cameras(..., pixels=...)`): conditioning a
training view then costs the selection's share of its pixels, not all of them.

A rectangle is [x_start, y_start, x_stop, y_stop] int64: the pixel columns x_start <= j < x_stop
and rows y_start <= i < y_stop, half-open and clipped to the image; empty when x_stop <= x_start.

`points_rectangles` bounds the pixels whose centre ray can meet the convex hull of some points
(a selection box's corners, a proxy's vertices). For points all in front of a camera, a ray from
its centre meets their hull exactly when the ray's point on the plane z = 1 (camera frame) lies
in the hull of the points' pinhole projections onto that plane, so inside their bounding
rectangle there. Each pixel-centre ray is the one the cameras shoot (`lens.camera_directions`:
distortion honoured), so this also holds for distorted and fisheye lenses, which bend the hull's
straight edges: the rectangle of the points' *distorted* projections could miss the bulge. A
camera with a point on or behind its plane (the hull's image is then unbounded) gets the full
frame.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax import camera as camera_lib
from signerf_jax import lens

# Points nearer the camera plane than this (scene units) count as behind it: the full frame.
CAMERA_PLANE_EPSILON = 1e-6
# A ray this far outside the hull (in pixels at the focal length) still counts as inside: float
# rounding in the renderer's ray-box and ray-triangle tests is far below a pixel, so it never
# finds a hit outside the rectangle.
TOLERANCE_PIXELS = 0.25


def _one_camera_bounds(cameras: camera_lib.Cameras, points, index):
  """[4] int32 bounds (x_start, y_start, x_stop, y_stop) of camera `index`'s pixels whose centre
  ray meets the hull of `points` [K, 3]; (0, 0, 0, 0) when none, the full frame when a point is
  not in front of the camera."""
  rotation, origin = cameras.camera_to_world[index, :, :3], cameras.camera_to_world[index, :, 3]
  local = (points - origin) @ rotation  # R^T (p - t), in OpenGL camera axes.
  x, y, z = local[:, 0], -local[:, 1], -local[:, 2]  # OpenCV axes: z forward.
  in_front = jnp.all(z > CAMERA_PLANE_EPSILON) & jnp.all(jnp.isfinite(local))
  safe_z = jnp.where(z > CAMERA_PLANE_EPSILON, z, 1.0)
  u, v = x / safe_z, y / safe_z
  fx, fy = cameras.fx[index], cameras.fy[index]
  rows = jnp.arange(cameras.height, dtype=jnp.float32)[:, None] + 0.5
  columns = jnp.arange(cameras.width, dtype=jnp.float32)[None, :] + 0.5
  directions = lens.camera_directions((columns - cameras.cx[index]) / fx,
                                      (rows - cameras.cy[index]) / fy,
                                      cameras.distortion[index], cameras.fisheye)
  forward = directions[..., 2] > 0
  safe_forward = jnp.where(forward, directions[..., 2], 1.0)
  plane_u, plane_v = directions[..., 0] / safe_forward, directions[..., 1] / safe_forward
  u_tolerance, v_tolerance = TOLERANCE_PIXELS / fx, TOLERANCE_PIXELS / fy
  inside = (forward & (plane_u >= u.min() - u_tolerance) & (plane_u <= u.max() + u_tolerance)
            & (plane_v >= v.min() - v_tolerance) & (plane_v <= v.max() + v_tolerance))
  hit_columns, hit_rows = inside.any(axis=0), inside.any(axis=1)
  bounds = jnp.stack([jnp.argmax(hit_columns), jnp.argmax(hit_rows),
                      cameras.width - jnp.argmax(hit_columns[::-1]),
                      cameras.height - jnp.argmax(hit_rows[::-1])]).astype(jnp.int32)
  bounds = jnp.where(inside.any(), bounds, 0)
  return jnp.where(in_front, bounds, jnp.array([0, 0, cameras.width, cameras.height], jnp.int32))


@jax.jit
def _hull_bounds(cameras: camera_lib.Cameras, points) -> jax.Array:
  """[N, 4] `_one_camera_bounds` of every camera, one camera at a time (memory: one image)."""
  return jax.lax.map(functools.partial(_one_camera_bounds, cameras, points),
                     jnp.arange(cameras.num_cameras))


def points_rectangles(cameras: camera_lib.Cameras, points, growth: int) -> np.ndarray:
  """The rectangle of each camera's pixels whose centre ray can meet the hull of `points`, grown
  by `growth` pixels on every side and clipped (module docstring).

  Args:
    cameras: N cameras (H x W).
    points: [K, 3] points in scene units.
    growth: pixels (>= 0) added on every side of a non-empty rectangle.
  Returns:
    [N, 4] int64 rectangles [x_start, y_start, x_stop, y_stop]; [0, 0, 0, 0] where no pixel-centre
    ray meets the hull, [0, 0, W, H] where some point is not in front of the camera.
  """
  # Padded to a power of two cameras (repeating the last), so the stages' sets of cameras share
  # a few programs instead of compiling one per count.
  count = cameras.num_cameras
  padded = np.minimum(np.arange(1 << max(count - 1, 0).bit_length()), count - 1)
  bounds = np.asarray(_hull_bounds(cameras.take(padded), jnp.asarray(points, jnp.float32)),
                      np.int64)[:count]
  empty = bounds[:, 2] <= bounds[:, 0]
  grown = bounds + np.array([-growth, -growth, growth, growth], np.int64)
  limits = np.array([cameras.width, cameras.height] * 2, np.int64)
  return np.where(empty[:, None], 0, np.clip(grown, 0, limits))


def box_rectangles(boxes, height: int, width: int) -> np.ndarray:
  """The rectangles of the pixels whose centres lie inside continuous boxes, clipped.

  Args:
    boxes: [N, 4] [x0, y0, box_width, box_height] in pixels (a pixel centre is j + 0.5, i + 0.5).
    height, width: the image size.
  Returns:
    [N, 4] int64 rectangles [x_start, y_start, x_stop, y_stop].
  """
  boxes = np.asarray(boxes, np.float64)
  start = np.ceil(boxes[:, :2] - 0.5)
  stop = np.floor(boxes[:, :2] + boxes[:, 2:] - 0.5) + 1
  limits = np.array([width, height], np.float64)
  return np.concatenate([np.clip(start, 0, limits), np.clip(stop, 0, limits)], -1).astype(np.int64)


def rectangle_pixels(rectangles, height: int, width: int) -> np.ndarray:
  """[N, H, W] bool: the pixels inside each camera's rectangle ([N, 4], module docstring)."""
  rectangles = np.asarray(rectangles, np.int64)
  columns, rows = np.arange(width), np.arange(height)
  in_columns = (columns >= rectangles[:, 0, None]) & (columns < rectangles[:, 2, None])
  in_rows = (rows >= rectangles[:, 1, None]) & (rows < rectangles[:, 3, None])
  return in_rows[:, :, None] & in_columns[:, None, :]
