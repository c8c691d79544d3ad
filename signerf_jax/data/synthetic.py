"""Synthetic scenes with exact ground truth: a textured ground with objects standing on it, their
shapes, materials and random layout (`synthetic_render` views, renders and writes them).

A scene is built directly in the normalised frame (z up, content inside [-1, 1]^3): a square
ground slab whose top is the plane z = 0, a few primitives (sphere, box, cylinder) and optionally
meshes (OBJ files, by default the shared meshes when present) standing on it, and one reserved
free spot on the ground where a later edit can place a proxy. Everything is deterministic in the
seed. Each shape is a canonical shape of `raycast` mapped into the scene, with an albedo: its
colour modulated by a procedural solid texture, or a function of canonical position. Object ids
are 0 for the ground and 1..K for the objects.

`SyntheticScene.describe` gives the scene.json that `synthetic_render.generate` writes beside
the views:
  format, version, seed, up ([0, 0, 1]), ground_height (0: the top of the ground),
  scene_bounds ([2, 3]), background_color, light {direction, ambient},
  ground (one entry, object_id 0, a box) and objects (a list, object_id 1..K), each
    {object_id, shape, transform, color, texture, texture_axis, texture_frequency,
    footprint {center [x, y], radius}, bounds [2, 3], mesh_path (meshes only)}; `transform`
    ([4, 4]) maps the shape's own coordinates into the scene: the canonical unit primitive of
    `raycast` for primitives, the OBJ file's vertex coordinates for meshes.
  free_spot {center [x, y, ground_height], radius}: a disc on the ground no object overlaps.
  generator: the settings the scene and cameras were made with (added by `generate`).
"""

from __future__ import annotations

import colorsys
import dataclasses
import os
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np
import trimesh

from signerf_jax import validation
from signerf_jax.data import poses as poses_lib
from signerf_jax.data import raycast
from signerf_jax.errors import InputError
from signerf_jax.validation import (Color, NonNegativeFloat, NonNegativeInt, PositiveFloat,
                                    UnitInterval, Vector3)

SHAPES = ("sphere", "box", "cylinder", "mesh")
PRIMITIVE_SHAPES = SHAPES[:3]
OBJECT_TEXTURES = ("blobs", "stripes")
GROUND_TEXTURES = ("checker", "speckle")
# The speckle: sinusoids along fixed random directions, up to SPECKLE_OCTAVES octaves above the
# base frequency, random phases. Unlike the periodic patterns, no two places look alike, which
# feature matching (`signerf process`) needs.
SPECKLE_WAVES, SPECKLE_OCTAVES = 48, 3
_SPECKLE_RANDOM = np.random.default_rng(20240617)
SPECKLE_DIRECTIONS = _SPECKLE_RANDOM.normal(size=(SPECKLE_WAVES, 3))
SPECKLE_DIRECTIONS /= np.linalg.norm(SPECKLE_DIRECTIONS, axis=1, keepdims=True)
SPECKLE_FREQUENCY_FACTORS = 2.0 ** _SPECKLE_RANDOM.uniform(0, SPECKLE_OCTAVES, SPECKLE_WAVES)
SPECKLE_PHASES = _SPECKLE_RANDOM.uniform(0, 2 * np.pi, SPECKLE_WAVES)
# The shared meshes (../shared/data/meshes next to the repository, or $SIGNERF_SHARED_DATA);
# this file is <repository>/signerf_jax/data/synthetic.py.
DEFAULT_MESH_DIRECTORY = str(Path(os.environ.get(
    "SIGNERF_SHARED_DATA", Path(__file__).resolve().parents[3] / "shared" / "data")) / "meshes")
GROUND_HEIGHT = 0.0
GROUND_COLOR = (0.78, 0.74, 0.66)
# Textures modulate albedo between this fraction of the colour and the full colour.
TEXTURE_DARK_FRACTION = 0.45
BOUNDS_MARGIN = 0.05
MAX_PLACEMENT_ATTEMPTS = 2000


@dataclasses.dataclass(frozen=True)
class SceneObject:
  """One shape of a synthetic scene.

  Attributes:
    object_id: 0 for the ground, 1..K for objects (the value in object-id maps).
    shape: one of SHAPES.
    object_to_world: [4, 4] affine map from the canonical shape (see `raycast`) to the scene.
    color: [3] base albedo.
    texture: "checker" or "speckle" (ground), "blobs" or "stripes", evaluated in canonical
      coordinates.
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

  def albedo(self, points: np.ndarray) -> np.ndarray:
    """[R, 3] albedo at canonical `points` [R, 3]: `albedo_function`'s, else `color` darkened
    by the texture's pattern."""
    if self.albedo_function is not None:
      return self.albedo_function(points)
    pattern = _texture(self, points)[:, None]
    return self.color * (TEXTURE_DARK_FRACTION + (1 - TEXTURE_DARK_FRACTION) * pattern)

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


def _texture(shape: SceneObject, points: np.ndarray) -> np.ndarray:
  """[R] pattern in [0, 1] at canonical `points` [R, 3]; smooth, so it does not alias badly."""
  k = shape.texture_frequency
  if shape.texture == "checker":
    signal = np.sin(k * points[:, 0]) * np.sin(k * points[:, 1]) * 4.0
  elif shape.texture == "speckle":
    waves = np.sin(k * SPECKLE_FREQUENCY_FACTORS * (points @ SPECKLE_DIRECTIONS.T) + SPECKLE_PHASES)
    signal = 3.0 * waves.mean(-1) * np.sqrt(SPECKLE_WAVES / 2)  # about unit variance, times 3
  elif shape.texture == "stripes":
    signal = 2.0 * np.sin(k * points @ shape.texture_axis)
  else:
    signal = np.sum(np.sin(k * points + shape.texture_axis * 3.0), -1)
  return 0.5 + 0.5 * np.tanh(signal)


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


@dataclasses.dataclass(frozen=True)
class SceneSettings(validation.CheckedFields):
  """What a random scene holds (gin: `synthetic_scene.<field>`).

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
    ground_texture: the ground's pattern, "checker" or "speckle" (aperiodic: what feature
      matching needs to recover the cameras).
    light_direction: direction towards the light; ambient: its ambient share in [0, 1].
    background_color: [3] RGB of the (bounded) background.
  """

  num_primitives: NonNegativeInt = 3
  num_meshes: NonNegativeInt = 1
  mesh_directory: str = DEFAULT_MESH_DIRECTORY
  ground_half_size: PositiveFloat = 0.9
  ground_thickness: PositiveFloat = 0.1
  object_radius_range: tuple[PositiveFloat, PositiveFloat] = (0.15, 0.27)
  free_spot_radius: NonNegativeFloat = 0.3
  texture_frequency: NonNegativeFloat = 5.0
  ground_texture_frequency: NonNegativeFloat = 12.0
  ground_texture: Literal[GROUND_TEXTURES] = "checker"
  light_direction: Vector3 = (0.45, -0.35, 0.82)
  ambient: UnitInterval = 0.35
  background_color: Color = (1.0, 1.0, 1.0)

  def __post_init__(self):
    """Also rejects settings whose objects cannot fit: radii out of order, or a scene outside
    the unit box."""
    super().__post_init__()
    minimum_radius, maximum_radius = self.object_radius_range
    if not minimum_radius <= maximum_radius:
      raise InputError(f"need min <= max, got {self.object_radius_range}",
                       field="SceneSettings.object_radius_range")
    # Tall shapes reach 3x their radius; with the margin everything must stay inside [-1, 1]^3.
    if self.ground_half_size + BOUNDS_MARGIN > 1 or 3 * maximum_radius + BOUNDS_MARGIN > 1:
      raise InputError("the scene would leave the unit box [-1, 1]^3",
                       field="SceneSettings.ground_half_size")


def make_scene(seed: int = 0, settings: SceneSettings = SceneSettings()) -> SyntheticScene:
  """Builds a random scene, deterministic in `seed` (and the meshes found)."""
  rng = np.random.default_rng(seed)
  footprints = _Footprints(rng, settings.ground_half_size)
  free_spot_center = footprints.place(settings.free_spot_radius)
  placed = [_random_primitive(rng, footprints, settings)
            for _ in range(settings.num_primitives)]
  placed += _random_meshes(rng, footprints, settings)
  objects = tuple(
      SceneObject(object_id=index + 1, color=_random_color(rng),
                  texture=OBJECT_TEXTURES[rng.integers(len(OBJECT_TEXTURES))],
                  texture_axis=_unit_vector(rng),
                  texture_frequency=settings.texture_frequency, **fields)
      for index, fields in enumerate(placed))
  ground = _ground(settings)
  light_direction = np.asarray(settings.light_direction, np.float64)
  return SyntheticScene(
      seed=seed, ground=ground, objects=objects,
      free_spot_center=np.array([*free_spot_center, GROUND_HEIGHT]),
      free_spot_radius=settings.free_spot_radius,
      light_direction=light_direction / np.linalg.norm(light_direction), ambient=settings.ambient,
      background_color=np.asarray(settings.background_color, np.float64),
      scene_bounds=_scene_bounds((ground,) + objects))


@dataclasses.dataclass
class _Footprints:
  """The discs taken on the ground so far ((centre [2], radius) each), and where the next goes."""

  rng: np.random.Generator
  ground_half_size: float
  taken: list[tuple[np.ndarray, float]] = dataclasses.field(default_factory=list)

  def place(self, radius: float) -> np.ndarray:
    """A footprint centre [2] on the ground clear of everything placed so far."""
    limit = self.ground_half_size - radius
    for _ in range(MAX_PLACEMENT_ATTEMPTS):
      center = self.rng.uniform(-limit, limit, 2)
      if all(np.linalg.norm(center - other) > radius + other_radius + 0.02
             for other, other_radius in self.taken):
        self.taken.append((center, radius))
        return center
    raise InputError("cannot fit the objects and the free spot on the ground; use fewer or "
                     "smaller objects", field="synthetic_scene")


def _random_primitive(rng: np.random.Generator, footprints: _Footprints,
                      settings: SceneSettings) -> dict[str, Any]:
  """A sphere, box or cylinder of random size and rotation about z on a free footprint: its
  SceneObject fields of shape and placement."""
  shape = PRIMITIVE_SHAPES[rng.integers(len(PRIMITIVE_SHAPES))]
  radius = rng.uniform(*settings.object_radius_range)
  center = footprints.place(radius)
  if shape == "sphere":
    half_extents = np.full(3, radius)
  elif shape == "box":
    half_extents = np.array([*rng.uniform(0.6, 1.0, 2) * radius / np.sqrt(2),
                             rng.uniform(0.5, 1.2) * radius])
  else:
    half_extents = np.array([radius, radius, rng.uniform(0.5, 1.5) * radius])
  linear = _rotation_about_z(rng.uniform(0, 2 * np.pi)) @ np.diag(half_extents)
  return dict(shape=shape,
              object_to_world=affine(linear, [*center, GROUND_HEIGHT + half_extents[2]]),
              footprint_center=center, footprint_radius=radius)


def _random_meshes(rng: np.random.Generator, footprints: _Footprints,
                   settings: SceneSettings) -> list[dict[str, Any]]:
  """Up to `settings.num_meshes` meshes of `settings.mesh_directory`, drawn at random, each on a
  free footprint: their SceneObject fields of shape and placement."""
  mesh_paths = (sorted(Path(settings.mesh_directory).glob("*.obj")) if settings.mesh_directory
                else [])
  chosen = rng.permutation(len(mesh_paths))[:settings.num_meshes] if mesh_paths else []
  meshes = []
  for index in chosen:
    radius = rng.uniform(*settings.object_radius_range)
    center = footprints.place(radius)
    file_to_canonical, clusters = load_canonical_mesh(mesh_paths[index])
    # Scaled so that its widest point stays inside the footprint disc whatever its rotation,
    # and (for slender meshes) no taller than 3 radii, like the primitives.
    scale = min(radius / np.max(np.linalg.norm(clusters.corners[..., :2], axis=-1)),
                1.5 * radius)
    linear = scale * _rotation_about_z(rng.uniform(0, 2 * np.pi))
    meshes.append(dict(
        shape="mesh", object_to_world=affine(linear, [*center, GROUND_HEIGHT + scale]),
        footprint_center=center, footprint_radius=radius, mesh_path=str(mesh_paths[index]),
        file_to_canonical=file_to_canonical, clusters=clusters))
  return meshes


def _ground(settings: SceneSettings) -> SceneObject:
  """The ground slab, object 0: [-h, h]^2 x [-thickness, 0], with `settings.ground_texture`."""
  ground_half_size = settings.ground_half_size
  return SceneObject(
      object_id=0, shape="box",
      object_to_world=affine(np.diag([ground_half_size, ground_half_size,
                                       settings.ground_thickness / 2]),
                             [0.0, 0.0, GROUND_HEIGHT - settings.ground_thickness / 2]),
      color=np.asarray(GROUND_COLOR), texture=settings.ground_texture,
      texture_axis=np.array([0.0, 0, 1]),
      texture_frequency=settings.ground_texture_frequency, footprint_center=np.zeros(2),
      footprint_radius=ground_half_size * np.sqrt(2))


def _scene_bounds(shapes: tuple[SceneObject, ...]) -> np.ndarray:
  """[2, 3] box around every shape with BOUNDS_MARGIN to spare, within [-1, 1]^3."""
  all_bounds = np.stack([shape.world_bounds() for shape in shapes])
  scene_bounds = np.stack([all_bounds[:, 0].min(0) - BOUNDS_MARGIN,
                           all_bounds[:, 1].max(0) + BOUNDS_MARGIN])
  return np.clip(scene_bounds, -1.0, 1.0)
