"""One sample of the default model's data: an object in a small synthetic scene, rendered.

A sample is one object (a catalogue kind with a palette colour and a pattern, `objects` and
`appearance`) standing on a textured ground slab as in `signerf_jax.data.synthetic`'s scenes
(random ground colour and texture, sometimes up to two distractor primitives, a constant
background colour, a random light), rendered by the synthetic ray caster either
  * as a single view (1 camera), or
  * as a multi-view sheet: `sheet_tiles` reference views then one slot view (6 for the 2 x 3
    sheet), all of the same object with one appearance under one light, in the order
    `signerf_jax.editing.sheet` takes them (tiles in grid order skipping the slot, then the slot).
Cameras come as in the editing pipeline. A "dataset" rig like the synthetic scenes' (hemisphere
or forward-facing, random distance, field of view, elevations and a random turn about the
vertical) looks at the scene centre; "reference" cameras are placed around the object from that
rig by `signerf_jax.geometry.reference_cameras.place_reference_cameras` (the object roughly
centred; its bounding sphere fills a random fraction of the frame within `fill_range`). A "crop"
view is a dataset camera that sees the object, cut down to the crop around the object that the
pipeline's selection crops take of a dataset view (`editing.crops.selection_crop_boxes`, with a
random margin in `crop_margin_range`; the object may sit off-centre where the crop meets the
frame's edge) and rendered directly at the tile size: what the shipped model is given in the
image set update with `SheetConfig.crops`. (Whole 64-pixel dataset frames, where an object
covers a few percent of the pixels, are left out: at this size neither the VAE nor the
diffusion model can draw such an object.) The sheet's tiles are reference views; its slot view
is a crop view with probability `slot_crop_view_probability`, else one more reference view. A
single view is a reference view with probability `reference_view_probability`, else a crop
view. Views in which the object shows fewer than `min_object_pixels` pixels are rejected and
the whole sample is drawn again.

Per view (V views of H x W):
  rgb                  [V, H, W, 3] uint8   the scene with the object;
  background_rgb       [V, H, W, 3] uint8   the same view without it (the "original scene");
  depth                [V, H, W] float16    z-depth with the object (0 where rays miss);
  silhouette           [V, H, W] uint8      1 where the object is visible (occluders cut it);
  dilated_silhouettes  [V, K, H, W] uint8   the silhouette dilated by each of
                                            `dilation_radii` pixels (nested, growing);
  boxes                [V, 4] int16         silhouette bounding box [x0, y0, x1, y1), pixels;
  control_near_far     [V, 2] float32       the z-range for the control depth: the object's
                                            bounding sphere seen from the camera, padded, as
                                            `control_depth.selection_depth_range` gives the
                                            pipeline (control = normalize_control_depth(depth,
                                            near, far): near = 1, far = 0; the same rule makes
                                            the tiles of a sheet comparable);
  camera_to_world      [V, 3, 4] float32    OpenGL poses; intrinsics [V, 4] float32 fx fy cx cy;
  view_kinds           [V] uint8            index into VIEW_KINDS.
Per sample: caption, kind, color, pattern (strings), names_color / names_pattern (whether the
caption names them), object_sphere [4] (centre, radius), light [4] (direction to the light,
ambient share).

Everything is drawn from the one `np.random.Generator` passed in, so a sample is reproducible
from its seed (and the catalogue, i.e. which shared meshes exist).
"""

from __future__ import annotations

import colorsys
import dataclasses

import gin
import jax
import numpy as np
import trimesh

from signerf_jax import camera as camera_lib
from signerf_jax.data import poses as poses_lib
from signerf_jax.data import synthetic
from signerf_jax.default_model import appearance as appearance_lib
from signerf_jax.default_model import captions
from signerf_jax.default_model import objects
from signerf_jax.editing import crops
from signerf_jax.errors import InputError
from signerf_jax.geometry import control_depth
from signerf_jax.geometry import masks
from signerf_jax.geometry import reference_cameras

VIEW_KINDS = ("reference", "crop")
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
        raise InputError(f"invalid value {getattr(self, name)!r} (image_size >= 8, sheet_tiles >= "
                         "1, the object must fit on the smallest ground, 0 < fill_range <= fill_range "
                         "< 1, 0 <= crop_margin_range ordered, crop_max_upscale >= 1, radii "
                         "positive and increasing, max_attempts >= 1)",
                         field=f"default_model_scenes.{name}")

  def catalogue(self) -> tuple[objects.ObjectKind, ...]:
    """The object kinds available (loads the meshes once per process)."""
    return objects.build_catalogue(self.mesh_directory or str(objects.default_mesh_directory()))


@dataclasses.dataclass(frozen=True)
class Sample:
  """A rendered sample (see the module docstring for the arrays).

  Attributes:
    attributes: the object's kind, colour and pattern.
    caption: its caption; names_color, names_pattern: which attributes the caption names.
    views: per-view arrays, each with a leading axis of V views.
    object_sphere: [4] the object's bounding sphere (centre, radius).
    light: [4] unit direction towards the light and the ambient share.
  """

  attributes: captions.Attributes
  caption: str
  names_color: bool
  names_pattern: bool
  views: dict[str, np.ndarray]
  object_sphere: np.ndarray
  light: np.ndarray

  def arrays(self) -> dict[str, np.ndarray]:
    """Everything as named arrays (what a shard stacks over samples)."""
    return {**self.views, "caption": np.array(self.caption), "kind": np.array(self.attributes.kind),
            "color": np.array(self.attributes.color),
            "pattern": np.array(self.attributes.pattern),
            "names_color": np.array(self.names_color), "names_pattern": np.array(self.names_pattern),
            "object_sphere": self.object_sphere.astype(np.float32),
            "light": self.light.astype(np.float32)}


def random_attributes(rng: np.random.Generator, catalogue) -> captions.Attributes:
  """A uniformly random kind (of the catalogue), colour and pattern."""
  return captions.Attributes(kind=catalogue[rng.integers(len(catalogue))].name,
                             color=appearance_lib.COLORS[rng.integers(len(appearance_lib.COLORS))],
                             pattern=appearance_lib.PATTERNS[rng.integers(len(appearance_lib.PATTERNS))])


def _hsv_color(rng, saturation_range, value_range) -> np.ndarray:
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


def dataset_rig(rng: np.random.Generator, settings: SceneSampling, scene_bounds
                ) -> camera_lib.Cameras:
  """A random rig like the synthetic scenes' cameras, turned by a random angle about the vertical."""
  rig = synthetic.CameraRig(
      layout="forward_facing" if rng.uniform() < settings.rig_forward_facing_probability
      else "hemisphere",
      num_views=settings.rig_views, image_size=settings.image_size,
      field_of_view_degrees=rng.uniform(*settings.rig_field_of_view_degrees_range),
      distance=rng.uniform(*settings.rig_distance_range),
      elevation_range_degrees=(rng.uniform(*settings.rig_low_elevation_degrees_range),
                               rng.uniform(*settings.rig_high_elevation_degrees_range)),
      arc_degrees=rng.uniform(*settings.rig_arc_degrees_range))
  cameras = synthetic.make_cameras(rig, scene_bounds)
  target = np.mean(np.asarray(scene_bounds, np.float64), axis=0)
  turn = trimesh.transformations.rotation_matrix(rng.uniform(0, 2 * np.pi), (0.0, 0.0, 1.0),
                                                 point=target)
  return poses_lib.transform_cameras(turn, cameras)


def _object_corners(scene: synthetic.SyntheticScene) -> np.ndarray:
  """[8, 3] corners of the object's bounding box."""
  bounds = scene.objects[0].world_bounds()
  return np.stack(np.meshgrid(*bounds.T, indexing="ij"), -1).reshape(-1, 3)


def _views_cameras(rng, settings: SceneSampling, scene, num_views: int, sheet: bool):
  """(cameras, view kinds) for a single view (num_views 1) or a sheet, or None if unseen."""
  dataset_cameras = dataset_rig(rng, settings, scene.scene_bounds)
  corners = _object_corners(scene)
  seeing = np.flatnonzero(reference_cameras.cameras_seeing(dataset_cameras, corners))
  if not len(seeing):
    return None
  references, _ = reference_cameras.place_reference_cameras(
      dataset_cameras, corners, count=settings.sheet_tiles + 1, up=(0.0, 0.0, 1.0),
      min_fill=rng.uniform(*settings.fill_range), max_fill=settings.fill_range[1])
  dataset_view = dataset_cameras.take([seeing[rng.integers(len(seeing))]])
  # Drawn for every sample, used or not, so that the random stream (the dataset) stays the same.
  crop_margin = rng.uniform(*settings.crop_margin_range)

  def crop_view():
    size = settings.image_size
    box = crops.selection_crop_boxes(dataset_view, corners, size, size, crop_margin,
                                     settings.crop_max_upscale)
    return jax.tree.map(np.asarray, dataset_view.cropped(box, size, size))

  if sheet:
    if rng.uniform() < settings.slot_crop_view_probability:
      tiles = references.take(slice(0, num_views - 1))
      return (jax.tree.map(lambda *arrays: np.concatenate(arrays), tiles, crop_view()),
              [0] * (num_views - 1) + [1])
    return references, [0] * num_views
  if rng.uniform() < settings.reference_view_probability:
    return references.take([rng.integers(references.num_cameras)]), [0]
  return crop_view(), [1]


def bounding_boxes(silhouette: np.ndarray) -> np.ndarray:
  """[V, 4] int16 [x0, y0, x1, y1) pixel bounds of each nonempty [V, H, W] silhouette."""
  rows, columns = silhouette.any(2), silhouette.any(1)
  first = lambda occupied: np.argmax(occupied, -1)
  last = lambda occupied: occupied.shape[-1] - np.argmax(occupied[:, ::-1], -1)
  return np.stack([first(columns), first(rows), last(columns), last(rows)], -1).astype(np.int16)


def render_views(scene: synthetic.SyntheticScene, background_scene: synthetic.SyntheticScene,
                 cameras: camera_lib.Cameras, settings: SceneSampling) -> dict[str, np.ndarray]:
  """The per-view arrays of the module docstring (without view_kinds)."""
  rgb, depth, object_ids = synthetic.render(scene, cameras)
  background_rgb, _, _ = synthetic.render(background_scene, cameras)
  silhouette = object_ids == OBJECT_ID
  dilated = np.stack([np.asarray(masks.dilate_and_feather(
      silhouette, radius=float(radius), reference_size=settings.image_size))
                      for radius in settings.dilation_radii], 1)
  center, radius = reference_cameras.selection_sphere(_object_corners(scene))
  near, far = control_depth.selection_depth_range(cameras, center, radius)
  to_uint8 = lambda image: np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)
  return {
      "rgb": to_uint8(rgb), "background_rgb": to_uint8(background_rgb),
      "depth": depth.astype(np.float16), "silhouette": silhouette.astype(np.uint8),
      "dilated_silhouettes": dilated.astype(np.uint8), "boxes": bounding_boxes(silhouette),
      "control_near_far": np.stack([near, far], -1).astype(np.float32),
      "camera_to_world": np.asarray(cameras.camera_to_world, np.float32),
      "intrinsics": np.stack([cameras.fx, cameras.fy, cameras.cx, cameras.cy], -1).astype(
          np.float32),
  }


def make_sample(rng: np.random.Generator, settings: SceneSampling,
                caption_settings: captions.CaptionSettings, sheet: bool,
                attributes: captions.Attributes | None = None) -> Sample:
  """A single view (sheet False) or a sheet of the same object; random attributes if None.

  Raises:
    InputError: no acceptable draw in `settings.max_attempts` (the settings make the object
      invisible or occluded too often).
  """
  catalogue = settings.catalogue()
  attributes = random_attributes(rng, catalogue) if attributes is None else attributes
  num_views = settings.sheet_tiles + 1 if sheet else 1
  for _ in range(settings.max_attempts):
    scene, background_scene = random_scene(rng, settings, attributes)
    chosen = _views_cameras(rng, settings, scene, num_views, sheet)
    if chosen is None:
      continue
    cameras, view_kinds = chosen
    views = render_views(scene, background_scene, cameras, settings)
    if views["silhouette"].sum((1, 2)).min() < settings.min_object_pixels:
      continue
    views["view_kinds"] = np.asarray(view_kinds, np.uint8)
    text, names_color, names_pattern = captions.random_caption(rng, attributes, caption_settings)
    center, radius = reference_cameras.selection_sphere(_object_corners(scene))
    return Sample(attributes=attributes, caption=text, names_color=names_color,
                  names_pattern=names_pattern, views=views,
                  object_sphere=np.array([*center, radius]),
                  light=np.array([*scene.light_direction, scene.ambient]))
  raise InputError(f"no draw of a {attributes.kind} showed {settings.min_object_pixels} object "
                   f"pixels in every view in {settings.max_attempts} attempts",
                   field="default_model_scenes")
