"""Rendering a trained model front to back (`front_to_back`), per sampler.

Proposal sampler (unbounded and forward-facing scenes): each proposal network evaluates only
its samples that its density grid (`render_state.proposal_grids`) does not show empty, front to
back; the field takes `RenderSettings.field_sample_fraction` of its samples at most, and
evaluates their colour where seen.

Occupancy sampler (bounded scenes): a ray's march has hundreds of steps, of which a few lie in
occupied cells, and most rays pass none. The rays that pass one are taken in groups
(`RenderSettings.hit_share`); each ray's first occupied blocks of steps are listed ([R,
list_samples], made from the blocks' occupancy) and evaluated and composited as a list; the
rays still visible after their list that have more occupied steps are rendered again with
every step of their march, as the full render does.

An edit region's model renders the rays that miss the region as its original does, and those
that cross it with every sample (`model.render_rays`).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax.camera import Rays
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf import occupancy, ray_samples, sampling, volume
from signerf_jax.nerf.front_to_back import (RenderSettings, flat_points, front_to_back, gather,
                                            shade, weight_statistics)

# Occupancy sampler: a ray's list (`RenderSettings.list_samples`) takes whole blocks of this many
# consecutive steps (`_occupied_blocks`).
LIST_BLOCK = 8


def _proposal_density(model, params, settings: RenderSettings, grids):
  """`ray_samples.proposal_edges`' proposal_density: each network front to back, only where its
  density grid (`render_state.proposal_grids`, or None) does not say the sample is empty."""

  def density(index, points, edges):
    network, flat, deltas = model.proposal_fields[index], flat_points(points), volume.interval_lengths(edges)
    variables = {"params": params[f"proposal_{index}"]}

    def evaluate(indices):
      return network.apply(variables, gather(flat, indices)), ()

    candidates = None
    if grids is not None and settings.empty_below > 0:
      candidates = occupancy.lookup(grids[index], points) * deltas >= settings.empty_below
    return front_to_back(evaluate, deltas, settings, candidates, templates=())[0]

  return density


def _along_edges(weights, rgbs, edges):
  """(weights, rgbs, centres, first edge, far edge) of samples on finished edges [R, N + 1]."""
  edges = jnp.minimum(edges, sampling.MAX_DISTANCE)
  return weights, rgbs, sampling.midpoints(edges), edges[..., 0], edges[..., -1]


def _proposal_render(model, variables, rays: Rays, settings: RenderSettings, grids):
  """Proposal sampler: each proposal network and the field's density front to back, the
  colour where seen. Returns (weights [R, N], rgbs [R, N, 3], centres [R, N], first edge [R],
  far edge [R])."""
  params = variables["params"]
  fraction = min(model.capacity.render_sample_fraction, settings.field_sample_fraction)
  model = dataclasses.replace(model, capacity=dataclasses.replace(
      model.capacity, render_sample_fraction=fraction))
  edges, _ = ray_samples.proposal_edges(
      model, params, rays, jax.random.PRNGKey(0), False, ray_samples.ray_range(model, rays),
      True, _proposal_density(model, params, settings, grids))
  # The points lie at the midpoints of the sampled intervals: the last one's finished edge
  # reaches infinity only for the compositing.
  points = ray_samples.points_of(model, rays, edges)
  edges = ray_samples.finish_edges(model, edges)
  weights, _, rgbs = shade(model, variables, rays, points, volume.interval_lengths(edges), settings)
  return _along_edges(weights, rgbs, edges)


def _first_true(mask, size: int):
  """[R, size] int32 indices of each row's first `size` True entries of mask [R, N] (N past the
  last), and their number [R] (which may exceed `size`)."""
  num_rows, length = mask.shape
  rank = jnp.cumsum(mask, axis=1, dtype=jnp.int32) - 1
  slot = jnp.where(mask & (rank < size), jnp.arange(num_rows)[:, None] * size + rank,
                   num_rows * size)
  indices = jnp.full(num_rows * size, length, jnp.int32).at[slot.reshape(-1)].set(
      jnp.broadcast_to(jnp.arange(length, dtype=jnp.int32), mask.shape).reshape(-1),
      mode="drop")
  return indices.reshape(num_rows, size), rank[:, -1] + 1


def _occupied_blocks(mask, size: int):
  """Each ray's first blocks of LIST_BLOCK consecutive steps that hold an occupied step (mask
  [R, N]), size // LIST_BLOCK of them: made from the blocks' occupancy, a tenth of the steps'.

  Returns:
    their steps [R, S] (S = size rounded down to whole blocks; N where there is no block),
    whether each step is occupied [R, S], and whether the ray has more such blocks [R].
  """
  num_rays, num_steps = mask.shape
  num_blocks = -(-num_steps // LIST_BLOCK)
  padded = jnp.pad(mask, ((0, 0), (0, num_blocks * LIST_BLOCK - num_steps)))
  blocks, count = _first_true(padded.reshape(num_rays, num_blocks, LIST_BLOCK).any(-1),
                              min(max(1, size // LIST_BLOCK), num_blocks))
  steps = (blocks[:, :, None] * LIST_BLOCK + np.arange(LIST_BLOCK)).reshape(num_rays, -1)
  occupied = jnp.take_along_axis(padded, jnp.minimum(steps, padded.shape[1] - 1), axis=1)
  occupied = occupied & (steps < num_steps)
  return jnp.minimum(steps, num_steps), occupied, count > blocks.shape[1]


def _occupancy_lists(model, variables, rays: Rays, settings: RenderSettings, march, occupied,
                     mask):
  """Occupancy sampler: each ray's first `settings.list_samples` occupied samples (mask
  [R, N]: the occupied steps of the march) front to back.

  Returns:
    (weights [R, M], rgbs [R, M, 3], centres [R, M], first edge [R], far edge [R]), and
    whether a ray was still visible after its list but had more occupied samples.
  """
  edges = ray_samples.occupied_samples(model, variables, rays, None, False,
                                       ray_samples.ray_range(model, rays), march, occupied)[0]
  num_steps = mask.shape[1]
  steps, occupied_steps, more = _occupied_blocks(mask, settings.list_samples)
  listed = steps < num_steps
  finished = jnp.minimum(ray_samples.finish_edges(model, edges), sampling.MAX_DISTANCE)

  def at(array, offset: int):
    """array [R, N + 1] at the listed steps' edges (offset 0: first, 1: last) [R, M]."""
    return jnp.take_along_axis(array, jnp.minimum(steps, num_steps - 1) + offset, axis=1)

  deltas = jnp.where(listed, jnp.maximum(at(finished, 1) - at(finished, 0), 0.0), 0.0)
  centres = jnp.where(listed, 0.5 * (at(finished, 0) + at(finished, 1)), finished[:, -1:])
  # The points lie at the midpoints of the march's own steps (the last one's finished edge
  # may reach infinity).
  points = model.to_unit_cube(rays.origins[:, None] + 0.5 * (at(edges, 0) + at(edges, 1))[
      ..., None] * rays.directions[:, None])
  weights, transmittance, rgbs = shade(model, variables, rays, points, deltas, settings,
                                       candidates=occupied_steps, deferred=False)
  overflow = more & (transmittance > settings.termination)
  return (weights, rgbs, centres, finished[:, 0], finished[:, -1]), overflow


def _occupancy_march(model, variables, rays: Rays, settings: RenderSettings, march, occupied):
  """Occupancy sampler, every step of the march front to back (rays whose lists overflow).
  Returns (weights, rgbs, centres [R, N], first edge, far edge [R])."""
  edges, points, mask = ray_samples.occupied_samples(
      model, variables, rays, None, False, ray_samples.ray_range(model, rays), march, occupied)
  edges = ray_samples.finish_edges(model, edges)
  # These rays are visible after their list's steps: passes as long as the list, not shorter.
  settings = dataclasses.replace(settings, first_pass=max(settings.first_pass,
                                                          settings.list_samples))
  weights, _, rgbs = shade(model, variables, rays, points, volume.interval_lengths(edges), settings,
                           candidates=mask, deferred=False)
  return _along_edges(weights, rgbs, edges)


def _image_outputs(model, rays: Rays, samples, near_distance, selection_box):
  """Per-ray outputs of (weights, rgbs, centres, first edge, far edge) [R, N, ...]."""
  weights, rgbs, centres, first, far = samples
  return {**volume.summarise(weights, rgbs, centres, first, far, rays.cos_to_optical_axis,
                             model.background),
          **weight_statistics(weights, centres, rays, near_distance, selection_box)}


def render_rays(model, variables, rays: Rays, settings: RenderSettings, skipping,
                near_distance, selection_box,
                occupied_march: ray_samples.OccupiedMarch | None = None):
  """Renders rays [R] of a trained model (`model.NerfModel`) front to back.

  An edit region's model renders the rays that miss its region as its original does (so its
  renders there equal the original's), and the rays that cross it with every sample
  (`model.render_rays`), as before.

  Args:
    skipping: `render_state.skipping` of the model (an edit region's: of its original), or {}
      (nothing known about where space is empty).
    near_distance, selection_box: see `weight_statistics`.
    occupied_march: the occupancy sampler's short march (`ray_samples.render_march`; an edit
      region's: its original's) or None.
  Returns:
    [R, ...] arrays: `volume.summarise`'s outputs and `weight_statistics`'.
  """
  if model.edit_region is not None:
    original = render_rays(model.original, variables["original"], rays, settings, skipping,
                           near_distance, selection_box, occupied_march)
    return _replaced(original, nerf_model.crosses_region(model, rays), rays, lambda subset, _: (
        _every_sample(model, variables, subset, near_distance, selection_box)),
                     _group_size(rays, settings))

  def outputs(samples, rays):
    return _image_outputs(model, rays, samples, near_distance, selection_box)

  if model.capacity.sampler != "occupancy":
    return outputs(_proposal_render(model, variables, rays, settings, skipping.get("proposal")),
                   rays)
  occupied = skipping.get("occupied")
  edges, _, mask = ray_samples.occupied_samples(model, variables, rays, None, False,
                                                ray_samples.ray_range(model, rays),
                                                occupied_march, occupied)
  edges = jnp.minimum(ray_samples.finish_edges(model, edges), sampling.MAX_DISTANCE)
  far = edges[:, -1]
  nothing = (jnp.zeros_like(far)[:, None], jnp.zeros(far.shape + (1, 3)), far[:, None],
             edges[:, 0], far)

  def hit(subset, part):
    """The rays `part` (indices [P], rays `subset`) that pass occupied cells."""
    listed, overflow = _occupancy_lists(model, variables, subset, settings, occupied_march,
                                        occupied, mask[jnp.minimum(part, mask.shape[0] - 1)])
    return _replaced(outputs(listed, subset), overflow, subset, lambda again, _: outputs(
        _occupancy_march(model, variables, again, settings, occupied_march, occupied), again),
                     _group_size(subset, settings))

  # Most rays of a bounded scene pass no occupied cell: only the others are listed.
  return _replaced(outputs(nothing, rays), jnp.any(mask, axis=1), rays, hit,
                   max(1, int(rays.shape[0] * settings.hit_share)))


def _every_sample(model, variables, rays: Rays, near_distance, selection_box):
  """Per-ray outputs of `model.render_rays` (every sample, as training renders)."""
  outputs, _ = nerf_model.render_rays(model, variables, rays, jax.random.PRNGKey(0),
                                      training=False)
  return {**outputs, **weight_statistics(outputs["weights"], sampling.midpoints(
      outputs["edges"]), rays, near_distance, selection_box)}


def _group_size(rays: Rays, settings: RenderSettings) -> int:
  return max(1, int(rays.shape[0] * settings.overflow_share))


def _replaced(outputs, marked, rays: Rays, render, size: int):
  """`outputs` (a dict of [R, ...] arrays, a key for each of `render`'s), but for the rays
  marked in `marked` [R] those of `render` (rays [size] and their indices [size] (R:
  padding) -> outputs), `size` rays at a time (nothing rendered again where no ray is
  marked)."""
  num_rays = rays.shape[0]
  padded = -(-num_rays // size) * size
  (indices,) = jnp.nonzero(marked, size=padded, fill_value=num_rays)
  count = jnp.sum(marked)

  def body(state):
    group, outputs = state
    part = jax.lax.dynamic_slice(indices, (group * size,), (size,))
    subset = jax.tree.map(lambda array: array[jnp.minimum(part, num_rays - 1)], rays)
    again = render(subset, part)
    return group + 1, {name: whole.at[part].set(again[name], mode="drop")
                       for name, whole in outputs.items()}

  return jax.lax.while_loop(lambda state: state[0] * size < count, body,
                            (jnp.int32(0), outputs))[1]
