"""Model only what a scene needs: derive grid sizes, samples and background from the scene.

A fixed large default (16 levels up to 2048^3, 2^19 rows per level) spends most of a CPU's time
on resolution the images cannot show and on Adam updates of rows no sample touches. Instead:
  * finest resolution ~ what one pixel covers at the scene's distance (the images cannot resolve
    finer detail): extent / (distance / focal), times an oversampling factor;
  * levels: a geometric series from a coarse base growing by about `level_growth` per level;
  * table rows per level: no more than the finest level's vertices, and about the number of
    finest cells a surface of the scene's size crosses (~ resolution^2), since empty cells only
    collide harmlessly (instant-NGP's argument);
  * samples: an occupancy grid for bounded scenes, marching steps about one finest cell long;
    one proposal network otherwise, with scene contraction for unbounded scenes and NDC's
    perspective warp for forward-facing ones (finest cells then sized by pixel angles);
  * background: the dataset's constant colour for bounded scenes; otherwise the last sample's
    interval reaches infinity and the field models the background itself.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Annotated, Any, Mapping

import numpy as np

from signerf_jax import validation
from signerf_jax.errors import InputError
from signerf_jax.nerf.scene_info import SceneInfo, check_scene
from signerf_jax.validation import PositiveFloat, PositiveInt, Range


# Capacity fields of older model.json files -> the one value the code still supports (it
# builds that model): every level of the grid hashed when it does not fit its table, and the
# cameras' poses as given (no trained pose corrections).
REMOVED_FIELDS = {"hashed": True, "pose_refinement": False}


@dataclasses.dataclass(frozen=True)
class Capacity:
  """Every size that shapes the model and its sampling (static under jit).

  Attributes:
    contract: map unbounded space into a finite cube (mip-NeRF 360) before the grid.
    perspective_warp: forward-facing scenes: the grid is over `sampling.perspective`
      coordinates (NDC's warp) and samples are spaced evenly in disparity.
    background: "constant" (the scene's colour) or "last_sample" (last interval to infinity).
    sampler: "occupancy" (bounded scenes) or "proposal" (nerfacto-style proposal networks).
    num_levels, base_resolution, finest_resolution, log2_table_size, features_per_level: the
      radiance field's grid (see `encoding.grid_layout`).
    mlp_width: hidden width of the radiance field's MLPs.
    appearance_embedding: learn a per-image appearance code.
    rays_per_batch: rays per training step.
    march_steps: candidate samples per ray (occupancy sampler).
    occupancy_resolution: occupancy grid cells per axis.
    samples_per_batch: network evaluations per training step after skipping empty space
      (occupancy sampler; rays that do not fit are left out of that step's loss).
    sample_groups: the occupancy sampler fills the sample budget per group of consecutive rays
      of a batch, samples_per_batch / sample_groups each (1: one budget for the whole batch).
      Groups are independent, so data-parallel training splits them over devices; a multiple
      of the device count lets each device evaluate only its own rays' samples.
    proposal_samples: intervals per ray for each proposal network (proposal sampler).
    samples_per_ray: intervals per ray for the radiance field (proposal sampler).
    render_sample_fraction: rendering (not training) takes this fraction of the radiance
      field's intervals per ray; the proposal networks keep all of theirs (`sample_counts`;
      see `CapacityRules`). Rendering front to back (`render.render_cameras`' default) takes
      at most `front_to_back.RenderSettings.field_sample_fraction`.
    proposal_finest_resolution, proposal_log2_table_size: the proposal networks' grids.
    near_gradient_scaling: scale each sample's gradients by its squared distance from the
      camera, up to the cameras' distance to the scene ("Floaters No More";
      `losses.near_camera_gradient_scaling`), against floaters in front of the cameras.
    coarse_to_fine: fraction of training over which the radiance field's finer grid levels
      are switched on one after another (`encoding.level_weights_at`); 0: all from the start.
    pixel_samples: rays per pixel side. A pixel is the mean colour of the pixel_samples^2 rays
      through a grid of points inside it (`camera.subpixel_positions`), as a photo's pixel is
      the mean of the light over its area: training compares that mean with the photo (an
      edit region's training and an edit's fine-tuning, `editing.finetune`, keep one ray a
      pixel) and rendering averages as many rays (`render.render_cameras`' default; the
      viewer renders one). 1: one ray through the pixel's centre.
    sh_degree: spherical-harmonics degree of the colour's view-direction encoding
      (sh_degree^2 channels; 1: the colour does not depend on the view).
  """

  contract: bool
  background: str
  sampler: str
  num_levels: int
  base_resolution: int
  finest_resolution: int
  log2_table_size: int
  features_per_level: int = 2
  mlp_width: int = 64
  appearance_embedding: bool = False
  rays_per_batch: int = 8192
  march_steps: int = 256
  occupancy_resolution: int = 64
  samples_per_batch: int = 65536
  sample_groups: int = 1
  proposal_samples: tuple[int, ...] = (64, 32)
  samples_per_ray: int = 24
  render_sample_fraction: float = 1.0
  proposal_finest_resolution: int = 128
  proposal_log2_table_size: int = 16
  near_gradient_scaling: bool = False
  coarse_to_fine: float = 0.0
  perspective_warp: bool = False
  pixel_samples: int = 1
  sh_degree: int = 4

  @classmethod
  def from_json(cls, value: Mapping[str, Any]) -> "Capacity":
    """The capacity a run's model.json records (`dataclasses.asdict`). Older files also hold
    the removed fields of `REMOVED_FIELDS`, which must have the value the code now always uses.

    Raises:
      InputError: a removed field with another value (a model this code cannot rebuild).
    """
    value = dict(value)
    for name, only_value in REMOVED_FIELDS.items():
      if value.get(name, only_value) != only_value:
        raise InputError(f"{name} = {value[name]!r}: a model with an option signerf no longer "
                         "has; train it again", field=f"capacity.{name}")
      value.pop(name, None)
    value["proposal_samples"] = tuple(value["proposal_samples"])
    return cls(**value)

  def sample_counts(self, training: bool) -> tuple[tuple[int, ...], int]:
    """(intervals per ray of each proposal network, of the field) for training or rendering:
    rendering takes `render_sample_fraction` of the field's (a multiple of 4, at least 4) and
    every proposal interval, which places the field's samples (a field sample costs about seven
    proposal samples; `CapacityRules.render_sample_fraction`)."""
    if training or self.render_sample_fraction == 1.0:
      return self.proposal_samples, self.samples_per_ray
    return self.proposal_samples, 4 * max(1, round(
        self.samples_per_ray * self.render_sample_fraction / 4))


# Captures with fewer training views than this are sparse (object captures of 10-15 views):
# `CapacityRules.pixel_samples`.
SPARSE_VIEWS = 16
# Spherical-harmonics degrees of the colour's view dependence (`CapacityRules.sh_degree`).
SH_DEGREE = 4
SPARSE_SH_DEGREE = 2
# The fraction of training over which sparse bounded captures switch on their finer grid levels
# (`CapacityRules.coarse_to_fine`).
SPARSE_COARSE_TO_FINE = 0.25


def _round_up(value: float, multiple: int) -> int:
  return int(math.ceil(value / multiple) * multiple)


@dataclasses.dataclass(frozen=True)
class CapacityRules(validation.CheckedFields):
  """The rules `derive_capacity` sizes a model by (gin: `CapacityRules.<field>`).

  Attributes:
    oversampling: finest grid cells per pixel footprint (cells / pixel).
    base_resolution: the coarsest grid level's cells per side.
    level_growth: target resolution ratio between consecutive grid levels (> 1).
    features_per_level: features (floats) per grid row.
    max_log2_table_size: cap on log2 of the rows of a hashed level.
    table_rows_per_surface_cell: rows per level = this * finest_resolution^2 (rounded up to a
      power of two): rows per finest cell of a surface spanning the scene.
    steps_per_finest_cell: marching steps per finest cell length (occupancy sampler).
    rays_per_batch: rays per training step; None derives it: with the occupancy sampler, enough
      rays to fill the sample budget at 8 occupied samples per ray (typical once empty space is
      pruned; rays that overflow the budget only cost their grid lookups); with proposals,
      enough rays for half of `samples_per_batch` radiance-field samples (see
      `_samples_and_rays`).
    samples_per_batch: radiance-field samples per training step.
    sample_groups: independent sample budgets per batch (occupancy sampler); 8 lets 1, 2, 4
      or 8 devices share training evenly (`Capacity.sample_groups`).
    appearance_embedding: per-image appearance codes (NeRF-W). Held-out views render with the
      mean code, which is no training view's own, so the codes lower held-out quality on
      forward-facing and 360-degree captures alike (docs/performance.md); they are off unless
      asked for (a capture whose exposure varies a lot may still want them).
    render_sample_fraction: the share of the radiance field's intervals per ray rendering
      takes (1: render as trained); the proposal networks keep theirs, as scaling them too
      loses more quality for the same speed-up. Fewer field samples render faster for a loss
      of quality that grows as the fraction shrinks (docs/performance.md), so the model takes
      every sample unless asked; rendering front to back takes two thirds at most
      (`front_to_back.RenderSettings.field_sample_fraction`: 0.1 dB on stitch), and the
      viewer's moving-camera frames a third (`viewer.progressive.MOVING_SAMPLE_FRACTION`).
    pixel_samples: `Capacity.pixel_samples`; None derives it: 2 for sparse bounded captures
      (fewer than `SPARSE_VIEWS` training views), 1 otherwise. Between so few views the field is
      unconstrained, and one ray through each pixel's centre fits a photo's pixel (the mean
      over its area) with whatever lies between the rays; averaging 2 x 2 rays a pixel fits
      the photos' pixels as they were taken, which improves held-out views of a sparse object
      capture. A capture with many views gains nothing, and a sparse real 360-degree
      (unbounded) capture loses (docs/performance.md), hence bounded and sparse only.
    sh_degree: `Capacity.sh_degree`; None derives it: SPARSE_SH_DEGREE for sparse bounded
      captures, SH_DEGREE otherwise. A few views see each surface from a few directions; a
      colour free to vary with direction fits each photo from its own and guesses the held-out
      ones, while a linear dependence still shows shading that moves with the view (lego with
      12 views: docs/performance.md).
    coarse_to_fine: `Capacity.coarse_to_fine`; None derives it: SPARSE_COARSE_TO_FINE for
      sparse bounded captures, 0 otherwise. Fitting the coarse levels first (FreeNeRF's
      frequency annealing) shapes the object before the fine levels can fit each photo's
      detail on its own.
    overrides: `Capacity` fields to force after deriving, e.g. a fixed large configuration for
      comparison; None for none. (A mapping makes the rules unhashable: they are never a static
      jit argument, only the `Capacity` they produce is.)
  """

  oversampling: PositiveFloat = 1.0
  base_resolution: PositiveInt = 16
  level_growth: Annotated[float, Range(1, low_inclusive=False)] = 1.5
  features_per_level: PositiveInt = 2
  max_log2_table_size: Annotated[int, Range(12, 30)] = 19
  table_rows_per_surface_cell: PositiveFloat = 4.0
  steps_per_finest_cell: PositiveFloat = 1.0
  rays_per_batch: PositiveInt | None = None
  samples_per_batch: PositiveInt = 65536
  sample_groups: PositiveInt = 8
  appearance_embedding: bool = False
  render_sample_fraction: Annotated[float, Range(0, 1, low_inclusive=False)] = 1.0
  pixel_samples: PositiveInt | None = None
  sh_degree: PositiveInt | None = None
  coarse_to_fine: Annotated[float, Range(0, 1)] | None = None
  overrides: Mapping[str, Any] | None = None

  def __post_init__(self):
    super().__post_init__()
    unknown = sorted(set(self.overrides or {}) - {field.name for field in
                                                  dataclasses.fields(Capacity)})
    if unknown:
      raise InputError(f"not fields of Capacity: {unknown}", field="CapacityRules.overrides")


def _grid_sizes(scene: SceneInfo, rules: CapacityRules) -> tuple[int, int, int]:
  """(finest resolution, number of levels, log2 rows per level) of the radiance field's grid."""
  inner_cells = rules.oversampling * scene.extent / scene.pixel_footprint
  if scene.perspective is not None:  # One finest cell per pixel across the widest image range.
    focal = scene.camera_distance / scene.pixel_footprint
    inner_cells = rules.oversampling * focal * scene.perspective.image_plane_extent
  # Contraction squeezes the inner box into half of the grid's side.
  contract = scene.kind == "unbounded"
  finest = max(rules.base_resolution, _round_up(2 * inner_cells if contract else inner_cells, 8))
  num_levels = 1 + max(0, math.ceil(math.log(finest / rules.base_resolution)
                                    / math.log(rules.level_growth)))
  vertices_log2 = math.ceil(math.log2((finest + 1)**3))
  surface_log2 = math.ceil(math.log2(rules.table_rows_per_surface_cell * finest**2))
  return finest, num_levels, max(12, min(rules.max_log2_table_size, surface_log2, vertices_log2))


def _samples_and_rays(scene: SceneInfo, rules: CapacityRules) -> tuple[tuple[int, ...], int, int]:
  """(proposal intervals per ray for each proposal network, field intervals per ray, rays per
  training step)."""
  # One proposal network and half the sample budget a step, as more and smaller steps fit more
  # in a time budget; 24 samples a ray for forward-facing scenes whatever the image size, more
  # for larger images of 360-degree captures (within nerfacto's ranges). Of the samples per
  # ray, rays per step and proposal networks tried under a fixed time budget, on a
  # forward-facing and a 360-degree capture, these gave the best held-out quality, the more so
  # for short budgets (docs/performance.md).
  forward_facing = scene.perspective is not None
  pixels_scale = math.sqrt(scene.width * scene.height) / 256.0
  samples_per_ray = 24 if forward_facing else int(np.clip(_round_up(24 * pixels_scale, 8), 16, 48))
  rays_per_batch = rules.rays_per_batch
  if rays_per_batch is None:
    bounded = scene.kind == "bounded"  # The occupancy sampler: ~8 occupied samples a ray.
    per_ray = 8 if bounded else samples_per_ray
    budget = rules.samples_per_batch if bounded else rules.samples_per_batch // 2
    rays_per_batch = max(256, budget // per_ray // 256 * 256)
  return (2 * samples_per_ray,), samples_per_ray, rays_per_batch


def derive_capacity(scene: SceneInfo, rules: CapacityRules = CapacityRules()) -> Capacity:
  """The capacity a scene needs, sized by `rules` (whose `overrides` pin any field).

  Args:
    scene: the scene's geometry and image size.
    rules: the knobs of the derivation (see `CapacityRules`).
  Raises:
    InputError: the scene's bounds, pixel footprint or camera distance (`check_scene`).
  """
  check_scene(scene)
  bounded = scene.kind == "bounded"
  contract = scene.kind == "unbounded"
  finest, num_levels, log2_table_size = _grid_sizes(scene, rules)
  cell = scene.extent / finest
  diagonal = math.sqrt(3.0) * scene.extent
  march_steps = _round_up(diagonal / (cell / rules.steps_per_finest_cell), 8)
  # About what a coarse pixel footprint covers per cell, capped where updates get expensive.
  occupancy_resolution = int(np.clip(_round_up(finest / 2, 16), 32, 128))
  proposal_samples, samples_per_ray, rays_per_batch = _samples_and_rays(scene, rules)
  sparse_object = bounded and scene.num_images < SPARSE_VIEWS
  capacity = Capacity(
      contract=contract,
      background="constant" if bounded and scene.background_color is not None else "last_sample",
      sampler="occupancy" if bounded else "proposal",
      num_levels=num_levels,
      base_resolution=rules.base_resolution,
      finest_resolution=finest,
      log2_table_size=log2_table_size,
      features_per_level=rules.features_per_level,
      appearance_embedding=rules.appearance_embedding,
      rays_per_batch=rays_per_batch,
      march_steps=march_steps,
      occupancy_resolution=occupancy_resolution,
      samples_per_batch=rules.samples_per_batch,
      sample_groups=rules.sample_groups,
      proposal_samples=proposal_samples,
      samples_per_ray=samples_per_ray,
      render_sample_fraction=rules.render_sample_fraction,
      proposal_finest_resolution=min(finest, 256),
      proposal_log2_table_size=min(log2_table_size, 17),
      # 360-degree captures put cameras among the content they see. Forward-facing ones see
      # it all in front of them, much of it nearer than the scene centre, whose gradients the
      # scaling would damp (it lowers a forward-facing capture's quality).
      near_gradient_scaling=contract,
      perspective_warp=scene.perspective is not None,
      pixel_samples=rules.pixel_samples or (2 if sparse_object else 1),
      sh_degree=rules.sh_degree or (SPARSE_SH_DEGREE if sparse_object else SH_DEGREE),
      coarse_to_fine=(rules.coarse_to_fine if rules.coarse_to_fine is not None
                      else SPARSE_COARSE_TO_FINE if sparse_object else 0.0),
  )
  return dataclasses.replace(capacity, **dict(rules.overrides or {}))


def describe(capacity: Capacity) -> str:
  """One line saying what the model spends its capacity and regularisation on."""
  if capacity.sampler == "occupancy":
    sampler = f"occupancy-grid sampling ({capacity.march_steps} steps per ray)"
  else:
    trained, rendered = (" > ".join(map(str, (*proposal, field))) for proposal, field in
                         map(capacity.sample_counts, (True, False)))
    rendering = "" if trained == rendered else f"; {rendered} when rendering"
    sampler = f"proposal sampling ({trained} samples per ray{rendering})"
  region = "a bounded region"
  if capacity.contract:
    region = "contracted unbounded space"
  elif capacity.perspective_warp:
    region = "perspective-warped space (NDC's warp) sampled evenly in disparity"
  parts = [
      region,
      f"{capacity.num_levels} grid levels {capacity.base_resolution}..{capacity.finest_resolution}"
      f" with up to 2^{capacity.log2_table_size} rows each",
      sampler,
      f"{capacity.rays_per_batch} rays per step",
      "the constant background colour" if capacity.background == "constant"
      else "the background modelled by the field",
  ]
  if capacity.appearance_embedding:
    parts.append("per-image appearance codes")
  if capacity.near_gradient_scaling:
    parts.append("near-camera gradient scaling")
  if capacity.coarse_to_fine > 0:
    parts.append(f"coarse-to-fine grid levels over {capacity.coarse_to_fine:.0%} of training")
  if capacity.sh_degree != SH_DEGREE:
    parts.append(f"view dependence of spherical-harmonics degree {capacity.sh_degree}")
  if capacity.pixel_samples > 1:
    parts.append(f"{capacity.pixel_samples} x {capacity.pixel_samples} rays a pixel in training "
                 "and rendering (a sparse bounded capture)")
  return "model: " + ", ".join(parts)
