"""The NeRF as pure functions over (model, variables): fields + sampling + volume rendering.

`NerfModel` is static (hashable; it fixes every shape); `variables` is the pytree that changes:
  {"params": {"field": ..., "proposal_0": ..., ...},    # trained by the optimizer
   "occupancy": [R, R, R] float32,                       # occupancy sampler only, not trained
   "level_weights": [L] float32,                         # coarse-to-fine training only
   "original": {"params": ..., "occupancy": ...}}        # edit regions only, frozen

An edited scene can be a NeRF with an *edit region*: a box inside which its own field is
rendered, while before and after the box every ray sees the original scene's field, frozen
(`variables["original"]`, same architecture). So an edit cannot move anything outside the box
(the original's renders there are reproduced exactly), and the trained field models only what
the box holds: its samples are spent there alone. Since the original is frozen, what it shows in
front of and behind the box along a training ray never changes: `region_surroundings` renders it
once, and training steps (`render_rays(..., surroundings=...)`) evaluate the trained field alone.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from signerf_jax.camera import Rays
from signerf_jax.errors import InputError
from signerf_jax.nerf import occupancy, packed, ray_samples, sampling, volume
from signerf_jax.nerf.capacity import Capacity
from signerf_jax.nerf.scene_info import SceneInfo
from signerf_jax.nerf.encoding import grid_layout
from signerf_jax.nerf.fields import DensityField, RadianceField

OCCUPANCY_DECAY = 0.95
# Optical depth of the untrained field along one scene extent (see
# `RadianceField.initial_density`): ~instant-NGP's density 1 per unit cube. Lower values (0.1)
# left surfaces soft for hundreds of steps (worse images and depth on a synthetic scene).
INITIAL_OPTICAL_DEPTH = 1.0
# Proposal networks only shape the sampling: a few levels suffice (nerfacto uses 5).
PROPOSAL_LEVELS = 5
# Spherical-harmonics degree of a diffuse colour's direction encoding (degree**2 channels): a
# constant, i.e. no view dependence.
DIFFUSE_SH_DEGREE = 1

Variables = dict[str, Any]


@dataclasses.dataclass(frozen=True)
class NerfModel:
  """A scene's NeRF architecture: its geometry and capacity (hashable, static under jit).

  Attributes:
    scene, capacity: the scene's geometry and the model's size.
    edit_region: None, or ((min x, y, z), (max x, y, z)) in scene units: the box where this
      model's field is rendered over the frozen original's (module docstring).
    region_view_dependence: the edit region's field colours by view direction as the
      original's does; False makes it diffuse (its colour independent of the direction), so
      views that disagree cannot each be fitted from their own direction.
  """

  scene: SceneInfo
  capacity: Capacity
  edit_region: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
  region_view_dependence: bool = True

  def __post_init__(self):
    if not isinstance(self.region_view_dependence, bool):
      raise InputError(f"must be true or false, got {self.region_view_dependence!r}",
                       field="region_view_dependence")
    if self.edit_region is not None:
      lower, upper = np.asarray(self.edit_region, np.float64).reshape(2, 3)
      if not np.all(upper > lower):
        raise InputError(f"an edit region needs min < max on every axis, got {self.edit_region}",
                         field="edit_region")
      object.__setattr__(self, "edit_region", (tuple(map(float, lower)),
                                               tuple(map(float, upper))))

  @property
  def original(self) -> "NerfModel":
    """The model of the original scene an edit region is rendered over."""
    return dataclasses.replace(self, edit_region=None, region_view_dependence=True)

  @functools.cached_property
  def field(self) -> RadianceField:
    capacity = self.capacity
    layout = grid_layout(capacity.num_levels, capacity.base_resolution,
                         capacity.finest_resolution, capacity.log2_table_size,
                         capacity.features_per_level)
    embeddings = self.scene.num_images if capacity.appearance_embedding else 0
    diffuse = self.edit_region is not None and not self.region_view_dependence
    return RadianceField(layout, width=capacity.mlp_width, num_appearance_embeddings=embeddings,
                         initial_density=self.initial_density,
                         sh_degree=DIFFUSE_SH_DEGREE if diffuse else capacity.sh_degree)

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
    """Scene points [..., 3] -> field coordinates in [0, 1]^3 (contracted if unbounded,
    perspective-warped if forward-facing; outside points are clipped by the grid)."""
    if self.capacity.perspective_warp:
      return self.scene.perspective(points)
    low, high = self.bounds
    if not self.capacity.contract:
      return (points - low) / (high - low)
    centre, half_extent = (low + high) / 2, (high - low) / 2
    return sampling.contract((points - centre) / half_extent) / 4.0 + 0.5

  def from_unit_cube(self, coordinates):
    """Field coordinates [..., 3] -> scene points [..., 3]: the inverse of `to_unit_cube`
    (inside the grid; the far boundary of a contracted grid is ~1e6 half-extents away)."""
    if self.capacity.perspective_warp:
      return self.scene.perspective.inverse(coordinates)
    low, high = self.bounds
    if not self.capacity.contract:
      return low + coordinates * (high - low)
    centre, half_extent = (low + high) / 2, (high - low) / 2
    return centre + sampling.uncontract((coordinates - 0.5) * 4.0) * half_extent

  @property
  def spacing_scale(self) -> float:
    """Distance at which mip-NeRF 360 spacing switches from linear to inverse distance (the
    near plane of forward-facing scenes: they are sampled evenly in disparity, as in NDC)."""
    if self.capacity.perspective_warp:
      return self.scene.near
    return 0.5 * self.scene.extent


@functools.partial(jax.jit, static_argnums=0)
def init_variables(model: NerfModel, key) -> Variables:
  """Fresh variables (random fields, occupancy all unvisited; for an edit region, an untrained
  original too, to be replaced by the original scene's variables).

  Jitted: run eagerly, each of the initialisers' ~90 small operations would be compiled on its
  own, about three times as long as compiling the one jitted program."""
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
  if model.capacity.coarse_to_fine > 0:
    # Every level on: what a trained field renders with. Training sets them by its progress.
    variables["level_weights"] = jnp.ones(model.capacity.num_levels, jnp.float32)
  if model.edit_region is not None:
    variables["original"] = init_variables(model.original, key)
  return variables


def field_density(model: NerfModel, variables: Variables, unit_points):
  """The radiance field's density at unit-cube points [..., 3] -> [...]."""
  return model.field.apply({"params": variables["params"]["field"]}, unit_points,
                           variables.get("level_weights"), method=RadianceField.density)


def update_occupancy(model: NerfModel, variables: Variables, key, update_index) -> Variables:
  """One occupancy-grid refresh (a slice of cells; see `occupancy.update`)."""
  grid = occupancy.update(
      variables["occupancy"], lambda points: field_density(model, variables, points),
      key, update_index, cells_per_update=4 * model.capacity.samples_per_batch,
      decay=OCCUPANCY_DECAY)
  return {**variables, "occupancy": grid}


def render_rays(model: NerfModel, variables: Variables, rays: Rays, key, *, training: bool,
                background=None, surroundings: "RegionSurroundings | None" = None,
                occupied_march: "ray_samples.OccupiedMarch | None" = None):
  """Renders rays [R] (flat batch).

  Args:
    model: the static model.
    variables: {"params", optional "occupancy"} (and "original" for an edit region).
    rays: Rays of shape [R].
    key: PRNG key for stratified jitter (ignored when not training).
    training: jitter samples, use appearance codes of `rays.camera_indices`, and (occupancy
      sampler) drop rays that overflow the fixed sample budget instead of evaluating them all.
    background: None (the model's background) or [R, 3] colours seen through empty space.
    surroundings: an edit region's only: the original field around the region on these rays
      (`region_surroundings`, shape [R]), so that only the trained field is evaluated; the
      outputs then hold "rgb" and "accumulation" alone.
  Returns:
    outputs: `volume.volume_render`'s dict, plus "ray_complete" [R] bool (False for dropped rays);
      training a model without an edit region with the occupancy sampler, which composites its
      samples packed (`_render_packed`), the dict lacks the weights and median depths.
    aux: terms for the losses and statistics, of the trained field alone (inside the edit
      region for an edit): "edges" [R, N + 1] and "weights" [R, N] of its samples, "proposals"
      [(edges, weights)] of the proposal networks (empty for the occupancy sampler),
      "samples_evaluated" (radiance-field evaluations, all fields), and with packed samples
      "packed" (`_render_packed`).
  """
  if model.edit_region is None and training and model.capacity.sampler == "occupancy":
    outputs, ray_complete, aux = _render_packed(model, variables, rays, key, background)
  elif model.edit_region is None:
    samples, ray_complete, aux = ray_samples.field_samples(
        model, variables, rays, key, training, ray_samples.ray_range(model, rays), finish=True,
        occupied_march=occupied_march)
    outputs = volume.volume_render(*samples, rays.cos_to_optical_axis,
                                   model.background if background is None else background)
    aux.update(edges=samples[2], weights=outputs["weights"])
  elif surroundings is None:
    outputs, ray_complete, aux = _render_edit(model, variables, rays, key, training, background)
  else:
    outputs, ray_complete, aux = _render_inside(model, variables, rays, key, training,
                                                background, surroundings)
  outputs["ray_complete"] = ray_complete
  return outputs, aux


def _render_packed(model: NerfModel, variables: Variables, rays: Rays, key, background):
  """Training with the occupancy sampler: its samples composited packed (`packed`), as
  `volume.volume_render` would the march's steps; the outputs lack the weights and median
  depths. Aux holds the packed samples and their weights ("packed", which
  `losses.distortion_loss` reads), and the weights spread over the march's steps ("weights",
  computed only where a loss reads them)."""
  samples, edges, ray_complete, aux = ray_samples.packed_occupancy_samples(
      model, variables, rays, key, ray_samples.ray_range(model, rays), finish=True)
  outputs, weights = packed.volume_render(
      samples, edges[:, 0], edges[:, -1], rays.cos_to_optical_axis,
      model.background if background is None else background)
  num_rays, num_steps = edges.shape[0], edges.shape[1] - 1
  aux.update(edges=edges, weights=packed.spread(weights, samples, num_rays, num_steps),
             packed=(samples, weights))
  return outputs, ray_complete, aux


def _region_interval(model: NerfModel, rays: Rays, t_near, t_far):
  """[R] (t_in, t_out, crossing): each ray's stretch inside the edit region within its modelled
  range [t_near, t_far], and whether it is not empty."""
  t_in, t_out, hit = sampling.intersect_aabb(rays.origins, rays.directions, model.edit_region)
  t_in = jnp.clip(t_in, t_near, t_far)
  t_out = jnp.clip(t_out, t_in, t_far)
  return t_in, t_out, hit & (t_out > t_in)


def crosses_region(model: NerfModel, rays: Rays):
  """[R] bool: the rays whose modelled range crosses the edit region (the only rays an edit
  region's field changes)."""
  return _region_interval(model, rays, *ray_samples.ray_range(model.original, rays))[2]


def _region_stretch(model: NerfModel, rays: Rays, t_near, t_far, empty_at):
  """[R] (t_in, t_out): each ray's stretch inside the edit region, within [t_near, t_far]; rays
  that miss it get the empty stretch at `empty_at` [R], where it splits no interval of the
  original's (ending its samples there), so they render exactly as the original does."""
  t_in, t_out, crossing = _region_interval(model, rays, t_near, t_far)
  return tuple(jnp.where(crossing, t, empty_at) for t in (t_in, t_out))


@struct.dataclass
class RegionSurroundings:
  """What the frozen original field shows along rays [R] around an edit region's stretch.

  Attributes:
    t_in, t_out: [R] the stretch (`_region_stretch`; equal for rays that miss the region).
    before_rgb: [R, 3] colour composited in front of t_in (weighted, i.e. premultiplied).
    before_transmittance: [R] light left at t_in.
    after_rgb: [R, 3] colour composited behind t_out as seen from t_out, background excluded.
    after_transmittance: [R] light left after the last sample (what the background gets).
  """

  t_in: jax.Array
  t_out: jax.Array
  before_rgb: jax.Array
  before_transmittance: jax.Array
  after_rgb: jax.Array
  after_transmittance: jax.Array


def region_surroundings(model: NerfModel, variables: Variables, rays: Rays
                        ) -> RegionSurroundings:
  """The original field's render around the edit region on `rays` [R] (no jitter): the same
  composite `_render_edit` makes, split at the region's stretch."""
  original = model.original
  t_near, t_far = ray_samples.ray_range(original, rays)
  (densities, rgbs, edges), _, _ = ray_samples.field_samples(
      original, variables["original"], rays, jax.random.PRNGKey(0), False, (t_near, t_far),
      finish=True)
  t_in, t_out = _region_stretch(model, rays, t_near, t_far, edges[..., -1])
  # Clipping the edges to one side of the stretch keeps the part of each interval on that side.
  before, _ = volume.compute_weights(densities, jnp.minimum(edges, t_in[..., None]))
  after, after_transmittance = volume.compute_weights(densities,
                                                      jnp.maximum(edges, t_out[..., None]))
  return RegionSurroundings(t_in, t_out, volume.composite(before, rgbs),
                            1.0 - jnp.sum(before, axis=-1), volume.composite(after, rgbs),
                            after_transmittance)


def _render_inside(model: NerfModel, variables: Variables, rays: Rays, key, training: bool,
                   background, surroundings: RegionSurroundings):
  """The trained field on each ray's stretch inside the edit region, composited between the
  original's precomputed surroundings: colour = before + T_before (inside + T_inside (after +
  T_after background))."""
  (densities, rgbs, edges), ray_complete, aux = ray_samples.field_samples(
      model, variables, rays, key, training, (surroundings.t_in, surroundings.t_out),
      finish=False)
  weights, inside_transmittance = volume.compute_weights(densities, edges)
  background = model.background if background is None else background
  behind = surroundings.after_rgb
  if background is not None:
    behind = behind + surroundings.after_transmittance[..., None] * background
  through = surroundings.before_transmittance * inside_transmittance
  rgb = surroundings.before_rgb + surroundings.before_transmittance[..., None] * (
      volume.composite(weights, rgbs) + inside_transmittance[..., None] * behind)
  aux.update(edges=edges, weights=weights)
  return ({"rgb": rgb, "accumulation": 1.0 - through * surroundings.after_transmittance},
          ray_complete, aux)


def _render_edit(model: NerfModel, variables: Variables, rays: Rays, key, training: bool,
                 background):
  """An edit region's rendering: the trained field on each ray's stretch inside the region, the
  frozen original field (`variables["original"]`) before and after it, composited as one field
  (`volume.merge_samples`)."""
  original = model.original
  original_key, edit_key = jax.random.split(key)
  t_near, t_far = ray_samples.ray_range(original, rays)
  outer, outer_complete, original_aux = ray_samples.field_samples(
      original, jax.lax.stop_gradient(variables["original"]), rays, original_key, training,
      (t_near, t_far), finish=True)
  t_in, t_out = _region_stretch(model, rays, t_near, t_far, outer[2][..., -1])
  inner, inner_complete, aux = ray_samples.field_samples(model, variables, rays, edit_key, training,
                                              (t_in, t_out), finish=False)
  aux.update(edges=inner[2], weights=volume.compute_weights(inner[0], inner[2])[0],
             samples_evaluated=aux["samples_evaluated"] + original_aux["samples_evaluated"])
  outputs = volume.volume_render(*volume.merge_samples(outer, inner, t_in, t_out),
                                 rays.cos_to_optical_axis,
                                 original.background if background is None else background)
  return outputs, outer_complete & inner_complete, aux
