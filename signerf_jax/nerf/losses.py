"""Training losses and regularisers: weighted colour error, mip-NeRF 360's distortion and
proposal (interlevel) losses, the depth error at known depths (`disparity_error`), and the
near-camera gradient scaling of "Floaters No More"."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from signerf_jax.nerf import packed, sampling


def weighted_mse(predicted, target, weights):
  """sum_r w_r |p_r - t_r|^2 / (3 sum_r w_r): mean squared error over weighted rays.

  Args:
    predicted, target: [R, 3].
    weights: [R] non-negative (0 drops a ray: masked pixels, rays that overflowed the budget).
  """
  squared = jnp.sum((predicted - target)**2, axis=-1)
  return jnp.sum(weights * squared) / jnp.maximum(3.0 * jnp.sum(weights), 1e-8)


def ray_distortion(edges, weights, scale: float):
  """[R] mip-NeRF 360 eq. 15 per ray: sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (t_i+1 - t_i).

  It pulls each ray's weight into as short a stretch as possible: crisp surfaces, so the
  expected depth the editing stages read is where the surface is, not smeared through it.
  The pairwise sum is computed in O(N) from prefix sums over the sorted midpoints.

  Args:
    edges: [R, N + 1] sorted finite interval edges; weights: [R, N].
    scale: distances are divided by it (the scene's extent), keeping the weight scale-free.
  """
  edges = edges / scale
  midpoints = sampling.midpoints(edges)
  cumulative_weight = jnp.cumsum(weights, axis=-1) - weights
  cumulative_moment = jnp.cumsum(weights * midpoints, axis=-1) - weights * midpoints
  pairwise = 2.0 * jnp.sum(weights * (midpoints * cumulative_weight - cumulative_moment), axis=-1)
  return pairwise + jnp.sum(weights**2 * (edges[..., 1:] - edges[..., :-1]), axis=-1) / 3.0


def distortion_loss(aux, scale: float, ray_weights):
  """The mean over rays of `ray_distortion`, weighted by `ray_weights` [R], of the samples in
  `nerf_model.render_rays`' aux: packed where it has them (its "packed" samples and weights,
  `packed.ray_distortion`), else its "edges" [R, N + 1] and "weights" [R, N]. An infinite last
  interval counts as twice as far as its start."""
  edges = aux["edges"]
  limit = 2.0 * edges[:, -2]
  if "packed" in aux:
    samples, weights = aux["packed"]
    sample_limit = packed.at_samples(limit, samples)
    samples = samples._replace(starts=jnp.minimum(samples.starts, sample_limit),
                               ends=jnp.minimum(samples.ends, sample_limit))
    per_ray = packed.ray_distortion(samples, weights, edges.shape[0], scale)
  else:
    per_ray = ray_distortion(jnp.minimum(edges, limit[:, None]), aux["weights"], scale)
  return jnp.sum(ray_weights * per_ray) / jnp.maximum(jnp.sum(ray_weights), 1e-8)


def opacity_entropy(weights, ray_weights):
  """Mean binary entropy (nats) of each ray's opacity a = sum_i w_i: zero for a ray that is
  empty or opaque, log 2 for a half-transparent one. It pushes a field whose views disagree
  towards solid surfaces and empty space instead of averaging them into a haze (the
  entropy is clamped away from a = 0 and 1, where its gradient is infinite).

  Args:
    weights: [R, N] compositing weights; ray_weights: [R] per-ray loss weights.
  """
  opacity = jnp.clip(jnp.sum(weights, axis=-1), 1e-4, 1.0 - 1e-4)
  entropy = -(opacity * jnp.log(opacity) + (1.0 - opacity) * jnp.log1p(-opacity))
  return jnp.sum(ray_weights * entropy) / jnp.maximum(jnp.sum(ray_weights), 1e-8)


def disparity_error(edges, weights, distances, distance_unit: float, ray_weights):
  """The mean over rays of E_w[(d - d*)^2]: the squared error of each interval's disparity
  d = distance_unit / m (m its midpoint; 0 for an infinite interval) against the ray's known
  disparity d* = distance_unit / distance, weighted by the rendering weights, the transparency
  left at disparity 0. Unlike the error of the expected disparity, it penalises weight anywhere
  but at the known depth, so fog in front and behind cannot average out to the right value; in
  disparity, an unbounded background's far points weigh little.

  Args:
    edges: [R, N + 1] sorted interval edges (distances along unit-length rays, scene units);
      weights: [R, N] compositing weights.
    distances: [R] known distances along the rays (scene units).
    ray_weights: [R] per-ray loss weights.
  """
  midpoints = sampling.midpoints(edges)
  disparity = jnp.where(jnp.isfinite(midpoints),
                        distance_unit / jnp.maximum(midpoints, 1e-6 * distance_unit), 0.0)
  target = distance_unit / jnp.maximum(distances, 1e-6 * distance_unit)
  transparent = jnp.maximum(1.0 - jnp.sum(weights, axis=-1), 0.0)
  error = jnp.sum(weights * (disparity - target[:, None])**2, axis=-1) + transparent * target**2
  return jnp.sum(ray_weights * error) / jnp.maximum(jnp.sum(ray_weights), 1e-8)


def _searchsorted(sorted_edges, queries):
  """For each query, the last edge index <= it and the first index > it (clamped to the ends).

  Dense comparisons instead of a binary search: cheap at these sizes and free of gathers on CPU.
  Args:
    sorted_edges: [..., M + 1]; queries: [..., K + 1].
  Returns:
    index_low, index_high: [..., K + 1] int.
  """
  index = jnp.arange(sorted_edges.shape[-1])
  above = queries[..., None, :] >= sorted_edges[..., :, None]  # [..., M + 1, K + 1]
  index_low = jnp.max(jnp.where(above, index[:, None], index[:1, None]), axis=-2)
  index_high = jnp.min(jnp.where(~above, index[:, None], index[-1:, None]), axis=-2)
  return index_low, index_high


def outer_weights(edges, proposal_edges, proposal_weights):
  """The largest weight the proposal histogram puts on each of `edges`' intervals (its outer
  measure: the mass of every proposal interval overlapping the interval).

  Args:
    edges: [..., K + 1] target intervals; proposal_edges: [..., M + 1]; proposal_weights: [..., M].
  Returns:
    [..., K].
  """
  cumulative = jnp.concatenate([jnp.zeros_like(proposal_weights[..., :1]),
                                jnp.cumsum(proposal_weights, axis=-1)], axis=-1)
  index_low, index_high = _searchsorted(proposal_edges, edges)
  low = jnp.take_along_axis(cumulative, index_low, axis=-1)
  high = jnp.take_along_axis(cumulative, index_high, axis=-1)
  return high[..., 1:] - low[..., :-1]


def interlevel_loss(edges, weights, proposals, ray_weights):
  """mip-NeRF 360 eq. 13: each proposal histogram must upper-bound the NeRF's weights.

  Only the proposal networks learn from it: the NeRF's edges and weights are held fixed.
  Args:
    edges, weights: [R, K + 1], [R, K] of the radiance field.
    proposals: list of (edges [R, M + 1], weights [R, M]) of the proposal networks.
    ray_weights: [R] per-ray loss weights.
  """
  edges, weights = jax.lax.stop_gradient(edges), jax.lax.stop_gradient(weights)
  total = 0.0
  for proposal_edges, proposal_weights in proposals:
    bound = outer_weights(edges, jax.lax.stop_gradient(proposal_edges), proposal_weights)
    excess = jnp.maximum(0.0, weights - bound)**2 / (weights + 1e-7)
    total = total + jnp.sum(ray_weights * jnp.sum(excess, axis=-1)) / jnp.maximum(
        jnp.sum(ray_weights), 1e-8)
  return total


@jax.custom_vjp
def scale_gradient(values, scale):
  """The identity on `values`, whose gradient is multiplied by `scale` (broadcast against it)."""
  return values


def _scale_gradient_forward(values, scale):
  return values, scale


def _scale_gradient_backward(scale, gradient):
  return gradient * scale, jnp.zeros_like(scale)


scale_gradient.defvjp(_scale_gradient_forward, _scale_gradient_backward)


def near_camera_gradient_scaling(densities, rgbs, distances, distance_unit: float):
  """Floaters No More (Philip & Deschaintre, EGSR 2023): each sample's density and colour
  gradients are scaled by min(1, (t / distance_unit)^2), t its distance from the camera.

  Space near a camera is seen by few rays but covers many pixels of them, so it receives large
  gradients from every view's errors and grows floaters that explain one view's pixels; the
  quadratic falloff evens out that density of gradient. Values are unchanged.

  Args:
    densities: [...]; rgbs: [..., 3]; distances: [...] of the samples (their midpoints).
    distance_unit: distance (scene units) from which gradients are unscaled (the cameras'
      distance to the scene, as nerfstudio's unit-scaled scenes use 1).
  """
  scale = jnp.minimum(jax.lax.stop_gradient(distances) / distance_unit, 1.0)**2
  return scale_gradient(densities, scale), scale_gradient(rgbs, scale[..., None])
