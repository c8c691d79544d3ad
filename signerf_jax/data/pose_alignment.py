"""How far recovered camera poses are from known ones, after the similarity (scale, rotation,
translation) that structure from motion cannot know: its world has an arbitrary origin,
orientation and scale."""

from __future__ import annotations

import numpy as np


def similarity_from_points(source: np.ndarray, target: np.ndarray) -> np.ndarray:
  """[4, 4] similarity S (s R | t) minimising sum |S source_i - target_i|^2 (Umeyama, 1991).

  Args:
    source, target: [N, 3] corresponding points, N >= 3 not all on one line.
  """
  source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
  source_mean, target_mean = source.mean(0), target.mean(0)
  centred_source, centred_target = source - source_mean, target - target_mean
  u, singular, vt = np.linalg.svd(centred_target.T @ centred_source / len(source))
  # A reflection is not a rotation: flip the weakest axis instead.
  sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
  rotation = u @ sign @ vt
  scale = np.trace(np.diag(singular) @ sign) / np.mean(np.sum(centred_source**2, -1))
  similarity = np.eye(4)
  similarity[:3, :3] = scale * rotation
  similarity[:3, 3] = target_mean - scale * rotation @ source_mean
  return similarity


def pose_errors(estimated: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                     float]:
  """Each camera's error after aligning the estimated camera centres to the true ones.

  Args:
    estimated, truth: [N, 3 or 4, 4] camera-to-world matrices of the same N cameras (any one
      camera-axis convention, the same for both).

  Returns:
    rotation_degrees: [N] angle between each aligned and true camera orientation.
    position: [N] distance between each aligned and true camera centre, in `truth`'s units.
    radius: the largest distance of a true camera centre from the centres' mean (the scene's
      size, for relative errors).
  """
  estimated, truth = np.asarray(estimated, np.float64), np.asarray(truth, np.float64)
  similarity = similarity_from_points(estimated[:, :3, 3], truth[:, :3, 3])
  scale = np.cbrt(np.linalg.det(similarity[:3, :3]))
  rotation = similarity[:3, :3] / scale
  aligned_centres = estimated[:, :3, 3] @ similarity[:3, :3].T + similarity[:3, 3]
  aligned_rotations = rotation @ estimated[:, :3, :3]
  relative = np.einsum("nji,njk->nik", aligned_rotations, truth[:, :3, :3])
  cosine = np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
  position = np.linalg.norm(aligned_centres - truth[:, :3, 3], axis=-1)
  radius = float(np.max(np.linalg.norm(truth[:, :3, 3] - truth[:, :3, 3].mean(0), axis=-1)))
  return np.degrees(np.arccos(cosine)), position, radius
