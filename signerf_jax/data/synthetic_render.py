"""A synthetic scene (`synthetic`) seen by cameras: the camera rig, exact ray-cast renders, and
`generate`, which writes them as a dataset.

Rendering casts one ray per pixel centre exactly (`raycast`) and shades each shape's albedo with
Lambert plus ambient light, giving RGB, z-depth and an object-id map (0 = ground or background;
objects are 1..K). `generate` writes the views in nerfstudio format (depth EXRs, object-id PNGs)
and the scene's `scene.json` (format: `synthetic`'s module docstring); the command that parsed
gin writes config.gin beside them.
"""

from __future__ import annotations

import dataclasses
import os
import typing
from pathlib import Path
from typing import Annotated, Literal

import jax
import numpy as np

from signerf_jax import camera, files, ownership, validation
from signerf_jax.data import nerfstudio, nerfstudio_writer
from signerf_jax.data import poses as poses_lib
from signerf_jax.data import raycast
from signerf_jax.data.dataset import Dataset
from signerf_jax.data.synthetic import SceneSettings, SyntheticScene, make_scene
from signerf_jax.validation import PositiveFloat, PositiveInt, Range

CameraLayout = Literal["sphere", "hemisphere", "forward_facing"]
CAMERA_LAYOUTS = typing.get_args(CameraLayout)
Elevation = Annotated[float, Range(-90, 90)]
SCENE_FILE_NAME = "scene.json"
# The generator datasets record in their provenance (the name it had before the renderer and
# writer moved out of `synthetic`).
GENERATOR_NAME = "signerf_jax.data.synthetic"
# Compiled once each: op-by-op execution would compile every primitive separately (seconds).
_look_at = jax.jit(camera.look_at)
_pixel_rays = jax.jit(camera.pixel_rays)
_INTERSECTORS = {"sphere": raycast.intersect_sphere, "box": raycast.intersect_box,
                 "cylinder": raycast.intersect_cylinder}


@dataclasses.dataclass(frozen=True)
class CameraRig(validation.CheckedFields):
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

  layout: CameraLayout = "hemisphere"
  num_views: PositiveInt = 40
  image_size: PositiveInt = 64
  field_of_view_degrees: Annotated[float, Range(0, 180, low_inclusive=False,
                                                high_inclusive=False)] = 50.0
  distance: PositiveFloat = 2.8
  elevation_range_degrees: tuple[Elevation, Elevation] = (15.0, 70.0)
  arc_degrees: Annotated[float, Range(0, 360, low_inclusive=False)] = 120.0


def make_cameras(rig: CameraRig, scene_bounds) -> camera.Cameras:
  """The rig's cameras, all looking at the centre of `scene_bounds` ([2, 3]), z up."""
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
    albedo[closer] = shape.albedo(points)
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


def generate(directory: str | os.PathLike, seed: int = 0,
             settings: SceneSettings = SceneSettings(), rig: CameraRig = CameraRig()
             ) -> tuple[Dataset, SyntheticScene]:
  """Makes, renders and writes a synthetic scene to `directory`.

  Args:
    directory: the output dataset directory: new, empty, or a dataset signerf wrote (never a
      folder of files it did not write, such as a capture: `ownership`).
    seed: the scene's random seed.
    settings, rig: what to build and how to view it.
  Writes transforms.json with images/, depths/ (EXR z-depth) and object_masks/ (id PNGs), and
  scene.json (whose `generator` records seed, settings and rig). Returns the dataset as rendered
  (before 8-bit quantisation) and the scene.
  """
  directory = Path(directory)
  ownership.check_claimable(directory, ownership.DATASET)  # Before the rendering's work.
  scene = make_scene(seed, settings)
  cameras = make_cameras(rig, scene.scene_bounds)
  images, depths, object_ids = render(scene, cameras)
  near, far = poses_lib.near_far_for_box(cameras, *scene.scene_bounds)
  dataset = Dataset(
      images=images, cameras=cameras,
      image_names=tuple(f"{nerfstudio_writer.IMAGE_FOLDER}/frame_{index:05d}.png"
                        for index in range(cameras.num_cameras)),
      scene_bounds=scene.scene_bounds.astype(np.float32), scene_kind="bounded", near=near,
      far=far, background_color=scene.background_color.astype(np.float32), depths=depths,
      extras={"object_masks": object_ids}, root=str(directory))
  description = scene.describe()
  description["generator"] = {"seed": seed, "scene": dataclasses.asdict(settings),
                              "cameras": dataclasses.asdict(rig)}
  with ownership.claimed(directory, ownership.DATASET):
    # The old transforms.json goes first: scene.json must never sit beside a stale dataset.
    ownership.remove_file(directory / nerfstudio.TRANSFORMS_NAME)
    files.write_json(directory / SCENE_FILE_NAME, description)
    nerfstudio_writer.write_nerfstudio(directory, dataset, provenance={
        "generator": GENERATOR_NAME, "seed": seed, "scene": SCENE_FILE_NAME})
  return dataset, scene
