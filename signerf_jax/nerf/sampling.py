"""Where along each ray to evaluate the field: the slab test (box intersection), stratified and
PDF sampling, scene contraction.

Every function keeps static shapes: a ray gets a fixed number of interval *edges* t [..., N + 1]
(sorted, metric distance along the unit direction); samples live at interval midpoints.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from signerf_jax import math as safe_math

# Distances are clamped here so points and midpoints stay finite when the far bound is infinite.
MAX_DISTANCE = 1e10


def ray_box_interval(origins, directions, minimum, maximum, closed: bool = True):
  """Where rays are inside an axis-aligned box (the slab test).

  Exact for direction components that are exactly zero (the ray is parallel to a slab: inside
  it for every t, or never; no 0 * inf) and for origins inside the box (the interval starts at
  0); gradients are finite.

  Args:
    origins, directions: [..., 3]; directions need not be unit (t is in their units).
    minimum, maximum: [3] box corners.
    closed: the box includes its faces, so a ray touching or grazing one meets it (selections);
      False: only rays through the interior do (sampling a volume).
  Returns:
    entry, exit: [...] ray parameters with 0 <= entry; meaningful where `hits`.
    hits: [...] bool, the ray (t >= 0) meets the box.
  """
  parallel = directions == 0
  safe_directions = jnp.where(parallel, 1.0, directions)
  to_minimum = (minimum - origins) / safe_directions
  to_maximum = (maximum - origins) / safe_directions
  if closed:
    inside_slab = (origins >= minimum) & (origins <= maximum)
  else:
    inside_slab = (origins > minimum) & (origins < maximum)
  slab_entry = jnp.where(parallel, jnp.where(inside_slab, -jnp.inf, jnp.inf),
                         jnp.minimum(to_minimum, to_maximum))
  slab_exit = jnp.where(parallel, jnp.where(inside_slab, jnp.inf, -jnp.inf),
                        jnp.maximum(to_minimum, to_maximum))
  entry = jnp.maximum(jnp.max(slab_entry, axis=-1), 0.0)
  exit_ = jnp.min(slab_exit, axis=-1)
  return entry, exit_, (entry <= exit_) if closed else (entry < exit_)


def intersect_aabb(origins, directions, bounds):
  """Entry and exit distances of rays through the interior of a box, finite for sampling.

  Args:
    origins, directions: [..., 3].
    bounds: [2, 3] (min corner, max corner).
  Returns:
    t_near, t_far: [...] with 0 <= t_near <= t_far <= MAX_DISTANCE; rays that miss have
      t_near == t_far.
    hit: [...] bool, True where the ray passes through the box's interior ahead of the origin.
  """
  bounds = jnp.asarray(bounds, jnp.float32)
  entry, exit_, _ = ray_box_interval(origins, directions, bounds[0], bounds[1], closed=False)
  t_near = jnp.clip(entry, 0.0, MAX_DISTANCE)
  t_far = jnp.clip(exit_, 0.0, MAX_DISTANCE)
  return t_near, jnp.maximum(t_far, t_near), t_far > t_near


def stratified_edges(key, t_near, t_far, num_intervals: int, randomized: bool):
  """Edges splitting [t_near, t_far] into equal intervals, jittered as one comb per ray.

  Args:
    key: PRNG key (used only when randomized).
    t_near, t_far: [...] ray bounds.
    num_intervals: N.
    randomized: shift each ray's comb by a uniform fraction of an interval (training); the edges
      stay inside [t_near, t_far].
  Returns:
    [..., N + 1] sorted edges.
  """
  fractions = jnp.linspace(0.0, 1.0, num_intervals + 1)
  if randomized:
    shift = jax.random.uniform(key, t_near.shape + (1,)) / num_intervals
    fractions = jnp.clip(fractions + shift - 0.5 / num_intervals, 0.0, 1.0)
  return t_near[..., None] + (t_far - t_near)[..., None] * fractions


def marching_edges(key, t_near, t_far, step: float, num_steps: int, randomized: bool):
  """Fixed-size steps from t_near, clamped to t_far (intervals past the exit have length 0).

  Constant steps (as in instant-NGP) make every sample cover the same distance, so the occupancy
  grid's "is this sample's alpha negligible" test uses one threshold for all rays.

  Returns:
    [..., num_steps + 1] sorted edges.
  """
  offsets = jnp.arange(num_steps + 1, dtype=jnp.float32)
  if randomized:
    offsets = offsets + jax.random.uniform(key, t_near.shape + (1,)) - 0.5
  edges = t_near[..., None] + step * jnp.maximum(offsets, 0.0)
  return jnp.minimum(edges, t_far[..., None])


def distance_to_spacing(t, scale):
  """mip-NeRF 360's spacing s = g(t / scale): linear up to `scale`, then in inverse distance.

  Maps [0, inf] onto [0, 2]: uniform steps in s sample the inner region linearly and the distant
  background in disparity, as the contraction expects.
  """
  x = t / scale
  return jnp.where(x < 1.0, x, 2.0 - safe_math.safe_div(1.0, x))


def spacing_to_distance(s, scale):
  """Inverse of `distance_to_spacing`; s = 2 maps to MAX_DISTANCE instead of inf."""
  x = jnp.where(s < 1.0, s, safe_math.safe_div(1.0, 2.0 - s))
  return jnp.minimum(x * scale, MAX_DISTANCE)


def spaced_edges(key, t_near, t_far, num_intervals: int, randomized: bool, scale: float):
  """Stratified edges uniform in mip-NeRF 360 spacing (for contracted, unbounded scenes)."""
  s_near = distance_to_spacing(t_near, scale)
  s_far = distance_to_spacing(t_far, scale)
  s_edges = stratified_edges(key, s_near, s_far, num_intervals, randomized)
  return spacing_to_distance(s_edges, scale)


def sample_pdf(key, edges, weights, num_intervals: int, randomized: bool,
               padding: float = 0.01):
  """Resamples interval edges from the piecewise-constant distribution `weights` (inverse CDF).

  Args:
    key: PRNG key (used only when randomized).
    edges: [..., M + 1] sorted edges of the coarse intervals.
    weights: [..., M] non-negative weights (need not sum to 1).
    num_intervals: N, the number of new intervals.
    randomized: jitter the quantiles by a common per-ray offset (training).
    padding: added to every weight so that empty-looking space keeps some samples (nerfstudio's
      histogram padding); also makes the CDF well defined for all-zero weights.
  Returns:
    [..., N + 1] sorted edges inside [edges[..., 0], edges[..., -1]].
  """
  weights = jax.lax.stop_gradient(weights) + padding / weights.shape[-1]
  cdf = jnp.cumsum(weights, axis=-1) / jnp.sum(weights, axis=-1, keepdims=True)
  cdf = jnp.concatenate([jnp.zeros_like(cdf[..., :1]), jnp.minimum(cdf[..., :-1], 1.0),
                         jnp.ones_like(cdf[..., :1])], axis=-1)
  quantiles = jnp.linspace(0.0, 1.0, num_intervals + 1)
  if randomized:
    shift = jax.random.uniform(key, edges.shape[:-1] + (1,)) / num_intervals
    quantiles = jnp.clip(quantiles + shift - 0.5 / num_intervals, 0.0, 1.0)
  else:
    quantiles = jnp.broadcast_to(quantiles, edges.shape[:-1] + (num_intervals + 1,))
  interpolate = jnp.vectorize(jnp.interp, signature="(n),(m),(m)->(n)")
  return jax.lax.stop_gradient(interpolate(quantiles, cdf, edges))


def contract(points):
  """mip-NeRF 360 contraction with the L-inf norm (as nerfstudio for grids): [-1, 1]^3 stays,
  everything else is squeezed into [-2, 2]^3.

  Args:
    points: [..., 3] in units where the modelled inner region is [-1, 1]^3.
  Returns:
    [..., 3] in [-2, 2]^3.
  """
  norm = jnp.max(jnp.abs(points), axis=-1, keepdims=True)
  scale = (2.0 - safe_math.safe_div(1.0, norm)) * safe_math.safe_div(1.0, norm)
  return jnp.where(norm <= 1.0, points, points * scale)


def uncontract(contracted):
  """The inverse of `contract`: [..., 3] in (-2, 2)^3 -> [..., 3] points (the L-inf norm n > 1
  came from 1 / (2 - n); the boundary, infinitely far, maps to ~1e6).
  """
  norm = jnp.max(jnp.abs(contracted), axis=-1, keepdims=True)
  far_norm = 1.0 / jnp.maximum(2.0 - norm, 1e-6)
  return jnp.where(norm <= 1.0, contracted,
                   contracted * safe_math.safe_div(far_norm, jnp.maximum(norm, 1.0)))


def perspective(offsets):
  """NDC's warp of forward-facing scenes: (x / depth, y / depth, 1 / depth) with depth along -z.
  A grid over these coordinates spends the same cells on what a pixel covers at every depth, as
  the images do (`perspective_warp.PerspectiveWarp`).

  Args:
    offsets: [..., 3] points in a camera's frame (it looks down -z).
  Returns:
    [..., 3]; points at or behind the camera plane map to depth 1e-6 (far outside the grid).
  """
  depth = jnp.maximum(-offsets[..., 2:], 1e-6)
  return jnp.concatenate([offsets[..., :2] / depth, 1.0 / depth], axis=-1)


def unperspective(warped):
  """The inverse of `perspective`: [..., 3] warped coordinates (third > 0) -> [..., 3] points
  in the camera's frame."""
  depth = 1.0 / jnp.maximum(warped[..., 2:], 1e-12)
  return jnp.concatenate([warped[..., :2] * depth, -depth], axis=-1)


def midpoints(edges):
  """[..., N + 1] edges -> [..., N] interval centres."""
  return 0.5 * (edges[..., 1:] + edges[..., :-1])
