"""The NeRF as pure functions over (model, variables): fields + sampling + volume rendering.

`NerfModel` is static (hashable; it fixes every shape); `variables` is the pytree that changes:
  {"params": {"field": ..., "proposal_0": ..., ...},    # trained by the optimizer
   "occupancy": [R, R, R] float32}                       # occupancy sampler only, not trained
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax.camera import Rays
from signerf_jax.errors import InputError
from signerf_jax.nerf import occupancy, sampling, volume
from signerf_jax.nerf.capacity import Capacity, SceneInfo
from signerf_jax.nerf.encoding import grid_layout
from signerf_jax.nerf.fields import DensityField, RadianceField

# A sample whose alpha is below this is skipped by the occupancy sampler (instant-NGP: 0.01).
OCCUPANCY_MIN_ALPHA = 0.01
OCCUPANCY_DECAY = 0.95
# Optical depth of the untrained field along one scene extent (see
# `RadianceField.initial_density`): ~instant-NGP's density 1 per unit cube. Lower values (0.1)
# left surfaces soft for hundreds of steps (synthetic scene: 3.7 dB worse, 2.5x the depth error).
INITIAL_OPTICAL_DEPTH = 1.0
# Proposal networks only shape the sampling: a few levels suffice (nerfacto uses 5).
PROPOSAL_LEVELS = 5

Variables = dict[str, Any]


@dataclasses.dataclass(frozen=True)
class NerfModel:
  """A scene's NeRF architecture: its geometry and capacity (hashable, static under jit)."""

  scene: SceneInfo
  capacity: Capacity

  @functools.cached_property
  def field(self) -> RadianceField:
    capacity = self.capacity
    layout = grid_layout(capacity.num_levels, capacity.base_resolution,
                         capacity.finest_resolution, capacity.log2_table_size,
                         capacity.features_per_level, capacity.hashed)
    embeddings = self.scene.num_images if capacity.appearance_embedding else 0
    return RadianceField(layout, width=capacity.mlp_width, num_appearance_embeddings=embeddings,
                         initial_density=self.initial_density)

  @functools.cached_property
  def proposal_fields(self) -> tuple[DensityField, ...]:
    capacity = self.capacity
    if capacity.sampler != "proposal":
      return ()
    layout = grid_layout(PROPOSAL_LEVELS, capacity.base_resolution,
                         capacity.proposal_finest_resolution, capacity.proposal_log2_table_size, 2)
    return tuple(DensityField(layout, initial_density=self.initial_density)
                 for _ in capacity.proposal_samples)

  @property
  def initial_density(self) -> float:
    """Untrained density: a ray crossing the whole scene starts ~63% opaque."""
    return INITIAL_OPTICAL_DEPTH / self.scene.extent

  @property
  def bounds(self) -> np.ndarray:
    return np.asarray(self.scene.bounds, np.float32)

  @property
  def march_step(self) -> float:
    """Marching step length (scene units) so that march_steps cover the box diagonal."""
    diagonal = float(np.linalg.norm(self.bounds[1] - self.bounds[0]))
    return diagonal / self.capacity.march_steps

  @property
  def background(self):
    if self.capacity.background == "constant":
      return jnp.asarray(self.scene.background_color, jnp.float32)
    return None

  def to_unit_cube(self, points):
    """Scene points [..., 3] -> field coordinates in [0, 1]^3 (contracted if unbounded)."""
    low, high = self.bounds
    if not self.capacity.contract:
      return (points - low) / (high - low)
    centre, half_extent = (low + high) / 2, (high - low) / 2
    return sampling.contract((points - centre) / half_extent) / 4.0 + 0.5

  @property
  def spacing_scale(self) -> float:
    """Distance at which mip-NeRF 360 spacing switches from linear to inverse distance."""
    return 0.5 * self.scene.extent


def init_variables(model: NerfModel, key) -> Variables:
  """Fresh variables (random fields, occupancy all unvisited)."""
  keys = jax.random.split(key, 1 + len(model.proposal_fields))
  points = jnp.full((1, 3), 0.5, jnp.float32)
  directions = jnp.array([[0.0, 0.0, 1.0]], jnp.float32)
  params = {"field": model.field.init(keys[0], points, directions, jnp.zeros((1,), jnp.int32))[
      "params"]}
  for index, (field, field_key) in enumerate(zip(model.proposal_fields, keys[1:])):
    params[f"proposal_{index}"] = field.init(field_key, points)["params"]
  variables = {"params": params}
  if model.capacity.sampler == "occupancy":
    variables["occupancy"] = occupancy.initial_grid(model.capacity.occupancy_resolution)
  return variables


def field_density(model: NerfModel, params, unit_points):
  """The radiance field's density at unit-cube points [..., 3] -> [...]."""
  return model.field.apply({"params": params["field"]}, unit_points,
                           method=RadianceField.density)


def update_occupancy(model: NerfModel, variables: Variables, key, update_index) -> Variables:
  """One occupancy-grid refresh (a slice of cells; see `occupancy.update`)."""
  grid = occupancy.update(
      variables["occupancy"], lambda points: field_density(model, variables["params"], points),
      key, update_index, cells_per_update=4 * model.capacity.samples_per_batch,
      decay=OCCUPANCY_DECAY)
  return {**variables, "occupancy": grid}


def _ray_range(model: NerfModel, rays: Rays):
  """[near, far] per ray: the box for bounded scenes (misses get [far, far]); else the scene's."""
  if model.capacity.sampler == "occupancy" or not model.capacity.contract:
    t_near, t_far, hit = sampling.intersect_aabb(rays.origins, rays.directions, model.bounds)
    t_near = jnp.where(hit, jnp.maximum(t_near, model.scene.near), model.scene.far)
    t_far = jnp.where(hit, t_far, model.scene.far)
    return t_near, jnp.maximum(t_far, t_near)
  shape = rays.shape
  return jnp.full(shape, model.scene.near), jnp.full(shape, model.scene.far)


def _finish_edges(model: NerfModel, edges):
  """'last_sample' background: the last interval reaches infinity (the field is the background)."""
  if model.capacity.background == "last_sample":
    edges = edges.at[..., -1].set(sampling.MAX_DISTANCE)
  return edges


def render_rays(model: NerfModel, variables: Variables, rays: Rays, key, *, training: bool):
  """Renders rays [R] (flat batch).

  Args:
    model: the static model.
    variables: {"params", optional "occupancy"}.
    rays: Rays of shape [R].
    key: PRNG key for stratified jitter (ignored when not training).
    training: jitter samples, use appearance codes of `rays.camera_indices`, and (occupancy
      sampler) drop rays that overflow the fixed sample budget instead of evaluating them all.
  Returns:
    outputs: `volume.volume_render`'s dict, plus "ray_complete" [R] bool (False for dropped rays).
    aux: terms for the losses and statistics: "edges" [R, N + 1] of `outputs["weights"]`,
      "proposals" [(edges, weights)] of the proposal networks (empty for the occupancy sampler),
      "samples_evaluated" (radiance-field evaluations).
  """
  if model.capacity.sampler == "occupancy":
    return _render_occupancy(model, variables, rays, key, training)
  return _render_proposal(model, variables, rays, key, training)


def _appearance(model: NerfModel, rays: Rays, training: bool):
  return rays.camera_indices if training else jnp.full(rays.shape, -1, jnp.int32)


def _render_occupancy(model, variables, rays, key, training):
  capacity = model.capacity
  t_near, t_far = _ray_range(model, rays)
  edges = sampling.marching_edges(key, t_near, t_far, model.march_step, capacity.march_steps,
                                  training)
  centres = sampling.midpoints(edges)
  unit_points = model.to_unit_cube(rays.origins[:, None] + centres[..., None] *
                                   rays.directions[:, None])  # [R, N, 3]
  occupied_grid = occupancy.occupied_cells(variables["occupancy"], model.march_step,
                                           OCCUPANCY_MIN_ALPHA)
  mask = occupancy.lookup(occupied_grid, unit_points) & (edges[:, 1:] > edges[:, :-1])
  num_rays, num_steps = mask.shape
  appearance = _appearance(model, rays, training)

  def evaluate(mask, unit_points, directions, appearance, indices):
    """The field at flat sample `indices` of `mask` [r, N] (index mask.size: padding)."""
    safe = jnp.minimum(indices, mask.size - 1)
    ray_index = safe // mask.shape[1]
    density, rgb = model.field.apply({"params": variables["params"]["field"]},
                                     unit_points.reshape(-1, 3)[safe], directions[ray_index],
                                     appearance[ray_index])
    return jnp.where(indices < mask.size, density, 0.0), rgb

  def scatter(target, indices, values):
    return target.at[indices].set(values, mode="drop")

  budget = capacity.samples_per_batch
  if training:
    groups = capacity.sample_groups
    if num_rays % groups or budget % groups:
      raise InputError(f"{groups} groups do not split {num_rays} rays and {budget} samples "
                       "evenly", field="Capacity.sample_groups")

    def render_group(mask, unit_points, directions, appearance):
      indices, valid, complete = occupancy.compact(mask, budget // groups)
      density, rgb = evaluate(mask, unit_points, directions, appearance, indices)
      return (scatter(jnp.zeros(mask.size, jnp.float32), indices, density),
              scatter(jnp.zeros((mask.size, 3), jnp.float32), indices, rgb), complete,
              jnp.sum(valid))

    # Each group of consecutive rays fills its own share of the sample budget: groups work
    # independently, so with the rays split over devices each device evaluates only its own.
    grouped = lambda array: array.reshape((groups, -1) + array.shape[1:])
    densities, rgbs, ray_complete, samples = jax.vmap(render_group)(
        grouped(mask), grouped(unit_points), grouped(rays.directions), grouped(appearance))
    ray_complete, samples = ray_complete.reshape(-1), jnp.sum(samples)
  else:
    # Evaluate every occupied sample, one fixed-size piece at a time (forward only).
    padded = int(np.ceil(mask.size / budget)) * budget
    all_indices, _, _ = occupancy.compact(mask, padded)
    count = jnp.sum(mask)

    def body(state):
      piece, densities, rgbs = state
      indices = jax.lax.dynamic_slice(all_indices, (piece * budget,), (budget,))
      density, rgb = evaluate(mask, unit_points, rays.directions, appearance, indices)
      return piece + 1, scatter(densities, indices, density), scatter(rgbs, indices, rgb)

    _, densities, rgbs = jax.lax.while_loop(
        lambda state: state[0] * budget < count, body,
        (jnp.int32(0), jnp.zeros(mask.size, jnp.float32), jnp.zeros((mask.size, 3), jnp.float32)))
    ray_complete, samples = jnp.ones(rays.shape, bool), count
  edges = _finish_edges(model, edges)
  outputs = volume.volume_render(densities.reshape(num_rays, num_steps),
                                 rgbs.reshape(num_rays, num_steps, 3), edges,
                                 rays.cos_to_optical_axis, model.background)
  outputs["ray_complete"] = ray_complete
  return outputs, {"proposals": [], "edges": edges, "samples_evaluated": samples}


def _render_proposal(model, variables, rays, key, training):
  capacity = model.capacity
  params = variables["params"]
  t_near, t_far = _ray_range(model, rays)
  keys = jax.random.split(key, len(model.proposal_fields) + 1)
  if capacity.contract:
    edges = sampling.spaced_edges(keys[0], t_near, t_far, capacity.proposal_samples[0], training,
                                  model.spacing_scale)
  else:
    edges = sampling.stratified_edges(keys[0], t_near, t_far, capacity.proposal_samples[0],
                                      training)

  def points_of(edges):
    centres = sampling.midpoints(edges)
    return model.to_unit_cube(rays.origins[..., None, :] +
                              centres[..., None] * rays.directions[..., None, :])

  proposals = []
  next_counts = list(capacity.proposal_samples[1:]) + [capacity.samples_per_ray]
  for index, (field, count) in enumerate(zip(model.proposal_fields, next_counts)):
    density = field.apply({"params": params[f"proposal_{index}"]}, points_of(edges))
    finished = _finish_edges(model, edges)
    weights, _ = volume.compute_weights(density, finished)
    proposals.append((finished, weights))
    edges = sampling.sample_pdf(keys[index + 1], edges, weights, count, training)
  sample_shape = edges.shape[:-1] + (edges.shape[-1] - 1,)
  directions = jnp.broadcast_to(rays.directions[..., None, :], sample_shape + (3,))
  appearance = jnp.broadcast_to(_appearance(model, rays, training)[..., None], sample_shape)
  density, rgb = model.field.apply({"params": params["field"]}, points_of(edges), directions,
                                   appearance)
  edges = _finish_edges(model, edges)
  outputs = volume.volume_render(density, rgb, edges, rays.cos_to_optical_axis, model.background)
  outputs["ray_complete"] = jnp.ones(rays.shape, bool)
  samples = sum(capacity.proposal_samples) + capacity.samples_per_ray
  return outputs, {"proposals": proposals, "edges": edges,
                   "samples_evaluated": jnp.int32(samples * rays.shape[0])}
