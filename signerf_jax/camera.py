"""Cameras with OpenCV's lens models, and the rays they shoot.

Conventions (as nerfstudio):
  * `camera_to_world` is [3, 4] = [R | t]; the camera's columns are right (+x), up (+y) and back
    (+z): the camera looks down -z (OpenGL). Converters from OpenCV/LLFF live at the dataset edge.
  * Pixel (row i, column j) covers [j, j + 1) x [i, i + 1); its centre is (j + 0.5, i + 0.5).
  * Intrinsics and distortion act on OpenCV normalised coordinates (x right, y down, z = 1).
  * Ray directions are unit vectors; `t` along a ray is metric distance. A pixel's *z-depth*
    (distance along the optical axis, what depth maps store) is `t * ray.cos_to_optical_axis`.

Lens models (distortion and its inverse) are OpenCV's, in `lens`; a camera carries its
coefficients and whether it is a fisheye.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from signerf_jax import lens
from signerf_jax import math as safe_math


@struct.dataclass
class Cameras:
  """A batch of N cameras sharing one image size and one lens model.

  Attributes:
    camera_to_world: [N, 3, 4] float32, OpenGL convention (see module docstring).
    fx, fy: [N] float32 focal lengths in pixels.
    cx, cy: [N] float32 principal point in pixels (image centre = width / 2, height / 2).
    distortion: [N, 8] float32 OpenCV coefficients (k1, k2, p1, p2, k3, k4, k5, k6), or for a
      fisheye (k1, k2, k3, k4, 0, 0, 0, 0); all zero for an ideal pinhole (or an ideal
      equidistant fisheye).
    width, height: image size in pixels (static: array shapes depend on them).
    fisheye: the lens model of every camera of the batch (static: it picks the code that runs):
      False for OpenCV's perspective model, True for cv2.fisheye's (module docstring).
  """

  camera_to_world: jax.Array
  fx: jax.Array
  fy: jax.Array
  cx: jax.Array
  cy: jax.Array
  distortion: jax.Array
  width: int = struct.field(pytree_node=False)
  height: int = struct.field(pytree_node=False)
  fisheye: bool = struct.field(pytree_node=False, default=False)

  @classmethod
  def create(cls, camera_to_world, fx, fy=None, cx=None, cy=None, *, width: int, height: int,
             distortion=None, fisheye: bool = False) -> "Cameras":
    """Builds cameras, broadcasting scalar intrinsics over the batch.

    Args:
      camera_to_world: [N, 3, 4] or [N, 4, 4] (the last row is dropped).
      fx, fy: focal lengths in pixels, scalar or [N]; fy defaults to fx.
      cx, cy: principal point, scalar or [N]; defaults to the image centre.
      width, height: image size in pixels.
      distortion: None, or OpenCV coefficients [K] or [N, K] in OpenCV's order: K = 4
        (k1, k2, p1, p2), 5 (then k3) or 8 (then k4, k5, k6); a fisheye's K = 4 (k1, k2, k3, k4).
        Missing coefficients are zero.
      fisheye: the lens model (see the class docstring).
    Raises:
      ValueError: another number of coefficients, or a fisheye given more than four.
    """
    camera_to_world = np.asarray(camera_to_world, np.float32)[..., :3, :4]
    if camera_to_world.ndim == 2:
      camera_to_world = camera_to_world[None]
    count = camera_to_world.shape[0]

    def per_camera(value, default):
      value = default if value is None else value
      return np.broadcast_to(np.asarray(value, np.float32), (count,)).copy()

    fx = per_camera(fx, None)
    return cls(
        camera_to_world=camera_to_world,
        fx=fx,
        fy=per_camera(fy, fx),
        cx=per_camera(cx, width / 2),
        cy=per_camera(cy, height / 2),
        distortion=lens.padded_distortion(distortion, count, fisheye),
        width=int(width),
        height=int(height),
        fisheye=bool(fisheye),
    )

  @property
  def num_cameras(self) -> int:
    return self.camera_to_world.shape[0]

  def __len__(self) -> int:
    return self.num_cameras

  def take(self, indices) -> "Cameras":
    """The cameras at `indices` ([K] ints or a slice), keeping the batch axis."""
    if isinstance(indices, slice):
      return jax.tree.map(lambda a: a[indices], self)
    indices = np.asarray(indices).reshape(-1)
    return jax.tree.map(lambda a: a[indices], self)

  def resized(self, width: int, height: int) -> "Cameras":
    """The same cameras rendering a `width` x `height` image (intrinsics scaled per axis)."""
    scale_x, scale_y = width / self.width, height / self.height
    return self.replace(fx=self.fx * scale_x, fy=self.fy * scale_y, cx=self.cx * scale_x,
                        cy=self.cy * scale_y, width=int(width), height=int(height))

  def cropped(self, boxes, width: int, height: int) -> "Cameras":
    """The cameras whose `width` x `height` images are the crop `boxes` of these cameras' images.

    Args:
      boxes: [N, 4] [x0, y0, box_width, box_height] in (continuous) pixels of these images, as
        `editing.crops` cuts tiles: new pixel centre (j + 0.5, i + 0.5) sees old pixel
        coordinate (x0 + (j + 0.5) box_width / width, y0 + (i + 0.5) box_height / height).
    """
    boxes = jnp.asarray(boxes, jnp.float32)
    scale_x, scale_y = width / boxes[:, 2], height / boxes[:, 3]
    return self.replace(fx=self.fx * scale_x, fy=self.fy * scale_y,
                        cx=(self.cx - boxes[:, 0]) * scale_x, cy=(self.cy - boxes[:, 1]) * scale_y,
                        width=int(width), height=int(height))

  def downscaled(self, factor: int) -> "Cameras":
    """Cameras for images downscaled by an integer factor (sizes rounded down, as OpenCV does)."""
    return self.resized(self.width // factor, self.height // factor)

  def intrinsic_matrices(self) -> jax.Array:
    """[N, 3, 3] OpenCV intrinsic matrices K."""
    zeros, ones = jnp.zeros_like(self.fx), jnp.ones_like(self.fx)
    rows = [[self.fx, zeros, self.cx], [zeros, self.fy, self.cy], [zeros, zeros, ones]]
    return jnp.stack([jnp.stack(row, -1) for row in rows], -2)

  @property
  def positions(self) -> jax.Array:
    """[N, 3] camera centres in world space."""
    return self.camera_to_world[:, :, 3]

  @property
  def forward(self) -> jax.Array:
    """[N, 3] unit viewing directions (the -z column)."""
    return -self.camera_to_world[:, :, 2]


@struct.dataclass
class Rays:
  """A batch of rays, any leading shape [...].

  Attributes:
    origins: [..., 3] world-space ray origins.
    directions: [..., 3] unit world-space directions.
    cos_to_optical_axis: [...] cosine between the ray and its camera's viewing axis, so that
      z-depth = t * cos_to_optical_axis.
    camera_indices: [...] int32 index of the camera each ray belongs to.
  """

  origins: jax.Array
  directions: jax.Array
  cos_to_optical_axis: jax.Array
  camera_indices: jax.Array

  @property
  def shape(self) -> tuple[int, ...]:
    return self.camera_indices.shape

  def reshape(self, *shape: int) -> "Rays":
    return jax.tree.map(lambda a: a.reshape(*shape, *a.shape[len(self.shape):]), self)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> jax.Array:
  """Camera-to-world matrices for cameras at `eye` looking at `target`.

  Args:
    eye, target: [..., 3] positions (must differ).
    up: [..., 3] approximate world up. When it is parallel to the viewing direction, an axis
      orthogonal to it is used instead, so the result is always a proper rotation.
  Returns:
    [..., 3, 4] OpenGL camera-to-world matrices.
  """
  eye, target = jnp.asarray(eye, jnp.float32), jnp.asarray(target, jnp.float32)
  up = jnp.broadcast_to(jnp.asarray(up, jnp.float32), eye.shape)
  back = safe_math.safe_normalize(eye - target)
  right = jnp.cross(up, back)
  # Looking straight along `up`: pick the world axis least aligned with the view instead.
  fallback_axis = jnp.eye(3, dtype=jnp.float32)[jnp.argmin(jnp.abs(back), axis=-1)]
  degenerate = jnp.linalg.norm(right, axis=-1, keepdims=True) < 1e-6
  right = jnp.where(degenerate, jnp.cross(fallback_axis, back), right)
  right = safe_math.safe_normalize(right)
  camera_up = jnp.cross(back, right)
  return jnp.stack([right, camera_up, back, eye], axis=-1)


def pixel_rays(cameras: Cameras, camera_indices, pixel_x, pixel_y) -> Rays:
  """Rays through (sub)pixel positions.

  Args:
    cameras: the camera batch.
    camera_indices: [...] int index into `cameras`.
    pixel_x, pixel_y: [...] continuous pixel coordinates (a pixel centre is j + 0.5, i + 0.5).
  Returns:
    Rays of shape [...]. A fisheye's rays past 90 degrees from the axis have
    cos_to_optical_axis <= 0 (their z-depth is behind the camera plane).
  """
  camera_indices = jnp.asarray(camera_indices, jnp.int32)
  pick = lambda array: array[camera_indices]
  x = (pixel_x - pick(cameras.cx)) / pick(cameras.fx)
  y = (pixel_y - pick(cameras.cy)) / pick(cameras.fy)
  directions_opencv = lens.camera_directions(x, y, pick(cameras.distortion), cameras.fisheye)
  # OpenCV (x right, y down, +z forward) -> OpenGL camera space (x right, y up, -z forward).
  directions_camera = directions_opencv * jnp.array([1.0, -1.0, -1.0], jnp.float32)
  camera_to_world = pick(cameras.camera_to_world)
  directions = jnp.einsum("...ij,...j->...i", camera_to_world[..., :3, :3], directions_camera)
  return Rays(
      origins=camera_to_world[..., :3, 3],
      directions=safe_math.safe_normalize(directions),
      cos_to_optical_axis=directions_opencv[..., 2],
      camera_indices=camera_indices,
  )


def image_rays(cameras: Cameras, camera_index, subpixel=(0.5, 0.5)) -> Rays:
  """One ray per pixel of one camera, shape [height, width].

  Args:
    subpixel: (x, y) where each ray crosses its pixel, in pixels from the pixel's top-left
      corner (a pair or a [2] array, e.g. a row of `subpixel_positions`); (0.5, 0.5) is the
      centre.
  """
  rows, columns = jnp.meshgrid(jnp.arange(cameras.height, dtype=jnp.float32) + subpixel[1],
                               jnp.arange(cameras.width, dtype=jnp.float32) + subpixel[0],
                               indexing="ij")
  indices = jnp.full(rows.shape, camera_index, jnp.int32)
  return pixel_rays(cameras, indices, columns, rows)


def subpixel_positions(samples_per_side: int) -> np.ndarray:
  """[samples_per_side^2, 2] float32 (x, y): the centres of a samples_per_side x
  samples_per_side grid of sub-pixels, in pixels from the pixel's top-left corner, row by row
  (1: the pixel's centre, (0.5, 0.5))."""
  steps = (np.arange(samples_per_side, dtype=np.float32) + 0.5) / samples_per_side
  x, y = np.meshgrid(steps, steps, indexing="xy")
  return np.stack([x.ravel(), y.ravel()], axis=-1)


def subpixel_rays(cameras: Cameras, camera_indices, rows, columns, samples_per_side: int
                  ) -> Rays:
  """The rays through the `subpixel_positions` of pixels [B] (integer rows and columns), pixel
  by pixel: shape [B * samples_per_side^2], pixel i's rays at i * samples_per_side^2 onwards."""
  positions = jnp.asarray(subpixel_positions(samples_per_side))
  count = positions.shape[0]
  repeat = lambda array: jnp.repeat(jnp.asarray(array), count, axis=0)
  offsets = jnp.tile(positions, (jnp.shape(camera_indices)[0], 1))
  return pixel_rays(cameras, repeat(camera_indices), repeat(columns) + offsets[:, 0],
                    repeat(rows) + offsets[:, 1])


def random_rays(key: jax.Array, cameras: Cameras, batch_size: int):
  """A uniform random batch of pixel-centre rays over all cameras and pixels.

  Returns:
    rays: Rays of shape [batch_size].
    pixels: (camera_index, row, column), each [batch_size] int32, to gather target colours.
  """
  camera_key, row_key, column_key = jax.random.split(key, 3)
  camera_index = jax.random.randint(camera_key, (batch_size,), 0, cameras.num_cameras)
  row = jax.random.randint(row_key, (batch_size,), 0, cameras.height)
  column = jax.random.randint(column_key, (batch_size,), 0, cameras.width)
  rays = pixel_rays(cameras, camera_index, column + 0.5, row + 0.5)
  return rays, (camera_index, row, column)


def project(cameras: Cameras, points):
  """Projects world points into every camera (with its lens model).

  Args:
    points: [..., 3] world-space points.
  Returns:
    pixels: [N, ..., 2] continuous pixel coordinates (x, y).
    z_depth: [N, ...] distance in front of each camera along its axis (<= 0: behind the camera
      plane, where a perspective camera sees nothing but a fisheye wider than 180 degrees does).
  """
  points = jnp.asarray(points, jnp.float32)
  extra_dims = points.ndim - 1
  expand = lambda array: array.reshape(array.shape[:1] + (1,) * extra_dims + array.shape[1:])
  rotation = expand(cameras.camera_to_world[:, :, :3])
  translation = expand(cameras.camera_to_world[:, :, 3])
  # world -> camera is R^T (p - t).
  local = jnp.einsum("...ji,...j->...i", rotation, points[None] - translation)
  # OpenGL camera space -> OpenCV's (x right, y down, z forward).
  x_camera, y_camera, z_depth = local[..., 0], -local[..., 1], -local[..., 2]
  distortion = expand(cameras.distortion)
  if cameras.fisheye:
    x, y = lens.fisheye_distort_points(x_camera, y_camera, z_depth, distortion)
  else:
    inverse_depth = safe_math.safe_div(1.0, z_depth)
    x, y = lens.distort(x_camera * inverse_depth, y_camera * inverse_depth, distortion)
  pixels = jnp.stack([x * expand(cameras.fx) + expand(cameras.cx),
                      y * expand(cameras.fy) + expand(cameras.cy)], axis=-1)
  return pixels, z_depth
