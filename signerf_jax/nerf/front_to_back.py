"""Evaluating a trained field only where it can be seen, front to back (`render_trained`
renders with it; training and the full render, `model.render_rays`, evaluate every sample).

Behind an opaque surface nothing is seen, and a sample of negligible weight adds nothing to the
colour. So
  * a ray's samples are evaluated in passes, front to back (`RenderSettings.first_pass`), and
    after each pass only the rays whose transmittance is still above
    `RenderSettings.termination` go on (early ray termination; what is left, at most that much
    light, goes to the background);
  * the colour network (the larger of the field's two) can be evaluated after the density, only
    at the samples that are seen (`RenderSettings.colour_weight`), from the geometry features
    the density pass kept;
  * the samples a pass evaluates are compacted into pieces with `jnp.nonzero(size=...)`:
    shapes are static, so nothing recompiles, and no piece runs past the last sample.
A sample left out has density 0 and colour 0, so a render differs from the full one by at most
the light left at termination plus the weight left without its colour, and whatever fewer
samples change (`RenderSettings.field_sample_fraction`; tests/nerf/test_render_fast.py).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax.camera import Rays
from signerf_jax.nerf import volume
from signerf_jax.nerf.fields import RadianceField


@dataclasses.dataclass(frozen=True)
class RenderSettings:
  """How a trained field is rendered (static under jit). The defaults keep held-out PSNR within
  0.12 dB of every sample's on stitch (the field-sample fraction) and 0.01 dB on lego
  (docs/results.md).

  Attributes:
    termination: a ray stops being evaluated once its transmittance is below this (0: never).
    colour_weight: proposal sampler: the colour is evaluated only at samples with at least this
      weight over the samples a ray has, so that the samples left out (taken as black) weigh
      this much at most (0: every sample's colour).
    field_sample_fraction: proposal sampler: the share of the field's samples a ray takes at
      most (`Capacity.sample_counts`; a model asking for fewer, as the viewer's moving frames
      do, takes its own).
    empty_below: proposal sampler: a proposal network's sample is not evaluated (its density is
      taken as 0) where the network's density grid (`render_state.proposal_grids`: an upper
      estimate per cell) times the sample's length is below this (0: every sample is).
    list_samples: occupancy sampler: the steps of a ray's list (its first occupied blocks of
      steps, `render_trained`); a ray still visible after them and with more occupied steps is
      rendered again with every step of its march.
    hit_share: occupancy sampler: the share of a chunk's rays listed at once, of those that
      pass an occupied cell (in as many groups as they need; the others see nothing).
    overflow_share: occupancy sampler: the share of a group's rays rendered again with every
      step at once (in as many groups as needed).
    first_pass: samples a ray's first front-to-back pass takes; each further pass takes twice
      as many as the one before (termination is checked between passes).
    piece_samples: samples a compacted pass evaluates at a time (the last piece is padded), at
      most: `piece_samples_per_ray` times the rays when fewer.
  """

  termination: float = 1e-2
  colour_weight: float = 1e-2
  field_sample_fraction: float = 2 / 3
  empty_below: float = 3e-3
  list_samples: int = 64
  hit_share: float = 0.0625
  overflow_share: float = 0.125
  first_pass: int = 4
  piece_samples: int = 8192
  piece_samples_per_ray: float = 2.0

  @property
  def max_optical_depth(self) -> float:
    """The optical depth at which a ray's transmittance falls below `termination`."""
    return math.inf if self.termination <= 0 else -math.log(self.termination)


def evaluate_compacted(evaluate, mask, piece_size: int, templates):
  """`evaluate` at the True entries of `mask`, `piece_size` entries at a time (forward only).

  Args:
    evaluate: flat indices [P] into `mask` (mask.size: padding) -> a pytree of [P, ...] arrays.
    mask: [R, N] bool.
    templates: a pytree shaped as `evaluate`'s outputs of one entry ([...] shapes, dtypes).
  Returns:
    the pytree of [R * N, ...] arrays: `evaluate`'s values at the True entries, 0 elsewhere.
  """
  padded = int(np.ceil(mask.size / piece_size)) * piece_size
  (indices,) = jnp.nonzero(mask.reshape(-1), size=padded, fill_value=mask.size)
  count = jnp.sum(mask)
  outputs = jax.tree.map(lambda t: jnp.zeros((mask.size,) + t.shape, t.dtype), templates)

  def body(state):
    piece, outputs = state
    piece_indices = jax.lax.dynamic_slice(indices, (piece * piece_size,), (piece_size,))
    values = evaluate(piece_indices)
    return piece + 1, jax.tree.map(
        lambda output, value: output.at[piece_indices].set(value, mode="drop"), outputs, values)

  _, outputs = jax.lax.while_loop(lambda state: state[0] * piece_size < count, body,
                                  (jnp.int32(0), outputs))
  return outputs


def _pass_bounds(num_samples: int, first_pass: int) -> list[tuple[int, int]]:
  """[(first, end)] sample ranges of the passes: `first_pass` samples, then each pass twice as
  many as the one before (most rays end in the first passes), up to `num_samples`; a last
  pass shorter than half the one before joins it (a pass is one more copy of the network to
  compile)."""
  ends = [min(first_pass * (2**(index + 1) - 1), num_samples)
          for index in range(max(1, math.ceil(math.log2(num_samples / first_pass + 1))))]
  if len(ends) > 2 and 2 * (ends[-1] - ends[-2]) < ends[-2] - ends[-3]:
    del ends[-2]
  return list(zip([0] + ends[:-1], ends))


def _piece_size(settings: "RenderSettings", num_rays: int) -> int:
  """Samples a compacted evaluation takes at once for `num_rays` rays: a piece is paid for
  whole, so a few rays (a chunk's rays rendered again) take small pieces."""
  return max(256, min(settings.piece_samples, int(num_rays * settings.piece_samples_per_ray)))


def front_to_back(evaluate, deltas, settings: RenderSettings, candidates=None, templates=None):
  """Evaluates samples [R, N] pass by pass, each pass only on the rays still visible.

  Args:
    evaluate: flat sample indices [P] into [R, N] (R * N: padding) -> (density [P], a pytree
      of [P, ...] arrays).
    deltas: [R, N] interval lengths (scene units).
    candidates: None (every sample) or [R, N] bool, the samples that may hold anything.
    templates: the pytree of `evaluate`'s other outputs for one sample (shapes, dtypes).
  Returns:
    density [R, N] and the pytree of [R, N, ...] arrays, 0 where not evaluated.
  """
  num_rays, num_samples = deltas.shape
  optical_depth = jnp.zeros(num_rays)
  slices = []
  for first, end in _pass_bounds(num_samples, settings.first_pass):
    width = end - first

    def in_pass(local, first=first, width=width):
      """Flat indices into this pass's [R, width] samples -> into [R, N] (padding: R * N)."""
      return jnp.where(local < num_rays * width,
                       local // width * num_samples + first + local % width,
                       num_rays * num_samples)

    if first == 0 and candidates is None:  # Every ray is visible at its first sample.
      values = evaluate(in_pass(jnp.arange(num_rays * width)))
    else:
      mask = (optical_depth < settings.max_optical_depth)[:, None]
      mask = mask & (True if candidates is None else candidates[:, first:end])
      values = evaluate_compacted(
          lambda local, in_pass=in_pass: evaluate(in_pass(local)),
          jnp.broadcast_to(mask, (num_rays, width)), _piece_size(settings, num_rays),
          (jax.ShapeDtypeStruct((), jnp.float32), templates))
    values = jax.tree.map(lambda v, width=width: v.reshape((num_rays, width) + v.shape[1:]),
                          values)
    optical_depth = optical_depth + jnp.sum(jnp.minimum(
        values[0] * deltas[:, first:end], volume.MAX_OPTICAL_DEPTH), axis=-1)
    slices.append(values)
  return jax.tree.map(lambda *parts: jnp.concatenate(parts, axis=1), *slices)


def flat_points(points):
  """Points [R, N, 3] as [R * N, 3], computed once: without the barrier XLA fuses their
  computation (the proposal's inverse CDF, the contraction) into the grid encoding's index
  arithmetic and repeats it for every level and corner (15% of a chunk on stitch)."""
  return jax.lax.optimization_barrier(points).reshape(-1, 3)


def gather(flat, indices):
  """flat [M, ...] at indices [P] (M: padding, read as the last entry)."""
  return flat[jnp.minimum(indices, flat.shape[0] - 1)]


def _seen_colour(model, variables, rays: Rays, weights, features, settings: RenderSettings):
  """Colours [R, N, 3] of the samples whose weight [R, N] reaches `settings.colour_weight` / N
  (0 elsewhere: at most colour_weight of a ray's weight is left without its colour), from
  their geometry features [R, N, G]."""
  num_rays, num_samples = weights.shape
  flat = features.reshape(num_rays * num_samples, -1)
  field_variables = {"params": variables["params"]["field"]}

  def colour(indices):
    safe = jnp.minimum(indices, flat.shape[0] - 1)
    ray_index = safe // num_samples
    return model.field.apply(field_variables, flat[safe], rays.directions[ray_index],
                             jnp.full(ray_index.shape, -1, jnp.int32),
                             method=RadianceField.colour)

  if settings.colour_weight <= 0:
    rgb = colour(jnp.arange(flat.shape[0]))
  else:  # Below colour_weight / N a sample, the samples left out weigh colour_weight at most.
    rgb = evaluate_compacted(colour, weights >= settings.colour_weight / num_samples,
                             _piece_size(settings, num_rays),
                             jax.ShapeDtypeStruct((3,), jnp.float32))
  return rgb.reshape(num_rays, num_samples, 3)


def shade(model, variables, rays: Rays, points, deltas, settings: RenderSettings,
           candidates=None, deferred: bool = True):
  """The field along rays [R] at unit-cube points [R, N, 3] of intervals of lengths deltas
  [R, N], front to back (only at `candidates` [R, N], if given).

  Args:
    deferred: evaluate the colour only where seen (`_seen_colour`), from geometry features the
      density pass keeps; False: with the density. Deferring pays where a ray has few samples
      (the proposal sampler's); with the occupancy sampler's lists it cost more than it saved.
  Returns:
    weights [R, N], the transmittance after them [R] and colours [R, N, 3].
  """
  flat = flat_points(points)
  num_samples = deltas.shape[1]
  field_variables = {"params": variables["params"]["field"]}
  level_weights = variables.get("level_weights")

  def evaluate(indices):
    """(density [P], geometry features [P, G] or colours [P, 3]) at flat sample indices [P]."""
    if deferred:
      return model.field.apply(field_variables, gather(flat, indices), level_weights,
                               method=RadianceField.geometry)
    ray_index = jnp.minimum(indices // num_samples, rays.shape[0] - 1)
    return model.field.apply(field_variables, gather(flat, indices), rays.directions[ray_index],
                             jnp.full(indices.shape, -1, jnp.int32), level_weights)

  values = jax.eval_shape(evaluate, jnp.zeros(1, jnp.int32))[1]
  density, values = front_to_back(evaluate, deltas, settings, candidates, templates=(
      jax.ShapeDtypeStruct(values.shape[1:], values.dtype)))
  weights, transmittance = volume.interval_weights(density, deltas)
  if deferred:
    values = _seen_colour(model, variables, rays, weights, values, settings)
  return weights, transmittance, values


def weight_statistics(weights, centres, rays: Rays, near_distance, selection_box):
  """near_weight [R]: the weight [R, N] of the samples (centres [R, N], ray distances) nearer
  than `near_distance` (scene units); selection_weight [R]: of those inside `selection_box`
  ([2, 3] low and high corners, scene units)."""
  points = rays.origins[:, None] + centres[..., None] * rays.directions[:, None]
  inside = jnp.all((points >= selection_box[0]) & (points <= selection_box[1]), axis=-1)
  return {"near_weight": jnp.sum(weights * (centres < near_distance), axis=-1),
          "selection_weight": jnp.sum(weights * inside, axis=-1)}
