"""Volume rendering: compositing densities and colours along rays into pixels.

The quadrature is the standard one (NeRF eq. 3): with optical depth tau_i = sigma_i * delta_i,
alpha_i = 1 - exp(-tau_i), transmittance T_i = exp(-sum_{j<i} tau_j) and weight w_i = T_i alpha_i.
It is written so values *and gradients* stay finite for densities from 0 to 1e10, zero-length and
infinite intervals, and rays whose samples are all empty.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from signerf_jax import math as safe_math
from signerf_jax.nerf.sampling import MAX_DISTANCE

# Beyond ~100 a sample is fully opaque in float32; clamping keeps the running sum of optical
# depths (and so exp(-sum)) finite for densities up to float32 max times infinite intervals.
MAX_OPTICAL_DEPTH = 1e6
# Rays with less accumulated weight than this count as empty: their depth is the far edge.
EMPTY_ACCUMULATION = 1e-6


def compute_weights(densities, edges):
  """Per-sample compositing weights.

  Args:
    densities: [..., N] non-negative volume densities (1 / scene units).
    edges: [..., N + 1] sorted interval edges (ray distances; the last may be inf).
  Returns:
    weights: [..., N], each in [0, 1], summing to <= 1 per ray.
    transmittance_after: [...] light left after the last sample (1 - sum of weights).
  """
  return interval_weights(densities, interval_lengths(edges))


def interval_lengths(edges):
  """[..., N] lengths (>= 0, finite) of the intervals between edges [..., N + 1] (sorted; the
  last may be inf: distances are capped at MAX_DISTANCE)."""
  edges = jnp.minimum(edges, MAX_DISTANCE)
  return jnp.maximum(edges[..., 1:] - edges[..., :-1], 0.0)


def interval_weights(densities, deltas):
  """`compute_weights` given the intervals' lengths [..., N] (>= 0, finite) instead of their
  edges: the intervals follow one another along the ray, with nothing between them."""
  optical_depth = jnp.minimum(densities * deltas, MAX_OPTICAL_DEPTH)
  alpha = -jnp.expm1(-optical_depth)
  accumulated = jnp.cumsum(optical_depth, axis=-1)
  exclusive = jnp.concatenate([jnp.zeros_like(accumulated[..., :1]), accumulated[..., :-1]], -1)
  weights = alpha * jnp.exp(-exclusive)
  return weights, jnp.exp(-accumulated[..., -1])


def composite(weights, values, background=None):
  """sum_i w_i v_i over samples, plus the leftover transmittance times `background`.

  Args:
    weights: [..., N].
    values: [..., N, C].
    background: None or [C] / [..., C].
  """
  result = jnp.sum(weights[..., None] * values, axis=-2)
  if background is not None:
    result = result + (1.0 - jnp.sum(weights, axis=-1, keepdims=True)) * background
  return result


def volume_render(densities, rgbs, edges, cos_to_optical_axis, background=None):
  """Renders a batch of rays.

  Args:
    densities: [..., N] non-negative densities.
    rgbs: [..., N, 3] colours in [0, 1].
    edges: [..., N + 1] sorted interval edges (ray distance along unit directions).
    cos_to_optical_axis: [...] converts ray distance to z-depth.
    background: None (black / nothing behind) or [3] / [..., 3] colour seen through empty space.
  Returns:
    dict with
      rgb: [..., 3] composited colour.
      accumulation: [...] opacity sum_i w_i in [0, 1].
      distance: [...] expected ray distance of the visible surface, sum w t / sum w; the far edge
        for empty rays.
      median_distance: [...] midpoint of the first sample at which the weights reach half the
        accumulation; the far edge for empty rays (no gradient).
      depth, median_depth: [...] the same as z-depth (distance * cos_to_optical_axis).
      weights: [..., N].
      edges: [..., N + 1] the intervals the weights belong to (infinite edges clamped).
  """
  weights, _ = compute_weights(densities, edges)
  finite_edges = jnp.minimum(edges, MAX_DISTANCE)
  centres = 0.5 * (finite_edges[..., 1:] + finite_edges[..., :-1])
  return {**summarise(weights, rgbs, centres, finite_edges[..., 0], finite_edges[..., -1],
                      cos_to_optical_axis, background),
          "weights": weights, "edges": finite_edges}


def summarise(weights, rgbs, centres, first, far, cos_to_optical_axis, background=None):
  """`volume_render`'s per-ray outputs from the samples' weights [..., N], colours [..., N, 3]
  and centres [..., N] (ray distances, increasing along the ray), the first edge [...] and the
  far edge [...] (finite): rgb, accumulation, distance, median_distance, depth, median_depth."""
  accumulation = jnp.sum(weights, axis=-1)
  empty = accumulation < EMPTY_ACCUMULATION
  expected = safe_math.safe_div(jnp.sum(weights * centres, axis=-1), accumulation)
  distance = jnp.where(empty, far, jnp.clip(expected, first, far))

  cumulative = jnp.cumsum(jax.lax.stop_gradient(weights), axis=-1)
  half = 0.5 * jax.lax.stop_gradient(accumulation)[..., None]
  median_index = jnp.argmax(cumulative >= half, axis=-1)
  median = jnp.take_along_axis(jax.lax.stop_gradient(centres), median_index[..., None], -1)[..., 0]
  median_distance = jnp.where(empty, jax.lax.stop_gradient(far), median)
  return {
      "rgb": composite(weights, rgbs, background),
      "accumulation": accumulation,
      "distance": distance,
      "median_distance": median_distance,
      "depth": distance * cos_to_optical_axis,
      "median_depth": median_distance * cos_to_optical_axis,
  }


def merge_samples(outer, inner, t_in, t_out):
  """The samples of two fields along the same rays as one set of intervals: the `inner` field's
  inside (t_in, t_out), the `outer` field's everywhere else.

  The merged edges are all edges of both plus t_in and t_out, so every merged interval lies
  within one interval of each field (or outside a field's range, where its density is 0).

  Args:
    outer, inner: (densities [..., M], rgbs [..., M, 3], edges [..., M + 1]) as
      `volume_render` takes them (M may differ between the two).
    t_in, t_out: [...] the inner field's stretch of each ray (t_in == t_out: none).
  Returns:
    densities [..., M_outer + M_inner + 3], rgbs [..., M_outer + M_inner + 3, 3] and
    edges [..., M_outer + M_inner + 4]; gradients flow to both fields' densities and colours.
  """
  boundaries = jnp.stack([t_in, t_out], axis=-1)
  candidates = jnp.concatenate([outer[2], inner[2], boundaries], axis=-1)
  # 0: outer edge, 1: inner edge, 2: boundary.
  labels = jnp.concatenate([jnp.full(array.shape, label, jnp.int32) for label, array in
                            enumerate((outer[2], inner[2], boundaries))], axis=-1)
  order = jnp.argsort(jax.lax.stop_gradient(candidates), axis=-1, stable=True)
  edges = jax.lax.stop_gradient(jnp.take_along_axis(candidates, order, axis=-1))
  labels = jnp.take_along_axis(labels, order, axis=-1)
  centres = 0.5 * (edges[..., 1:] + edges[..., :-1])

  def lookup(field, label):
    """The field's density and colour on each merged interval: the merged interval after the
    k-th of the field's edges lies in the field's interval k - 1 (if k is in 1..M)."""
    densities, rgbs, field_edges = field
    passed = jnp.cumsum(labels == label, axis=-1)[..., :-1]
    index = jnp.clip(passed - 1, 0, densities.shape[-1] - 1)
    covered = (passed >= 1) & (passed < field_edges.shape[-1])
    density = jnp.where(covered, jnp.take_along_axis(densities, index, axis=-1), 0.0)
    rgb = jnp.take_along_axis(rgbs, index[..., None], axis=-2)
    return density, rgb

  outer_density, outer_rgb = lookup(outer, 0)
  inner_density, inner_rgb = lookup(inner, 1)
  inside = (centres > t_in[..., None]) & (centres < t_out[..., None])
  densities = jnp.where(inside, inner_density, outer_density)
  rgbs = jnp.where(inside[..., None], inner_rgb, outer_rgb)
  return densities, rgbs, edges
