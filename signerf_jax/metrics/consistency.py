"""Multi-view consistency of an image set: verified correspondences between neighbouring views.

The paper's appendix ("Multiview Consistency") counts LoFTR correspondences between views of the
original images, of the reference-sheet-propagated edit and of independent per-view edits:
independent generation loses ~70% of the correspondences, sheet propagation ~15%. Here the same
experiment uses OpenCV, which needs no learned weights, with one of two matchers (`matcher`):

  "sift"     SIFT keypoints and descriptors (`cv2.SIFT_create`), nearest-neighbour descriptor
             matching with Lowe's ratio test (`ratio`): distinctive points, but few in small or
             soft images (upsampled 64 px views: about one verified match per pair);
  "tracked"  Shi-Tomasi corners (`cv2.goodFeaturesToTrack`, every corner at least 1/1000 as
             strong as the strongest, 2 px apart), followed into the other view by pyramidal
             Lucas-Kanade optical flow and back (`cv2.calcOpticalFlowPyrLK`), kept where the
             round trip returns within `forward_backward_threshold_pixels`: a semi-dense matcher
             that finds tens of correspondences where SIFT finds one, for views close enough for
             flow to follow (neighbours, not opposite sides of an object).

  1. points per view, optionally only inside the view's selection mask dilated by
     `mask_dilation_pixels` (the edit is what changes between image sets; the unchanged
     background would otherwise dominate the counts);
  2. view pairs: each view with its `num_neighbours` nearest views by camera-centre distance
     ("distance"), by the angle between viewing directions ("angle"), or the next views by index
     ("index", the only choice without cameras);
  3. per pair, the matcher's matches (from the first view's points into the second view);
  4. two verified counts per pair:
     * fundamental_inliers: RANSAC inliers of a fundamental matrix fitted to the matches
       (`cv2.findFundamentalMat`, threshold `ransac_threshold_pixels`): geometry estimated from
       the images themselves, so a consistent-looking but wrong set of matches can still pass;
     * epipolar_inliers (needs cameras): matches within `epipolar_threshold_pixels` of the epipolar
       lines implied by the *known* cameras (symmetric distance, keypoints undistorted first):
       stricter, since it cannot adapt to the matches.

`image_set_consistency` returns every pair's counts and the summary (mean and total per pair);
`relative_change` compares an edited image set with the original one, e.g. -0.7 for the paper's
independent edits. Keypoints follow OpenCV's convention (pixel centres at integers) and are moved
to this project's (centres at +0.5) before any camera geometry.
"""

from __future__ import annotations

import dataclasses
from typing import Annotated, Any, Literal

import cv2
import numpy as np

from signerf_jax import camera as camera_lib
from signerf_jax import lens, validation
from signerf_jax.errors import InputError
from signerf_jax.validation import (NonNegativeInt, OpenUnitInterval, PositiveFloat, PositiveInt,
                                    Range)

NeighbourMode = Literal["distance", "angle", "index"]
Matcher = Literal["sift", "tracked"]
# The 8-point algorithm inside RANSAC needs at least eight correspondences.
MIN_MATCHES_FOR_FUNDAMENTAL = 8
# The tracked matcher's corners and flow: OpenCV's usual Lucas-Kanade window, and pyramid levels
# enough for the ~30 px steps between neighbouring 256 px views.
CORNER_QUALITY = 1e-3
CORNER_MIN_DISTANCE_PIXELS = 2
FLOW_WINDOW_PIXELS = 21
FLOW_PYRAMID_LEVELS = 4
# Keypoints are undistorted in batches of a power of two, at least this many.
MIN_UNDISTORT_BATCH = 256


@dataclasses.dataclass(frozen=True)
class ConsistencySettings(validation.CheckedFields):
  """How views are paired, matched and verified (gin: `consistency.<field>`).

  Attributes:
    matcher: "sift" or "tracked" (see the module docstring).
    neighbours: "distance", "angle" or "index" (see the module docstring).
    num_neighbours: neighbours per view (pairs are de-duplicated).
    ratio: SIFT's Lowe's ratio test: keep a match if its distance < ratio * the second best's.
    forward_backward_threshold_pixels: the tracked matcher keeps a point whose flow there and
      back returns within this distance.
    ransac_threshold_pixels, ransac_confidence, ransac_iterations: `cv2.findFundamentalMat`.
    epipolar_threshold_pixels: maximum symmetric distance to the known epipolar lines.
    mask_dilation_pixels: radius of the square dilation of the selection masks (when given).
    max_keypoints: SIFT's `nfeatures`, the tracked matcher's most corners (0: all).
  """

  matcher: Matcher = "sift"
  neighbours: NeighbourMode = "distance"
  num_neighbours: PositiveInt = 2
  ratio: Annotated[float, Range(0, 1, low_inclusive=False)] = 0.75
  forward_backward_threshold_pixels: PositiveFloat = 1.0
  ransac_threshold_pixels: PositiveFloat = 1.0
  ransac_confidence: OpenUnitInterval = 0.999
  ransac_iterations: PositiveInt = 2000
  epipolar_threshold_pixels: PositiveFloat = 1.0
  mask_dilation_pixels: NonNegativeInt = 8
  max_keypoints: NonNegativeInt = 0


@dataclasses.dataclass(frozen=True)
class PairCorrespondences:
  """Counts for one view pair (first < second).

  Attributes:
    first, second: view indices.
    matches: SIFT's descriptor matches passing the ratio test, or the points tracked there and
      back.
    fundamental_inliers: RANSAC inliers of the fitted fundamental matrix (0 below 8 matches).
    epipolar_inliers: matches consistent with the known cameras (None without cameras).
  """

  first: int
  second: int
  matches: int
  fundamental_inliers: int
  epipolar_inliers: int | None


@dataclasses.dataclass(frozen=True)
class ConsistencyReport:
  """All pairs of one image set; `summary()` gives the numbers to report."""

  pairs: tuple[PairCorrespondences, ...]

  def summary(self) -> dict[str, Any]:
    """num_pairs and, for matches / fundamental_inliers / epipolar_inliers, the mean per pair
    (`mean_<name>`) and the total (`total_<name>`); epipolar values are None without cameras."""
    result: dict[str, Any] = {"num_pairs": len(self.pairs)}
    for name in ("matches", "fundamental_inliers", "epipolar_inliers"):
      values = [getattr(pair, name) for pair in self.pairs]
      known = bool(values) and None not in values
      result[f"mean_{name}"] = float(np.mean(values)) if known else None
      result[f"total_{name}"] = int(np.sum(values)) if known else None
    return result

  def to_json(self) -> dict[str, Any]:
    return {"summary": self.summary(), "pairs": [dataclasses.asdict(p) for p in self.pairs]}


def relative_change(edited: ConsistencyReport, original: ConsistencyReport) -> dict[str, Any]:
  """(edited - original) / original of each mean count (-0.7: 70% fewer correspondences).

  Both reports must cover the same pairs (same cameras, masks and settings). A count that is
  None or zero in the original gives None.
  """
  if [(p.first, p.second) for p in edited.pairs] != [(p.first, p.second) for p in original.pairs]:
    raise ValueError("the two reports cover different view pairs")
  edited_summary, original_summary = edited.summary(), original.summary()
  result = {}
  for name in ("matches", "fundamental_inliers", "epipolar_inliers"):
    key = f"mean_{name}"
    before, after = original_summary[key], edited_summary[key]
    result[key] = None if not before or after is None else (after - before) / before
  return result


def neighbour_pairs(num_views: int, settings: ConsistencySettings,
                    cameras: camera_lib.Cameras | None = None) -> np.ndarray:
  """[P, 2] int view pairs (first < second, sorted, unique) as `settings.neighbours` says."""
  count = min(settings.num_neighbours, num_views - 1)
  if settings.neighbours == "index":
    pairs = [(i, i + step) for step in range(1, count + 1) for i in range(num_views - step)]
  else:
    if cameras is None:
      raise InputError(f"neighbours={settings.neighbours!r} needs the cameras (use 'index' "
                       "without them)", field="consistency.neighbours")
    nearest = nearest_cameras(cameras, count, settings.neighbours)
    pairs = [(min(i, j), max(i, j)) for i in range(num_views) for j in nearest[i]]
  return np.asarray(sorted(set(pairs)), np.int64).reshape(-1, 2)


def nearest_cameras(cameras: camera_lib.Cameras, count: int, by: str = "distance"
                    ) -> np.ndarray:
  """[N, count] int: each camera's `count` nearest other cameras, nearest first, by the
  distance between their centres ("distance") or the angle between their viewing directions
  ("angle")."""
  if by == "distance":
    positions = np.asarray(cameras.positions, np.float64)
    dissimilarity = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
  else:
    forward = np.asarray(cameras.forward, np.float64)
    dissimilarity = -forward @ forward.T  # Ordered like the angle between directions.
  np.fill_diagonal(dissimilarity, np.inf)
  return np.argsort(dissimilarity, axis=1, kind="stable")[:, :count]


def gray_uint8(image: np.ndarray) -> np.ndarray:
  """[H, W, 3] float in [0, 1] or uint8 -> [H, W] uint8 luma (OpenCV's RGB weights)."""
  image = np.asarray(image)
  if image.dtype != np.uint8:
    image = np.round(np.clip(image, 0.0, 1.0) * 255).astype(np.uint8)
  return cv2.cvtColor(np.ascontiguousarray(image[..., :3]), cv2.COLOR_RGB2GRAY)


def _detection_mask(mask: np.ndarray, dilation_pixels: int) -> np.ndarray:
  mask = (np.asarray(mask) != 0).astype(np.uint8) * 255
  if dilation_pixels:
    kernel = np.ones((2 * dilation_pixels + 1,) * 2, np.uint8)
    mask = cv2.dilate(mask, kernel)
  return mask


def _detection_masks(masks, count: int, settings: ConsistencySettings) -> list:
  """Per view, the dilated selection mask points are detected in (None: the whole view)."""
  if masks is None:
    return [None] * count
  return [_detection_mask(mask, settings.mask_dilation_pixels) for mask in masks]


def detect_features(grays, masks=None, settings: ConsistencySettings = ConsistencySettings()
                    ) -> list[tuple[np.ndarray, np.ndarray]]:
  """SIFT keypoints and descriptors of each view.

  Args:
    grays: N [H, W] uint8 luma images (`gray_uint8`).
    masks: optional [N, H, W] selection masks; keypoints are kept inside their dilation only.
    settings: `max_keypoints` and `mask_dilation_pixels` apply.
  Returns:
    per view, (keypoints [K, 2] float64 (x, y) in OpenCV pixels, descriptors [K, 128] float32).
  """
  sift = cv2.SIFT_create(nfeatures=settings.max_keypoints)
  features = []
  for gray, detection_mask in zip(grays, _detection_masks(masks, len(grays), settings)):
    keypoints, descriptors = sift.detectAndCompute(gray, detection_mask)
    if descriptors is None:
      descriptors = np.zeros((0, 128), np.float32)
    points = np.array([keypoint.pt for keypoint in keypoints], np.float64).reshape(-1, 2)
    features.append((points, descriptors))
  return features


def detect_corners(grays, masks=None, settings: ConsistencySettings = ConsistencySettings()
                   ) -> list[np.ndarray]:
  """Shi-Tomasi corners of each view (the tracked matcher's points): per view [K, 2] float32
  (x, y) in OpenCV pixels; `grays`, `masks` and `settings` as `detect_features`."""
  corners = []
  for gray, detection_mask in zip(grays, _detection_masks(masks, len(grays), settings)):
    found = cv2.goodFeaturesToTrack(gray, settings.max_keypoints, CORNER_QUALITY,
                                    CORNER_MIN_DISTANCE_PIXELS, mask=detection_mask)
    corners.append(np.zeros((0, 2), np.float32) if found is None else found.reshape(-1, 2))
  return corners


def track_points(first_gray: np.ndarray, second_gray: np.ndarray, points: np.ndarray,
                 settings: ConsistencySettings) -> tuple[np.ndarray, np.ndarray]:
  """Points [K, 2] of the first view followed into the second by Lucas-Kanade flow.

  Returns [M, 2] float64 positions in the first view and in the second (OpenCV pixels) of the
  points found both ways whose round trip ends within `forward_backward_threshold_pixels`.
  """
  if len(points) == 0:
    return np.zeros((0, 2)), np.zeros((0, 2))
  points = np.asarray(points, np.float32).reshape(-1, 1, 2)
  def flow(source, target, start):
    return cv2.calcOpticalFlowPyrLK(source, target, start, None,
                                    winSize=(FLOW_WINDOW_PIXELS,) * 2,
                                    maxLevel=FLOW_PYRAMID_LEVELS)[:2]
  there, found = flow(first_gray, second_gray, points)
  back, found_back = flow(second_gray, first_gray, there)
  round_trip = np.linalg.norm((back - points).reshape(-1, 2), axis=-1)
  kept = ((found.ravel() == 1) & (found_back.ravel() == 1)
          & (round_trip <= settings.forward_backward_threshold_pixels))
  return (points.reshape(-1, 2)[kept].astype(np.float64),
          there.reshape(-1, 2)[kept].astype(np.float64))


def ratio_test_matches(first_descriptors: np.ndarray, second_descriptors: np.ndarray,
                       ratio: float) -> np.ndarray:
  """[M, 2] (first index, second index) of nearest-neighbour matches passing Lowe's test."""
  if len(first_descriptors) == 0 or len(second_descriptors) < 2:
    return np.zeros((0, 2), np.int64)
  candidates = cv2.BFMatcher(cv2.NORM_L2).knnMatch(first_descriptors, second_descriptors, k=2)
  kept = [(best.queryIdx, best.trainIdx) for best, second_best in candidates
          if best.distance < ratio * second_best.distance]
  return np.asarray(kept, np.int64).reshape(-1, 2)


def fundamental_inliers(first_points: np.ndarray, second_points: np.ndarray,
                        settings: ConsistencySettings) -> int:
  """RANSAC inliers of a fundamental matrix fitted to matched [M, 2] pixel positions."""
  if len(first_points) < MIN_MATCHES_FOR_FUNDAMENTAL:
    return 0
  matrix, inliers = cv2.findFundamentalMat(
      first_points, second_points, cv2.FM_RANSAC, settings.ransac_threshold_pixels,
      settings.ransac_confidence, settings.ransac_iterations)
  return 0 if matrix is None or inliers is None else int(np.count_nonzero(inliers))


def _undistort_padded(x: np.ndarray, y: np.ndarray, distortion: np.ndarray,
                      fisheye: bool) -> tuple[np.ndarray, np.ndarray]:
  """`lens.undistort` of [K] normalised coordinates, padded to a power of two so that the
  varying keypoint counts of an evaluation's pairs share a few compiled programs instead of
  one each."""
  count = len(x)
  padding = max(MIN_UNDISTORT_BATCH, 1 << max(count - 1, 0).bit_length()) - count
  x, y = (np.pad(value, (0, padding)) for value in (x, y))
  x, y = lens.undistort(x, y, np.pad(distortion, ((0, padding), (0, 0))), fisheye)
  return np.asarray(x, np.float64)[:count], np.asarray(y, np.float64)[:count]


def ideal_pixels(cameras: camera_lib.Cameras, keypoints: list[np.ndarray]) -> list[np.ndarray]:
  """Per view, [K, 3] homogeneous undistorted pixel positions (this project's convention, pixel
  centres at +0.5) of OpenCV keypoints [K, 2]; all views are undistorted in one call (a
  fisheye's keypoints 90 degrees or more off its axis have no pinhole position: they come back
  clamped, see `lens.undistort`)."""
  view = np.concatenate([np.full(len(points), index) for index, points in enumerate(keypoints)])
  points = np.concatenate(keypoints).reshape(-1, 2) + 0.5
  fx, fy = (np.asarray(value, np.float64)[view] for value in (cameras.fx, cameras.fy))
  cx, cy = (np.asarray(value, np.float64)[view] for value in (cameras.cx, cameras.cy))
  x, y = (points[:, 0] - cx) / fx, (points[:, 1] - cy) / fy
  distortion = np.asarray(cameras.distortion)[view]
  if np.any(distortion):
    x, y = _undistort_padded(x, y, distortion, cameras.fisheye)
  ideal = np.stack([x * fx + cx, y * fy + cy, np.ones(len(view))], -1)
  return np.split(ideal, np.cumsum([len(points) for points in keypoints])[:-1])


def fundamental_from_cameras(cameras: camera_lib.Cameras, first: int, second: int) -> np.ndarray:
  """[3, 3] F with p2^T F p1 = 0 for ideal pixel positions (centres at +0.5) of two cameras."""
  # OpenCV camera axes are OpenGL's with y and z flipped.
  flip = np.diag([1.0, -1.0, -1.0])
  camera_to_world = np.asarray(cameras.camera_to_world, np.float64)
  rotation_1, centre_1 = camera_to_world[first, :, :3], camera_to_world[first, :, 3]
  rotation_2, centre_2 = camera_to_world[second, :, :3], camera_to_world[second, :, 3]
  # x_2 = R x_1 + t between the two OpenCV camera frames.
  rotation = flip @ rotation_2.T @ rotation_1 @ flip
  translation = flip @ rotation_2.T @ (centre_1 - centre_2)
  cross = np.array([[0.0, -translation[2], translation[1]],
                    [translation[2], 0.0, -translation[0]],
                    [-translation[1], translation[0], 0.0]])
  intrinsics = np.asarray(cameras.intrinsic_matrices(), np.float64)
  return np.linalg.inv(intrinsics[second]).T @ cross @ rotation @ np.linalg.inv(intrinsics[first])


def symmetric_epipolar_distance(fundamental: np.ndarray, first_points: np.ndarray,
                                second_points: np.ndarray) -> np.ndarray:
  """[M] max of the distances of p2 to the line F p1 and of p1 to F^T p2 (homogeneous [M, 3])."""
  def line_distance(lines, points):
    return np.abs(np.sum(lines * points, -1)) / np.maximum(np.hypot(lines[:, 0], lines[:, 1]),
                                                           1e-12)
  return np.maximum(line_distance(first_points @ fundamental.T, second_points),
                    line_distance(second_points @ fundamental, first_points))


def _matcher(grays, masks, settings: ConsistencySettings):
  """(first, second) -> matched positions [M, 2] in each view (OpenCV pixels), by
  `settings.matcher`; each view's points are found once."""
  if settings.matcher == "sift":
    features = detect_features(grays, masks, settings)
    def match(first, second):
      (first_points, first_descriptors), (second_points, second_descriptors) = (
          features[first], features[second])
      matches = ratio_test_matches(first_descriptors, second_descriptors, settings.ratio)
      return first_points[matches[:, 0]], second_points[matches[:, 1]]
  else:
    corners = detect_corners(grays, masks, settings)
    def match(first, second):
      return track_points(grays[first], grays[second], corners[first], settings)
  return match


def image_set_consistency(images, cameras: camera_lib.Cameras | None = None, masks=None,
                          settings: ConsistencySettings = ConsistencySettings()
                          ) -> ConsistencyReport:
  """Verified correspondences between neighbouring views of one image set.

  Args:
    images: [N, H, W, 3] float in [0, 1] or uint8.
    cameras: the N cameras (needed for neighbours "distance"/"angle" and for epipolar_inliers).
    masks: optional [N, H, W] selection masks restricting keypoints (see the module docstring).
    settings: pairing, matching and verification parameters.
  """
  images = np.asarray(images)
  if cameras is not None and cameras.num_cameras != len(images):
    raise InputError(f"{len(images)} images but {cameras.num_cameras} cameras", field="cameras")
  if masks is not None and np.shape(masks) != images.shape[:3]:
    raise InputError(f"masks have shape {np.shape(masks)}, expected {images.shape[:3]}",
                     field="masks")
  match = _matcher([gray_uint8(image) for image in images], masks, settings)
  pairs = []
  for first, second in neighbour_pairs(len(images), settings, cameras):
    matched_first, matched_second = match(first, second)
    epipolar = None
    if cameras is not None:
      ideal_first, ideal_second = ideal_pixels(cameras.take([first, second]),
                                               [matched_first, matched_second])
      distances = symmetric_epipolar_distance(
          fundamental_from_cameras(cameras, first, second), ideal_first, ideal_second)
      epipolar = int(np.count_nonzero(distances <= settings.epipolar_threshold_pixels))
    pairs.append(PairCorrespondences(
        first=int(first), second=int(second), matches=len(matched_first),
        fundamental_inliers=fundamental_inliers(matched_first, matched_second, settings),
        epipolar_inliers=epipolar))
  return ConsistencyReport(tuple(pairs))
