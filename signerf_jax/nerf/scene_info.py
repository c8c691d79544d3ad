"""What the model must know about a scene: its region, kind, ray range, image size and how far
the cameras stand (`SceneInfo`, saved in every run directory), checked before a model is sized."""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

import numpy as np

from signerf_jax.errors import InputError
from signerf_jax.nerf.perspective_warp import PerspectiveWarp


# Scene bounds whose largest side is below this fraction of the cameras' distance to them are
# degenerate: float32 scene coordinates (7 significant digits) cannot place a sample inside, and
# the grid's cells would be smaller than the rounding of every position.
MIN_EXTENT_FRACTION = 1e-5


def check_scene(scene: "SceneInfo", path=None) -> None:
  """Refuses a scene no model can be sized for (`derive_capacity` would divide by zero, or
  size the grid from NaN).

  Args:
    scene: the scene.
    path: the dataset (or run) it came from, for errors; None when unknown.
  Raises:
    InputError naming `path` and the field: non-finite or degenerate bounds (see
      MIN_EXTENT_FRACTION), or a pixel footprint or camera distance that is not finite and
      positive.
  """
  bounds = np.asarray(scene.bounds, np.float64)
  if bounds.shape != (2, 3) or not np.all(np.isfinite(bounds)):
    raise InputError(f"must be two finite corners (x, y, z), got {scene.bounds}", path,
                     "scene_bounds")
  for name in ("camera_distance", "pixel_footprint"):
    value = getattr(scene, name)
    if not (math.isfinite(value) and value > 0):
      raise InputError(f"{name.replace('_', ' ')} {value} is not positive and finite (corrupt "
                       "camera positions or focal lengths)", path, name)
  sides = bounds[1] - bounds[0]
  if not np.all(sides > 0) or not np.max(sides) > MIN_EXTENT_FRACTION * scene.camera_distance:
    raise InputError(f"the region {bounds.tolist()} is degenerate (sides {sides.tolist()}, the "
                     f"cameras {scene.camera_distance:.3g} away): every side must be positive and "
                     f"the largest above {MIN_EXTENT_FRACTION:g} of the cameras' distance", path,
                     "scene_bounds")


def camera_distances(bounds, cameras) -> np.ndarray:
  """[N] distances (scene units) of the cameras to the centre of `bounds` ([2, 3] min, max)."""
  centre = np.mean(np.asarray(bounds, np.float64), axis=0)
  return np.linalg.norm(np.asarray(cameras.positions, np.float64) - centre, axis=-1)


@dataclasses.dataclass(frozen=True)
class SceneInfo:
  """What the model must know about a scene (JSON-friendly; saved in every run directory).

  Attributes:
    bounds: ((x, y, z) min, (x, y, z) max) region modelled in detail, scene units.
    kind: "bounded", "forward_facing" or "unbounded" (see `Dataset`).
    near, far: ray range in scene units.
    background_color: RGB seen through empty space in bounded scenes, or None.
    num_images: training images (for appearance embeddings).
    width, height: training image size in pixels.
    pixel_footprint: scene units one pixel spans at the typical camera-to-scene distance.
    camera_distance: the cameras' median distance to the centre of the bounds (scene units).
    perspective: forward-facing scenes' field-coordinate warp; None for the others.
  """

  bounds: tuple[tuple[float, float, float], tuple[float, float, float]]
  kind: str
  near: float
  far: float
  background_color: tuple[float, float, float] | None
  num_images: int
  width: int
  height: int
  pixel_footprint: float
  camera_distance: float
  perspective: PerspectiveWarp | None = None

  @classmethod
  def from_dataset(cls, dataset) -> "SceneInfo":
    bounds = np.asarray(dataset.scene_bounds, np.float64)
    cameras = dataset.cameras
    distances = camera_distances(bounds, cameras)
    focal = np.asarray(cameras.fx, np.float64)
    background = dataset.background_color
    scene = cls(
        bounds=(tuple(map(float, bounds[0])), tuple(map(float, bounds[1]))),
        kind=dataset.scene_kind,
        near=float(dataset.near),
        far=float(dataset.far),
        background_color=None if background is None else tuple(map(float, background)),
        num_images=int(dataset.num_images),
        width=int(dataset.width),
        height=int(dataset.height),
        pixel_footprint=float(np.median(distances / focal)),
        camera_distance=float(np.median(distances)),
    )
    check_scene(scene, dataset.root or None)  # Before the warp computes with the cameras.
    if dataset.scene_kind != "forward_facing":
      return scene
    return dataclasses.replace(scene, perspective=PerspectiveWarp.from_cameras(
        cameras, float(dataset.near), float(dataset.far)))

  @classmethod
  def from_json(cls, value: Mapping[str, Any]) -> "SceneInfo":
    value = dict(value)
    value["bounds"] = tuple(tuple(map(float, corner)) for corner in value["bounds"])
    if value["background_color"] is not None:
      value["background_color"] = tuple(value["background_color"])
    if value.get("perspective") is not None:
      value["perspective"] = PerspectiveWarp.from_json(value["perspective"])
    return cls(**value)

  @property
  def extent(self) -> float:
    """Largest side of the bounds."""
    return float(np.max(np.subtract(self.bounds[1], self.bounds[0])))
