"""NDC's perspective warp as field coordinates for forward-facing scenes: the range of the warped
coordinates over what the cameras see, so that the grid's finest cells match pixel angles.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

from signerf_jax import camera as camera_lib
from signerf_jax.data import poses
from signerf_jax.nerf import sampling


Vector = tuple[float, float, float]


def _as_vector(values) -> Vector:
  return tuple(map(float, values))


@dataclasses.dataclass(frozen=True)
class PerspectiveWarp:
  """A forward-facing scene's field coordinates, NDC's warp: `sampling.perspective` of points in
  the cameras' mean frame, mapped from [low, high] onto [0, 1]^3 (`__call__`).

  Attributes:
    centre: the cameras' mean position (scene units).
    rotation: rows are the mean camera's right, up and backward axes (it looks down -z).
    low, high: the range of the warped coordinates over what the cameras see (`from_cameras`).
  """

  centre: Vector
  rotation: tuple[Vector, Vector, Vector]
  low: Vector
  high: Vector

  @classmethod
  def from_cameras(cls, cameras, near: float, far: float) -> "PerspectiveWarp":
    """The warp whose range holds what every camera sees from `near` to `far` (ray distances,
    scene units): the rays through each image's corners and centre, at both distances."""
    camera_to_world = np.asarray(cameras.camera_to_world, np.float64)
    rotation = poses.mean_rotation(camera_to_world).T
    centre = camera_to_world[:, :, 3].mean(0)
    count = len(camera_to_world)
    pixel_x = np.array([0.0, cameras.width, 0.0, cameras.width, cameras.width / 2], np.float32)
    pixel_y = np.array([0.0, 0.0, cameras.height, cameras.height, cameras.height / 2],
                       np.float32)
    rays = camera_lib.pixel_rays(cameras, np.repeat(np.arange(count), len(pixel_x)),
                                 np.tile(pixel_x, count), np.tile(pixel_y, count))
    origins, directions = np.asarray(rays.origins, np.float64), np.asarray(rays.directions)
    points = np.concatenate([origins + distance * directions for distance in (near, far)])
    warped = np.asarray(sampling.perspective((points - centre) @ rotation.T), np.float64)
    return cls(_as_vector(centre), tuple(map(_as_vector, rotation)), _as_vector(warped.min(0)),
               _as_vector(warped.max(0)))

  @classmethod
  def from_json(cls, value: Mapping[str, Any]) -> "PerspectiveWarp":
    return cls(_as_vector(value["centre"]), tuple(map(_as_vector, value["rotation"])),
               _as_vector(value["low"]), _as_vector(value["high"]))

  @property
  def image_plane_extent(self) -> float:
    """The larger side of the warped image-plane range (tangent units)."""
    return float(np.max(np.subtract(self.high[:2], self.low[:2])))

  def __call__(self, points):
    """Scene points [..., 3] -> [..., 3] warped field coordinates, [0, 1] inside the range."""
    rotation, centre, low, high = (np.asarray(value, np.float32) for value in
                                   (self.rotation, self.centre, self.low, self.high))
    return (sampling.perspective((points - centre) @ rotation.T) - low) / (high - low)

  def inverse(self, coordinates):
    """Field coordinates [..., 3] (warped, [0, 1] inside the range) -> [..., 3] scene points."""
    rotation, centre, low, high = (np.asarray(value, np.float32) for value in
                                   (self.rotation, self.centre, self.low, self.high))
    return sampling.unperspective(low + coordinates * (high - low)) @ rotation + centre
