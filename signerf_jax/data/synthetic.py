"""Synthetic scenes with exact ground truth: a textured ground with objects, ray cast from cameras.

A scene is built directly in the normalised frame (z up, content inside [-1, 1]^3): a square
ground slab whose top is the plane z = 0, a few primitives (sphere, box, cylinder) and optionally
meshes (OBJ files, by default the shared meshes when present) standing on it, and one reserved
free spot on the ground where a later edit can place a proxy. Everything is deterministic in the
seed. Rendering casts one ray per pixel centre exactly (`raycast`) and shades with Lambert plus
ambient light and procedural solid textures, giving RGB, z-depth and an object-id map
(0 = ground or background; objects are 1..K).

`generate` writes the views in nerfstudio format (depth EXRs, object-id PNGs), a `scene.json`
describing the objects, and the gin configuration. scene.json holds:
  format, version, seed, up ([0, 0, 1]), ground_height (0: the top of the ground),
  scene_bounds ([2, 3]), background_color, light {direction, ambient},
  ground (one entry, object_id 0, a box) and objects (a list, object_id 1..K), each
    {object_id, shape, transform, color, texture, texture_axis, texture_frequency,
    footprint {center [x, y], radius}, bounds [2, 3], mesh_path (meshes only)}; `transform`
    ([4, 4]) maps the shape's own coordinates into the scene: the canonical unit primitive of
    `raycast` for primitives, the OBJ file's vertex coordinates for meshes.
  free_spot {center [x, y, ground_height], radius}: a disc on the ground no object overlaps.
  generator: the settings the scene and cameras were made with.
"""

from __future__ import annotations

import colorsys
import dataclasses
import os
from pathlib import Path
from typing import Any, Callable

import gin
import jax
import numpy as np
import trimesh

from signerf_jax import camera
from signerf_jax import configs
from signerf_jax import files
from signerf_jax.data import nerfstudio
from signerf_jax.data import poses as poses_lib
from signerf_jax.data import raycast
from signerf_jax.data.dataset import Dataset
from signerf_jax.errors import InputError

SHAPES = ("sphere", "box", "cylinder", "mesh")
PRIMITIVE_SHAPES = SHAPES[:3]
OBJECT_TEXTURES = ("blobs", "stripes")
CAMERA_LAYOUTS = ("sphere", "hemisphere", "forward_facing")
SCENE_FILE_NAME = "scene.json"
# The shared meshes (../shared/data/meshes next to the repository, or $SIGNERF_SHARED_DATA).
DEFAULT_MESH_DIRECTORY = str(Path(os.environ.get(
    "SIGNERF_SHARED_DATA", configs.GIN_CONFIG_DIR.parent.parent / "shared" / "data")) / "meshes")
GROUND_HEIGHT = 0.0
GROUND_COLOR = (0.78, 0.74, 0.66)
# Textures modulate albedo between this fraction of the colour and the full colour.
TEXTURE_DARK_FRACTION = 0.45
BOUNDS_MARGIN = 0.05
MAX_PLACEMENT_ATTEMPTS = 2000
# Compiled once each: op-by-op execution would compile every primitive separately (seconds).
_look_at = jax.jit(camera.look_at)
_pixel_rays = jax.jit(camera.pixel_rays)
_INTERSECTORS = {"sphere": raycast.intersect_sphere, "box": raycast.intersect_box,
                 "cylinder": raycast.intersect_cylinder}


@dataclasses.dataclass(frozen=True)
class SceneObject:
  """One shape of a synthetic scene.

  Attributes:
    object_id: 0 for the ground, 1..K for objects (the value in object-id maps).
    shape: one of SHAPES.
    object_to_world: [4, 4] affine map from the canonical shape (see `raycast`) to the scene.
    color: [3] base albedo.
    texture: "checker" (ground), "blobs" or "stripes", evaluated in canonical coordinates.
    texture_axis: [3] unit direction of the stripes.
    texture_frequency: angular frequency of the pattern in canonical units.
    footprint_center, footprint_radius: [2] and float, the disc the object covers on the ground.
    mesh_path: the OBJ file (meshes only).
    file_to_canonical: [4, 4] from the OBJ's coordinates into the canonical frame (meshes only).
    clusters: the canonical triangles for ray casting (meshes only).
    albedo_function: canonical points [R, 3] -> albedo [R, 3]; when given it replaces `color`
      and `texture` (procedural appearances defined elsewhere, e.g. the default model's data).
  """

  object_id: int
  shape: str
  object_to_world: np.ndarray
  color: np.ndarray
  texture: str
  texture_axis: np.ndarray
  texture_frequency: float
  footprint_center: np.ndarray
  footprint_radius: float
  mesh_path: str | None = None
  file_to_canonical: np.ndarray | None = None
  clusters: raycast.TriangleClusters | None = None
  albedo_function: Callable[[np.ndarray], np.ndarray] | None = None

  def world_bounds(self) -> np.ndarray:
    """[2, 3] axis-aligned bounds of the shape in the scene."""
    matrix = self.object_to_world
    if self.shape == "mesh":
      corners = self.clusters.corners.reshape(-1, 3)
      points = poses_lib.transform_points(matrix, corners)
      return np.stack([points.min(0), points.max(0)])
    linear = np.abs(matrix[:3, :3])
    if self.shape == "sphere":
      half_extent = np.linalg.norm(matrix[:3, :3], axis=1)
    elif self.shape == "cylinder":  # a disc's extent plus the axis segment's
      half_extent = np.linalg.norm(matrix[:3, :2], axis=1) + linear[:, 2]
    else:
      half_extent = linear.sum(1)
    return np.stack([matrix[:3, 3] - half_extent, matrix[:3, 3] + half_extent])

  def describe(self) -> dict[str, Any]:
    """The scene.json entry (see the module docstring)."""
    transform = self.object_to_world
    if self.shape == "mesh":
      transform = transform @ self.file_to_canonical
    entry = {
        "object_id": self.object_id, "shape": self.shape, "transform": transform,
        "color": self.color, "texture": self.texture, "texture_axis": self.texture_axis,
        "texture_frequency": self.texture_frequency,
        "footprint": {"center": self.footprint_center, "radius": self.footprint_radius},
        "bounds": self.world_bounds(),
    }
    if self.mesh_path is not None:
      entry["mesh_path"] = self.mesh_path
    return entry


@dataclasses.dataclass(frozen=True)
class SyntheticScene:
  """A ground, objects standing on it, lighting and the region they occupy."""

  seed: int
  ground: SceneObject
  objects: tuple[SceneObject, ...]
  free_spot_center: np.ndarray  # [3] on the ground plane
  free_spot_radius: float
  light_direction: np.ndarray  # [3] unit vector towards the light
  ambient: float
  background_color: np.ndarray  # [3]
  scene_bounds: np.ndarray  # [2, 3]

  @property
  def shapes(self) -> tuple[SceneObject, ...]:
    return (self.ground,) + self.objects

  def describe(self) -> dict[str, Any]:
    """The scene.json content (without the generator settings)."""
    return {
        "format": "signerf-synthetic-scene", "version": 1, "seed": self.seed,
        "up": [0.0, 0.0, 1.0], "ground_height": GROUND_HEIGHT,
        "scene_bounds": self.scene_bounds, "background_color": self.background_color,
        "light": {"direction": self.light_direction, "ambient": self.ambient},
        "ground": self.ground.describe(),
        "objects": [shape.describe() for shape in self.objects],
        "free_spot": {"center": self.free_spot_center, "radius": self.free_spot_radius},
    }


def affine(linear, translation) -> np.ndarray:
  """The [4, 4] matrix x -> linear @ x + translation."""
  matrix = np.eye(4)
  matrix[:3, :3], matrix[:3, 3] = linear, translation
  return matrix


def _rotation_about_z(angle: float) -> np.ndarray:
  cosine, sine = np.cos(angle), np.sin(angle)
  return np.array([[cosine, -sine, 0.0], [sine, cosine, 0.0], [0.0, 0.0, 1.0]])


def load_canonical_mesh(path: str | os.PathLike) -> tuple[np.ndarray, raycast.TriangleClusters]:
  """Loads a +y-up OBJ and fits it into the canonical cube, resting on z = -1.

  The mesh is turned z-up (+y -> +z), centred in x and y, and scaled uniformly so its largest
  half-extent is 1.
  Returns:
    file_to_canonical: [4, 4] similarity from the file's coordinates.
    clusters: the canonical triangles with smooth vertex normals.
  """
  try:
    mesh = trimesh.load(str(path), force="mesh")
  except Exception as error:  # trimesh raises many exception types for unreadable files.
    raise InputError(f"not a readable mesh ({error})", path) from None
  if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
    raise InputError("holds no triangles", path)
  return canonical_mesh(mesh)


def canonical_mesh(mesh: trimesh.Trimesh) -> tuple[np.ndarray, raycast.TriangleClusters]:
  """`load_canonical_mesh` for a mesh in memory (+y up): (file_to_canonical, clusters)."""
  y_up_to_z_up = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
  vertices = mesh.vertices @ y_up_to_z_up.T
  lower, upper = vertices.min(0), vertices.max(0)
  scale = 2.0 / np.max(upper - lower)
  offset = -scale * np.array([(lower[0] + upper[0]) / 2, (lower[1] + upper[1]) / 2, lower[2]])
  file_to_canonical = affine(scale * y_up_to_z_up, offset - [0.0, 0.0, 1.0])
  canonical = poses_lib.transform_points(file_to_canonical, mesh.vertices)
  normals = mesh.vertex_normals @ y_up_to_z_up.T
  return file_to_canonical, raycast.TriangleClusters.build(canonical, mesh.faces, normals)


def _random_color(rng: np.random.Generator) -> np.ndarray:
  hue, saturation, value = rng.uniform(0, 1), rng.uniform(0.5, 0.8), rng.uniform(0.7, 0.95)
  return np.array(colorsys.hsv_to_rgb(hue, saturation, value))


def _unit_vector(rng: np.random.Generator) -> np.ndarray:
  vector = rng.normal(size=3)
  return vector / np.linalg.norm(vector)


@gin.configurable("synthetic_scene")
@dataclasses.dataclass(frozen=True)
class SceneSettings:
  """What a random scene holds (bound through gin as `synthetic_scene.<field>`).

  Attributes:
    num_primitives: spheres, boxes and cylinders (shape chosen at random).
    num_meshes: OBJ meshes drawn from `mesh_directory/*.obj` (fewer when fewer exist; none
      when the directory is absent or empty). Primitives and the free spot are placed first,
      so they do not depend on which meshes exist.
    mesh_directory: where the meshes come from ("" for none).
    ground_half_size, ground_thickness: the ground slab, [-h, h]^2 x [-thickness, 0].
    object_radius_range: (min, max) radius of each object's footprint on the ground.
    free_spot_radius: radius of the reserved empty disc on the ground.
    texture_frequency, ground_texture_frequency: pattern frequencies (canonical units).
    light_direction: direction towards the light; ambient: its ambient share in [0, 1].
    background_color: [3] RGB of the (bounded) background.
  """

  num_primitives: int = 3
  num_meshes: int = 1
  mesh_directory: str = DEFAULT_MESH_DIRECTORY
  ground_half_size: float = 0.9
  ground_thickness: float = 0.1
  object_radius_range: tuple[float, float] = (0.15, 0.27)
  free_spot_radius: float = 0.3
  texture_frequency: float = 5.0
  ground_texture_frequency: float = 12.0
  light_direction: tuple[float, float, float] = (0.45, -0.35, 0.82)
  ambient: float = 0.35
  background_color: tuple[float, float, float] = (1.0, 1.0, 1.0)


def make_scene(seed: int = 0, settings: SceneSettings | None = None) -> SyntheticScene:
  """Builds a random scene, deterministic in `seed` (and the meshes found)."""
  settings = SceneSettings() if settings is None else settings
  minimum_radius, maximum_radius = settings.object_radius_range
  ground_half_size = settings.ground_half_size
  if not 0 < minimum_radius <= maximum_radius:
    raise InputError(f"need 0 < min <= max, got {settings.object_radius_range}",
                     field="synthetic_scene.object_radius_range")
  # Tall shapes reach 3x their radius; with the margin everything must stay inside [-1, 1]^3.
  if ground_half_size + BOUNDS_MARGIN > 1 or 3 * maximum_radius + BOUNDS_MARGIN > 1:
    raise InputError("the scene would leave the unit box [-1, 1]^3",
                     field="synthetic_scene.ground_half_size / object_radius_range")
  rng = np.random.default_rng(seed)
  footprints: list[tuple[np.ndarray, float]] = []

  def place(radius: float) -> np.ndarray:
    """A footprint centre on the ground clear of everything placed so far."""
    limit = ground_half_size - radius
    for _ in range(MAX_PLACEMENT_ATTEMPTS):
      center = rng.uniform(-limit, limit, 2)
      if all(np.linalg.norm(center - other) > radius + other_radius + 0.02
             for other, other_radius in footprints):
        footprints.append((center, radius))
        return center
    raise InputError("cannot fit the objects and the free spot on the ground; use fewer or "
                     "smaller objects", field="synthetic_scene")

  free_spot_center = place(settings.free_spot_radius)
  objects = []
  for _ in range(settings.num_primitives):
    shape = PRIMITIVE_SHAPES[rng.integers(len(PRIMITIVE_SHAPES))]
    radius = rng.uniform(minimum_radius, maximum_radius)
    center = place(radius)
    if shape == "sphere":
      half_extents = np.full(3, radius)
    elif shape == "box":
      half_extents = np.array([*rng.uniform(0.6, 1.0, 2) * radius / np.sqrt(2),
                               rng.uniform(0.5, 1.2) * radius])
    else:
      half_extents = np.array([radius, radius, rng.uniform(0.5, 1.5) * radius])
    linear = _rotation_about_z(rng.uniform(0, 2 * np.pi)) @ np.diag(half_extents)
    objects.append(dict(shape=shape, object_to_world=affine(
        linear, [*center, GROUND_HEIGHT + half_extents[2]]), footprint_center=center,
                        footprint_radius=radius))

  mesh_directory = Path(settings.mesh_directory)
  mesh_paths = sorted(mesh_directory.glob("*.obj")) if settings.mesh_directory else []
  chosen = rng.permutation(len(mesh_paths))[:settings.num_meshes] if mesh_paths else []
  for index in chosen:
    radius = rng.uniform(minimum_radius, maximum_radius)
    center = place(radius)
    file_to_canonical, clusters = load_canonical_mesh(mesh_paths[index])
    # Scaled so that its widest point stays inside the footprint disc whatever its rotation,
    # and (for slender meshes) no taller than 3 radii, like the primitives.
    scale = min(radius / np.max(np.linalg.norm(clusters.corners[..., :2], axis=-1)),
                1.5 * radius)
    linear = scale * _rotation_about_z(rng.uniform(0, 2 * np.pi))
    objects.append(dict(shape="mesh", object_to_world=affine(
        linear, [*center, GROUND_HEIGHT + scale]), footprint_center=center,
                        footprint_radius=radius, mesh_path=str(mesh_paths[index]),
                        file_to_canonical=file_to_canonical, clusters=clusters))

  objects = tuple(
      SceneObject(object_id=index + 1, color=_random_color(rng),
                  texture=OBJECT_TEXTURES[rng.integers(len(OBJECT_TEXTURES))],
                  texture_axis=_unit_vector(rng),
                  texture_frequency=settings.texture_frequency, **fields)
      for index, fields in enumerate(objects))
  ground = SceneObject(
      object_id=0, shape="box",
      object_to_world=affine(np.diag([ground_half_size, ground_half_size,
                                       settings.ground_thickness / 2]),
                              [0.0, 0.0, GROUND_HEIGHT - settings.ground_thickness / 2]),
      color=np.asarray(GROUND_COLOR), texture="checker", texture_axis=np.array([0.0, 0, 1]),
      texture_frequency=settings.ground_texture_frequency, footprint_center=np.zeros(2),
      footprint_radius=ground_half_size * np.sqrt(2))
  all_bounds = np.stack([shape.world_bounds() for shape in (ground,) + objects])
  scene_bounds = np.stack([all_bounds[:, 0].min(0) - BOUNDS_MARGIN,
                           all_bounds[:, 1].max(0) + BOUNDS_MARGIN])
  light_direction = np.asarray(settings.light_direction, np.float64)
  return SyntheticScene(
      seed=seed, ground=ground, objects=objects,
      free_spot_center=np.array([*free_spot_center, GROUND_HEIGHT]),
      free_spot_radius=settings.free_spot_radius,
      light_direction=light_direction / np.linalg.norm(light_direction), ambient=settings.ambient,
      background_color=np.asarray(settings.background_color, np.float64),
      scene_bounds=np.clip(scene_bounds, -1.0, 1.0))


@gin.configurable("synthetic_cameras")
@dataclasses.dataclass(frozen=True)
class CameraRig:
  """Square pinhole cameras looking at the scene centre (gin: `synthetic_cameras.<field>`).

  Attributes:
    layout: "sphere" (a Fibonacci spiral over the whole sphere), "hemisphere" (the same over
      the band of elevations `elevation_range_degrees`, area-uniform) or "forward_facing"
      (evenly along a horizontal arc of `arc_degrees` at the middle elevation, facing +y).
    num_views: number of cameras.
    image_size: width and height in pixels.
    field_of_view_degrees: full field of view.
    distance: from the cameras to the centre.
  """

  layout: str = "hemisphere"
  num_views: int = 40
  image_size: int = 64
  field_of_view_degrees: float = 50.0
  distance: float = 2.8
  elevation_range_degrees: tuple[float, float] = (15.0, 70.0)
  arc_degrees: float = 120.0


def make_cameras(rig: CameraRig, scene_bounds) -> camera.Cameras:
  """The rig's cameras, all looking at the centre of `scene_bounds` ([2, 3]), z up."""
  if rig.layout not in CAMERA_LAYOUTS:
    raise InputError(f"must be one of {CAMERA_LAYOUTS}, got {rig.layout!r}",
                     field="synthetic_cameras.layout")
  if (rig.num_views < 1 or rig.image_size < 1 or not 0 < rig.field_of_view_degrees < 180
      or rig.distance <= 0):
    raise InputError("need num_views >= 1, image_size >= 1, 0 < field_of_view_degrees < 180 "
                     "and distance > 0", field="synthetic_cameras")
  num_views = rig.num_views
  target = np.mean(np.asarray(scene_bounds, np.float64), axis=0)
  fraction = (np.arange(num_views) + 0.5) / num_views
  golden_angle = np.pi * (3.0 - np.sqrt(5.0))
  azimuth = golden_angle * np.arange(num_views)
  low, high = np.sin(np.radians(rig.elevation_range_degrees))
  if rig.layout == "sphere":
    heights = 1.0 - 2.0 * fraction
  elif rig.layout == "hemisphere":
    heights = low + (high - low) * fraction
  else:
    heights = np.full(num_views, np.sin(np.radians(np.mean(rig.elevation_range_degrees))))
    azimuth = -np.pi / 2 + np.radians(rig.arc_degrees) * (fraction - 0.5)
  ring = np.sqrt(1.0 - heights**2)
  directions = np.stack([ring * np.cos(azimuth), ring * np.sin(azimuth), heights], -1)
  camera_to_world = _look_at(target + rig.distance * directions, target)
  focal = 0.5 * rig.image_size / np.tan(np.radians(rig.field_of_view_degrees) / 2)
  return camera.Cameras.create(np.asarray(camera_to_world), fx=focal, width=rig.image_size,
                               height=rig.image_size)


def _texture(shape: SceneObject, points: np.ndarray) -> np.ndarray:
  """[R] pattern in [0, 1] at canonical `points` [R, 3]; smooth, so it does not alias badly."""
  k = shape.texture_frequency
  if shape.texture == "checker":
    signal = np.sin(k * points[:, 0]) * np.sin(k * points[:, 1]) * 4.0
  elif shape.texture == "stripes":
    signal = 2.0 * np.sin(k * points @ shape.texture_axis)
  else:
    signal = np.sum(np.sin(k * points + shape.texture_axis * 3.0), -1)
  return 0.5 + 0.5 * np.tanh(signal)


@dataclasses.dataclass(frozen=True)
class RayHits:
  """First hits of a batch of rays [R] in a scene.

  Attributes:
    t: [R] distance along the unit ray (inf on a miss).
    object_ids: [R] int32 id of the shape hit (0: ground or a miss).
    normals: [R, 3] unit world normals facing the ray (zero on a miss).
    albedo: [R, 3] textured colour at the hit (zero on a miss).
  """

  t: np.ndarray
  object_ids: np.ndarray
  normals: np.ndarray
  albedo: np.ndarray


def cast_rays(scene: SyntheticScene, origins: np.ndarray, directions: np.ndarray) -> RayHits:
  """The first hit of each world ray (origins, unit directions: [R, 3]) in the scene."""
  origins, directions = np.asarray(origins, np.float64), np.asarray(directions, np.float64)
  count = len(origins)
  t = np.full(count, np.inf)
  object_ids = np.zeros(count, np.int32)
  normals, albedo = np.zeros((count, 3)), np.zeros((count, 3))
  for shape in scene.shapes:
    world_to_object = np.linalg.inv(shape.object_to_world)
    linear = world_to_object[:3, :3]
    local_origins = raycast.linear_map(linear, origins) + world_to_object[:3, 3]
    local_directions = raycast.linear_map(linear, directions)
    if shape.shape == "mesh":
      shape_t, local_normals = raycast.intersect_mesh(shape.clusters, local_origins,
                                                      local_directions)
    else:
      shape_t, local_normals = _INTERSECTORS[shape.shape](local_origins, local_directions)
    closer = shape_t < t
    t[closer] = shape_t[closer]
    object_ids[closer] = shape.object_id
    # Normals map with the inverse transpose: n_world = L^-T n_local.
    normals[closer] = raycast.linear_map(linear.T, local_normals[closer])
    points = local_origins[closer] + shape_t[closer, None] * local_directions[closer]
    if shape.albedo_function is not None:
      albedo[closer] = shape.albedo_function(points)
    else:
      pattern = _texture(shape, points)[:, None]
      albedo[closer] = shape.color * (TEXTURE_DARK_FRACTION
                                      + (1 - TEXTURE_DARK_FRACTION) * pattern)
  length = np.linalg.norm(normals, axis=-1, keepdims=True)
  normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
  # Two-sided shading: the visible side of a surface faces the ray.
  normals *= np.where(np.sum(normals * directions, -1, keepdims=True) > 0, -1.0, 1.0)
  return RayHits(t=t, object_ids=object_ids, normals=normals, albedo=albedo)


def render(scene: SyntheticScene, cameras: camera.Cameras):
  """Ray casts every camera through its pixel centres.

  Returns:
    rgb: [N, H, W, 3] float32 in [0, 1] (background colour where rays miss).
    depth: [N, H, W] float32 z-depth (0 where rays miss, the Dataset's "unknown").
    object_ids: [N, H, W] int32 (0: ground or background).
  """
  rows, columns = np.meshgrid(np.arange(cameras.height) + 0.5, np.arange(cameras.width) + 0.5,
                              indexing="ij")
  indices = np.broadcast_to(np.arange(cameras.num_cameras)[:, None, None],
                            (cameras.num_cameras,) + rows.shape)
  rays = _pixel_rays(cameras, indices, np.broadcast_to(columns, indices.shape),
                     np.broadcast_to(rows, indices.shape))
  origins = np.asarray(rays.origins, np.float64).reshape(cameras.num_cameras, -1, 3)
  directions = np.asarray(rays.directions, np.float64).reshape(cameras.num_cameras, -1, 3)
  cosines = np.asarray(rays.cos_to_optical_axis, np.float64).reshape(cameras.num_cameras, -1)
  shape = (cameras.num_cameras, cameras.height, cameras.width)
  rgb, depth = np.zeros(shape + (3,), np.float32), np.zeros(shape, np.float32)
  object_ids = np.zeros(shape, np.int32)
  for index in range(cameras.num_cameras):
    hits = cast_rays(scene, origins[index], directions[index])
    hit = np.isfinite(hits.t)
    light = scene.ambient + (1 - scene.ambient) * np.maximum(hits.normals @ scene.light_direction,
                                                             0.0)
    color = np.where(hit[:, None], hits.albedo * light[:, None], scene.background_color)
    rgb[index] = np.clip(color, 0, 1).reshape(shape[1:] + (3,))
    depth[index] = np.where(hit, hits.t * cosines[index], 0.0).reshape(shape[1:])
    object_ids[index] = hits.object_ids.reshape(shape[1:])
  return rgb, depth, object_ids


def generate(directory: str | os.PathLike, seed: int = 0, settings: SceneSettings | None = None,
             rig: CameraRig | None = None) -> tuple[Dataset, SyntheticScene]:
  """Makes, renders and writes a synthetic scene to `directory`.

  Args:
    directory: the output dataset directory.
    seed: the scene's random seed.
    settings, rig: what to build and how to view it (default: the gin-bound values).
  Writes transforms.json with images/, depths/ (EXR z-depth) and object_masks/ (id PNGs),
  scene.json and config.gin. Returns the dataset as rendered (before 8-bit quantisation) and
  the scene.
  """
  directory = Path(directory)
  settings = SceneSettings() if settings is None else settings
  rig = CameraRig() if rig is None else rig
  scene = make_scene(seed, settings)
  cameras = make_cameras(rig, scene.scene_bounds)
  images, depths, object_ids = render(scene, cameras)
  near, far = poses_lib.near_far_for_box(cameras, *scene.scene_bounds)
  dataset = Dataset(
      images=images, cameras=cameras,
      image_names=tuple(f"{nerfstudio.IMAGE_FOLDER}/frame_{index:05d}.png"
                        for index in range(cameras.num_cameras)),
      scene_bounds=scene.scene_bounds.astype(np.float32), scene_kind="bounded", near=near,
      far=far, background_color=scene.background_color.astype(np.float32), depths=depths,
      extras={"object_masks": object_ids}, root=str(directory))
  # The old transforms.json goes first: scene.json must never sit beside a stale dataset.
  (directory / nerfstudio.TRANSFORMS_NAME).unlink(missing_ok=True)
  description = scene.describe()
  description["generator"] = {"seed": seed, "scene": dataclasses.asdict(settings),
                              "cameras": dataclasses.asdict(rig)}
  files.write_json(directory / SCENE_FILE_NAME, description)
  configs.save_gin_config(directory)
  nerfstudio.write_nerfstudio(directory, dataset, provenance={
      "generator": "signerf_jax.data.synthetic", "seed": seed, "scene": SCENE_FILE_NAME})
  return dataset, scene
