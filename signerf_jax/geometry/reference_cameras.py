"""Reference cameras around the selection, for the reference sheet (paper, "Reference Sheet").

Automatic placement of M cameras (default 5), all looking at the selection's centre c:
  1. The dataset cameras that see the selection (a selection point projects into their image,
     in front of them) are described in spherical coordinates around c with respect to the
     scene's up direction: azimuth, elevation, distance.
  2. Their azimuths cover an arc (the circle minus its largest empty gap, at least
     `min_arc_degrees`; the full circle when that gap is narrower than 360 / M degrees). The M
     reference azimuths split it evenly: start + arc (k + 1/2) / M.
  3. Each reference camera takes the median elevation and distance of the `neighbours` dataset
     cameras nearest to it in azimuth, so the views stay close to the original distribution.
  4. The distance is then clipped to where the selection's bounding sphere fills between
     `min_fill` and `max_fill` of the frame (area of its projected bounding square): a distant
     selection gets cameras that move closer (more pixels for the edit, as the paper advises),
     and a selection that would not fit gets cameras that back off.
  5. Intrinsics: the dataset cameras' median focal lengths, principal point at the image centre,
     no distortion.
The report gives the arc the dataset covers, each camera's azimuth/elevation/distance, and the
fraction of the frame the selection's projected bounding box fills in each reference view.
Placement is a few dozen numbers of host arithmetic (numpy); only the renders that follow are
heavy.
"""

from __future__ import annotations

import dataclasses
from typing import Annotated, Any

import jax
import numpy as np

from signerf_jax import camera as camera_lib
from signerf_jax import validation
from signerf_jax.errors import InputError
from signerf_jax.validation import OpenUnitInterval, PositiveInt, Range, Vector3

# Compiled once per shape instead of dispatching many tiny operations one by one.
_project = jax.jit(camera_lib.project)
_look_at = jax.jit(camera_lib.look_at)


def _project_points(cameras: camera_lib.Cameras, points) -> tuple[np.ndarray, np.ndarray]:
  """`camera.project` of [K, 3] points: pixels [N, K, 2] and z-depths [N, K] (numpy).

  The points are padded (last one repeated) to the next power of two, so that a selection's
  points and those plus its centre share one compilation.
  """
  points = np.asarray(points, np.float32).reshape(-1, 3)
  count = len(points)
  padded = np.concatenate([points, np.repeat(points[-1:], (1 << (count - 1).bit_length()) - count,
                                             axis=0)])
  pixels, depth = _project(cameras, padded)
  return np.asarray(pixels)[:, :count], np.asarray(depth)[:, :count]


@dataclasses.dataclass(frozen=True)
class ReferenceCameraReport:
  """How the reference cameras relate to the selection and the dataset cameras.

  Attributes:
    up: [3] the up direction azimuth and elevation refer to.
    dataset_views_seeing_selection: how many dataset cameras see the selection.
    dataset_arc_degrees: azimuth arc (around the selection centre) the dataset cameras cover.
    reference_arc_degrees: azimuth arc between the first and last reference camera.
    azimuth_degrees, elevation_degrees, distance: [M] per reference camera.
    fill_ratio: [M] fraction of the frame's area covered by the selection's projected bounding
      box (clipped to the frame).
  """

  up: np.ndarray
  dataset_views_seeing_selection: int
  dataset_arc_degrees: float
  reference_arc_degrees: float
  azimuth_degrees: np.ndarray
  elevation_degrees: np.ndarray
  distance: np.ndarray
  fill_ratio: np.ndarray

  def to_json(self) -> dict[str, Any]:
    return {field.name: np.asarray(getattr(self, field.name)).tolist()
            for field in dataclasses.fields(self)}


def selection_sphere(points) -> tuple[np.ndarray, float]:
  """Centre (of the bounding box) and radius of a sphere enclosing [K, 3] selection points."""
  points = np.asarray(points, np.float64).reshape(-1, 3)
  if points.shape[0] == 0 or not np.all(np.isfinite(points)):
    raise InputError("selection needs at least one finite point", field="selection")
  center = (points.min(axis=0) + points.max(axis=0)) / 2
  return center, float(np.max(np.linalg.norm(points - center, axis=-1)))


def scene_up(cameras: camera_lib.Cameras) -> np.ndarray:
  """The mean of the cameras' up vectors (normalised); +z if they cancel out."""
  mean_up = np.asarray(cameras.camera_to_world, np.float64)[:, :, 1].mean(axis=0)
  norm = np.linalg.norm(mean_up)
  return mean_up / norm if norm > 1e-3 else np.array([0.0, 0.0, 1.0])


def _azimuth_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """Two unit vectors spanning the plane orthogonal to `up` (azimuth 0 and 90 degrees)."""
  helper = np.eye(3)[np.argmin(np.abs(up))]
  first = np.cross(up, helper)
  first /= np.linalg.norm(first)
  return first, np.cross(up, first)


def _spherical(positions, center, up):
  """Azimuth, elevation (radians) and distance of positions [N, 3] around `center`."""
  first, second = _azimuth_basis(up)
  offsets = positions - center
  distance = np.linalg.norm(offsets, axis=-1)
  azimuth = np.arctan2(offsets @ second, offsets @ first)
  elevation = np.arcsin(np.clip(offsets @ up / np.maximum(distance, 1e-12), -1.0, 1.0))
  return azimuth, elevation, distance


def projected_fill(cameras: camera_lib.Cameras, points) -> np.ndarray:
  """[N] fraction of each frame covered by the projected bounding box of [K, 3] points.

  Points behind a camera are ignored; a camera seeing no point in front of it gets 0.
  """
  pixels, depth = _project_points(cameras, points)
  pixels, depth = pixels.astype(np.float64), depth.astype(np.float64)
  in_front = depth > 0
  limits = np.array([cameras.width, cameras.height], np.float64)
  low = np.where(in_front[..., None], pixels, np.inf).min(axis=1)
  high = np.where(in_front[..., None], pixels, -np.inf).max(axis=1)
  low, high = np.clip(low, 0, limits), np.clip(high, 0, limits)
  area = np.prod(np.maximum(high - low, 0), axis=-1)
  return np.where(in_front.any(axis=1), area / np.prod(limits), 0.0)


def cameras_seeing(cameras: camera_lib.Cameras, points) -> np.ndarray:
  """[N] bool: some of the [K, 3] points projects inside the image, in front of the camera."""
  pixels, depth = _project_points(cameras, points)
  inside = ((pixels[..., 0] >= 0) & (pixels[..., 0] <= cameras.width) & (pixels[..., 1] >= 0)
            & (pixels[..., 1] <= cameras.height) & (depth > 0))
  return inside.any(axis=1)


def _covered_arc(azimuth: np.ndarray, min_arc: float) -> tuple[float, float]:
  """(start, length) in radians of the smallest arc holding every azimuth, at least `min_arc`."""
  ordered = np.sort(np.mod(azimuth, 2 * np.pi))
  gaps = np.diff(np.concatenate([ordered, ordered[:1] + 2 * np.pi]))
  largest = int(np.argmax(gaps))
  start = ordered[(largest + 1) % len(ordered)]
  length = 2 * np.pi - gaps[largest]
  if length < min_arc:
    start -= (min_arc - length) / 2
    length = min_arc
  return float(start), float(length)


def _fill_distance(fill: float, radius: float, focal: float, width: int, height: int) -> float:
  """Distance at which a sphere's projected bounding square covers `fill` of the frame's area."""
  half_angle_tangent = np.sqrt(fill * width * height) / (2 * focal)
  return radius / np.sin(np.arctan(half_angle_tangent))


def _unit_up(dataset_cameras: camera_lib.Cameras, up) -> np.ndarray:
  up = scene_up(dataset_cameras) if up is None else np.asarray(up, np.float64)
  norm = np.linalg.norm(up)
  if up.shape != (3,) or not norm > 0:
    raise InputError(f"up must be a non-zero 3-vector, got {up.tolist()}", field="up")
  return up / norm


def _dataset_views_of_selection(dataset_cameras: camera_lib.Cameras, points: np.ndarray,
                                up: np.ndarray):
  """Azimuth, elevation (radians) and distance of the dataset cameras that see the selection.

  Raises:
    InputError: no dataset camera sees the selection, or all that do sit at its centre.
  """
  center, radius = selection_sphere(points)
  seeing = cameras_seeing(dataset_cameras, np.concatenate([points, center[None]]))
  if not seeing.any():
    raise InputError(f"none of the {dataset_cameras.num_cameras} dataset cameras sees the "
                     "selection", field="selection")
  positions = np.asarray(dataset_cameras.positions, np.float64)[seeing]
  azimuth, elevation, distance = _spherical(positions, center, up)
  away = distance > 1e-6 * max(radius, 1.0)
  if not away.any():
    raise InputError("every dataset camera that sees the selection sits at its centre, so no "
                     "viewing direction can be derived", field="selection")
  return azimuth[away], elevation[away], distance[away]


@dataclasses.dataclass(frozen=True)
class ReferencePlacement(validation.CheckedFields):
  """How reference cameras are placed around the selection (gin: `ReferencePlacement.<field>`;
  see the module docstring).

  Attributes:
    up: (x, y, z) scene up direction (any length); None: the dataset cameras' mean up vector.
    neighbours: dataset cameras (nearest in azimuth) each reference camera takes its elevation
      and distance from.
    min_fill, max_fill: bounds on the fraction of the frame's area the selection's bounding
      sphere may cover (0 < min_fill <= max_fill < 1).
    min_arc_degrees: the azimuth arc (degrees) used when the dataset cameras cover less.
  """

  up: Vector3 | None = None
  neighbours: PositiveInt = 3
  min_fill: OpenUnitInterval = 0.25
  max_fill: OpenUnitInterval = 0.6
  min_arc_degrees: Annotated[float, Range(0, 360, low_inclusive=False)] = 30.0

  def __post_init__(self):
    super().__post_init__()
    if not self.min_fill <= self.max_fill:
      raise InputError(f"need 0 < min_fill <= max_fill < 1, got {self.min_fill}, "
                       f"{self.max_fill}", field="ReferencePlacement.min_fill")


def _reference_views(azimuth, elevation, distance, count: int, placement: ReferencePlacement
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """[count] azimuths, elevations (radians) and distances of the reference cameras from the
  dataset cameras' own (steps 2 and 3 of the module docstring; distances not yet clipped)."""
  start, arc = _covered_arc(azimuth, np.deg2rad(placement.min_arc_degrees))
  if 2 * np.pi - arc <= 2 * np.pi / count:
    # The uncovered gap is narrower than the spacing the cameras would get: all around.
    arc = 2 * np.pi
  reference_azimuth = start + arc * (np.arange(count) + 0.5) / count
  angular_gap = np.abs(np.angle(np.exp(1j * (reference_azimuth[:, None] - azimuth[None]))))
  nearest = np.argsort(angular_gap, axis=1, kind="stable")[:, :placement.neighbours]
  return (reference_azimuth, np.median(elevation[nearest], axis=1),
          np.median(distance[nearest], axis=1))


def place_reference_cameras(
    dataset_cameras: camera_lib.Cameras, selection_points, count: int = 5,
    placement: ReferencePlacement = ReferencePlacement(), width: int | None = None,
    height: int | None = None) -> tuple[camera_lib.Cameras, ReferenceCameraReport]:
  """Places `count` reference cameras around the selection (see the module docstring).

  Args:
    dataset_cameras: the N dataset cameras.
    selection_points: [K, 3] points spanning the selection (box corners, proxy vertices).
    count: M, the number of reference cameras.
    placement: up direction, neighbours, fill bounds and minimum arc.
    width, height: reference image size in pixels; default the dataset's.
  Returns:
    (reference cameras, report).
  Raises:
    InputError: no dataset camera sees the selection, or all that do sit at its centre.
  """
  if count < 1:
    raise InputError(f"need at least one reference camera, got {count}", field="count")
  points = np.asarray(selection_points, np.float64).reshape(-1, 3)
  center, radius = selection_sphere(points)
  up = _unit_up(dataset_cameras, placement.up)
  azimuth, elevation, distance = _reference_views(
      *_dataset_views_of_selection(dataset_cameras, points, up), count, placement)

  width = dataset_cameras.width if width is None else int(width)
  height = dataset_cameras.height if height is None else int(height)
  fx = float(np.median(np.asarray(dataset_cameras.fx))) * width / dataset_cameras.width
  fy = float(np.median(np.asarray(dataset_cameras.fy))) * height / dataset_cameras.height
  focal = (fx + fy) / 2
  distance = np.clip(distance, _fill_distance(placement.max_fill, radius, focal, width, height),
                     _fill_distance(placement.min_fill, radius, focal, width, height))

  first, second = _azimuth_basis(up)
  directions = (np.cos(elevation)[:, None]
                * (np.cos(azimuth)[:, None] * first + np.sin(azimuth)[:, None] * second)
                + np.sin(elevation)[:, None] * up)
  eyes = center + distance[:, None] * directions
  camera_to_world = _look_at(eyes.astype(np.float32), center.astype(np.float32),
                             up.astype(np.float32))
  cameras = camera_lib.Cameras.create(np.asarray(camera_to_world), fx=fx, fy=fy, width=width,
                                      height=height)
  return cameras, describe_reference_cameras(cameras, dataset_cameras, points, up)


def describe_reference_cameras(cameras: camera_lib.Cameras, dataset_cameras: camera_lib.Cameras,
                               selection_points, up=None) -> ReferenceCameraReport:
  """The report for user-given reference cameras, which must all see the selection.

  Raises:
    InputError: some reference camera does not see the selection (its index is named).
  """
  points = np.asarray(selection_points, np.float64).reshape(-1, 3)
  center, _ = selection_sphere(points)
  up = _unit_up(dataset_cameras, up)
  blind = np.flatnonzero(~cameras_seeing(cameras, np.concatenate([points, center[None]])))
  if len(blind):
    raise InputError(f"reference cameras {blind.tolist()} do not see the selection",
                     field="reference_cameras")
  dataset_azimuth = _dataset_views_of_selection(dataset_cameras, points, up)[0]
  azimuth, elevation, distance = _spherical(np.asarray(cameras.positions, np.float64), center, up)
  return ReferenceCameraReport(
      up=up,
      dataset_views_seeing_selection=len(dataset_azimuth),
      dataset_arc_degrees=float(np.rad2deg(_covered_arc(dataset_azimuth, 0.0)[1])),
      reference_arc_degrees=float(np.rad2deg(_covered_arc(azimuth, 0.0)[1])),
      azimuth_degrees=np.rad2deg(azimuth),
      elevation_degrees=np.rad2deg(elevation),
      distance=distance,
      fill_ratio=projected_fill(cameras, points),
  )
