"""Cameras with OpenCV's lens models, and the rays they shoot.

Conventions (as nerfstudio):
  * `camera_to_world` is [3, 4] = [R | t]; the camera's columns are right (+x), up (+y) and back
    (+z): the camera looks down -z (OpenGL). Converters from OpenCV/LLFF live at the dataset edge.
  * Pixel (row i, column j) covers [j, j + 1) x [i, i + 1); its centre is (j + 0.5, i + 0.5).
  * Intrinsics and distortion act on OpenCV normalised coordinates (x right, y down, z = 1).
  * Ray directions are unit vectors; `t` along a ray is metric distance. A pixel's *z-depth*
    (distance along the optical axis, what depth maps store) is `t * ray.cos_to_optical_axis`.

Lens models are OpenCV's, so calibrations from OpenCV, COLMAP and nerfstudio carry over exactly:
  * perspective (`Cameras.fisheye` False), cv2.projectPoints' rational radial-tangential model of
    a point (x, y) of the z = 1 plane, with r^2 = x^2 + y^2:
      radial = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
      x_distorted = x radial + 2 p1 x y + p2 (r^2 + 2 x^2)
      y_distorted = y radial + p1 (r^2 + 2 y^2) + 2 p2 x y
  * fisheye (`Cameras.fisheye` True), cv2.fisheye's model: a ray at angle theta from the optical
    axis lands at distance theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
    from the principal point (normalised units), in the ray's own direction. cv2.fisheye takes
    theta = atan(r) on the z = 1 plane; `project` and `pixel_rays` take it from the ray itself, so
    a fisheye sees up to and past 180 degrees where its calibration reaches.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from signerf_jax import math as safe_math


# OpenCV's coefficients in its own order: (k1, k2, p1, p2, k3, k4, k5, k6) for a perspective lens;
# a fisheye uses the first four slots for its (k1, k2, k3, k4).
DISTORTION_SIZE = 8
FISHEYE_DISTORTION_SIZE = 4
# Coefficient counts `Cameras.create` accepts: OpenCV's 4-, 5- and 8-coefficient forms.
ACCEPTED_DISTORTION_SIZES = (4, 5, 8)
# A fisheye ray 90 degrees or more off the optical axis meets the z = 1 plane nowhere; `undistort`
# returns it at this angle instead (finite plane coordinates, about 1e4 from the centre).
MAX_PLANE_ANGLE = 0.5 * np.pi - 1e-4


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
        distortion=_padded_distortion(distortion, count, fisheye),
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


def _padded_distortion(distortion, count: int, fisheye: bool) -> np.ndarray:
  """[count, 8] float32 coefficients from None, [K] or [count, K] (see `Cameras.create`)."""
  if distortion is None:
    return np.zeros((count, DISTORTION_SIZE), np.float32)
  distortion = np.asarray(distortion, np.float32)
  size = distortion.shape[-1] if distortion.ndim else 0
  if size not in ACCEPTED_DISTORTION_SIZES:
    raise ValueError(f"distortion needs {ACCEPTED_DISTORTION_SIZES} OpenCV coefficients, got "
                     f"shape {distortion.shape}")
  padded = np.zeros((count, DISTORTION_SIZE), np.float32)
  padded[:, :size] = distortion
  if fisheye and np.any(padded[:, FISHEYE_DISTORTION_SIZE:] != 0):
    raise ValueError("a fisheye lens has four coefficients (k1, k2, k3, k4), got "
                     f"{distortion.tolist()}")
  return padded


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


def distort(x, y, distortion, fisheye: bool = False):
  """Applies an OpenCV lens model (module docstring) to points of the z = 1 plane.

  Args:
    x, y: [...] undistorted normalised coordinates (x right, y down).
    distortion: [..., 8] coefficients (see `Cameras`), broadcast against x.
    fisheye: the lens model: OpenCV's perspective model (False) or cv2.fisheye's (True).
  Returns:
    (x_distorted, y_distorted), each [...].
  """
  if fisheye:
    return _fisheye_distort(x, y, jnp.ones_like(x), distortion)
  k1, k2, p1, p2, k3, k4, k5, k6 = jnp.moveaxis(distortion, -1, 0)
  r2 = x * x + y * y
  radial = ((1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))
            / (1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))))
  x_distorted = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
  y_distorted = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
  return x_distorted, y_distorted


def _fisheye_radius(theta, distortion):
  """cv2.fisheye's theta_d: [...] distorted radius of rays at angle `theta` (radians)."""
  k1, k2, k3, k4 = jnp.moveaxis(distortion[..., :FISHEYE_DISTORTION_SIZE], -1, 0)
  theta2 = theta * theta
  return theta * (1.0 + theta2 * (k1 + theta2 * (k2 + theta2 * (k3 + theta2 * k4))))


def _fisheye_distort(x, y, z, distortion):
  """Distorted normalised coordinates of camera-frame points (OpenCV axes) through a fisheye.

  theta is the angle of the point's ray from the optical axis (atan2, not atan of the z = 1
  plane), so points beside or behind the camera plane land beyond 90 degrees.
  """
  rho = jnp.hypot(x, y)
  theta = jnp.arctan2(rho, z)
  on_axis = rho == 0
  # theta_d / rho scales the point onto the image; on the axis in front its limit is 1 / z, and
  # behind, every direction is the same point, so any finite value will do.
  limit = jnp.where(z > 0, safe_math.safe_div(1.0, z), 0.0)
  scale = jnp.where(on_axis, limit,
                    _fisheye_radius(theta, distortion) / jnp.where(on_axis, 1.0, rho))
  return x * scale, y * scale


# The Newton solvers are jitted so that eager callers reuse one compilation per shape (an eager
# `fori_loop` retraces its body on every call).
@functools.partial(jax.jit, static_argnames=("iterations",))
def fisheye_angle(x_distorted, y_distorted, distortion, iterations: int = 10):
  """[...] angle (radians) from the optical axis of a fisheye's ray through distorted
  normalised coordinates: inverts theta_d = theta (1 + k1 theta^2 + ...) by Newton's method
  (as cv2.fisheye.undistortPoints does), starting from theta = theta_d; never negative."""
  target = jnp.hypot(x_distorted, y_distorted)
  target = jnp.broadcast_to(target, jnp.broadcast_shapes(target.shape, distortion.shape[:-1]))

  def newton_step(_, theta):
    radius, slope = jax.jvp(lambda angle: _fisheye_radius(angle, distortion), (theta,),
                            (jnp.ones_like(theta),))
    # Where the lens model folds over (slope 0) or overflows, Newton stays put.
    valid = jnp.abs(slope) > 1e-8
    updated = theta - (radius - target) / jnp.where(valid, slope, 1.0)
    return jnp.maximum(jnp.where(valid & jnp.isfinite(updated), updated, theta), 0.0)

  return jax.lax.fori_loop(0, iterations, newton_step, target)


def _fisheye_polar(x_distorted, y_distorted, distortion, iterations: int):
  """A fisheye point's ray angle theta [...] and the unit direction (u_x, u_y) it lies in, each
  [...] (zero at the principal point, where theta is 0 and the direction does not matter)."""
  x_distorted, y_distorted = jnp.broadcast_arrays(x_distorted, y_distorted,
                                                  distortion[..., 0])[:2]
  theta_distorted = jnp.hypot(x_distorted, y_distorted)
  length = jnp.where(theta_distorted > 0, theta_distorted, 1.0)
  theta = fisheye_angle(x_distorted, y_distorted, distortion, iterations)
  return theta, x_distorted / length, y_distorted / length


@functools.partial(jax.jit, static_argnames=("fisheye", "iterations"))
def undistort(x_distorted, y_distorted, distortion, fisheye: bool = False,
              iterations: int = 10):
  """Inverts `distort` with Newton's method (as nerfstudio / OpenCV do; no closed form exists).

  Args:
    x_distorted, y_distorted: [...] distorted normalised coordinates.
    distortion: [..., 8] coefficients (see `Cameras`), broadcast against x.
    fisheye: the lens model (see `distort`).
    iterations: Newton steps; 10 reach float32 precision for realistic lenses.
  Returns:
    (x, y) undistorted normalised coordinates, each [...], always finite: where the lens model
    folds over, Newton stops; a fisheye's rays at MAX_PLANE_ANGLE or more from the axis come
    back at MAX_PLANE_ANGLE (`camera_directions` gives their true direction).
  """
  if fisheye:
    theta, direction_x, direction_y = _fisheye_polar(x_distorted, y_distorted, distortion,
                                                     iterations)
    plane_radius = jnp.tan(jnp.minimum(theta, MAX_PLANE_ANGLE))
    return direction_x * plane_radius, direction_y * plane_radius
  x_distorted, y_distorted = jnp.broadcast_arrays(x_distorted, y_distorted,
                                                  distortion[..., 0])[:2]

  def newton_step(_, xy):
    x, y = xy
    ones = jnp.ones_like(x)
    # The Jacobian by forward-mode differentiation of `distort` itself, so the inverse always
    # matches the forward model exactly.
    (model_x, model_y), (dx_dx, dy_dx) = jax.jvp(lambda x: distort(x, y, distortion), (x,),
                                                 (ones,))
    _, (dx_dy, dy_dy) = jax.jvp(lambda y: distort(x, y, distortion), (y,), (ones,))
    residual_x, residual_y = model_x - x_distorted, model_y - y_distorted
    determinant = dx_dx * dy_dy - dx_dy * dy_dx
    # A vanishing Jacobian (the model folds over) or an overflowing model (far outside the
    # calibrated field) stops the update instead of sending the point to infinity.
    invertible = jnp.abs(determinant) > 1e-8
    inverse_determinant = 1.0 / jnp.where(invertible, determinant, 1.0)
    updated_x = x - (dy_dy * residual_x - dx_dy * residual_y) * inverse_determinant
    updated_y = y - (dx_dx * residual_y - dy_dx * residual_x) * inverse_determinant
    valid = invertible & jnp.isfinite(updated_x) & jnp.isfinite(updated_y)
    return jnp.where(valid, updated_x, x), jnp.where(valid, updated_y, y)

  return jax.lax.fori_loop(0, iterations, newton_step, (x_distorted, y_distorted))


@functools.partial(jax.jit, static_argnames=("fisheye", "iterations"))
def camera_directions(x_distorted, y_distorted, distortion, fisheye: bool = False,
                      iterations: int = 10) -> jax.Array:
  """[..., 3] unit ray directions in the OpenCV camera frame (x right, y down, z forward) of
  distorted normalised coordinates; a fisheye's may point 90 degrees or more off the axis.

  Arguments as for `undistort`.
  """
  if fisheye:
    theta, direction_x, direction_y = _fisheye_polar(x_distorted, y_distorted, distortion,
                                                     iterations)
    sine = jnp.sin(theta)
    return jnp.stack([direction_x * sine, direction_y * sine, jnp.cos(theta)], -1)
  x, y = undistort(x_distorted, y_distorted, distortion, iterations=iterations)
  return jnp.stack([x, y, jnp.ones_like(x)], -1) * jax.lax.rsqrt(1.0 + x * x + y * y)[..., None]


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
  directions_opencv = camera_directions(x, y, pick(cameras.distortion), cameras.fisheye)
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


def rotation_from_axis_angle(axis_angle):
  """[..., 3, 3] rotations exp([w]x) of axis-angle vectors w [..., 3] (Rodrigues' formula;
  exact and differentiable at w = 0)."""
  angle_squared = jnp.sum(axis_angle**2, axis=-1)[..., None, None]
  x, y, z = jnp.moveaxis(axis_angle, -1, 0)
  zeros = jnp.zeros_like(x)
  skew = jnp.stack([jnp.stack([zeros, -z, y], -1), jnp.stack([z, zeros, -x], -1),
                    jnp.stack([-y, x, zeros], -1)], -2)
  # sin(a) / a and (1 - cos(a)) / a^2 by their Taylor series near 0 (the closed forms are 0/0).
  small = angle_squared < 1e-8
  safe = jnp.where(small, 1.0, angle_squared)
  angle = jnp.sqrt(safe)
  first = jnp.where(small, 1.0 - angle_squared / 6.0, jnp.sin(angle) / angle)
  second = jnp.where(small, 0.5 - angle_squared / 24.0, (1.0 - jnp.cos(angle)) / safe)
  return jnp.eye(3) + first * skew + second * (skew @ skew)


def refine_rays(rays: Rays, adjustments) -> Rays:
  """The rays of cameras whose poses are corrected: camera i turned about its own centre by the
  axis-angle adjustments[i, :3] (radians, world axes) and moved by adjustments[i, 3:] (scene
  units). Used to refine poses while training (the corrections are trained parameters).

  Args:
    rays: Rays [...], whose camera_indices index `adjustments`.
    adjustments: [N, 6] float32 per-camera corrections (zero: the rays unchanged).
  """
  correction = adjustments[rays.camera_indices]
  rotation = rotation_from_axis_angle(correction[..., :3])
  return rays.replace(origins=rays.origins + correction[..., 3:],
                      directions=jnp.einsum("...ij,...j->...i", rotation, rays.directions))


def image_rays(cameras: Cameras, camera_index) -> Rays:
  """All pixel-centre rays of one camera, shape [height, width]."""
  rows, columns = jnp.meshgrid(jnp.arange(cameras.height, dtype=jnp.float32) + 0.5,
                               jnp.arange(cameras.width, dtype=jnp.float32) + 0.5, indexing="ij")
  indices = jnp.full(rows.shape, camera_index, jnp.int32)
  return pixel_rays(cameras, indices, columns, rows)


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
    x, y = _fisheye_distort(x_camera, y_camera, z_depth, distortion)
  else:
    inverse_depth = safe_math.safe_div(1.0, z_depth)
    x, y = distort(x_camera * inverse_depth, y_camera * inverse_depth, distortion)
  pixels = jnp.stack([x * expand(cameras.fx) + expand(cameras.cx),
                      y * expand(cameras.fy) + expand(cameras.cy)], axis=-1)
  return pixels, z_depth
