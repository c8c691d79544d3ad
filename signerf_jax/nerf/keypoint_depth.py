"""Depth where the training photos themselves fix it: keypoints matched between neighbouring
training views, verified against the known cameras and triangulated (DS-NeRF's depth from
structure from motion, with the capture's own poses instead of a new reconstruction).

Between few views the photometric loss alone leaves each view free to explain its pixels with
content at the wrong depth (stitch with 13 views: most held-out error is at pixels two or more
training views see, i.e. geometry the photos determine but training does not find,
docs/performance.md). A matched keypoint pins its ray's depth in both views.

  1. SIFT keypoints of each view, matched with each of its `num_neighbours` nearest views by
     camera position (Lowe's ratio test; `metrics.consistency`);
  2. a match is kept within `epipolar_threshold_pixels` of the known cameras' epipolar lines;
  3. it is triangulated (linear, in undistorted pixels) and kept when in front of both cameras,
     seen at an angle of at least `min_angle_degrees` (a narrow angle leaves depth uncertain)
     and reprojected within `epipolar_threshold_pixels` in both views.

Each kept point gives both views an observation: the pixel (this project's convention, centres
at +0.5) and the distance along its ray.
"""

from __future__ import annotations

import dataclasses

import cv2
import jax
import numpy as np
from flax import struct

from signerf_jax import camera as camera_lib
from signerf_jax import validation
from signerf_jax.metrics import consistency
from signerf_jax.validation import PositiveFloat, PositiveInt


@dataclasses.dataclass(frozen=True)
class KeypointSettings(validation.CheckedFields):
  """How keypoints are matched and kept (see the module docstring)."""

  num_neighbours: PositiveInt = 2
  ratio: PositiveFloat = 0.8
  epipolar_threshold_pixels: PositiveFloat = 1.0
  min_angle_degrees: PositiveFloat = 2.0


@struct.dataclass
class KeypointDepths:
  """Observed depths of triangulated keypoints, one row per (point, view).

  Attributes:
    camera_indices: [K] int32 training view.
    pixels: [K, 2] float32 (x, y) in pixels (centres at +0.5, distorted: where the photo has it).
    distances: [K] float32 distance from the camera centre along the pixel's ray (scene units).
  """

  camera_indices: jax.Array
  pixels: jax.Array
  distances: jax.Array

  @property
  def count(self) -> int:
    return int(self.distances.shape[0])


def _projection_matrix(cameras: camera_lib.Cameras, index: int) -> np.ndarray:
  """[3, 4] K [R | t] of an OpenCV camera (world -> undistorted pixel, centres at +0.5)."""
  flip = np.diag([1.0, -1.0, -1.0])
  camera_to_world = np.asarray(cameras.camera_to_world, np.float64)[index]
  rotation = flip @ camera_to_world[:, :3].T
  translation = -rotation @ camera_to_world[:, 3]
  intrinsics = np.asarray(cameras.intrinsic_matrices(), np.float64)[index]
  return intrinsics @ np.concatenate([rotation, translation[:, None]], axis=1)


def _triangulated(cameras, first, second, ideal_first, ideal_second, settings):
  """[M, 3] world points of matched ideal pixels [M, 3] and [M] bool: kept (module docstring)."""
  projections = [_projection_matrix(cameras, index) for index in (first, second)]
  homogeneous = cv2.triangulatePoints(projections[0], projections[1],
                                      ideal_first[:, :2].T, ideal_second[:, :2].T).T
  points = homogeneous[:, :3] / np.where(np.abs(homogeneous[:, 3:]) > 1e-12,
                                         homogeneous[:, 3:], 1e-12)
  kept = np.ones(len(points), bool)
  for projection, ideal in zip(projections, (ideal_first, ideal_second)):
    image = np.concatenate([points, np.ones((len(points), 1))], 1) @ projection.T
    kept &= image[:, 2] > 0
    reprojected = image[:, :2] / np.maximum(image[:, 2:], 1e-12)
    kept &= np.linalg.norm(reprojected - ideal[:, :2], axis=1) <= (
        settings.epipolar_threshold_pixels)
  centres = np.asarray(cameras.positions, np.float64)[[first, second]]
  rays = [points - centre for centre in centres]
  cosine = np.sum(rays[0] * rays[1], 1) / np.maximum(
      np.linalg.norm(rays[0], axis=1) * np.linalg.norm(rays[1], axis=1), 1e-12)
  kept &= cosine <= np.cos(np.radians(settings.min_angle_degrees))
  return points, kept


def triangulate(images, cameras: camera_lib.Cameras,
                settings: KeypointSettings = KeypointSettings()) -> KeypointDepths:
  """The keypoint depths of training `images` [N, H, W, 3] (float in [0, 1] or uint8) taken by
  `cameras` (module docstring). Empty when nothing matches (e.g. textureless views)."""
  grays = [consistency.gray_uint8(image) for image in images]
  features = consistency.detect_features(grays)
  ideal = consistency.ideal_pixels(cameras, [points for points, _ in features])
  pairs = consistency.neighbour_pairs(len(images), consistency.ConsistencySettings(
      neighbours="distance", num_neighbours=settings.num_neighbours), cameras)
  centres = np.asarray(cameras.positions, np.float64)
  indices, pixels, distances = [], [], []
  for first, second in pairs:
    matches = consistency.ratio_test_matches(features[first][1], features[second][1],
                                             settings.ratio)
    if not len(matches):
      continue
    ideal_first, ideal_second = ideal[first][matches[:, 0]], ideal[second][matches[:, 1]]
    epipolar = consistency.symmetric_epipolar_distance(
        consistency.fundamental_from_cameras(cameras, first, second), ideal_first, ideal_second)
    close = epipolar <= settings.epipolar_threshold_pixels
    points, kept = _triangulated(cameras, first, second, ideal_first[close], ideal_second[close],
                                 settings)
    for view, column in ((first, 0), (second, 1)):
      indices.append(np.full(int(kept.sum()), view))
      pixels.append(features[view][0][matches[close][kept, column]] + 0.5)
      distances.append(np.linalg.norm(points[kept] - centres[view], axis=1))
  if not indices:
    return KeypointDepths(np.zeros(0, np.int32), np.zeros((0, 2), np.float32),
                          np.zeros(0, np.float32))
  return KeypointDepths(np.concatenate(indices).astype(np.int32),
                        np.concatenate(pixels).astype(np.float32),
                        np.concatenate(distances).astype(np.float32))


def sample_rays(key, keypoints: KeypointDepths, cameras: camera_lib.Cameras, count: int
                ) -> tuple[camera_lib.Rays, jax.Array]:
  """`count` uniformly drawn observations: their rays [count] and known distances [count]."""
  choice = jax.random.randint(key, (count,), 0, keypoints.distances.shape[0])
  pixels = keypoints.pixels[choice]
  rays = camera_lib.pixel_rays(cameras, keypoints.camera_indices[choice], pixels[:, 0],
                               pixels[:, 1])
  return rays, keypoints.distances[choice]
