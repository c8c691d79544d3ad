"""Colour agreement of a ray's samples with the neighbouring training views: a soft plane sweep
along every training ray.

A training pixel's colour c is what its surface looks like. A sample at the surface projects
into a neighbouring training view onto the same surface, so that view's pixel there has colour
near c; a sample in free space (a floater) projects onto whatever lies behind it from that
view, usually another colour. The loss is the rendering-weighted mean, over a ray's samples, of
the colour difference to the best-agreeing neighbour (the minimum over neighbours tolerates a
surface one neighbour sees occluded), truncated so that occlusion and reflections cost little;
its gradient moves a ray's weight from samples that disagree to samples that agree. Samples no
neighbour sees (outside its image or behind it) take no part. Between few views the colour
loss alone leaves each view free to explain its pixels with content at any depth; this ties
the depth to what the other photos show at every pixel two views see, where keypoints
(`keypoint_depth`) pin it only at a few hundred.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from signerf_jax import camera as camera_lib
from signerf_jax.metrics import consistency
from signerf_jax.nerf import sampling


# Below this much of a ray's weight on samples some neighbour sees, the disagreement is summed
# instead of averaged (`sample_disagreement`).
MIN_NORMALISED_WEIGHT = 0.5


def neighbour_views(cameras: camera_lib.Cameras, count: int) -> jax.Array:
  """[N, K] int32: each of `cameras`' K = min(`count`, N - 1) nearest other cameras by the
  distance between their centres."""
  count = min(count, cameras.num_cameras - 1)
  return jnp.asarray(consistency.nearest_cameras(cameras, count), jnp.int32)


def bilinear_colours(images, views, pixels):
  """Colours [..., 3] of `images` [N, H, W, 3] at continuous `pixels` [..., 2] (x, y; centres at
  +0.5) of `views` [...] int, interpolated bilinearly and clamped at the border."""
  height, width = images.shape[1:3]
  x = jnp.clip(pixels[..., 0] - 0.5, 0.0, width - 1.0)
  y = jnp.clip(pixels[..., 1] - 0.5, 0.0, height - 1.0)
  x0 = jnp.minimum(jnp.floor(x), width - 2.0)
  y0 = jnp.minimum(jnp.floor(y), height - 2.0)
  fx, fy = (x - x0)[..., None], (y - y0)[..., None]
  x0, y0 = x0.astype(jnp.int32), y0.astype(jnp.int32)
  at = lambda row, column: images[views, row, column]
  top = at(y0, x0) * (1 - fx) + at(y0, x0 + 1) * fx
  bottom = at(y0 + 1, x0) * (1 - fx) + at(y0 + 1, x0 + 1) * fx
  return top * (1 - fy) + bottom * fy


def sample_disagreement(edges, weights, rays: camera_lib.Rays, images,
                        cameras: camera_lib.Cameras, neighbour_views: jax.Array, ray_weights,
                        truncation: float):
  """The mean over rays of each ray's weighted mean colour disagreement (module docstring).

  Args:
    edges: [R, S + 1] sorted interval edges (distances along the unit rays); weights: [R, S].
    rays: the R training rays of `cameras`, the N training cameras.
    images: [N, H, W, 3] their images in [0, 1]. A ray's own colour is its image's at the ray's
      pixel (for RGBA photos the composited one, not a step's random background).
    neighbour_views: [N, K] int the views each view's samples are compared in
      (`neighbour_views`).
    ray_weights: [R] per-ray loss weights.
    truncation: largest disagreement a sample counts (mean absolute difference over RGB).
  Returns:
    scalar; its gradient reaches the weights alone.
  """
  midpoints = sampling.midpoints(edges)
  finite = jnp.isfinite(midpoints)
  distances = jnp.where(finite, midpoints, 0.0)
  # A point a unit along each ray (it projects onto the ray's own (sub)pixel), then its samples.
  distances = jnp.concatenate([jnp.ones_like(distances[:, :1]), distances], axis=1)
  points = rays.origins[:, None] + distances[..., None] * rays.directions[:, None]
  # Projected into each ray's own camera (index 0) and its neighbours'.
  viewers = jnp.concatenate([rays.camera_indices[:, None],
                             neighbour_views[rays.camera_indices]], axis=1)  # [R, 1 + K]
  project = lambda indices, ray_points: camera_lib.project(
      jax.tree.map(lambda array: jnp.asarray(array)[indices], cameras), ray_points)
  pixels, depth = jax.vmap(project)(viewers, jax.lax.stop_gradient(points))  # [R, 1 + K, 1 + S]
  targets = bilinear_colours(images, rays.camera_indices, pixels[:, 0, 0])
  neighbours, pixels, depth = viewers[:, 1:], pixels[:, 1:, 1:], depth[:, 1:, 1:]
  height, width = images.shape[1:3]
  inside = ((depth > 0) & (pixels[..., 0] >= 0) & (pixels[..., 0] <= width)
            & (pixels[..., 1] >= 0) & (pixels[..., 1] <= height))
  colours = bilinear_colours(images, jnp.broadcast_to(neighbours[..., None], depth.shape), pixels)
  difference = jnp.minimum(jnp.mean(jnp.abs(colours - targets[:, None, None]), axis=-1),
                           truncation)
  best = jnp.min(jnp.where(inside, difference, jnp.inf), axis=1)  # [R, S]
  seen = jnp.isfinite(best) & finite
  best = jax.lax.stop_gradient(jnp.where(seen, best, 0.0))
  seen_weights = weights * seen
  # A ray whose seen samples hold little weight (mostly background, or outside the neighbours'
  # images) is not normalised: its gradient would grow as 1 / its weight.
  per_ray = jnp.sum(seen_weights * best, axis=-1) / jnp.maximum(
      jnp.sum(seen_weights, axis=-1), MIN_NORMALISED_WEIGHT)
  return jnp.sum(ray_weights * per_ray) / jnp.maximum(jnp.sum(ray_weights), 1e-8)
