"""Where a NeRF evaluates its field along rays: each ray's modelled range, and the two samplers.

The occupancy sampler (bounded scenes) marches fixed steps and evaluates the field only where
the occupancy grid says something is; the proposal sampler (unbounded and forward-facing
scenes) resamples each ray from small density networks' weights (mip-NeRF 360's proposal
sampling; `losses.interlevel_loss` trains them). Both return the samples `volume` composites.
`model` is always a `nerf.model.NerfModel`.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax.camera import Rays
from signerf_jax.nerf import losses, occupancy, packed, sampling, volume

# A sample whose alpha is below this is skipped by the occupancy sampler (instant-NGP: 0.01).
OCCUPANCY_MIN_ALPHA = 0.01
# Rendering evaluates the occupied samples of a chunk in pieces of this many: a piece is paid
# for whole, and a chunk of 4096 rays holds ~8 occupied samples a ray (lego), so pieces of the
# training budget (65536) were half empty and made a chunk take nearly twice as long.
RENDER_PIECE_SAMPLES = 8192
Variables = dict[str, Any]


def ray_range(model, rays: Rays):
  """[near, far] per ray: the box for bounded scenes (misses get [far, far]); else the scene's."""
  if model.capacity.sampler == "occupancy" or not model.capacity.contract:
    t_near, t_far, hit = sampling.intersect_aabb(rays.origins, rays.directions, model.bounds)
    t_near = jnp.where(hit, jnp.maximum(t_near, model.scene.near), model.scene.far)
    t_far = jnp.where(hit, t_far, model.scene.far)
    return t_near, jnp.maximum(t_far, t_near)
  shape = rays.shape
  return jnp.full(shape, model.scene.near), jnp.full(shape, model.scene.far)


def finish_edges(model, edges):
  """'last_sample' background: the last interval reaches infinity (the field is the background)."""
  if model.capacity.background == "last_sample":
    edges = edges.at[..., -1].set(sampling.MAX_DISTANCE)
  return edges


def field_samples(model, variables: Variables, rays: Rays, key, training: bool, interval,
                  finish: bool, occupied_march: OccupiedMarch | None = None):
  """The field's samples along each ray's (near [R], far [R]) = `interval` (e.g. `ray_range`).

  Args:
    finish: apply the background model to the last interval (`finish_edges`): False for a
      stretch of the ray that other samples continue.
    occupied_march: rendering with the occupancy sampler only: march just the steps through
      the box around the occupied cells (`render_march`).
  Returns:
    (densities [R, N], rgbs [R, N, 3], edges [R, N + 1]), ray_complete [R] bool, and
    {"proposals", "samples_evaluated"} (see `render_rays`).
  """
  if model.capacity.sampler == "occupancy":
    return _occupancy_samples(model, variables, rays, key, training, interval, finish,
                              occupied_march)
  return _proposal_samples(model, variables, rays, key, training, interval, finish)


def _near_camera_scaled(model, training: bool, densities, rgbs, distances):
  """The samples' densities and rgbs, their gradients scaled near the cameras while training
  where the capacity asks (`losses.near_camera_gradient_scaling`; `distances`: the samples'
  midpoints)."""
  if not (training and model.capacity.near_gradient_scaling):
    return densities, rgbs
  return losses.near_camera_gradient_scaling(densities, rgbs, distances,
                                             model.scene.camera_distance)


def packed_occupancy_samples(model, variables: Variables, rays: Rays, key, interval,
                             finish: bool):
  """Training with the occupancy sampler: the field at the occupied samples of the march over
  `interval` (near [R], far [R]) within the sample budget (`occupancy.evaluate_in_groups`),
  packed (`packed.PackedSamples`) instead of spread over the march's steps.

  Returns:
    the packed samples, the march's edges [R, N + 1] (finished if `finish`), ray_complete [R]
    bool, and {"proposals": [], "samples_evaluated"} (see `render_rays`).
  """
  capacity = model.capacity
  edges, unit_points, mask = occupied_samples(model, variables, rays, key, True, interval)
  indices, density, rgb, ray_complete, count = occupancy.evaluate_in_groups(
      functools.partial(_field_at, model, variables), mask, unit_points, rays.directions,
      _appearance(model, rays, True), capacity.samples_per_batch, capacity.sample_groups)
  if finish:
    edges = finish_edges(model, edges)
  num_rays, num_steps = mask.shape
  rays_per_group = num_rays // capacity.sample_groups
  ray, step = indices // num_steps, indices % num_steps

  def intervals(group_edges, ray, step):
    ray = jnp.minimum(ray, rays_per_group - 1)  # Padding: any interval (its density is 0).
    return group_edges[ray, step], group_edges[ray, step + 1]

  starts, ends = jax.vmap(intervals)(edges.reshape(capacity.sample_groups, rays_per_group, -1),
                                     ray, step)
  density, rgb = _near_camera_scaled(model, True, density, rgb, 0.5 * (starts + ends))
  samples = packed.PackedSamples(ray, step, starts, ends, density, rgb)
  return samples, edges, ray_complete, {"proposals": [], "samples_evaluated": count}


def _appearance(model, rays: Rays, training: bool):
  return rays.camera_indices if training else jnp.full(rays.shape, -1, jnp.int32)


def _field_at(model, variables, mask, unit_points, directions, appearance, indices):
  """The field at flat sample `indices` of `mask` [r, N] (index mask.size: padding).

  Returns:
    density [K] (0 at padding) and rgb [K, 3].
  """
  safe = jnp.minimum(indices, mask.size - 1)
  ray_index = safe // mask.shape[1]
  density, rgb = model.field.apply({"params": variables["params"]["field"]},
                                   unit_points.reshape(-1, 3)[safe], directions[ray_index],
                                   appearance[ray_index], variables.get("level_weights"))
  return jnp.where(indices < mask.size, density, 0.0), rgb


class OccupiedMarch(NamedTuple):
  """Rendering with the occupancy sampler: march only `steps` steps (static) of each ray, those
  through `box` ([2, 3] scene units), the box around the occupied cells (`render_march`)."""
  box: Any
  steps: int


def render_march(model, variables: Variables) -> OccupiedMarch | None:
  """The box around the occupied cells, leaving out specks (`occupancy.without_specks`), and
  the steps a ray needs to cross it, rounded up to a multiple of 8 so that a slowly changing
  grid rarely recompiles; None without the occupancy sampler, with an edit region, or when the
  box needs the whole march.

  The whole march spends most of a bounded scene's rendering time on empty cells around the
  object: lego's occupied cells fill 0.47 x 0.80 x 0.53 of the scene box. Specks outside the
  box are not rendered.
  """
  if model.capacity.sampler != "occupancy" or model.edit_region is not None:
    return None
  grid = np.asarray(variables["occupancy"])
  occupied = np.asarray(occupancy.occupied_cells(grid, model.march_step, OCCUPANCY_MIN_ALPHA))
  low, high = model.bounds.astype(np.float64)
  cell_size = float(np.min(high - low)) / grid.shape[0]
  box = occupancy.occupied_box(occupancy.without_specks(grid, occupied, cell_size))
  size = np.maximum(box[1] - box[0], 0.0) * (high - low)
  # Two more steps: one for the comb's start rounded down, one for the last interval (past it).
  steps = int(np.ceil((np.linalg.norm(size) / model.march_step + 2) / 8)) * 8
  if steps >= model.capacity.march_steps:
    return None
  return OccupiedMarch(np.float32(box * (high - low) + low), steps)


def _occupied_marching_edges(model, rays: Rays, interval, march: OccupiedMarch):
  """Rendering: `march.steps` consecutive steps of the whole march (`sampling.marching_edges`
  over `interval`), from the one where the ray enters `march.box`, and the last edge at the
  ray's far bound as in the whole march. The whole march's other samples all lie outside the
  box, in empty cells (or specks), so the rendering is the same.

  Returns:
    [R, march.steps + 1] sorted edges.
  """
  t_near, t_far = interval
  entry, _, hits = sampling.intersect_aabb(rays.origins, rays.directions, march.box)
  first_step = jnp.floor((jnp.maximum(entry, t_near) - t_near) / model.march_step)
  # Rays that miss the box keep only the far bound (all their intervals are empty).
  first_step = jnp.where(hits, first_step, model.capacity.march_steps)
  offsets = first_step[:, None] + jnp.arange(march.steps + 1, dtype=jnp.float32)
  edges = jnp.minimum(t_near[:, None] + model.march_step * offsets, t_far[:, None])
  return edges.at[:, -1].set(t_far)


def occupied_samples(model, variables: Variables, rays: Rays, key, training: bool, interval,
                     march: OccupiedMarch | None = None, occupied_grid=None):
  """The occupancy sampler's march along rays [R] over `interval` (near [R], far [R]).

  Args:
    occupied_grid: None, or the occupied cells [G, G, G] bool if known already (rendering).
  Returns:
    edges [R, N + 1] (not finished), unit-cube points [R, N, 3] at their midpoints, and
    [R, N] bool: the samples in occupied cells (with a non-empty interval).
  """
  if occupied_grid is None:
    occupied_grid = occupancy.occupied_cells(variables["occupancy"], model.march_step,
                                             OCCUPANCY_MIN_ALPHA)
  if march is None:
    t_near, t_far = interval
    edges = sampling.marching_edges(key, t_near, t_far, model.march_step,
                                    model.capacity.march_steps, training)
  else:
    edges = _occupied_marching_edges(model, rays, interval, march)
  centres = sampling.midpoints(edges)
  unit_points = model.to_unit_cube(rays.origins[:, None] + centres[..., None] *
                                   rays.directions[:, None])  # [R, N, 3]
  mask = occupancy.lookup(occupied_grid, unit_points) & (edges[:, 1:] > edges[:, :-1])
  return edges, unit_points, mask


def _occupancy_samples(model, variables, rays, key, training, interval, finish, march):
  if training:
    samples, edges, ray_complete, aux = packed_occupancy_samples(model, variables, rays, key,
                                                                 interval, finish)
    num_rays, num_steps = edges.shape[0], edges.shape[1] - 1
    spread = lambda values: packed.spread(values, samples, num_rays, num_steps)
    return (spread(samples.densities), spread(samples.rgbs), edges), ray_complete, aux
  edges, unit_points, mask = occupied_samples(model, variables, rays, key, training, interval,
                                              march)
  num_rays, num_steps = mask.shape
  densities, rgbs, samples = occupancy.evaluate_every_occupied(
      functools.partial(_field_at, model, variables), mask, unit_points, rays.directions,
      _appearance(model, rays, training), RENDER_PIECE_SAMPLES)
  if finish:
    edges = finish_edges(model, edges)
  along_rays = (densities.reshape(num_rays, num_steps), rgbs.reshape(num_rays, num_steps, 3),
                edges)
  return along_rays, jnp.ones(rays.shape, bool), {"proposals": [], "samples_evaluated": samples}


def proposal_edges(model, params, rays: Rays, key, training: bool, interval, finish: bool,
                   proposal_density=None):
  """The proposal networks' resampling (mip-NeRF 360): each network's density along its
  intervals places the next set of intervals, the last set the field's.

  Args:
    params: the model's parameters ({"proposal_0", ...}).
    proposal_density: None (`DensityField` at the intervals' midpoints), or a function
      (network index, points [R, M, 3], finished edges [R, M + 1]) -> densities [R, M] that
      computes them another way (rendering: front to back, `front_to_back`).
  Returns:
    the field's edges [R, N + 1] (not finished) and [(finished edges, weights)] per network.
  """
  capacity = model.capacity
  t_near, t_far = interval
  finished = (lambda edges: finish_edges(model, edges)) if finish else (lambda edges: edges)
  keys = jax.random.split(key, len(model.proposal_fields) + 1)
  proposal_counts, field_count = capacity.sample_counts(training)
  if capacity.contract or capacity.perspective_warp:
    edges = sampling.spaced_edges(keys[0], t_near, t_far, proposal_counts[0], training,
                                  model.spacing_scale)
  else:
    edges = sampling.stratified_edges(keys[0], t_near, t_far, proposal_counts[0], training)
  proposals = []
  next_counts = list(proposal_counts[1:]) + [field_count]
  for index, (field, count) in enumerate(zip(model.proposal_fields, next_counts)):
    points, coarse_edges = points_of(model, rays, edges), finished(edges)
    if proposal_density is None:
      density = field.apply({"params": params[f"proposal_{index}"]}, points)
    else:
      density = proposal_density(index, points, coarse_edges)
    weights, _ = volume.compute_weights(density, coarse_edges)
    proposals.append((coarse_edges, weights))
    edges = sampling.sample_pdf(keys[index + 1], edges, weights, count, training)
  return edges, proposals


def points_of(model, rays: Rays, edges):
  """Unit-cube points [R, N, 3] at the midpoints of edges [R, N + 1] (`NerfModel.to_unit_cube`)."""
  centres = sampling.midpoints(edges)
  return model.to_unit_cube(rays.origins[..., None, :] +
                            centres[..., None] * rays.directions[..., None, :])


def _proposal_samples(model, variables, rays, key, training, interval, finish):
  params = variables["params"]
  edges, proposals = proposal_edges(model, params, rays, key, training, interval, finish)
  finished = finish_edges(model, edges) if finish else edges
  sample_shape = edges.shape[:-1] + (edges.shape[-1] - 1,)
  directions = jnp.broadcast_to(rays.directions[..., None, :], sample_shape + (3,))
  appearance = jnp.broadcast_to(_appearance(model, rays, training)[..., None], sample_shape)
  density, rgb = model.field.apply({"params": params["field"]}, points_of(model, rays, edges),
                                   directions, appearance, variables.get("level_weights"))
  density, rgb = _near_camera_scaled(model, training, density, rgb, sampling.midpoints(finished))
  proposal_counts, field_count = model.capacity.sample_counts(training)
  samples = sum(proposal_counts) + field_count
  return ((density, rgb, finished), jnp.ones(rays.shape, bool),
          {"proposals": proposals, "samples_evaluated": jnp.int32(samples * rays.shape[0])})
