"""Camera poses at the dataset boundary: validation, convention changes and normalisation.

Every reader brings its poses into one *normalised scene frame* whose content lies inside
[-1, 1]^3. The map from the source's own world frame is a similarity (uniform scale, rotation,
translation) stored as a [4, 4] matrix `world_from_source`, so that anything placed in source
coordinates (a proxy mesh, a box) can be mapped into the scene: x_world = world_from_source @ x.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from signerf_jax.camera import Cameras
from signerf_jax.errors import InputError

# A pose whose rotation deviates this much from orthonormal is not a rigid camera: it would shear
# or scale rays, which the ray generator silently assumes away.
ROTATION_TOLERANCE = 1e-3
# Camera coordinates beyond this (in the source's units) are refused. Real captures stay far
# below: Earth-centred coordinates are under 6.4e6 metres (6.4e9 in millimetres). Larger values
# are corrupt files, and they break the arithmetic that follows: cameras are stored as float32
# (1e39 is infinite there) and squared distances overflow from ~1e19.
MAX_CAMERA_COORDINATE = 1e10


def check_camera_to_world(matrix, path: str | os.PathLike, field: str) -> np.ndarray:
  """Validates one camera-to-world pose read from a file.

  Args:
    matrix: a nested list or array, [3, 4] or [4, 4] (then the last row must be [0, 0, 0, 1]).
    path, field: where it came from, for the error message (e.g. `frames[3].transform_matrix`).
  Returns:
    [3, 4] float64 [R | t].
  Raises:
    InputError: wrong shape, non-numeric or non-finite entries, a position beyond
      MAX_CAMERA_COORDINATE, or a rotation that is not proper (orthonormal within
      ROTATION_TOLERANCE with determinant +1).
  """
  try:
    pose = np.asarray(matrix, np.float64)
  except (TypeError, ValueError):
    raise InputError("is not a numeric matrix", path, field) from None
  if pose.shape not in ((3, 4), (4, 4)):
    raise InputError(f"must be a 3x4 or 4x4 matrix, got shape {pose.shape}", path, field)
  if not np.all(np.isfinite(pose)):
    raise InputError("contains non-finite values", path, field)
  position = pose[:3, 3]
  if np.max(np.abs(position)) > MAX_CAMERA_COORDINATE:
    raise InputError(f"camera position {position.tolist()} has a coordinate beyond "
                     f"{MAX_CAMERA_COORDINATE:g}: no capture places a camera that far (a corrupt "
                     "pose)", path, field)
  if pose.shape == (4, 4) and np.max(np.abs(pose[3] - [0, 0, 0, 1])) > ROTATION_TOLERANCE:
    raise InputError(f"last row must be [0, 0, 0, 1], got {pose[3].tolist()}", path, field)
  rotation = pose[:3, :3]
  deviation = np.max(np.abs(rotation.T @ rotation - np.eye(3)))
  if deviation > ROTATION_TOLERANCE:
    raise InputError(f"rotation is not orthonormal (|R^T R - I| = {deviation:.2g})", path, field)
  if np.linalg.det(rotation) < 0:
    raise InputError("rotation has determinant -1 (a reflection, not a camera pose)", path, field)
  return pose[:3]


def check_focal_length(value, path: str | os.PathLike, field: str) -> float:
  """A focal length (pixels) must be a finite positive number (not a string or a bool)."""
  if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
    raise InputError(f"must be a number, got {value!r}", path, field)
  if not np.isfinite(value) or value <= 0:
    raise InputError(f"must be a finite positive focal length, got {value}", path, field)
  return float(value)


def llff_to_opengl(rotation_columns: np.ndarray) -> np.ndarray:
  """LLFF's camera axes [down, right, backwards] -> OpenGL [right, up, backwards].

  Args:
    rotation_columns: [..., 3, 3 + k] matrices whose first three columns are LLFF's axes.
  Returns:
    The same matrices with the first three columns reordered (other columns untouched).
  """
  down, right, back = (rotation_columns[..., :, i] for i in range(3))
  converted = np.array(rotation_columns, copy=True)
  converted[..., :, 0], converted[..., :, 1], converted[..., :, 2] = right, -down, back
  return converted


def camera_to_world_from_opencv(rotation, translation) -> np.ndarray:
  """OpenCV's world-to-camera pose (x_camera = R x_world + t; camera axes right, down, forward,
  as COLMAP and cv2 give them) -> [..., 3, 4] float64 OpenGL camera-to-world.

  Args:
    rotation: [..., 3, 3] R; translation: [..., 3] t.
  """
  rotation = np.asarray(rotation, np.float64)
  camera_to_world_rotation = np.swapaxes(rotation, -1, -2)
  centre = -np.einsum("...ij,...j->...i", camera_to_world_rotation,
                      np.asarray(translation, np.float64))
  # OpenCV's down and forward axes are OpenGL's up and backwards, negated.
  opengl_rotation = camera_to_world_rotation * np.array([1.0, -1.0, -1.0])
  return np.concatenate([opengl_rotation, centre[..., None]], axis=-1)


def similarity(scale: float = 1.0, rotation=None, translation=None) -> np.ndarray:
  """The [4, 4] float64 matrix x -> scale * rotation @ x + translation."""
  matrix = np.eye(4)
  matrix[:3, :3] = scale * (np.eye(3) if rotation is None else np.asarray(rotation, np.float64))
  matrix[:3, 3] = 0.0 if translation is None else translation
  return matrix


def similarity_scale(matrix: np.ndarray) -> float:
  """The uniform scale of a similarity transform."""
  return float(np.cbrt(np.linalg.det(np.asarray(matrix, np.float64)[:3, :3])))


def unit_box_similarity(lower, upper) -> np.ndarray:
  """The similarity that centres the box [lower, upper] and scales its largest side to [-1, 1]."""
  lower, upper = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
  scale = 1.0 / max(np.max(upper - lower) / 2, 1e-12)
  return similarity(scale, translation=-scale * (lower + upper) / 2)


def mean_rotation(camera_to_world) -> np.ndarray:
  """[3, 3] camera-to-world rotation of the cameras' average orientation (LLFF's): its backward
  axis is the mean of theirs, its right axis perpendicular to that and their mean up axis.

  Args:
    camera_to_world: [N, 3, 4] OpenGL poses.
  Raises:
    InputError when the cameras look in all directions (no mean viewing direction).
  """
  camera_to_world = np.asarray(camera_to_world, np.float64)
  back = camera_to_world[:, :, 2].mean(0)
  if np.linalg.norm(back) < 0.1:
    raise InputError("the cameras look in all directions: not a forward-facing capture",
                     field="scene_kind")
  back /= np.linalg.norm(back)
  right = np.cross(camera_to_world[:, :, 1].sum(0), back)
  right /= np.linalg.norm(right)
  return np.stack([right, np.cross(back, right), back], -1)


def rotation_between(source, target) -> np.ndarray:
  """The [3, 3] rotation taking unit direction `source` onto unit direction `target`."""
  source = np.asarray(source, np.float64) / np.linalg.norm(source)
  target = np.asarray(target, np.float64) / np.linalg.norm(target)
  axis = np.cross(source, target)
  cosine = float(source @ target)
  if np.linalg.norm(axis) < 1e-9:
    if cosine > 0:
      return np.eye(3)
    # Opposite directions: half a turn about any axis orthogonal to them.
    orthogonal = np.cross(source, np.eye(3)[np.argmin(np.abs(source))])
    orthogonal /= np.linalg.norm(orthogonal)
    return 2 * np.outer(orthogonal, orthogonal) - np.eye(3)
  skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
  return np.eye(3) + skew + skew @ skew / (1 + cosine)


def transform_points(matrix: np.ndarray, points) -> np.ndarray:
  """Applies a [4, 4] affine matrix to [..., 3] points."""
  matrix = np.asarray(matrix, np.float64)
  return np.asarray(points, np.float64) @ matrix[:3, :3].T + matrix[:3, 3]


def transform_poses(matrix: np.ndarray, camera_to_world) -> np.ndarray:
  """Maps [N, 3, 4] camera-to-world poses through a similarity; rotations stay orthonormal."""
  matrix = np.asarray(matrix, np.float64)
  camera_to_world = np.asarray(camera_to_world, np.float64)
  rotation = matrix[:3, :3] / similarity_scale(matrix)
  return np.concatenate([rotation @ camera_to_world[..., :3],
                         transform_points(matrix, camera_to_world[..., 3])[..., None]], axis=-1)


def transform_cameras(matrix: np.ndarray, cameras: Cameras) -> Cameras:
  """The same cameras expressed in the frame `matrix` (a similarity) maps into."""
  poses = transform_poses(matrix, cameras.camera_to_world)
  return cameras.replace(camera_to_world=poses.astype(np.float32))


def near_far_for_box(cameras: Cameras, lower, upper) -> tuple[float, float]:
  """A ray-distance range [near, far] that covers the box [lower, upper] from every camera.

  far is the largest camera-to-corner distance; near the smallest camera-to-box distance (a
  camera inside the box gets a small positive near, 1e-3 of far, so rays start past the lens).
  """
  lower, upper = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
  positions = np.asarray(cameras.positions, np.float64)
  corners = np.stack(np.meshgrid(*zip(lower, upper), indexing="ij"), -1).reshape(-1, 3)
  far = float(np.max(np.linalg.norm(positions[:, None] - corners[None], axis=-1)))
  outside = np.maximum(np.maximum(lower - positions, positions - upper), 0.0)
  near = float(np.min(np.linalg.norm(outside, axis=-1)))
  return max(near, 1e-3 * far), far


def check_similarity(value: Any, path: str | os.PathLike, field: str) -> np.ndarray:
  """`value` (a 3x4 or 4x4 matrix read from `path`) as a [4, 4] similarity: a rotation, a uniform
  positive scale and a translation, as a capture's frame change (nerfstudio's
  `applied_transform`) must be, since positions and sizes are converted through it and its
  inverse.

  Raises:
    InputError naming `path` and `field`: not a finite matrix, singular, a reflection, shearing
      or scaling unevenly.
  """
  try:
    matrix = np.asarray(value, np.float64)
  except (TypeError, ValueError):
    matrix = None
  if matrix is None or matrix.shape not in ((3, 4), (4, 4)) or not np.all(np.isfinite(matrix)):
    raise InputError("must be a finite 3x4 or 4x4 matrix", path, field)
  if matrix.shape == (4, 4) and np.max(np.abs(matrix[3] - [0, 0, 0, 1])) > 1e-9:
    raise InputError(f"last row must be [0, 0, 0, 1], got {matrix[3].tolist()}", path, field)
  linear = matrix[:3, :3]
  determinant = np.linalg.det(linear)
  # Relative to the columns' size, so a scaled rotation is judged like the rotation.
  size = max(float(np.max(np.abs(linear))), np.finfo(np.float64).tiny)
  if not determinant / size**3 > ROTATION_TOLERANCE:
    raise InputError(f"is singular or a reflection (determinant {determinant:.3g} of its 3x3 "
                     "part): it must be a rotation, uniform scale and translation",
                     path, field)
  rotation = linear / np.cbrt(determinant)
  deviation = float(np.max(np.abs(rotation.T @ rotation - np.eye(3))))
  if deviation > ROTATION_TOLERANCE:
    raise InputError(f"its 3x3 part shears or scales unevenly (|R^T R - I| = {deviation:.2g} "
                     "after removing the scale): it must be a rotation, uniform scale and "
                     "translation", path, field)
  return np.concatenate([matrix[:3], [[0.0, 0.0, 0.0, 1.0]]])
