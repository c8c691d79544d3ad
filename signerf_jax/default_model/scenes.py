"""The random scene of one sample, and how samples are drawn (`SceneSampling`).

A sample's scene is one object (a catalogue kind with a palette colour and a pattern, `objects`
and `appearance`) standing on a textured ground slab as in `signerf_jax.data.synthetic`'s scenes
(random ground colour and texture, sometimes up to two distractor primitives, a constant
background colour, a random light); the same scene without the object is the "original scene"
the pipeline inpaints. `SceneSampling` also holds how the views of a sample are drawn (`views`)
and when a sample is rejected (`samples`).
"""

from __future__ import annotations

import colorsys
import dataclasses

import gin
import numpy as np

from signerf_jax.data import synthetic
from signerf_jax.default_model import appearance as appearance_lib
from signerf_jax.default_model import captions
from signerf_jax.default_model import objects
from signerf_jax.errors import InputError

DISTRACTOR_KINDS = ("cube", "ball", "cylinder")
GROUND_TEXTURES = ("checker", "stripes", "blobs")
OBJECT_ID = 1
# As the synthetic scenes' defaults.
GROUND_THICKNESS = 0.1
DISTRACTOR_TEXTURE_FREQUENCY = 5.0
# Clearance between footprints on the ground.
FOOTPRINT_GAP = 0.05
MAX_PLACEMENT_ATTEMPTS = 100


@gin.configurable("default_model_scenes")
@dataclasses.dataclass(frozen=True)
class SceneSampling:
  """How samples are drawn (gin: `default_model_scenes.<field>`); ranges are (min, max).

  Attributes:
    image_size: view width and height in pixels (64: the demo's scene resolution).
    sheet_tiles: reference views of a sheet (a sheet sample has sheet_tiles + 1 views).
    mesh_directory: the shared meshes ("": $SIGNERF_SHARED_DATA/meshes or ../shared/data/meshes).
    ground_half_size_range: the square ground slab's half size.
    object_radius_range: the object's footprint radius.
    distractor_probability, max_distractors, distractor_radius_range: other primitives.
    plain_ground_probability, demo_ground_probability: ground without texture / with the
      synthetic scenes' colour; ground_texture_frequency_range: its pattern frequency.
    white_background_probability: else a random light, weakly saturated colour.
    light_elevation_degrees_range, ambient_range: the light.
    rig_views: cameras of the dataset rig; rig_forward_facing_probability: else a hemisphere;
    rig_distance_range, rig_field_of_view_degrees_range, rig_low_elevation_degrees_range,
    rig_high_elevation_degrees_range, rig_arc_degrees_range: the rig's `CameraRig` fields.
    fill_range: fraction of the frame the object's bounding sphere fills in reference views.
    crop_margin_range: context around the object's projected bounding box in crop views, as a
      fraction of its size on each side (`crops.selection_crop_boxes`' margin).
    crop_max_upscale: crop views are at least image_size / crop_max_upscale dataset pixels wide.
    reference_view_probability: a single view is a reference view (else a crop view).
    slot_crop_view_probability: a sheet's slot view is a crop view (else a reference view).
    dilation_radii: pixels the stored dilated silhouettes grow by.
    min_object_pixels: fewer visible object pixels in any view rejects the sample.
    max_attempts: draws before giving up on a sample.
  """

  image_size: int = 64
  sheet_tiles: int = 5
  mesh_directory: str = ""
  ground_half_size_range: tuple[float, float] = (0.75, 1.0)
  object_radius_range: tuple[float, float] = (0.15, 0.35)
  distractor_probability: float = 0.5
  max_distractors: int = 2
  distractor_radius_range: tuple[float, float] = (0.1, 0.25)
  plain_ground_probability: float = 0.25
  demo_ground_probability: float = 0.3
  ground_texture_frequency_range: tuple[float, float] = (8.0, 16.0)
  white_background_probability: float = 0.5
  light_elevation_degrees_range: tuple[float, float] = (35.0, 80.0)
  ambient_range: tuple[float, float] = (0.35, 0.5)
  rig_views: int = 24
  rig_forward_facing_probability: float = 0.3
  rig_distance_range: tuple[float, float] = (2.4, 3.2)
  rig_field_of_view_degrees_range: tuple[float, float] = (42.0, 58.0)
  rig_low_elevation_degrees_range: tuple[float, float] = (10.0, 30.0)
  rig_high_elevation_degrees_range: tuple[float, float] = (45.0, 75.0)
  rig_arc_degrees_range: tuple[float, float] = (90.0, 180.0)
  fill_range: tuple[float, float] = (0.2, 0.6)
  crop_margin_range: tuple[float, float] = (0.15, 0.6)
  crop_max_upscale: float = 4.0
  reference_view_probability: float = 0.5
  slot_crop_view_probability: float = 0.5
  dilation_radii: tuple[int, ...] = (2, 4, 8)
  min_object_pixels: int = 16
  max_attempts: int = 30

  def __post_init__(self):
    checks = {
        "image_size": self.image_size >= 8,
        "sheet_tiles": self.sheet_tiles >= 1,
        "ground_half_size_range": (self.ground_half_size_range[0]
                                   >= self.object_radius_range[1] + FOOTPRINT_GAP),
        "fill_range": 0 < self.fill_range[0] <= self.fill_range[1] < 1,
        "crop_margin_range": 0 <= self.crop_margin_range[0] <= self.crop_margin_range[1],
        "crop_max_upscale": self.crop_max_upscale >= 1,
        "dilation_radii": (all(radius > 0 for radius in self.dilation_radii)
                           and list(self.dilation_radii) == sorted(set(self.dilation_radii))),
        "max_attempts": self.max_attempts >= 1,
    }
    for name, valid in checks.items():
      if not valid:
        raise InputError(f"invalid value {getattr(self, name)!r} (image_size >= 8, "
                         "sheet_tiles >= 1, the object must fit on the smallest ground, "
                         "0 < fill_range <= fill_range < 1, 0 <= crop_margin_range ordered, "
                         "crop_max_upscale >= 1, radii positive and increasing, "
                         "max_attempts >= 1)",
                         field=f"default_model_scenes.{name}")

  def catalogue(self) -> tuple[objects.ObjectKind, ...]:
    """The object kinds available (loads the meshes once per process)."""
    return objects.build_catalogue(self.mesh_directory or str(objects.default_mesh_directory()))


def _hsv_color(rng, saturation_range, value_range) -> np.ndarray:
  """[3] RGB of a uniformly random hue, its saturation and value drawn from the ranges."""
  return np.array(colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(*saturation_range),
                                      rng.uniform(*value_range)))


def _free_spot(rng, half_size: float, radius: float, taken) -> np.ndarray | None:
  """A footprint centre on the ground clear of `taken` [(centre, radius)], or None."""
  limit = half_size - radius - FOOTPRINT_GAP
  for _ in range(MAX_PLACEMENT_ATTEMPTS):
    center = rng.uniform(-limit, limit, 2)
    if all(np.linalg.norm(center - other) > radius + other_radius + FOOTPRINT_GAP
           for other, other_radius in taken):
      return center
  return None


def _ground(rng, settings: SceneSampling, half_size: float) -> synthetic.SceneObject:
  """The square ground slab: the synthetic scenes' colour or a random one, textured or plain."""
  thickness = GROUND_THICKNESS
  color = (np.asarray(synthetic.GROUND_COLOR) if rng.uniform() < settings.demo_ground_probability
           else _hsv_color(rng, (0.05, 0.45), (0.45, 0.9)))
  plain = rng.uniform() < settings.plain_ground_probability
  return synthetic.SceneObject(
      object_id=0, shape="box",
      object_to_world=synthetic.affine(np.diag([half_size, half_size, thickness / 2]),
                                       [0.0, 0.0, synthetic.GROUND_HEIGHT - thickness / 2]),
      color=color, texture=GROUND_TEXTURES[rng.integers(len(GROUND_TEXTURES))],
      texture_axis=_unit_horizontal(rng),
      texture_frequency=0.0 if plain else rng.uniform(*settings.ground_texture_frequency_range),
      footprint_center=np.zeros(2), footprint_radius=half_size * np.sqrt(2))


def _unit_horizontal(rng) -> np.ndarray:
  """[3] a uniformly random unit vector in the ground plane."""
  angle = rng.uniform(0, 2 * np.pi)
  return np.array([np.cos(angle), np.sin(angle), 0.0])


def _distractors(rng, settings: SceneSampling, catalogue, half_size: float, taken):
  """Up to `max_distractors` primitives with the synthetic scenes' random colours and textures."""
  if rng.uniform() >= settings.distractor_probability:
    return []
  by_name = {kind.name: kind for kind in catalogue}
  result = []
  for index in range(rng.integers(1, settings.max_distractors + 1)):
    kind = by_name[DISTRACTOR_KINDS[rng.integers(len(DISTRACTOR_KINDS))]]
    radius = rng.uniform(*settings.distractor_radius_range)
    center = _free_spot(rng, half_size, radius, taken)
    if center is None:
      break
    taken.append((center, radius))
    placement = objects.random_placement(rng, kind, center, radius)
    result.append(synthetic.SceneObject(
        object_id=OBJECT_ID + 1 + index, shape=kind.shape,
        object_to_world=objects.object_to_world(kind, placement, synthetic.GROUND_HEIGHT),
        color=_hsv_color(rng, (0.4, 0.8), (0.5, 0.95)),
        texture=synthetic.OBJECT_TEXTURES[rng.integers(len(synthetic.OBJECT_TEXTURES))],
        texture_axis=_unit_horizontal(rng), texture_frequency=DISTRACTOR_TEXTURE_FREQUENCY,
        footprint_center=center, footprint_radius=radius))
  return result


def random_scene(rng: np.random.Generator, settings: SceneSampling, attributes: captions.Attributes
                 ) -> tuple[synthetic.SyntheticScene, synthetic.SyntheticScene]:
  """The scene with the object (id OBJECT_ID) and the same scene without it."""
  catalogue = settings.catalogue()
  kind = next(kind for kind in catalogue if kind.name == attributes.kind)
  half_size = rng.uniform(*settings.ground_half_size_range)
  radius = rng.uniform(*settings.object_radius_range)
  center = _free_spot(rng, half_size, radius, [])
  placement = objects.random_placement(rng, kind, center, radius)
  appearance = appearance_lib.random_appearance(rng, attributes.color, attributes.pattern)
  main = objects.scene_object(kind, placement, appearance, OBJECT_ID)
  ground = _ground(rng, settings, half_size)
  distractors = _distractors(rng, settings, catalogue, half_size, [(center, radius)])
  elevation = np.radians(rng.uniform(*settings.light_elevation_degrees_range))
  light = np.cos(elevation) * _unit_horizontal(rng) + [0.0, 0.0, np.sin(elevation)]
  background = (np.ones(3) if rng.uniform() < settings.white_background_probability
                else _hsv_color(rng, (0.0, 0.25), (0.75, 1.0)))
  shapes = [ground, main, *distractors]
  bounds = np.stack([shape.world_bounds() for shape in shapes])
  scene_bounds = np.clip(np.stack([bounds[:, 0].min(0) - synthetic.BOUNDS_MARGIN,
                                   bounds[:, 1].max(0) + synthetic.BOUNDS_MARGIN]), -1.0, 1.0)
  scene = synthetic.SyntheticScene(
      seed=-1, ground=ground, objects=(main, *distractors),
      free_spot_center=np.array([*center, synthetic.GROUND_HEIGHT]), free_spot_radius=radius,
      light_direction=light, ambient=float(rng.uniform(*settings.ambient_range)),
      background_color=background, scene_bounds=scene_bounds)
  return scene, dataclasses.replace(scene, objects=tuple(distractors))


def object_corners(scene: synthetic.SyntheticScene) -> np.ndarray:
  """[8, 3] corners of the object's bounding box."""
  bounds = scene.objects[0].world_bounds()
  return np.stack(np.meshgrid(*bounds.T, indexing="ij"), -1).reshape(-1, 3)
