"""Control depth in the form depth ControlNets expect: near = 1 (white), far = 0 (black).

Depth ControlNets are trained on MiDaS-style maps: relative *inverse* depth (disparity), min-max
normalised per image. We do the same, but over a range fixed by the selection rather than by each
image's content:

  normalised = (1 / z - 1 / far) / (1 / near - 1 / far), clipped to [0, 1],

with [near, far] the z-range of the selection's bounding sphere in that camera, widened by
`padding` times the radius on both sides. Everything nearer than `near` (an occluder) is 1,
everything beyond `far` (background, empty pixels, +inf) is 0.

Why a per-camera range from the 3D selection and not one metric range for all views: the dataset
cameras of the slot update can be much nearer or farther from the selection than the reference
cameras, and one metric range would clip them to all-white or all-black. Defined from the same
3D sphere, the selection spans the same normalised band in every tile and every slot view: the
tiles of a sheet and each view put in its slot are comparable, which is what the sheet needs.
Passing scalar `near` / `far` instead gives one shared metric range when that is wanted.

Both functions are jitted: called on concrete arrays, as the editing stages do, each is one
compiled program rather than a score of small operations, each compiled on its first call.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from signerf_jax import camera as camera_lib


@jax.jit
def selection_depth_range(cameras: camera_lib.Cameras, center, radius, padding: float = 0.25,
                          min_near_fraction: float = 0.05):
  """Per-camera z-range of the selection's bounding sphere, padded.

  Args:
    cameras: N cameras.
    center: [3] sphere centre; radius: sphere radius (scene units).
    padding: extra margin on both sides, as a fraction of the radius.
    min_near_fraction: `near` is at least this fraction of `far`, which bounds the inverse-depth
      contrast when a camera is at or inside the sphere.
  Returns:
    near, far: [N] float32 z-depths with 0 < near < far.
  """
  _, center_depth = camera_lib.project(cameras, jnp.asarray(center, jnp.float32))
  half_width = jnp.asarray(radius, jnp.float32) * (1.0 + padding)
  far = jnp.maximum(center_depth + half_width, half_width)
  near = jnp.maximum(center_depth - half_width, min_near_fraction * far)
  return near, far


@jax.jit
def normalize_control_depth(z_depth, near, far) -> jax.Array:
  """Normalised inverse depth in [0, 1] (near = 1, far = 0).

  Args:
    z_depth: [N, H, W] z-depth; +inf, nan and values <= 0 mean nothing there (0).
    near, far: scalars or [N] per-camera range with 0 < near < far.
  Returns:
    [N, H, W] float32.
  """
  near = jnp.asarray(near, jnp.float32).reshape(jnp.shape(near) + (1, 1))
  far = jnp.asarray(far, jnp.float32).reshape(jnp.shape(far) + (1, 1))
  valid = jnp.isfinite(z_depth) & (z_depth > 0)
  inverse = jnp.where(valid, 1.0 / jnp.where(valid, z_depth, 1.0), 0.0)
  normalised = (inverse - 1.0 / far) / (1.0 / near - 1.0 / far)
  return jnp.where(valid, jnp.clip(normalised, 0.0, 1.0), 0.0)


def control_image(normalised) -> jax.Array:
  """[..., H, W] normalised depth -> [..., H, W, 3] grey image, as ControlNet takes it."""
  return jnp.repeat(jnp.asarray(normalised)[..., None], 3, axis=-1)
