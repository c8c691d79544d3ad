"""OpenCV's lens models: distortion of normalised image coordinates and its inverse.

The models are OpenCV's, so calibrations from OpenCV, COLMAP and nerfstudio carry over exactly:
  * perspective (`camera.Cameras.fisheye` False), cv2.projectPoints' rational radial-tangential
    model of a point (x, y) of the z = 1 plane, with r^2 = x^2 + y^2:
      radial = (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)
      x_distorted = x radial + 2 p1 x y + p2 (r^2 + 2 x^2)
      y_distorted = y radial + p1 (r^2 + 2 y^2) + 2 p2 x y
  * fisheye (`camera.Cameras.fisheye` True), cv2.fisheye's model: a ray at angle theta from the
    optical axis lands at distance theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 +
    k4 theta^8) from the principal point (normalised units), in the ray's own direction.
    cv2.fisheye takes theta = atan(r) on the z = 1 plane; `camera.project` and
    `camera.pixel_rays` take it from the ray itself, so a fisheye sees up to and past 180
    degrees where its calibration reaches.

Normalised coordinates are OpenCV's (x right, y down, on the z = 1 plane); coefficients come
[..., 8] in OpenCV's order, broadcast against the coordinates.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

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


def padded_distortion(distortion, count: int, fisheye: bool) -> np.ndarray:
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
    return fisheye_distort_points(x, y, jnp.ones_like(x), distortion)
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


def fisheye_distort_points(x, y, z, distortion):
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
