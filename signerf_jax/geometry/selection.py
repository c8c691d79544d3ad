"""Where to edit: shape selection (an axis-aligned box) and proxy selection (a placed mesh).

Both turn NeRF renders of N cameras into a per-pixel inpainting mask and a control depth map
(paper, "Selection Modes"). Depths here are per pixel and per camera, [N, H, W]:
  * a NeRF depth is given as z-depth (the project's depth-map convention) or as ray distance;
  * pixels without NeRF content (accumulation below `min_accumulation`) have no surface and count
    as infinitely far;
  * control depths come out as z-depth in scene units, +inf where nothing is there.

Shape selection, per pixel ray r(t) = o + t d with NeRF surface distance t_s and box interval
[t_entry, t_exit] (t_entry clamped to 0 when the camera is inside the box):
  * mask ("surface" mode, the default): the surface point r(t_s) lies inside the box, i.e. the
    ray meets the box and t_entry <= t_s <= t_exit;
    ("silhouette" mode): the box is visible, i.e. the ray meets the box and t_entry <= t_s (the
    scene does not hide the box's front); this also selects empty space inside the box, which
    lets an edit grow beyond the current surface.
  * control depth: the paper clamps the NeRF depth to "the point closest and furthest away to the
    rendering camera within the bounding box": min(t_s, t_exit) where the ray meets the box and
    t_s >= t_entry, so surfaces behind the box (and empty background) read as the box's back
    face. A surface in front of the box (an occluder, t_s < t_entry) keeps its own depth: it is
    outside every mask and must stay consistent with the pixels the diffusion model keeps.
    Rays that miss the box keep the NeRF depth.
Proxy selection composites NeRF and proxy depth (nearest wins); the mask is where the proxy is
the nearest surface (visible), and the control depth is the composite.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from flax import struct

from signerf_jax import camera as camera_lib
from signerf_jax.errors import InputError
from signerf_jax.nerf import sampling

DEPTH_KINDS = ("z", "distance")
MASK_MODES = ("surface", "silhouette")


@struct.dataclass
class Box:
  """An axis-aligned box: `minimum`, `maximum` are [3] float32 corners in scene units."""

  minimum: jax.Array
  maximum: jax.Array

  @classmethod
  def create(cls, minimum, maximum) -> "Box":
    minimum = jnp.asarray(minimum, jnp.float32)
    maximum = jnp.asarray(maximum, jnp.float32)
    if minimum.shape != (3,) or maximum.shape != (3,):
      raise InputError("box corners must be 3-vectors", field="box")
    if not bool(jnp.all(jnp.isfinite(minimum)) & jnp.all(jnp.isfinite(maximum))):
      raise InputError("box corners must be finite", field="box")
    if not bool(jnp.all(maximum > minimum)):
      raise InputError(f"box maximum {maximum.tolist()} must exceed minimum {minimum.tolist()} "
                       "on every axis", field="box")
    return cls(minimum, maximum)

  @classmethod
  def from_center_size(cls, center, size) -> "Box":
    center, size = jnp.asarray(center, jnp.float32), jnp.asarray(size, jnp.float32)
    return cls.create(center - size / 2, center + size / 2)

  @property
  def center(self) -> jax.Array:
    return (self.minimum + self.maximum) / 2

  @property
  def corners(self) -> jax.Array:
    """[8, 3] corner points."""
    choose = jnp.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], bool)
    return jnp.where(choose, self.maximum, self.minimum)


@struct.dataclass
class Selection:
  """The selection as seen by N cameras, [N, H, W] each.

  Attributes:
    mask: bool, pixels to inpaint (before dilation).
    control_depth: float32 z-depth in scene units for the depth ControlNet; +inf = nothing.
  """

  mask: jax.Array
  control_depth: jax.Array


def surface_distance(depth, cos_to_optical_axis, accumulation=None, depth_kind: str = "z",
                     min_accumulation: float = 0.5):
  """NeRF depth as distance along unit rays, +inf where the NeRF has no content.

  Args:
    depth: [...] z-depth or ray distance (see `depth_kind`); values <= 0 or non-finite mean
      "unknown" and count as no surface.
    cos_to_optical_axis: [...] from the pixel rays.
    accumulation: None or [...] NeRF opacity in [0, 1].
    depth_kind: "z" or "distance".
    min_accumulation: opacity below which a pixel has no surface.
  """
  if depth_kind not in DEPTH_KINDS:
    raise InputError(f"depth_kind must be one of {DEPTH_KINDS}, got {depth_kind!r}",
                     field="depth_kind")
  distance = depth / cos_to_optical_axis if depth_kind == "z" else depth
  has_surface = jnp.isfinite(distance) & (distance > 0)
  if accumulation is not None:
    has_surface &= accumulation >= min_accumulation
  return jnp.where(has_surface, distance, jnp.inf)


def _per_camera(function, cameras: camera_lib.Cameras, *per_camera_arrays):
  """Maps `function(rays [H, W], *arrays [H, W])` over the cameras with vmap."""

  def one_camera(camera_index, *arrays):
    return function(camera_lib.image_rays(cameras, camera_index), *arrays)

  return jax.vmap(one_camera)(jnp.arange(cameras.num_cameras), *per_camera_arrays)


@functools.partial(jax.jit, static_argnames=("depth_kind", "mask_mode", "min_accumulation"))
def shape_selection(cameras: camera_lib.Cameras, box: Box, depth, accumulation=None,
                    depth_kind: str = "z", mask_mode: str = "surface",
                    min_accumulation: float = 0.5) -> Selection:
  """Mask and control depth of an axis-aligned box selection (see the module docstring).

  Args:
    cameras: N cameras (H x W).
    box: the selected region.
    depth: [N, H, W] NeRF depth, kind given by `depth_kind`.
    accumulation: None or [N, H, W] NeRF opacity.
    depth_kind: "z" or "distance".
    mask_mode: "surface" or "silhouette".
    min_accumulation: opacity below which a pixel has no NeRF content.
  Returns:
    Selection with [N, H, W] mask and z-depth control.
  """
  if mask_mode not in MASK_MODES:
    raise InputError(f"mask_mode must be one of {MASK_MODES}, got {mask_mode!r}",
                     field="mask_mode")
  if accumulation is None:
    accumulation = jnp.ones_like(depth)

  def one_camera(rays, depth, accumulation):
    distance = surface_distance(depth, rays.cos_to_optical_axis, accumulation, depth_kind,
                                min_accumulation)
    entry, exit_, hits = sampling.ray_box_interval(rays.origins, rays.directions, box.minimum,
                                                   box.maximum)
    box_visible = hits & (distance >= entry)
    mask = box_visible & (distance <= exit_) if mask_mode == "surface" else box_visible
    control = jnp.where(box_visible, jnp.minimum(distance, exit_), distance)
    return Selection(mask=mask, control_depth=control * rays.cos_to_optical_axis)

  return _per_camera(one_camera, cameras, depth, accumulation)


@functools.partial(jax.jit, static_argnames=("depth_kind", "min_accumulation"))
def proxy_selection(cameras: camera_lib.Cameras, depth, proxy_z_depth, accumulation=None,
                    depth_kind: str = "z", min_accumulation: float = 0.5) -> Selection:
  """Mask and control depth of a proxy mesh placed in the NeRF scene.

  Args:
    cameras: N cameras (H x W).
    depth: [N, H, W] NeRF depth, kind given by `depth_kind`.
    proxy_z_depth: [N, H, W] proxy z-depth, +inf where the proxy is not hit
      (`mesh_depth.render_mesh_depth(...).z_depth`).
    accumulation: None or [N, H, W] NeRF opacity.
    depth_kind: "z" or "distance" for `depth`.
    min_accumulation: opacity below which a pixel has no NeRF content.
  Returns:
    Selection: mask = the proxy is hit and not behind the NeRF surface (ties go to the proxy);
    control depth = the nearer of the two (z-depth).
  """
  if accumulation is None:
    accumulation = jnp.ones_like(depth)

  def one_camera(rays, depth, proxy_z_depth, accumulation):
    nerf_z_depth = surface_distance(depth, rays.cos_to_optical_axis, accumulation, depth_kind,
                                    min_accumulation) * rays.cos_to_optical_axis
    mask = jnp.isfinite(proxy_z_depth) & (proxy_z_depth <= nerf_z_depth)
    return Selection(mask=mask, control_depth=jnp.minimum(nerf_z_depth, proxy_z_depth))

  return _per_camera(one_camera, cameras, depth, proxy_z_depth, accumulation)
